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

from ablations.cli import ABLATE_GROUPS, _one_paragraph, ablate_main
from ablations.population import prepare
from ablations.run_config import RunConfig
from ablations.run_folder import read_metrics
from ablations.runs import PROBE_KEYS, REQUIRED_KEYS, TIMING_KEYS
from ablations.tree_hash import tree_hash
from gradlab.checkpoint import atomic_write_json, checkpoint_path, save_checkpoint

TINY = ["--num-envs", "2", "--horizon", "3", "--image-size", "24", "--critic-iterations", "1",
        "--critic-batches", "1", "--device", "cpu", "--no-progress"]


def ablate(*args: str) -> None:
    ablate_main(list(args))


def strip_timing(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIMING_KEYS} for r in rows]


@pytest.mark.parametrize("task", ["cartpole", pytest.param("ant", marks=pytest.mark.slow)])
@pytest.mark.parametrize("mode", ["full", "decoupled", "state", "blind"])
def test_smoke_every_mode(tmp_path, task, mode, capsys):
    probes = ["--cosine-every", "2"] if mode in ("full", "decoupled") else []  # state, blind: no probes to give
    ablate("--task", task, "--mode", mode, "--iters", "2", *probes, "--video-every", "2",
           "--video-steps", "3", "--out", str(tmp_path), "--name", "run", *TINY)
    run = tmp_path / "run"
    out = capsys.readouterr().out
    # the closing lines: the absolute run folder and the command that continues it
    assert f"run folder         {run.resolve()}\n" in out and f"ablate --resume {run.resolve()} --iters N" in out
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
    # the training tree's hash, which a device copy without a repository records alike
    assert cfg["tree_hash"] == tree_hash().value and cfg["tree_hash_source"] in ("git", "files")
    assert (run / "git.txt").read_text().startswith(("commit ", "git information unavailable"))
    summary = json.loads((run / "summary.json").read_text())
    assert summary["status"] == "finished" and summary["iterations"] == 2
    assert summary["ended_utc"] >= cfg["started_utc"]
    # the deterministic evaluation of the last video iteration, in the summary and the closing lines
    assert summary["final_eval_return"] == rows[-1]["eval_return_mean"] and summary["final_eval_iter"] == 2
    assert summary["final_eval_std"] == rows[-1]["eval_return_std"]
    assert summary["best_eval_return"] == max(r["eval_return_mean"] for r in rows if "eval_return_mean" in r)
    assert 1 <= rows[-1]["eval_length_mean"] <= 1000
    assert (f"evaluation return  {summary['final_eval_return']:>9.1f} +- {summary['final_eval_std']:.1f}  "
            f"(deterministic policy, at iteration 2)") in out
    assert (run / "checkpoints" / "ckpt_000002.pt").exists()
    video = run / "videos" / "iter_000002.mp4"
    assert video.exists() and video.stat().st_size > 1000


def test_a_short_cheetah_run_from_pixels(tmp_path, capsys):
    """The cheetah trains from pixels on the CPU with its D.Va preset (examples/cfg/dva/cheetah.yaml critic lr
    2e-3) and is evaluated over whole (shortened) episodes, which it never ends early (no termination)."""
    ablate("--task", "cheetah", "--mode", "decoupled", "--iters", "2", "--cosine-every", "0", "--eval-every", "2",
           "--eval-envs", "2", "--episode-length", "6", "--video-every", "0", "--out", str(tmp_path), "--name", "run",
           *TINY)
    run = tmp_path / "run"
    rows = read_metrics(run)
    assert [r["iter"] for r in rows] == [1, 2] and rows[-1]["eval_length_mean"] == 6
    assert all(set(REQUIRED_KEYS) <= set(r) for r in rows)
    cfg = json.loads((run / "config.json").read_text())
    assert (cfg["config"]["task"], cfg["config"]["critic_lr"], cfg["config"]["actor_hidden"]) == (
        "cheetah", 2e-3, [128, 64, 32])
    assert "cheetah/decoupled seed 0: finished after 2 iterations" in capsys.readouterr().out


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
    # each start of the run is recorded with its code (the resume's beside the first's)
    starts = [json.loads(line) for line in (cut / "provenance.jsonl").read_text().splitlines()]
    assert [(p["event"], p["iteration"]) for p in starts] == [("start", 0), ("resume", 2)]
    assert starts[0]["tree_hash"] == starts[1]["tree_hash"] and starts[1]["tree_hash"].startswith("sha256:")


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
    prepared = prepare(RunConfig(resume=tmp_path / "run", progress=False))
    assert (prepared.cfgs[0].task, prepared.device.type) == ("cartpole", "cpu")
    assert prepared.states == [{"iteration": 2}]
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
    cfg = prepare(RunConfig(resume=tmp_path / "run", progress=False)).cfgs[0]
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


