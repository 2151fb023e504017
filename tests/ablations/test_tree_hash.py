"""ablations.tree_hash on small trees whose files are known: deterministic, the same with git and without where the
files are the tracked ones, and changed by exactly what should change it."""

from __future__ import annotations

import hashlib
import shutil
import subprocess

import pytest

from ablations import tree_hash as th

PKGS = ("pkg_a", "pkg_b")


def make_tree(root):
    (root / "pkg_a" / "sub").mkdir(parents=True)
    (root / "pkg_b").mkdir()
    (root / "pkg_a" / "__init__.py").write_text("x = 1\n")
    (root / "pkg_a" / "sub" / "m.py").write_text("y = 2\n")
    (root / "pkg_b" / "data.json").write_text("{}\n")
    (root / "outside.py").write_text("not hashed\n")
    return root


def git(root, *args):
    subprocess.run(["git", "-C", str(root), *args], check=True, capture_output=True)


@pytest.fixture
def repo(tmp_path):
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    root = make_tree(tmp_path / "repo")
    git(root, "init", "-q")
    git(root, "add", ".")
    return root


def test_the_hash_is_the_documented_digest(tmp_path):
    root = make_tree(tmp_path)
    lines = "".join(f"{rel}\0{hashlib.sha256((root / rel).read_bytes()).hexdigest()}\n"
                    for rel in ("pkg_a/__init__.py", "pkg_a/sub/m.py", "pkg_b/data.json"))
    got = th.tree_hash(root, PKGS)
    assert got == th.TreeHash("sha256:" + hashlib.sha256(lines.encode()).hexdigest(), 3, "files")
    assert th.tree_hash(root, PKGS) == got  # deterministic


def test_a_copy_without_git_hashes_as_the_checkout(repo, tmp_path):
    with_git = th.tree_hash(repo, PKGS)
    assert with_git.source == "git" and with_git.files == 3
    copy = tmp_path / "copy"
    shutil.copytree(repo, copy, ignore=shutil.ignore_patterns(".git"))
    assert th.tree_hash(copy, PKGS).value == with_git.value
    assert th.tree_hash(repo, PKGS, use_git=False).value == with_git.value


def test_bytecode_and_hidden_files_do_not_count_an_edit_does(repo):
    before = th.tree_hash(repo, PKGS).value
    (repo / "pkg_a" / "__pycache__").mkdir()
    (repo / "pkg_a" / "__pycache__" / "m.cpython-312.pyc").write_bytes(b"\0")
    (repo / "pkg_a" / ".hidden").write_text("x")
    (repo / "outside.py").write_text("changed, outside the packages\n")
    assert th.tree_hash(repo, PKGS).value == th.tree_hash(repo, PKGS, use_git=False).value == before
    (repo / "pkg_a" / "sub" / "m.py").write_text("y = 3\n")  # an edit of a tracked file, uncommitted
    assert th.tree_hash(repo, PKGS).value != before


def test_untracked_files_count_only_without_git(repo):
    before = th.tree_hash(repo, PKGS).value
    (repo / "pkg_b" / "scratch.py").write_text("z = 0\n")
    assert th.tree_hash(repo, PKGS).value == before
    assert th.tree_hash(repo, PKGS, use_git=False).value != before


def test_this_checkout_has_a_hash():
    got = th.tree_hash()
    assert got.value.startswith("sha256:") and len(got.value) == 71 and got.files > 50
