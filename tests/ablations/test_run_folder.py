"""The run folder: one module writes, lists and reads it; reading imports no torch."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from ablations.run_folder import (
    MetricsTail,
    RunFolder,
    evaluation_of,
    find_runs,
    load_run,
    read_metrics,
)
from ablations.run_records import environment_info
from tests.ablations.conftest import write_run

ROOT = Path(__file__).resolve().parents[2]


def test_reading_run_folders_and_their_statistics_imports_no_torch(tmp_path):
    """ablations.reports.stats reads run folders through this module and must stay usable without torch."""
    for seed in (0, 1):
        write_run(tmp_path, task="hopper", mode="decoupled", seed=seed)
    code = ("import sys\nfrom ablations.run_folder import find_runs\nimport ablations.reports.stats as stats\n"
            f"runs = find_runs([{str(tmp_path)!r}])\n"
            f"curves = stats.load_arms({{'decoupled': [{str(tmp_path)!r}]}})\n"
            "assert len(runs) == 2 and len(curves) == 2\n"
            "print(sorted(m for m in ('torch', 'gradlab.shac') if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]"


def test_create_refuses_a_folder_with_files_and_existing_needs_a_config(tmp_path):
    folder = RunFolder.create(tmp_path / "runs", "a")
    assert folder.path.is_dir()
    RunFolder.create(tmp_path / "runs", "a")  # empty: still fine
    folder.write_config({"config": {"task": "cartpole", "mode": "state"}})
    with pytest.raises(ValueError, match="exists and is not empty: pass --resume"):
        RunFolder.create(tmp_path / "runs", "a")
    assert RunFolder.existing(folder.path).path == folder.path
    with pytest.raises(ValueError, match=r"no config\.json there"):
        RunFolder.existing(tmp_path)
    empty = RunFolder.create(tmp_path / "runs", "b")
    empty.remove_if_empty()
    folder.remove_if_empty()
    assert not empty.path.exists() and folder.path.exists()


def test_a_resume_keeps_every_readable_metrics_line_and_sets_the_rest_aside_named(tmp_path):
    """settle_metrics (what --resume does to metrics.jsonl): lines up to the checkpoint stay as written, a damaged
    line in the middle and the lines after the checkpoint go to files beside it, each named in one line; only a
    torn last line is dropped (said too); a missing file and iterations without a line are named."""
    folder = RunFolder.create(tmp_path, "r")
    for it in (1, 2, 3, 4, 5):
        folder.append_metrics({"iter": it, "return_mean": float(it)})
    text = folder.metrics_path.read_text().splitlines(keepends=True)
    text[1] = '{"iter": 2, "ret\x00\x00\n'  # damaged in place (a disk fault)
    folder.metrics_path.write_text("".join(text) + '{"iter": 6, "ret')  # and a run killed mid-write
    # readers keep every readable line, the ones after the damaged one included
    assert [r["iter"] for r in read_metrics(folder.path)] == [1, 3, 4, 5]
    notes = folder.settle_metrics(4)
    assert [r["iter"] for r in read_metrics(folder.path)] == [1, 3, 4]
    assert folder.metrics_path.read_text() == "".join(text[i] for i in (0, 2, 3))
    damaged = next(tmp_path.glob("r/metrics.jsonl.damaged-*"))
    redone = next(tmp_path.glob("r/metrics.jsonl.redone-*"))
    assert damaged.read_text() == text[1] and redone.read_text() == text[4]
    assert len(notes) == 4, notes
    assert notes[0].startswith(f"warning: {folder.metrics_path} line 2 is damaged") and damaged.name in notes[0]
    assert "iteration(s) 5 come after the checkpoint of iteration 4" in notes[1] and redone.name in notes[1]
    assert "last line was cut off mid-write" in notes[2] and "dropped" in notes[2]
    assert notes[3].endswith("has no line for iteration(s) 2 (plots and reports of this run show a gap there)")
    assert folder.settle_metrics(4) == [notes[3]]  # settled: nothing more to move
    folder.metrics_path.unlink()
    assert folder.settle_metrics(4) == [f"warning: {folder.metrics_path} is missing: iterations 1..4 have no "
                                        f"metrics (plots and reports of this run start at iteration 5)"]
    assert RunFolder(tmp_path / "none").read_metrics() == []


def test_a_damaged_line_that_is_not_utf8_is_set_aside_byte_for_byte(tmp_path):
    """Bytes that are not UTF-8 make a line damaged (decoded strictly), and its .damaged-* copy holds them as they
    were on disk (no U+FFFD in their place); the kept lines stay byte-identical."""
    folder = RunFolder.create(tmp_path, "r")
    for it in (1, 2, 3):
        folder.append_metrics({"iter": it, "return_mean": float(it)})
    lines = folder.metrics_path.read_bytes().splitlines(keepends=True)
    bad = b'{"iter": 2, "return_mean": \xff\xfe\x00\x9c}\n'
    folder.metrics_path.write_bytes(lines[0] + bad + lines[2])
    assert [r["iter"] for r in read_metrics(folder.path)] == [1, 3]
    notes = folder.settle_metrics(3)
    damaged = next(tmp_path.glob("r/metrics.jsonl.damaged-*"))
    assert damaged.read_bytes() == bad
    assert folder.metrics_path.read_bytes() == lines[0] + lines[2]
    assert "line 2 is damaged" in notes[0] and "xff" in notes[0], notes


def test_a_restart_keeps_the_old_records_beside(tmp_path):
    folder = RunFolder.create(tmp_path, "r")
    folder.append_metrics({"iter": 1})
    folder.write_summary({"status": "interrupted"})
    folder.write_video(1, [np.zeros((8, 8, 3), np.uint8)])
    notes = folder.set_aside_for_restart()
    assert len(notes) == 3 and not folder.metrics_path.exists() and not folder.summary_path.exists()
    assert sorted(p.name.split(".before-restart-")[0] for p in folder.path.glob("*.before-restart-*")) == \
        ["metrics.jsonl", "summary.json", "videos"]


def test_a_second_damaged_copy_of_a_checkpoint_is_set_aside_beside_the_first(tmp_path, capsys):
    # a run resumed twice from a rewritten, again damaged checkpoint of one iteration keeps both damaged files
    folder = RunFolder.create(tmp_path, "r")
    for it in (2, 4):
        folder.save_checkpoint(it, {"iteration": it})
    for _ in range(2):
        folder.newest_checkpoint().write_bytes(b"not a checkpoint")
        assert folder.load_checkpoint().state == {"iteration": 2}
        folder.save_checkpoint(4, {"iteration": 4})
    assert capsys.readouterr().err.count("ckpt_000004.pt is damaged") == 2
    assert sorted(p.name for p in folder.checkpoint_dir.iterdir()) == [
        "ckpt_000002.pt", "ckpt_000004.pt", "ckpt_000004.pt.damaged", "ckpt_000004.pt.damaged-2"]


def test_checkpoints_are_pruned_listed_and_a_damaged_newest_is_set_aside(tmp_path, capsys):
    folder = RunFolder.create(tmp_path, "r")
    assert folder.load_checkpoint() is None  # none at all: a resume starts from the first iteration
    for it in (2, 4, 6):
        folder.save_checkpoint(it, {"iteration": it})
        folder.prune_checkpoints(2)
    assert [p.name for p in folder.checkpoints()] == ["ckpt_000006.pt", "ckpt_000004.pt"]
    folder.newest_checkpoint().write_bytes(b"not a checkpoint")
    loaded = folder.load_checkpoint()
    assert loaded.state == {"iteration": 4}
    assert "ckpt_000006.pt is damaged" in capsys.readouterr().err
    assert sorted(p.name for p in folder.checkpoint_dir.iterdir()) == ["ckpt_000004.pt", "ckpt_000006.pt.damaged"]
    folder.newest_checkpoint().write_bytes(b"")
    with pytest.raises(ValueError, match="no readable checkpoint"):
        folder.load_checkpoint()
    folder.drop_checkpoints()
    assert folder.newest_checkpoint() is None


def test_summary_and_videos(tmp_path):
    folder = RunFolder.create(tmp_path, "r")
    assert folder.read_summary() is None
    folder.summary_path.write_text("{torn")
    assert folder.read_summary() is None
    folder.write_summary({"status": "finished"})
    assert folder.read_summary() == {"status": "finished"}
    frames = [np.full((16, 16, 3), i * 40, np.uint8) for i in range(4)]
    assert folder.write_video(3, []) is None
    path = folder.write_video(3, frames)
    assert path == folder.video_dir / "iter_000003.mp4" and path.stat().st_size > 0
    assert folder.videos() == [path] and not list(folder.video_dir.glob(".*"))


def test_the_evaluation_return_of_a_line_in_either_form():
    assert evaluation_of({"eval_return_mean": 5.0, "eval_return_std": 1.5, "eval_return": 9.0}) == (5.0, 1.5)
    mean, std = evaluation_of({"eval_return": 7.0, "eval_return_std": 2.0})  # older lines: no spread
    assert mean == 7.0 and math.isnan(std)
    assert evaluation_of({"return_mean": 3.0}) is None and evaluation_of({"eval_return_mean": None}) is None
    assert evaluation_of({"eval_return_mean": float("nan")}) is None


def test_load_run_parses_a_folder_and_find_runs_takes_parents(tmp_path):
    run = write_run(tmp_path / "runs", task="ant", mode="full", seed=3, settings={"raster_model": "alpha"})
    loaded = load_run(run)
    assert (loaded.task, loaded.mode, loaded.seed, loaded.setting("raster_model")) == ("ant", "full", 3, "alpha")
    assert loaded.summary["status"] == "finished" and len(loaded.metrics) == 12
    x, y = loaded.series("iter", "return_mean")
    assert list(x) == list(range(3, 13)) and list(y) == [10.0 * i + 3 for i in range(3, 13)]
    assert [r.path for r in find_runs([tmp_path / "runs"])] == [run]
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "config.json").write_text("[1]")
    with pytest.raises(ValueError, match="has no 'config' object"):
        load_run(tmp_path / "bad")


def test_find_runs_takes_an_experiment_folder_of_populations_at_any_depth(tmp_path):
    # docs/<experiment>/runs/<population>/<member>: one path stands for every member of every population
    a = write_run(tmp_path / "exp" / "ant_b", task="ant", mode="full", seed=1)
    b = write_run(tmp_path / "exp" / "ant_a", task="ant", mode="decoupled", seed=0)
    c = write_run(tmp_path / "exp" / "deeper" / "hopper", task="hopper", mode="blind", seed=2)
    (a / "videos").mkdir()  # a run's own subfolders are not searched for runs
    write_run(a / "videos", task="ant", mode="blind", seed=9)
    assert [r.path for r in find_runs([tmp_path / "exp"])] == [b, a, c]
    (tmp_path / "empty" / "sub").mkdir(parents=True)
    with pytest.raises(ValueError):
        find_runs([tmp_path / "empty"])


def test_metrics_lines_reach_the_disk_before_the_checkpoint_or_summary_that_covers_them(tmp_path, monkeypatch):
    """Lines are forced to the disk once, before the checkpoint (a resume truncates the metrics to it) or the
    summary that covers them, not one fsync a line and a member; a killed process still loses none (each line is
    handed to the operating system at once)."""
    folder = RunFolder.create(tmp_path, "r")
    synced = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(os.readlink(f"/proc/self/fd/{fd}")), real_fsync(fd)))
    for it in (1, 2):
        folder.append_metrics({"iter": it})
    assert synced == []
    assert [r["iter"] for r in read_metrics(folder.path)] == [1, 2]  # what another process reads now
    folder.save_checkpoint(2, {"x": 1})
    assert synced[0] == str(folder.metrics_path)
    synced.clear()
    folder.write_summary({"status": "finished"})
    assert synced[0] == str(folder.metrics_path)


def test_metrics_tail_reads_only_what_was_appended(tmp_path):
    folder = RunFolder.create(tmp_path, "r")
    tail = MetricsTail(folder.metrics_path)
    assert tail.poll() is None
    folder.append_metrics({"iter": 1})
    with open(folder.metrics_path, "a") as f:
        f.write('{"iter": 2')
    assert tail.poll() == {"iter": 1}
    with open(folder.metrics_path, "a") as f:
        f.write("}\n")
    assert tail.poll() == {"iter": 2}
    folder.settle_metrics(1)  # a resume rewrites the file
    assert tail.poll() == {"iter": 1}


def test_environment_records_package_versions_from_their_metadata():
    """pytorch_kinematics has no __version__; its installed distribution has one."""
    import torch

    env = environment_info(torch.device("cpu"))
    assert env["pytorch_kinematics"] == metadata.version("pytorch-kinematics") != "unknown"
    assert env["mujoco"] == metadata.version("mujoco")
    assert env["packages"]["torch"] == metadata.version("torch") and env["threads"] == torch.get_num_threads()
    json.dumps(env)  # it goes into config.json


def test_a_thin_copy_keeps_the_records_every_kth_iteration_probes_and_evaluations(tmp_path):
    from ablations.run_folder import RunFolder, load_run, thin_copy

    src = RunFolder.create(tmp_path, "run")
    src.write_config({"config": {"task": "hopper", "mode": "full", "seed": 1}})
    for it in range(1, 34):
        row = {"iter": it, "probed": it % 7 == 0}
        if it == 25:
            row.update(eval_return_mean=100.0, eval_return_std=1.0)
        src.append_metrics(row)
    src.save_checkpoint(30, {"x": 1})
    thin = thin_copy(src.path, tmp_path / "thin" / "run", every=10)
    assert [r["iter"] for r in thin.read_metrics()] == [7, 10, 14, 20, 21, 25, 28, 30, 33]  # 33: the last
    assert not thin.checkpoint_dir.exists() and load_run(thin.path).config["mode"] == "full"


def test_a_copy_of_the_tree_without_its_repository_records_the_commit_it_is_named(tmp_path, monkeypatch):
    """git.txt of a run started from a copy of the tree with no repository (a GPU machine's detached runs): the
    commit $PIXELGRAD_COMMIT names, and why it is named; without the variable, that git is unavailable."""
    from ablations.run_records import git_info

    monkeypatch.delenv("PIXELGRAD_COMMIT", raising=False)
    text, diff = git_info(tmp_path)
    assert text.startswith("git information unavailable") and diff == ""
    monkeypatch.setenv("PIXELGRAD_COMMIT", "46ae056")
    text, diff = git_info(tmp_path)
    assert text.startswith("commit 46ae056\nnamed by $PIXELGRAD_COMMIT") and diff == ""
    text, _ = git_info()  # this checkout is a repository: git's own answer wins
    assert text.startswith("commit ") and "named by" not in text


def test_what_two_resumes_in_one_second_set_aside_is_kept_twice(tmp_path, monkeypatch):
    """Two resumes within one second that each set lines aside (trained again after the checkpoint): the second
    file gets -2, the first is not overwritten."""
    import ablations.run_folder as rf

    monkeypatch.setattr(rf, "_stamp", lambda: "20261128T184500Z")
    folder = RunFolder(tmp_path / "run")
    folder.path.mkdir()
    for upto, lines in ((1, [1, 2, 3]), (1, [1, 2])):
        folder.metrics_path.write_text("".join(json.dumps({"iter": i, "return_mean": float(i)}) + "\n" for i in lines))
        folder.settle_metrics(upto)
    first, second = tmp_path / "run" / "metrics.jsonl.redone-20261128T184500Z", \
        tmp_path / "run" / "metrics.jsonl.redone-20261128T184500Z-2"
    assert [json.loads(x)["iter"] for x in first.read_text().splitlines()] == [2, 3]
    assert [json.loads(x)["iter"] for x in second.read_text().splitlines()] == [2]