# One refusal in a process of its own, as a user meets it; every other bad value is refused through the same path
# in-process (test_cli_errors.py), where it costs no Python start-up.
@pytest.mark.parametrize(("args", "message"), [
    (["--task", "cartpol"],
     "unknown task 'cartpol'; valid tasks: cartpole, cartpole-swingup, hopper, ant, humanoid, cheetah"),
    (["--mode", "full", "--renderer", "warp"], "--renderer warp renders without gradient, but --mode full"),
    (["--device", "tpu"], "unknown device 'tpu'"),
])
def test_bad_input_is_one_clear_line_before_any_work(tmp_path, args, message):
    """Every bad value is one line naming its flag as typed, and nothing is created: no output folder, no run
    folder."""
    r = run_cli(*args, "--out", str(tmp_path / "o"), "--no-progress")
    assert r.returncode == 2
    assert message in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o").exists()


def test_unwritable_output_folder(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    r = run_cli("--out", str(blocker / "runs"), "--no-progress")
    assert r.returncode == 2 and "not writable" in r.stderr


def test_resume_of_a_non_run_folder(tmp_path):
    r = run_cli("--resume", str(tmp_path), "--no-progress")
    assert r.returncode == 2 and "no config.json" in r.stderr


def ablate_help(columns: int) -> str:
    r = subprocess.run([sys.executable, "-m", "ablations", "ablate", "--help"], capture_output=True, text=True,
                       env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]), COLUMNS=str(columns)),
                       timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_help_is_grouped_essentials_first_and_each_flags_help_one_paragraph():
    text = ablate_help(120)  # one panel under the other
    # every flag once, in its panel; the essentials' panel first
    for f in dataclasses.fields(RunConfig):
        flag = "--" + f.name.replace("_", "-")
        assert len(re.findall(rf"^│ {re.escape(flag)}[ ,]", text, re.M)) == 1, flag  # where its entry starts
    panels = re.findall(r"╭─ ([\w-]+) options", text)
    assert panels[0] == "essentials" and set(panels) <= set(ABLATE_GROUPS) | {"more"}
    essentials = text[text.index("essentials options"):text.index("evaluation-and-probes options")]
    for flag in ("--task", "--mode", "--seed", "--iters", "--device", "--threads", "--out", "--compile",
                 "--resume"):
        assert re.search(rf"^│ {flag}[ ,]", essentials, re.M), flag
    # the progress bar's fields are explained
    for field in ("ret=", "eval=", "ms=", "gn="):
        assert field in essentials, field
    # a docstring's source line breaks do not break its help (tyro would keep them: "hopper,\n ant"); wide enough,
    # a flag's help is one line
    wide = ablate_help(400)
    assert "hopper, ant, humanoid or cheetah" in wide and "blind: the decoupled visual actor" in wide


def test_one_paragraph_joins_a_docstrings_lines_and_keeps_its_paragraphs():
    assert _one_paragraph("first line,\n    continued (a, b)\n    - and more\n\n    second") == \
        "first line, continued (a, b) - and more\n\nsecond"
    assert _one_paragraph(lambda: "lazy\n  help") == "lazy help" and _one_paragraph(None) is None


