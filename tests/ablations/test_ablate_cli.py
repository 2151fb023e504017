"""The ``ablate`` command: smoke runs of every mode, run-folder contents, resume, determinism, bad input."""

from __future__ import annotations

import dataclasses
import json
import os
import random
import re
import subprocess
import sys
from pathlib import Path

import pytest

from ablations.cli import ablate_main
from ablations.runs import PROBE_KEYS, REQUIRED_KEYS, TIMING_KEYS, RunConfig, prepare, read_metrics
from gradlab.checkpoint import atomic_write_json, checkpoint_path, save_checkpoint

TINY = ["--num-envs", "2", "--horizon", "3", "--image-size", "24", "--critic-iterations", "1",
        "--critic-batches", "1", "--device", "cpu", "--no-progress"]


def ablate(*args: str) -> None:
    ablate_main(list(args))


def strip_timing(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIMING_KEYS} for r in rows]


@pytest.mark.parametrize("task", ["cartpole", "ant"])
@pytest.mark.parametrize("mode", ["full", "decoupled", "state", "blind"])
def test_smoke_every_mode(tmp_path, task, mode, capsys):
    ablate("--task", task, "--mode", mode, "--iters", "2", "--cosine-every", "2", "--video-every", "2",
           "--video-steps", "3", "--out", str(tmp_path), "--name", "run", *TINY)
    run = tmp_path / "run"
    assert capsys.readouterr().out.strip().endswith(str(run))
    rows = read_metrics(run)
    assert [r["iter"] for r in rows] == [1, 2]
    for r in rows:
        assert set(REQUIRED_KEYS) <= set(r)
    probed = [r for r in rows if r["probed"]]
    if mode in ("state", "blind"):
        assert not probed
    else:
        assert len(probed) == 1 and set(PROBE_KEYS) <= set(probed[0])
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["config"]["task"] == task and cfg["config"]["mode"] == mode
    # the dva preset resolved: D.Va's critic lr, SHAC's state-based one for state cartpole (1e-3)
    assert cfg["config"]["critic_lr"] == {"cartpole": 1e-3 if mode == "state" else 2e-4, "ant": 2e-3}[task]
    assert cfg["preset"]["name"] == "dva" and cfg["preset"]["supplied"]["critic_lr"] == cfg["config"]["critic_lr"]
    assert cfg["started_utc"].endswith("+00:00")
    assert (run / "git.txt").read_text().startswith(("commit ", "git information unavailable"))
    summary = json.loads((run / "summary.json").read_text())
    assert summary["status"] == "finished" and summary["iterations"] == 2
    assert summary["ended_utc"] >= cfg["started_utc"]
    assert (run / "checkpoints" / "ckpt_000002.pt").exists()
    video = run / "videos" / "iter_000002.mp4"
    assert video.exists() and video.stat().st_size > 1000


def test_resume_equals_uninterrupted_and_same_seed_same_metrics(tmp_path):
    common = ["--task", "cartpole", "--mode", "decoupled", "--iters", "4", "--cosine-every", "3",
              "--video-every", "0", "--checkpoint-every", "2", "--out", str(tmp_path), *TINY]
    ablate(*common, "--name", "whole")
    ablate(*common, "--name", "whole2")
    assert strip_timing(read_metrics(tmp_path / "whole")) == strip_timing(read_metrics(tmp_path / "whole2"))

    # Interrupt after iteration 3 (checkpoint at 2, one more line already written), then resume.
    ablate(*common, "--name", "cut")
    cut = tmp_path / "cut"
    rows = read_metrics(cut)
    (cut / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows[:3]) + '{"iter": 4, "torn')
    for ck in (cut / "checkpoints").glob("ckpt_000004.pt"):
        ck.unlink()
    ablate("--resume", str(cut), "--no-progress")
    assert strip_timing(read_metrics(cut)) == strip_timing(read_metrics(tmp_path / "whole"))


def test_resume_starts_from_the_newest_readable_checkpoint(tmp_path, capsys):
    """The resume decision alone (no trainer): damaged newer checkpoints are named, set aside and skipped."""
    ckpts = tmp_path / "run" / "checkpoints"
    atomic_write_json(tmp_path / "run" / "config.json",
                      {"config": dataclasses.asdict(RunConfig(task="cartpole", device="cpu", out=tmp_path))})
    for it in (2, 4, 6):
        save_checkpoint(checkpoint_path(ckpts, it), {"iteration": it})
    # overwritten with random bytes (fixed: which error torch.load raises depends on the bytes)
    checkpoint_path(ckpts, 6).write_bytes(random.Random(6).randbytes(4096))
    checkpoint_path(ckpts, 4).write_bytes(b"")  # truncated to nothing
    cfg, _, device, loaded = prepare(RunConfig(resume=tmp_path / "run", progress=False))
    assert (cfg.task, device.type) == ("cartpole", "cpu")
    assert loaded.path == checkpoint_path(ckpts, 2) and loaded.state == {"iteration": 2}
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2
    assert re.match(rf"warning: checkpoint {re.escape(str(checkpoint_path(ckpts, 6)))} is damaged "
                    r"\(\w+: .+\); renamed to ckpt_000006\.pt\.damaged", err[0]), err[0]
    assert err[1].startswith(f"warning: checkpoint {checkpoint_path(ckpts, 4)} is damaged (EOFError")
    assert sorted(p.name for p in ckpts.iterdir()) == ["ckpt_000002.pt", "ckpt_000004.pt.damaged",
                                                       "ckpt_000006.pt.damaged"]


