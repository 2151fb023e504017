"""``task-floors`` and ``robot-snapshots``: tyro configs whose docstrings are the --help, one-line errors that name
the flag (before anything is written), and a tiny real run of each."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

import tasks
from tasks import floors, snapshots

FLOORS_FLAGS = ("--tasks", "--episodes", "--num-envs", "--seed", "--device", "--out", "--fresh", "--threads",
                "--no-progress")
SNAPSHOTS_FLAGS = ("--out", "--tasks", "--poses", "--size", "--steps-between", "--seed")


@pytest.mark.parametrize("main, flags", [(floors.main, FLOORS_FLAGS), (snapshots.main, SNAPSHOTS_FLAGS)])
def test_help_lists_every_flag(main, flags, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for flag in flags:
        assert flag in out, flag


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    return err


@pytest.mark.parametrize("main, out_name, argv, message", [
    (floors.main, "f.json", ["--episodes", "0"], "--episodes must be >= 1, got 0"),
    (floors.main, "f.json", ["--num-envs", "-2"], "--num-envs must be >= 1, got -2"),
    (floors.main, "f.json", ["--threads", "0"], "--threads must be >= 1, got 0"),
    (floors.main, "f.json", ["--tasks", "walker", "hopper"], "--tasks: unknown task(s) ['walker']"),
    (floors.main, "f.json", ["--tasks"], "--tasks: unknown task(s) (none given)"),
    (floors.main, "f.json", ["--device", "tpu"], "--device: unknown device 'tpu'"),
    (snapshots.main, "robots", ["--poses", "0"], "--poses must be >= 1, got 0"),
    (snapshots.main, "robots", ["--size", "8"], "--size must be >= 16, got 8"),
    (snapshots.main, "robots", ["--steps-between", "-1"], "--steps-between must be >= 0, got -1"),
    (snapshots.main, "robots", ["--tasks", "walker"], "--tasks: unknown task(s) ['walker']"),
])
def test_bad_flags_are_one_line_errors_before_any_output(main, out_name, argv, message, tmp_path, capsys):
    out = tmp_path / out_name
    with pytest.raises(SystemExit) as e:
        main([*argv, "--out", str(out)])
    assert e.value.code == 2 and message in _one_line_error(capsys)
    assert not out.exists()


def test_floors_out_must_be_a_readable_json_file(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        floors.main(["--out", str(tmp_path)])
    assert e.value.code == 2 and f"--out {tmp_path} is a folder" in _one_line_error(capsys)
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    with pytest.raises(SystemExit) as e:
        floors.main(["--tasks", "cartpole", "--device", "cpu", "--out", str(bad)])
    assert e.value.code == 2 and "--out" in _one_line_error(capsys) and bad.read_text() == "{"


@pytest.mark.skipif(torch.cuda.is_available(), reason="asks for CUDA where there is none")
def test_floors_cuda_without_cuda_names_the_flag(capsys):
    with pytest.raises(SystemExit):
        floors.main(["--device", "cuda", "--tasks", "cartpole"])
    assert "--device" in _one_line_error(capsys)


def test_floors_tiny_run_writes_what_action_floors_measures(tmp_path, capsys, monkeypatch):
    # 8-step episodes: the command is under test here, the physics in test_fidelity.py
    monkeypatch.setattr(floors, "make", lambda name, n, **kw: tasks.make(name, n, **kw, episode_length=8))
    out = tmp_path / "f.json"
    old_umask = os.umask(0o022)
    try:
        assert floors.main(["--tasks", "cartpole", "--episodes", "1", "--num-envs", "1", "--device", "cpu",
                            "--no-progress", "--out", str(out)]) == 0
    finally:
        os.umask(old_umask)
    printed = capsys.readouterr().out
    entry = json.loads(out.read_text())["tasks"]["cartpole"]
    assert entry == floors.action_floors("cartpole", episodes=1, num_envs=1, seed=0, device="cpu")
    assert entry["episode_length"] == 8
    assert "cartpole" in printed and printed.rstrip().endswith(f"wrote {out}")
    assert (out.stat().st_mode & 0o777) == 0o644  # readable by others, as the umask allows


def test_snapshots_out_must_be_a_folder(tmp_path, capsys):
    (tmp_path / "file").write_text("")
    with pytest.raises(SystemExit) as e:
        snapshots.main(["--out", str(tmp_path / "file")])
    assert e.value.code == 2 and f"--out {tmp_path / 'file'} is a file" in _one_line_error(capsys)


def test_snapshots_tiny_run_writes_the_strip(tmp_path, capsys):
    from PIL import Image

    out = tmp_path / "robots"
    snapshots.main(["--tasks", "cartpole", "--poses", "2", "--size", "16", "--steps-between", "1", "--out", str(out)])
    assert capsys.readouterr().out.split() == [str(out / "cartpole.png")]
    saved = Image.open(out / "cartpole.png")
    assert saved.mode == "P"  # a palette PNG, as the shipped pictures are
    image = np.asarray(saved.convert("RGB"))
    expected = snapshots.snapshot("cartpole", poses=2, size=16, steps_between=1, seed=0)
    assert image.shape == (16, 32, 3)
    assert len(np.unique(expected.reshape(-1, 3), axis=0)) <= 256
    np.testing.assert_array_equal(image, expected)  # at most 256 colours: the palette keeps them exactly
    assert [p.name for p in out.iterdir()] == ["cartpole.png"]  # no temporary file left
    assert set(tasks.TASKS) == set(snapshots.SnapshotsConfig().tasks)


def test_the_readmes_floors_command_leaves_the_shipped_file_alone(tmp_path, capsys, monkeypatch):
    """The README's ``task-floors --tasks cartpole hopper ant``, run in a checkout whose shipped floors file is
    read-only, writes ./floors.json and leaves the shipped one as it was; updating it is naming it."""
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    assert "task-floors --tasks cartpole hopper ant " in readme
    monkeypatch.setattr(floors, "make", lambda name, n, **kw: tasks.make(name, n, **kw, episode_length=4))
    real = floors.SHIPPED
    real_shipped = real.read_bytes()
    shipped = tmp_path / "docs" / "floors.json"
    shipped.parent.mkdir()
    shipped.write_bytes(real_shipped)
    shipped.chmod(0o444)
    monkeypatch.setattr(floors, "SHIPPED", shipped)
    monkeypatch.chdir(tmp_path)
    try:
        assert floors.main(["--tasks", "cartpole", "hopper", "ant", "--no-progress"]) == 0
        assert capsys.readouterr().out.rstrip().endswith("wrote floors.json")
        assert set(json.loads((tmp_path / "floors.json").read_text())["tasks"]) == {"cartpole", "hopper", "ant"}
        assert shipped.read_bytes() == real_shipped and (shipped.stat().st_mode & 0o777) == 0o444
        # from the shipped file's own folder, the default would be the shipped file: refused, not written
        monkeypatch.chdir(shipped.parent)
        with pytest.raises(SystemExit) as e:
            floors.main(["--tasks", "cartpole", "--no-progress"])
        assert e.value.code == 2 and "is the shipped" in _one_line_error(capsys)
        assert shipped.read_bytes() == real_shipped
        # named, it is updated: a choice made on the command line
        assert floors.main(["--tasks", "cartpole", "--no-progress", "--out", str(shipped)]) == 0
        assert json.loads(shipped.read_text())["tasks"]["cartpole"]["episode_length"] == 4
    finally:
        shipped.chmod(0o644)
    assert real.read_bytes() == real_shipped


@pytest.mark.parametrize(("main", "argv", "message"), [
    (floors.main, ["--episodes", "1.5"], "--episodes must be an integer, got '1.5'"),
    (floors.main, ["--threads", "3"], "--threads 3 is more than the 2 cores"),
    (floors.main, ["--tasks", "cartpole", "--tasks", "ant"], "--tasks is given twice"),
    (snapshots.main, ["--size", "big"], "--size must be an integer, got 'big'"),
])
def test_bad_values_are_one_line_not_a_box(main, argv, message, capsys, monkeypatch, tmp_path):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    with pytest.raises(SystemExit) as e:
        main([*argv, "--out", str(tmp_path / "out")])
    assert e.value.code == 2 and message in _one_line_error(capsys)
    assert not (tmp_path / "out").exists()