def test_time_limit_stops_cleanly(tmp_path):
    ablate("--task", "cartpole", "--mode", "state", "--iters", "1000", "--time-limit-min", "0.0001",
           "--video-every", "0", "--out", str(tmp_path), "--name", "t", *TINY)
    summary = json.loads((tmp_path / "t" / "summary.json").read_text())
    assert summary["status"] == "time_limit" and summary["iterations"] == 1
    assert (tmp_path / "t" / "checkpoints" / "ckpt_000001.pt").exists()
    # The budget is training wall-clock carried by the checkpoint: a resumed run whose budget is spent trains no
    # further iteration, and one given a larger budget goes on from where it stopped.
    ablate("--resume", str(tmp_path / "t"), "--time-limit-min", "0.0001")  # config.json keeps --video-every 0
    summary = json.loads((tmp_path / "t" / "summary.json").read_text())
    assert summary["status"] == "time_limit" and summary["iterations"] == 1
    ablate("--resume", str(tmp_path / "t"), "--iters", "2", "--time-limit-min", "100")
    summary = json.loads((tmp_path / "t" / "summary.json").read_text())
    assert summary["status"] == "finished" and summary["iterations"] == 2


@pytest.mark.parametrize("folder", [pytest.param("bytecode", marks=pytest.mark.slow), "off"])
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


# ---------------------------------------------------------------------------------------------------------
# CPU threads


def test_the_thread_count_is_applied_and_recorded(tmp_path):
    import torch

    before = torch.get_num_threads()
    try:
        ablate("--task", "cartpole", "--mode", "state", "--iters", "1", "--video-every", "0", "--out", str(tmp_path),
               "--name", "t", *TINY, "--threads", "2")
        assert torch.get_num_threads() == 2 and os.environ["OMP_NUM_THREADS"] == "2"
        record = json.loads((tmp_path / "t" / "config.json").read_text())
        assert record["config"]["threads"] == 2 and record["environment"]["threads"] == 2
        assert json.loads((tmp_path / "t" / "summary.json").read_text())["threads"] == 2
        # a resume keeps the recorded count unless told another
        ablate("--resume", str(tmp_path / "t"), "--iters", "2", "--no-progress")
        assert torch.get_num_threads() == 2
        ablate("--resume", str(tmp_path / "t"), "--iters", "3", "--no-progress", "--threads", "1")
        assert torch.get_num_threads() == 1
        assert json.loads((tmp_path / "t" / "summary.json").read_text())["threads"] == 1
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize(("cores", "omp", "expected"), [
    (2, None, 1), (3, None, 1), (16, None, 8), (64, None, 8), (1, None, 1), (16, "3", 3), (2, "junk", 1)])
def test_default_threads_is_half_the_usable_cores_capped_or_omp_num_threads(monkeypatch, cores, omp, expected):
    from ablations.run_config import default_threads

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cores)))
    if omp is None:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("OMP_NUM_THREADS", omp)
    assert default_threads() == expected


# ---------------------------------------------------------------------------------------------------------
# How a run ends: closing lines, signals, warnings, file modes


def test_the_summary_has_the_final_and_best_evaluation_return_in_either_form():
    from ablations.run_log import summary

    cfg = RunConfig(task="hopper", warmup_iters=0, threads=1)
    rows = [{"iter": 1, "env_steps": 8, "wall_s": 1.0, "return_mean": None},
            {"iter": 2, "env_steps": 16, "wall_s": 2.0, "return_mean": 5.0, "eval_return": 40.0},  # older lines
            {"iter": 3, "env_steps": 24, "wall_s": 3.0, "return_mean": 6.0, "eval_return_mean": 30.0,
             "eval_return_std": 2.5, "eval_length_mean": 1000.0}]
    s = summary(rows, cfg, "finished", None, 0.0)
    assert (s["final_eval_return"], s["final_eval_std"], s["final_eval_iter"], s["best_eval_return"]) == \
        (30.0, 2.5, 3, 40.0)
    s = summary(rows[:2], cfg, "finished", None, 0.0)
    assert (s["final_eval_return"], s["final_eval_std"], s["best_eval_return"]) == (40.0, None, 40.0)
    s = summary(rows[:1], cfg, "finished", None, 0.0)
    assert s["final_eval_return"] is None and s["best_eval_return"] is None


