"""Resume provenance and settings drift: each start of a run appends the code it ran (provenance.jsonl, a dirty
resume's own diff), and a resume refuses a config.json with settings this version does not know or lacks one that
has no recorded "absent means" value."""

from __future__ import annotations

import dataclasses
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from ablations.population import prepare
from ablations.run_config import RunConfig
from ablations.run_folder import ABSENT_MEANS, PROVENANCE, RESUME_FILES, RunFolder
from ablations.tree_hash import tree_hash
from gradlab.checkpoint import atomic_write_json, checkpoint_path, save_checkpoint


def git(repo: Path, *args: str) -> None:
    subprocess.run(["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", *args], check=True,
                   capture_output=True)


def test_each_start_appends_its_code_and_a_dirty_resume_keeps_its_own_diff(tmp_path):
    repo = tmp_path / "repo"
    (repo / "gradlab").mkdir(parents=True)
    (repo / "gradlab" / "a.py").write_text("x = 1\n")
    (repo / "notes.txt").write_text("not code\n")
    git(repo, "init", "-q")
    git(repo, "add", ".")
    git(repo, "commit", "-qm", "one")
    folder = RunFolder.create(tmp_path, "run")
    first = folder.append_provenance("start", 0, repo=repo)
    assert first["dirty"] is False and len(first["commit"]) == 40 and "diff" not in first
    (repo / "notes.txt").write_text("edited, but not code\n")
    assert tree_hash(repo).value == first["tree_hash"]  # only the code counts
    (repo / "gradlab" / "a.py").write_text("x = 2\n")
    for _ in range(2):
        folder.append_provenance("resume", 4, repo=repo)
    starts = folder.read_provenance()
    assert [s["event"] for s in starts] == ["start", "resume", "resume"] and PROVENANCE in RESUME_FILES
    assert starts[1]["dirty"] is True and starts[1]["tree_hash"] != first["tree_hash"]
    diffs = [folder.path / s["diff"] for s in starts[1:]]
    assert diffs[0] != diffs[1] and all("+x = 2" in d.read_text() for d in diffs)  # one diff each, none overwritten
    # a copy of the tree without its repository (a device's) names the same code by the same hash
    copy = tmp_path / "copy"
    shutil.copytree(repo, copy, ignore=shutil.ignore_patterns(".git"))
    assert tree_hash(copy).value == tree_hash(repo).value == starts[2]["tree_hash"]
    assert RunFolder(tmp_path / "old").read_provenance() == []  # a folder from before provenance: read as none


def _folder(tmp_path: Path, **edit) -> Path:
    run = tmp_path / "run"
    config = dataclasses.asdict(RunConfig(task="cartpole", device="cpu", out=tmp_path, iters=8))
    del config["restart"]  # as runs.py records it
    for k, v in edit.items():
        if v is None:
            del config[k]
        else:
            config[k] = v
    atomic_write_json(run / "config.json", {"config": config})
    save_checkpoint(checkpoint_path(run / "checkpoints", 2), {"iteration": 2, "wall_s": 1.0})
    return run


def test_a_key_missing_from_an_old_config_follows_the_absent_means_table(tmp_path):
    assert ABSENT_MEANS["precision"] == "fp32"
    run = _folder(tmp_path, precision=None)  # 52 of the 72 shipped docs/seeded configs lack it
    assert prepare(RunConfig(resume=run, progress=False)).cfgs[0].precision == "fp32"


@pytest.mark.parametrize("edit, message", [
    ({"num_envs": None}, "has no num_envs: a resume would take today's default"),
    ({"gamma": None, "eval_every": None}, "has no eval_every, gamma: a resume would take today's defaults"),
    ({"frobnicate": 3, "zeta": 1}, "records setting(s) this version does not know: frobnicate, zeta"),
])
def test_a_resume_refuses_unknown_and_unexplained_missing_settings_naming_them(tmp_path, edit, message):
    run = _folder(tmp_path, **edit)
    with pytest.raises(ValueError, match=re.escape(f"--resume {run}: {run / 'config.json'} {message}")) as e:
        prepare(RunConfig(resume=run, progress=False))
    assert "\n" not in str(e.value)
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["ckpt_000002.pt"]


def test_reports_still_read_old_folders_without_the_new_keys(tmp_path):
    """Readers never go through the resume's checks: a folder without precision or provenance still loads."""
    from ablations.run_folder import load_run

    run = _folder(tmp_path, precision=None)
    assert load_run(run).setting("precision") is None and load_run(run).task == "cartpole"