def test_a_run_folder_whose_preset_has_no_table_resumes_with_its_recorded_values(tmp_path, capsys):
    """config.json records every value a preset supplied, so a folder naming a preset this toolkit has no table for
    (``project``) resumes with exactly those values, said on stderr; one without them is a clear error."""
    from gradlab.config import resolve_config
    from gradlab.presets import PRESET_FIELDS

    recorded = dataclasses.asdict(resolve_config(RunConfig(task="hopper", device="cpu", out=tmp_path, iters=30)))
    recorded.update(preset="project", actor_init="orthogonal", obs_clip=5.0, bootstrap_last_step=False,
                    lr_decay_iters=30)
    atomic_write_json(tmp_path / "run" / "config.json", {"config": recorded})
    save_checkpoint(checkpoint_path(tmp_path / "run" / "checkpoints", 2), {"iteration": 2})
    cfg, _, _, _ = prepare(RunConfig(resume=tmp_path / "run", progress=False))
    assert cfg.preset == "dva" and "preset 'project' has no table here" in capsys.readouterr().err
    assert resolve_config(cfg) == cfg  # nothing left for the preset to fill in
    assert {k: getattr(cfg, k) for k in PRESET_FIELDS} == {k: (tuple(v) if isinstance(v, list) else v)
                                                           for k, v in recorded.items() if k in PRESET_FIELDS}
    recorded["obs_clip"] = None  # a value the preset would have to supply
    atomic_write_json(tmp_path / "run" / "config.json", {"config": recorded})
    with pytest.raises(ValueError, match="unknown preset 'project'; valid presets: dva, shac-diffrender"):
        prepare(RunConfig(resume=tmp_path / "run", progress=False))


@pytest.mark.slow
def test_resume_skips_a_damaged_checkpoint_and_says_when_none_is_readable(tmp_path, capsys):
    """End to end with the trainer: the resumed run reproduces the uninterrupted one from the older checkpoint."""
    common = ["--task", "cartpole", "--mode", "decoupled", "--iters", "4", "--cosine-every", "3",
              "--video-every", "0", "--checkpoint-every", "2", "--out", str(tmp_path), *TINY]
    ablate(*common, "--name", "run")
    run = tmp_path / "run"
    ckpts = run / "checkpoints"
    whole = strip_timing(read_metrics(run))
    newest = ckpts / "ckpt_000004.pt"
    newest.write_bytes(random.Random(4).randbytes(4096))  # e.g. a disk fault or a copy that went wrong
    capsys.readouterr()

    ablate("--resume", str(run), "--no-progress")
    err = capsys.readouterr().err
    # Named with its reason, set aside, and the run continues from the older checkpoint to the same result.
    assert f"warning: checkpoint {newest} is damaged (" in err and "resuming from ckpt_000002.pt" in err
    assert (ckpts / "ckpt_000004.pt.damaged").exists()
    assert strip_timing(read_metrics(run)) == whole
    assert sorted(p.name for p in ckpts.glob("ckpt_*.pt")) == ["ckpt_000002.pt", "ckpt_000004.pt"]

    for p in ckpts.glob("ckpt_*.pt"):
        p.write_bytes(b"")  # a disk that filled up: both checkpoints empty
    with pytest.raises(SystemExit) as e:
        ablate("--resume", str(run), "--no-progress")
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "no readable checkpoint" in err
    assert str(ckpts / "ckpt_000004.pt") in err and str(ckpts / "ckpt_000002.pt") in err