def test_closing_lines_set_the_returns_against_the_floors(tmp_path):
    from ablations.population import closing_lines
    from ablations.reports import load_floors
    from tests.ablations.conftest import write_run

    floors = tmp_path / "floors.json"
    floors.write_text(json.dumps({"tasks": {"hopper": {"zero": {"mean": 50.0}, "random": {"mean": 20.0}}}}))
    run = write_run(tmp_path / "runs", task="hopper", mode="decoupled", seed=0)
    summary = json.loads((run / "summary.json").read_text())
    summary.update(final_eval_return=30.0, final_eval_std=2.0, final_eval_iter=12, wall_s=61.0)
    (run / "summary.json").write_text(json.dumps(summary))
    lines = closing_lines(run, floors=load_floors(floors))
    assert lines[0] == "hopper/decoupled seed 0: finished after 12 iterations (384 environment steps, 61 s of training)"
    assert lines[1].startswith("  training return        120.0  (mean of the last 100 finished training episodes")
    assert lines[2] == "  evaluation return       30.0 +- 2.0  (deterministic policy, at iteration 12)"
    assert lines[3] == f"  floors             zero action 50.0, random action 20.0  ({floors})"
    assert lines[4] == "  the evaluation return is below the zero-action floor and above the random-action floor"
    assert lines[5:] == [f"  run folder         {run.resolve()}",
                         f"  resume             ablate --resume {run.resolve()} --iters N  (to train longer)"]

    summary.update(status="interrupted", error="SIGINT after iteration 12", final_eval_return=None)
    (run / "summary.json").write_text(json.dumps(summary))
    lines = closing_lines(run, floors=load_floors(tmp_path / "floors.json"))
    assert lines[0].endswith("; SIGINT after iteration 12") and lines[-1].endswith(f"ablate --resume {run.resolve()}")
    assert "none yet" in lines[2] and not any("the evaluation return is" in line for line in lines)
    lines = closing_lines(write_run(tmp_path / "runs", task="ant", mode="state", seed=0), floors=load_floors(floors))
    assert "none for ant" in lines[3] and "task-floors --tasks ant" in lines[3]


def test_stop_on_signal_defers_the_first_signal_to_the_end_of_the_iteration(capsys):
    """Real signals to this process: before the loop they stop at once; inside it, the first is a request and
    the second stops at once. Outside ``with`` the previous handlers are back."""
    import signal

    from ablations.stopping import StopOnSignal

    before = signal.getsignal(signal.SIGTERM)
    with StopOnSignal() as stop:
        with pytest.raises(KeyboardInterrupt, match="SIGINT"):
            os.kill(os.getpid(), signal.SIGINT)
        stop.defer_to_iteration_end()
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.requested == "SIGTERM"
        assert "SIGTERM: stopping once this iteration has finished" in capsys.readouterr().err
        with pytest.raises(KeyboardInterrupt, match="SIGINT"):
            os.kill(os.getpid(), signal.SIGINT)
    assert signal.getsignal(signal.SIGTERM) is before


def test_warnings_are_one_plain_line_each_once(capsys):
    import warnings

    from ablations.stopping import plain_warnings
    from diffrender import BinCapacityWarning

    with warnings.catch_warnings(), plain_warnings():
        warnings.simplefilter("always")  # Python would show every one of them
        for _ in range(3):
            warnings.warn("bin capacity grown from 384 to 512", BinCapacityWarning, stacklevel=1)
        warnings.warn("something else", UserWarning, stacklevel=1)
        warnings.warn("bin capacity grown from 384 to 512", BinCapacityWarning, stacklevel=1)
    assert capsys.readouterr().err == "warning: bin capacity grown from 384 to 512\nwarning: something else\n"


@pytest.mark.parametrize("mask", [0o022, 0o027])
def test_run_files_are_readable_as_the_umask_allows(tmp_path, mask):
    import stat

    old = os.umask(mask)
    try:
        ablate("--task", "cartpole", "--mode", "decoupled", "--iters", "2", "--video-every", "2", "--video-steps",
               "3", "--cosine-every", "0", "--out", str(tmp_path), "--name", "m", *TINY)
        from ablations.reports import PlotConfig, plot_runs

        pngs = list(plot_runs(PlotConfig(runs=(tmp_path / "m",), out=tmp_path / "plots")).files.values())
    finally:
        os.umask(old)
    run = tmp_path / "m"
    files = [run / "config.json", run / "summary.json", run / "metrics.jsonl", run / "git.txt",
             run / "checkpoints" / "ckpt_000002.pt", run / "videos" / "iter_000002.mp4", *pngs]
    assert pngs
    for path in files:
        assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~mask, path


