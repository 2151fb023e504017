"""Atomic checkpoints and results: a killed run never leaves a half-written file behind."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import torch

__all__ = ["atomic_write_bytes", "atomic_write_text", "atomic_write_json", "save_checkpoint", "load_checkpoint",
           "latest_checkpoint"]


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write to a temporary file in the same folder, fsync, then rename over ``path`` (atomic on POSIX)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n")


def save_checkpoint(path: str | os.PathLike, state: dict) -> None:
    """torch.save to bytes, then an atomic write."""
    import io

    buf = io.BytesIO()
    torch.save(state, buf)
    atomic_write_bytes(path, buf.getvalue())


def load_checkpoint(path: str | os.PathLike, *, map_location: str | torch.device = "cpu") -> dict:
    # Our own checkpoints hold RNG states and numpy arrays besides tensors, so weights_only=False; only load
    # checkpoints you wrote.
    return torch.load(path, map_location=map_location, weights_only=False)


def latest_checkpoint(folder: str | os.PathLike) -> Path | None:
    """The newest ``ckpt_<iter>.pt`` in folder (by iteration number), or None."""
    folder = Path(folder)
    best, best_it = None, -1
    for p in folder.glob("ckpt_*.pt"):
        try:
            it = int(p.stem.split("_")[1])
        except (IndexError, ValueError):
            continue
        if it > best_it:
            best, best_it = p, it
    return best