def test_resume_with_a_damaged_config_names_the_file(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text('{"config": "\x01 torn')
    with pytest.raises(SystemExit) as e:
        ablate("--resume", str(run), "--no-progress")
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and str(run / "config.json") in err and "JSONDecodeError" in err

    (run / "config.json").write_text('["not", "a", "run config"]')
    with pytest.raises(SystemExit):
        ablate("--resume", str(run), "--no-progress")
    assert f"{run / 'config.json'} has no 'config' object" in capsys.readouterr().err


def run_cli(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    return subprocess.run([sys.executable, "-c", "from ablations.cli import ablate_main; ablate_main()", *args],
                          capture_output=True, text=True, env=env, timeout=120)


@pytest.mark.parametrize(("args", "message"), [
    (["--task", "cartpol"], "unknown task 'cartpol'; valid tasks: cartpole, cartpole-swingup, hopper, ant, humanoid"),
    (["--mode", "ful"], "full"),  # tyro lists the valid choices
    (["--num-envs", "0"], "num_envs must be a positive integer"),
    (["--horizon", "-2"], "horizon must be a positive integer"),
    (["--iters", "0"], "iters must be a positive integer"),
    (["--device", "tpu"], "unknown device 'tpu'"),
    (["--preset", "paper"], "--preset"),  # tyro names the flag and lists dva, shac-diffrender
    (["--raster-model", "blurry"], "--raster-model"),
    (["--mode", "full", "--renderer", "warp"], "--renderer warp renders without gradient, but --mode full"),
])
def test_bad_input_is_one_clear_line_before_any_work(tmp_path, args, message):
    r = run_cli(*args, "--out", str(tmp_path / "o"), "--no-progress")
    assert r.returncode == 2
    assert message in r.stderr
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_unwritable_output_folder(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    r = run_cli("--out", str(blocker / "runs"), "--no-progress")
    assert r.returncode == 2 and "not writable" in r.stderr


def test_resume_of_a_non_run_folder(tmp_path):
    r = run_cli("--resume", str(tmp_path), "--no-progress")
    assert r.returncode == 2 and "no config.json" in r.stderr


def test_help_documents_every_flag():
    r = run_cli("--help")
    assert r.returncode == 0
    for flag in ("--mode", "--task", "--iters", "--num-envs", "--horizon", "--seed", "--device", "--out",
                 "--cosine-every", "--resume", "--video-every", "--tensorboard"):
        assert flag in r.stdout
    assert "decoupled (D.Va)" in r.stdout.replace("\n", " ").replace("  ", " ") or "D.Va" in r.stdout


def test_time_limit_stops_cleanly(tmp_path):
    ablate("--task", "cartpole", "--mode", "state", "--iters", "1000", "--time-limit-min", "0.0001",
           "--video-every", "0", "--out", str(tmp_path), "--name", "t", *TINY)
    summary = json.loads((tmp_path / "t" / "summary.json").read_text())
    assert summary["status"] == "time_limit" and summary["iterations"] == 1
    assert (tmp_path / "t" / "checkpoints" / "ckpt_000001.pt").exists()
    # The budget is training wall-clock carried by the checkpoint: a resumed run whose budget is spent trains no
    # further iteration, and one given a larger budget goes on from where it stopped.
    ablate("--resume", str(tmp_path / "t"), "--time-limit-min", "0.0001", "--video-every", "0")
    summary = json.loads((tmp_path / "t" / "summary.json").read_text())
    assert summary["status"] == "time_limit" and summary["iterations"] == 1
    ablate("--resume", str(tmp_path / "t"), "--iters", "2", "--time-limit-min", "100", "--video-every", "0")
    summary = json.loads((tmp_path / "t" / "summary.json").read_text())
    assert summary["status"] == "finished" and summary["iterations"] == 2


@pytest.mark.parametrize("folder", ["bytecode", "off"])
def test_ablate_keeps_pythons_bytecode_in_its_folder_where_the_install_gets_none(tmp_path, folder):
    """Told not to write bytecode beside the sources (PYTHONDONTWRITEBYTECODE, as in many container images),
    ``ablate`` keeps it in $PIXELGRAD_BYTECODE_CACHE from its first line, torch's included, so that the next start
    does not compile torch's Python again (ablations/startup/bytecode.py); ``off`` keeps none."""
    import torch

    import ablations.runs

    kept_in = tmp_path / "bytecode"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPYCACHEPREFIX"}
    env.update(PYTHONDONTWRITEBYTECODE="1", PYTHONPATH=str(Path(__file__).resolve().parents[2]),
               PIXELGRAD_BYTECODE_CACHE=str(kept_in) if folder == "bytecode" else "off")
    out = subprocess.run([sys.executable, "-m", "ablations", "ablate", "--help"], capture_output=True, text=True,
                         env=env, timeout=300)
    assert out.returncode == 0 and "--compile-cache" in out.stdout, out.stderr[-2000:]

    def kept(source: str) -> bool:  # where Python keeps a source's bytecode under a prefix: its absolute path
        source = Path(source).resolve()
        return (kept_in / source.parent.relative_to(source.anchor)
                / f"{source.stem}.{sys.implementation.cache_tag}.pyc").is_file()

    wanted = folder == "bytecode"
    assert kept(ablations.runs.__file__) is wanted and kept(torch.__file__) is wanted
    assert kept_in.exists() is wanted