def test_a_resume_without_a_checkpoint_is_refused_unless_restart_which_keeps_the_old_metrics(tmp_path, capsys):
    """A run stopped before its first checkpoint (killed, say) recorded iterations a resume cannot continue: the
    resume says so and starts nothing; --restart trains it from the first iteration in the same folder, with the
    old metrics kept beside."""
    common = ["--task", "cartpole", "--mode", "decoupled", "--iters", "3", "--cosine-every", "2",
              "--video-every", "0", "--out", str(tmp_path), *TINY]
    ablate(*common, "--name", "whole")
    ablate(*common, "--name", "cut")
    cut = tmp_path / "cut"
    for p in (cut / "checkpoints").iterdir():
        p.unlink()
    old = json.dumps(read_metrics(cut)[0]) + "\n"
    (cut / "metrics.jsonl").write_text(old)  # killed (SIGKILL) during its second iteration: no summary either
    (cut / "summary.json").unlink()
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        ablate("--resume", str(cut), "--no-progress")
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith(f"error: --resume {cut}: no checkpoint to resume from") and \
        "add --restart" in err and err.count("\n") == 1
    assert (cut / "metrics.jsonl").read_text() == old
    ablate("--resume", str(cut), "--restart", "--no-progress")
    assert strip_timing(read_metrics(cut)) == strip_timing(read_metrics(tmp_path / "whole"))
    kept = list(cut.glob("metrics.jsonl.before-restart-*"))
    assert len(kept) == 1 and kept[0].read_text() == old
    assert f"note: --restart: {cut / 'metrics.jsonl'} kept as {kept[0].name}" in capsys.readouterr().err
    # the restart's own records: the first start's config.json and git.txt kept beside them
    assert len(list(cut.glob("config.json.before-restart-*"))) == 1 and (cut / "config.json").is_file()
    assert len(list(cut.glob("git.txt.before-restart-*"))) == 1 and (cut / "git.txt").is_file()
    # finished: a resume without --iters says so, and how to train it longer
    ablate("--resume", str(cut), "--no-progress")
    assert capsys.readouterr().out == (f"{cut} is finished at iteration 3 (--iters 3): nothing to do; to train it "
                                       f"longer: ablate --resume {cut} --iters M  (M > 3)\n")
    # a flag given to a resume counts, its default value too (--iters 500): here the time budget then stops it
    ablate("--resume", str(cut), "--no-progress", "--iters", "500", "--time-limit-min", "0.0001")
    assert capsys.readouterr().out.startswith(f"{cut} has used its --time-limit-min 0.0001 at iteration 3")


