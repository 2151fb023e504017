"""The ``ablate`` command: smoke runs of every mode, run-folder contents, resume, determinism, bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ablations.cli import ablate_main
from ablations.runs import PROBE_KEYS, REQUIRED_KEYS, TIMING_KEYS, read_metrics

TINY = ["--num-envs", "2", "--horizon", "3", "--image-size", "24", "--critic-iterations", "1",
        "--critic-batches", "1", "--device", "cpu", "--no-progress"]


def ablate(*args: str) -> None:
    ablate_main(list(args))


def strip_timing(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIMING_KEYS} for r in rows]


@pytest.mark.parametrize("task", ["cartpole", "ant"])
@pytest.mark.parametrize("mode", ["full", "decoupled", "state"])
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
    if mode == "state":
        assert not probed
    else:
        assert len(probed) == 1 and set(PROBE_KEYS) <= set(probed[0])
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["config"]["task"] == task and cfg["config"]["mode"] == mode
    assert cfg["config"]["critic_lr"] == {"cartpole": 2e-4, "ant": 2e-3}[task]  # task default resolved
    assert (run / "git.txt").read_text().startswith(("commit ", "git information unavailable"))
    summary = json.loads((run / "summary.json").read_text())
    assert summary["status"] == "finished" and summary["iterations"] == 2
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


def run_cli(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    return subprocess.run([sys.executable, "-c", "from ablations.cli import ablate_main; ablate_main()", *args],
                          capture_output=True, text=True, env=env, timeout=120)


@pytest.mark.parametrize(("args", "message"), [
    (["--task", "cartpol"], "unknown task 'cartpol'; valid tasks: cartpole, hopper, ant, humanoid"),
    (["--mode", "ful"], "full"),  # tyro lists the valid choices
    (["--num-envs", "0"], "num_envs must be a positive integer"),
    (["--horizon", "-2"], "horizon must be a positive integer"),
    (["--iters", "0"], "iters must be a positive integer"),
    (["--device", "tpu"], "unknown device 'tpu'"),
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
