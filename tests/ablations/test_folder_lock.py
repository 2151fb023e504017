"""One process a folder: a run folder, a population folder (and each member's) and a sweep's --out are locked by
the process that trains into them; a second one refuses in one line naming the holder, and readers say when a
metrics.jsonl shows that two processes wrote it."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from ablations.folder_lock import LOCK, FolderBusy, FolderLock
from ablations.run_folder import find_runs, metrics_notes, say_metrics_notes
from tests.ablations.conftest import write_run

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def holder():
    """Start another process that holds the lock of a folder until it is killed: ``hold(folder) -> Popen``."""
    procs = []

    def hold(folder: Path) -> subprocess.Popen:
        code = ("import sys, time\nfrom ablations.folder_lock import FolderLock\n"
                "lock = FolderLock(sys.argv[1]).acquire()\nprint('held', flush=True)\ntime.sleep(120)\n")
        proc = subprocess.Popen([sys.executable, "-c", code, str(folder)], stdout=subprocess.PIPE, text=True,
                                env=dict(os.environ, PYTHONPATH=str(ROOT)))
        procs.append(proc)
        assert proc.stdout.readline().strip() == "held"
        return proc

    yield hold
    for proc in procs:
        proc.kill()
        proc.wait()


def test_a_second_process_is_refused_naming_the_holder_and_a_dead_holder_frees_the_folder(tmp_path, holder):
    proc = holder(tmp_path)
    with pytest.raises(FolderBusy) as e:
        FolderLock(tmp_path).acquire("run folder")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"run folder {tmp_path} is in use by another process (pid {proc.pid} ")
    proc.send_signal(signal.SIGKILL)  # the kernel releases a dead holder's lock: nothing to clear by hand
    proc.wait()
    with FolderLock(tmp_path) as lock:
        assert f"pid {os.getpid()} " in (tmp_path / LOCK).read_text() and lock.held
    assert not (tmp_path / LOCK).exists()  # released: removed, so an empty folder is empty again
    tmp_path.rmdir()


def test_a_resume_of_a_folder_in_use_is_refused_before_anything_in_it_changes(tmp_path, holder):
    """prepare locks the run folder before it reads or renames anything in it (a damaged checkpoint stays)."""
    from ablations.population import prepare
    from ablations.run_config import RunConfig
    from gradlab.checkpoint import atomic_write_json, checkpoint_path

    run = tmp_path / "run"
    atomic_write_json(run / "config.json",
                      {"config": dataclasses.asdict(RunConfig(task="cartpole", device="cpu", out=tmp_path))})
    checkpoint_path(run / "checkpoints", 2).parent.mkdir()
    checkpoint_path(run / "checkpoints", 2).write_bytes(b"damaged")
    proc = holder(run)
    with pytest.raises(ValueError, match=rf"--resume {run}: run folder {run} is in use by another process "
                                         rf"\(pid {proc.pid} "):
        prepare(RunConfig(resume=run, progress=False))
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["ckpt_000002.pt"]


def test_a_population_is_locked_through_any_of_its_folders(tmp_path, holder):
    """A member's folder held by another process refuses a resume of the population folder, and the population
    folder held refuses a resume of a member's folder; a fresh population's folders are locked until released."""
    from ablations.population import prepare
    from ablations.run_config import RunConfig

    members = [RunConfig(task="cartpole", mode="decoupled", seed=s, device="cpu", out=tmp_path, name="pop",
                         progress=False) for s in (0, 1)]
    prepared = prepare(members)
    home, member = prepared.home, prepared.folders[1].path
    assert {p.name for p in home.iterdir()} >= {LOCK, "population.json"} and (member / LOCK).exists()
    with pytest.raises(FolderBusy, match=f"population folder {home} is in use"):
        FolderLock(home).acquire("population folder")
    prepared.release()
    for f in prepared.folders:  # what the population's cleanup does when nothing was recorded
        f.remove_if_empty()
    assert not any(f.path.exists() for f in prepared.folders)
    for i, f in enumerate(prepared.folders):  # now as a resumable population
        f.path.mkdir()
        f.write_config({"config": dataclasses.asdict(prepared.cfgs[i]),
                        "population": {"folder": home.name, "members": [g.path.name for g in prepared.folders],
                                       "index": i}})
    proc = holder(member)
    with pytest.raises(ValueError, match=rf"run folder {member} is in use by another process \(pid {proc.pid} "):
        prepare(RunConfig(resume=home, progress=False))
    proc.kill()
    proc.wait()
    holder(home)
    with pytest.raises(ValueError, match=f"population folder {home} is in use"):
        prepare(RunConfig(resume=member, progress=False))


def test_a_second_sweep_driver_on_one_out_is_refused(tmp_path, holder, capsys):
    from ablations.sweep import main

    out = tmp_path / "s"
    out.mkdir()
    proc = holder(out)
    with pytest.raises(SystemExit) as e:
        main(["--out", str(out), "--modes", "state", "--seeds", "0", "--set", "iters=2", "--no-progress"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: sweep folder {out} is in use by another process (pid {proc.pid} ")
    assert "\n" not in err and not (out / "sweep.json").exists()


def test_readers_say_when_lines_are_damaged_repeated_or_out_of_order(tmp_path, capsys):
    run = write_run(tmp_path, task="cartpole", mode="decoupled", seed=0, iters=4)
    assert metrics_notes(run) == []
    lines = (run / "metrics.jsonl").read_text().splitlines(keepends=True)
    # what two processes training into one folder leave: 1, 2, 3, 4, 3, 4, and a line cut in the middle
    (run / "metrics.jsonl").write_text("".join(lines + lines[2:3] + ['{"iter": 4, "ret\n'] + lines[3:]))
    notes = metrics_notes(run)
    assert len(notes) == 3, notes
    assert notes[0] == f"warning: {run / 'metrics.jsonl'}: line(s) 6 damaged (not a JSON record), skipped"
    assert "iteration(s) 3..4 appear more than once" in notes[1]
    assert "out of order (iteration 3 after a later one)" in notes[2]
    say_metrics_notes(find_runs([tmp_path]))
    assert capsys.readouterr().err.splitlines() == notes


@pytest.mark.parametrize("command", ["plot", pytest.param("report", marks=pytest.mark.slow)])
def test_ablate_plot_and_report_print_the_notes_once(tmp_path, capsys, command):
    from ablations.cli import plot_main, report_main

    run = write_run(tmp_path / "runs", task="cartpole", mode="decoupled", seed=0, iters=4)
    text = (run / "metrics.jsonl").read_text()
    (run / "metrics.jsonl").write_text(text + text.splitlines(keepends=True)[1])
    if command == "plot":
        plot_main([str(tmp_path / "runs"), "--out", str(tmp_path / "figs")])
    else:
        report_main([str(tmp_path / "runs"), "--out", str(tmp_path / "rep" / "report.md"), "--reps", "10"])
    err = capsys.readouterr().err
    assert err.count("iteration(s) 2 appear more than once") == 1, err
    assert json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])["iter"] == 2  # readers change nothing
