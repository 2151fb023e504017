"""Atomic result files: readable by others as the umask allows, never half written."""

from __future__ import annotations

import os
import stat

import pytest
import torch

from gradlab.checkpoint import atomic_write_bytes, atomic_write_json, save_checkpoint


@pytest.fixture
def umask():
    """Set the process umask for one test (restored after)."""
    old = os.umask(0o022)
    yield lambda mask: os.umask(mask)
    os.umask(old)


@pytest.mark.parametrize("mask", [0o022, 0o027, 0o077])
def test_files_are_created_as_open_creates_them_respecting_the_umask(tmp_path, umask, mask):
    """0644 under the usual umask 022 (tempfile.mkstemp's 0600 would lock collaborators out), 0640 under 027."""
    umask(mask)
    atomic_write_bytes(tmp_path / "a.bin", b"x")
    atomic_write_json(tmp_path / "b.json", {"k": 1})
    save_checkpoint(tmp_path / "ckpt_000001.pt", {"w": torch.zeros(2)})
    for name in ("a.bin", "b.json", "ckpt_000001.pt"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o666 & ~mask, name
    # what a plain open() makes under the same umask
    (tmp_path / "plain").write_text("x")
    assert stat.S_IMODE((tmp_path / "plain").stat().st_mode) == 0o666 & ~mask


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    path = tmp_path / "r.json"
    atomic_write_json(path, {"v": 1})

    def full_disk(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", full_disk)  # the new file is written, its rename fails
    with pytest.raises(OSError, match="No space left"):
        atomic_write_json(path, {"v": 2})
    assert path.read_text() == '{\n  "v": 1\n}\n'
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


def test_an_overwrite_keeps_no_temporary_files(tmp_path):
    for i in range(3):
        atomic_write_bytes(tmp_path / "f", bytes([i]))
    assert (tmp_path / "f").read_bytes() == b"\x02" and [p.name for p in tmp_path.iterdir()] == ["f"]


def test_a_device_error_while_loading_is_no_damage(tmp_path, monkeypatch):
    """read_checkpoint names a file that does not load as damaged, but a full or failing device (a resume loads
    onto the GPU) is raised: the newest checkpoint must not be set aside for it."""
    import gradlab.checkpoint as checkpoint

    bad = tmp_path / "ckpt_000001.pt"
    bad.write_bytes(b"not a checkpoint")
    state, why = checkpoint.read_checkpoint(bad)
    assert state is None and why
    save_checkpoint(tmp_path / "ckpt_000002.pt", {"iteration": 2})
    assert checkpoint.read_checkpoint(tmp_path / "ckpt_000002.pt") == ({"iteration": 2}, None)
    for error in (torch.OutOfMemoryError("CUDA out of memory"), RuntimeError("CUDA error: an illegal memory access")):
        def load(path, map_location="cpu", error=error):
            raise error

        monkeypatch.setattr(checkpoint, "load_checkpoint", load)
        with pytest.raises(type(error)):
            checkpoint.read_checkpoint(tmp_path / "ckpt_000002.pt")