@pytest.mark.parametrize("sig", ["SIGINT", pytest.param("SIGTERM", marks=pytest.mark.slow)])
def test_a_signal_checkpoints_the_last_iteration_and_the_resume_repeats_nothing(tmp_path, sig):
    """A real signal to a child ablate: it finishes its iteration, checkpoints it, marks the summary, prints the
    resume command and exits 130 without a traceback; the resumed run's metrics have every iteration once and
    equal an uninterrupted run's."""
    import signal
    import time

    iters = 40
    common = ["--task", "cartpole", "--mode", "decoupled", "--iters", str(iters), "--cosine-every", "3",
              "--video-every", "0", "--checkpoint-every", "1000", "--out", str(tmp_path), *TINY, "--threads", "1"]
    cut = tmp_path / "cut"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.Popen([sys.executable, "-m", "ablations", "ablate", *common, "--name", "cut"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while len(read_metrics(cut)) < 3 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.send_signal(getattr(signal, sig))
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err and f"{sig}: stopping once this iteration has finished" in err
    summary = json.loads((cut / "summary.json").read_text())
    done = summary["iterations"]
    assert summary["status"] == "interrupted" and summary["error"] == f"{sig} after iteration {done}"
    assert 3 <= done < iters, "the run ended before the signal: give it more iterations"
    assert [r["iter"] for r in read_metrics(cut)] == list(range(1, done + 1))
    assert [p.name for p in (cut / "checkpoints").iterdir()] == [f"ckpt_{done:06d}.pt"]
    assert f"ablate --resume {cut.resolve()}\n" in out and "interrupted after" in out

    ablate("--resume", str(cut), "--no-progress")
    ablate(*common, "--name", "whole")
    rows = read_metrics(cut)
    assert [r["iter"] for r in rows] == list(range(1, iters + 1))
    assert strip_timing(rows) == strip_timing(read_metrics(tmp_path / "whole"))


def start_ablate(*args: str, **popen) -> subprocess.Popen:
    """A child ``python -m ablations ablate`` of this checkout, its output in pipes."""
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    return subprocess.Popen([sys.executable, "-m", "ablations", "ablate", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **popen)


def wait_for_lines(proc: subprocess.Popen, run: Path, n: int, timeout: float = 120) -> None:
    import time

    deadline = time.monotonic() + timeout
    while len(read_metrics(run)) < n and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert proc.poll() is None, "the run ended before the signal: give it more iterations"


@pytest.mark.slow
@pytest.mark.parametrize("second", ["SIGINT", "SIGTERM"])
def test_a_second_signal_stops_at_once_and_the_last_finished_iteration_resumes(tmp_path, second):
    """Two signals to a child ablate once it has written its first metrics line, with --checkpoint-every far
    away: it stops at once, checkpoints its last finished iteration from the copy it holds and says so; the
    resume from there equals a run that went through. SIGINT then SIGTERM are both pending before either is
    handled: the second lands inside the iteration the first let finish. SIGINT twice (Ctrl-C, Ctrl-C): the
    second follows the first's message, wherever the run is then; the outcome is resumable either way."""
    import signal
    import time

    iters = 6
    # a horizon of 8: iterations of a few hundred milliseconds, against the few the run spends between them
    common = ["--task", "cartpole", "--mode", "decoupled", "--iters", str(iters), "--cosine-every", "3",
              "--video-every", "0", "--checkpoint-every", "1000", "--out", str(tmp_path), *TINY[:2], "--horizon", "8",
              *TINY[4:], "--threads", "1"]
    cut = tmp_path / "cut"
    proc = start_ablate(*common, "--name", "cut")
    wait_for_lines(proc, cut, 1)
    time.sleep(0.05)  # past the end of the first iteration's records: into the second iteration
    proc.send_signal(signal.SIGINT)
    if second == "SIGINT":
        err_first = ""
        while "stopping once this iteration" not in err_first and proc.poll() is None:
            err_first += proc.stderr.readline()
        time.sleep(0.005)
    else:
        err_first = ""
    proc.send_signal(getattr(signal, second))
    out, err = proc.communicate(timeout=120)
    err = err_first + err
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err
    summary = json.loads((cut / "summary.json").read_text())
    done = summary["iterations"]
    assert summary["status"] == "interrupted" and 1 <= done < iters and summary["lost"] is None
    assert summary["resumes_from"] == done
    assert [r["iter"] for r in read_metrics(cut)] == list(range(1, done + 1))
    assert [p.name for p in (cut / "checkpoints").iterdir()] == [f"ckpt_{done:06d}.pt"]
    if second == "SIGTERM":
        assert summary["error"] == (f"SIGTERM during iteration {done + 1}: stopped at once, iteration {done + 1} is "
                                    f"lost; resumes from iteration {done}")
    elif "stopped at once" in summary["error"]:
        assert summary["error"].startswith(f"SIGINT during iteration {done + 1}: stopped at once") or \
            summary["error"].startswith(f"SIGINT after iteration {done}: stopped at once")
    else:  # the iteration had ended: the second signal came while the run was writing its records
        assert summary["error"] == f"SIGINT after iteration {done}"
    assert out.rstrip("\n").splitlines()[-1] == f"  resume             ablate --resume {cut.resolve()}"

    ablate("--resume", str(cut), "--no-progress")
    ablate(*common, "--name", "whole")
    rows = read_metrics(cut)
    assert [r["iter"] for r in rows] == list(range(1, iters + 1))
    assert strip_timing(rows) == strip_timing(read_metrics(tmp_path / "whole"))


def test_a_resume_keeps_every_readable_metrics_line_and_names_what_it_could_not(tmp_path, capsys):
    """A damaged line in the middle of metrics.jsonl: the resume keeps every other line (the ones after it too)
    and names the damaged one; a deleted metrics.jsonl is named, and the resume goes on from its checkpoint."""
    common = ["--task", "cartpole", "--mode", "state", "--video-every", "0", "--checkpoint-every", "2",
              "--out", str(tmp_path), "--name", "run", *TINY]
    ablate(*common, "--iters", "4")
    run = tmp_path / "run"
    lines = (run / "metrics.jsonl").read_text().splitlines(keepends=True)
    lines[1] = "{garbage\n"
    (run / "metrics.jsonl").write_text("".join(lines))
    capsys.readouterr()
    ablate("--resume", str(run), "--iters", "5", "--no-progress")
    err = capsys.readouterr().err
    assert [r["iter"] for r in read_metrics(run)] == [1, 3, 4, 5]
    damaged = next(run.glob("metrics.jsonl.damaged-*"))
    assert damaged.read_text() == "{garbage\n"
    assert f"warning: {run / 'metrics.jsonl'} line 2 is damaged (not a JSON record: '{{garbage'); moved to " \
           f"{damaged.name}\n" in err
    assert f"warning: {run / 'metrics.jsonl'} has no line for iteration(s) 2 (plots and reports" in err

    (run / "metrics.jsonl").unlink()
    ablate("--resume", str(run), "--iters", "6", "--no-progress")
    err = capsys.readouterr().err
    assert f"warning: {run / 'metrics.jsonl'} is missing: iterations 1..5 have no metrics" in err
    assert [r["iter"] for r in read_metrics(run)] == [6]


def test_out_of_memory_on_the_cpu_is_one_error_line_and_a_final_status(tmp_path):
    """A real allocation that fails: the child's address space is limited (as a batch system's memory limit
    does), so that the first large tensor of --num-envs 50000 cannot be had; no traceback, one error line,
    summary.json says oom."""
    import resource

    limit = 5 * 2**30

    def limited() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    proc = start_ablate("--task", "cartpole", "--num-envs", "50000", "--iters", "3", "--device", "cpu",
                        "--threads", "1", "--no-progress", "--out", str(tmp_path), "--name", "oom",
                        preexec_fn=limited)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 1, err[-3000:]
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("error: out of memory on the CPU during iteration 1 (an allocation of "), err
    assert last.endswith("; no iteration finished, nothing to resume")
    summary = json.loads((tmp_path / "oom" / "summary.json").read_text())
    assert summary["status"] == "oom" and summary["error"] == last.removeprefix("error: ")


def test_a_run_stopped_by_an_error_records_it_and_says_what_it_keeps(tmp_path, capsys):
    """An error inside an iteration (here the abort guard): summary.json ends in its final status, and the last
    line says what the run folder keeps."""
    with pytest.raises(SystemExit) as e:
        ablate("--task", "cartpole", "--mode", "state", "--iters", "3", "--abort-grad-norm", "1e-12",
               "--video-every", "0", "--out", str(tmp_path), "--name", "run", *TINY)
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "abort_grad_norm" in err[0], err
    assert err[0].startswith("error: ") and err[0].endswith("; no iteration finished, nothing to resume")
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["status"] == "nonfinite" and summary["error"] == err[0].removeprefix("error: ")


def test_ctrl_c_while_starting_is_one_line_and_exit_130(tmp_path):
    """SIGINT while ablate is still importing (torch takes seconds): a short line, no traceback, nothing
    written."""
    import signal
    import time

    proc = start_ablate("--task", "cartpole", "--iters", "3", "--device", "cpu", "--no-progress",
                        "--out", str(tmp_path / "runs"))
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "nothing was written" in err and not (tmp_path / "runs").exists()


def test_python_m_ablations_runs_every_ablations_console_script(tmp_path):
    """``python -m ablations X`` is the console script ``ablate-X`` (``ablate`` for ablate), same function."""
    import tomllib

    from ablations.__main__ import COMMANDS

    scripts = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())["project"]["scripts"]
    ours = {name.removeprefix("ablate-") if name != "ablate" else name: target for name, target in scripts.items()
            if target.startswith("ablations.")}
    assert COMMANDS == ours
    r = subprocess.run([sys.executable, "-m", "ablations", "sweep", "--dry-run", "--modes", "state", "--set",
                        "iters=2", "--out", str(tmp_path / "sweep")], capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2])))
    assert r.returncode == 0 and "start    cartpole_state_seed0: ablate" in r.stdout, r.stderr[-2000:]
