"""Atomic result files and training checkpoints: a killed run never leaves a half-written file behind.

Every file a run or a sweep writes for later reading goes through :func:`atomic_write_bytes` (temp file in
the same folder, fsync, rename; :mod:`gradlab.files`, re-exported here): a reader, or a process killed mid-write,
sees the old file or the new one. Checkpoints are ``ckpt_<iteration>.pt`` files in one folder;
:func:`load_newest_readable` resumes from the newest one that still loads and names every newer one that does not.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import NamedTuple

import torch

from gradlab.files import atomic_write_bytes, atomic_write_json, atomic_write_text

__all__ = ["atomic_write_bytes", "atomic_write_text", "atomic_write_json", "save_checkpoint", "load_checkpoint",
           "checkpoint_iteration", "checkpoint_path", "list_checkpoints", "latest_checkpoint", "prune_checkpoints",
           "load_newest_readable", "read_checkpoint", "LoadedCheckpoint", "NoReadableCheckpointError"]


def save_checkpoint(path: str | os.PathLike, state: dict) -> None:
    """torch.save to bytes, then an atomic write."""
    buf = io.BytesIO()
    torch.save(state, buf)
    atomic_write_bytes(path, buf.getvalue())


def load_checkpoint(path: str | os.PathLike, *, map_location: str | torch.device = "cpu") -> dict:
    # Our own checkpoints hold RNG states and numpy arrays besides tensors, so weights_only=False; only load
    # checkpoints you wrote.
    return torch.load(path, map_location=map_location, weights_only=False)


def checkpoint_path(folder: str | os.PathLike, iteration: int) -> Path:
    """``folder/ckpt_<iteration>.pt``, the iteration zero-padded to 6 digits."""
    return Path(folder) / f"ckpt_{iteration:06d}.pt"


def checkpoint_iteration(path: Path) -> int | None:
    """The iteration of a ``ckpt_<iter>.pt`` file; None for any other name."""
    try:
        return int(path.stem.split("_", 1)[1])
    except (IndexError, ValueError):
        return None


def list_checkpoints(folder: str | os.PathLike) -> list[Path]:
    """The ``ckpt_<iter>.pt`` files in folder, newest (highest iteration) first; other names are ignored."""
    found = [(it, p) for p in Path(folder).glob("ckpt_*.pt") if (it := checkpoint_iteration(p)) is not None]
    return [p for _, p in sorted(found, reverse=True)]


def latest_checkpoint(folder: str | os.PathLike) -> Path | None:
    """The newest ``ckpt_<iter>.pt`` in folder (by iteration number), or None."""
    found = list_checkpoints(folder)
    return found[0] if found else None


def prune_checkpoints(folder: str | os.PathLike, *, keep: int) -> list[Path]:
    """Delete all but the ``keep`` newest checkpoints of folder; returns the deleted paths."""
    if keep < 1:
        raise ValueError(f"keep must be at least 1 (the checkpoint a resume starts from), got {keep}")
    old = list_checkpoints(folder)[keep:]
    for p in old:
        p.unlink(missing_ok=True)
    return old


class LoadedCheckpoint(NamedTuple):
    """What :func:`load_newest_readable` found: the state, its file, and the newer files that did not load."""

    path: Path
    state: dict
    damaged: list[tuple[Path, str]]
    """(file, reason) for every newer checkpoint that could not be read, newest first."""


class NoReadableCheckpointError(ValueError):
    """The folder holds no checkpoint that loads (none at all, or every one is damaged)."""


def _why(exc: BaseException) -> str:
    first = (str(exc).strip().splitlines() or [""])[0]
    return f"{type(exc).__name__}: {first}"[:300] if first else type(exc).__name__


def read_checkpoint(path: str | os.PathLike, *,
                    map_location: str | torch.device = "cpu") -> tuple[dict | None, str | None]:
    """(the checkpoint's dict, None) where ``path`` loads as one, else (None, why it counts as damaged: torch.load
    failed on it, e.g. truncated or overwritten, or it does not hold a dict)."""
    try:
        state = load_checkpoint(path, map_location=map_location)
    except torch.OutOfMemoryError:
        raise  # the device is full, the file is not damaged
    except Exception as e:  # torch.load raises pickle, zip, EOF and runtime errors on damaged files
        if isinstance(e, RuntimeError) and "CUDA" in str(e):
            raise  # a device error (or a GPU checkpoint on a machine without one): not the file's
        return None, _why(e)
    if not isinstance(state, dict):
        return None, f"holds a {type(state).__name__}, not a checkpoint dict"
    return state, None


def load_newest_readable(folder: str | os.PathLike, *,
                         map_location: str | torch.device = "cpu") -> LoadedCheckpoint:
    """Load the newest checkpoint of folder that can be read, skipping (and reporting) damaged newer ones.

    A file counts as damaged when ``torch.load`` fails on it (truncated, overwritten, not a checkpoint) or it
    does not hold a dict. Raises :class:`NoReadableCheckpointError` naming every file and its reason when no
    checkpoint loads. The caller decides what to tell the user about ``damaged``; nothing is deleted here.
    """
    folder = Path(folder)
    damaged: list[tuple[Path, str]] = []
    for path in list_checkpoints(folder):
        state, why = read_checkpoint(path, map_location=map_location)
        if state is None:
            damaged.append((path, why))
            continue
        return LoadedCheckpoint(path, state, damaged)
    if not damaged:
        raise NoReadableCheckpointError(f"no checkpoint (ckpt_<iter>.pt) in {folder}")
    listed = "; ".join(f"{p} ({why})" for p, why in damaged)
    raise NoReadableCheckpointError(f"no readable checkpoint in {folder}: {listed}")
