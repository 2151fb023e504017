"""What ablate says when a run ends or cannot start: an out-of-memory hint that names every setting that cuts
memory and how to apply one, a nonexistent --resume folder named as such, and no "--restart:" note unasked."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from ablations.stopping import describe_error


@pytest.mark.parametrize("error, device", [
    (torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB"), "cuda"),
    (MemoryError(), "cpu"),
])
def test_the_out_of_memory_hint_names_the_settings_that_cut_memory_and_that_resume_keeps_them(error, device):
    status, line = describe_error(error, device, "during iteration 3")
    assert status == "oom" and "\n" not in line
    for flag in ("--num-envs", "--eval-envs", "--image-size", "--horizon"):
        assert flag in line, line
    assert "--resume keeps a run's settings, so start a new run with them" in line


def test_a_nonexistent_resume_folder_is_named_as_nonexistent(tmp_path):
    from ablations.population import prepare
    from ablations.run_config import RunConfig

    with pytest.raises(ValueError, match=f"--resume {tmp_path / 'nope'}: {tmp_path / 'nope'}: no such folder"):
        prepare(RunConfig(resume=tmp_path / "nope", progress=False))
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="is a file, not a run folder"):
        prepare(RunConfig(resume=tmp_path / "file", progress=False))
    with pytest.raises(ValueError, match=r"no config\.json there \(not a run folder\)"):
        prepare(RunConfig(resume=tmp_path, progress=False))


@pytest.mark.slow
def test_a_resume_of_a_folder_that_trained_nothing_prints_no_restart_note(tmp_path, capsys):
    """A run stopped before its first iteration keeps config.json and summary.json; its resume starts it again
    from iteration 1 without --restart, and says nothing of a --restart that was not given."""
    from ablations.cli import ablate_main
    from ablations.run_config import RunConfig
    from gradlab.checkpoint import atomic_write_json

    run = tmp_path / "run"
    cfg = dataclasses.asdict(RunConfig(task="cartpole", mode="state", device="cpu", out=tmp_path, iters=1,
                                       num_envs=2, horizon=3, critic_iterations=1, critic_batches=1,
                                       video_every=0, eval_every=0, threads=1))
    del cfg["restart"]
    atomic_write_json(run / "config.json", {"config": cfg})
    atomic_write_json(run / "summary.json", {"status": "interrupted", "iterations": 0})
    ablate_main(["--resume", str(run), "--no-progress"])
    captured = capsys.readouterr()
    assert "--restart" not in captured.err, captured.err
    assert "finished after 1 iterations" in captured.out
