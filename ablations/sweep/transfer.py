"""Run folders as tar archives: the only way files travel between a worker node and the driver's node.

An archive holds one run folder, or a population folder (population.json and its members' run folders): every
rule below applies to each run folder in it, found by its ``checkpoints/`` folder and its metrics.jsonl.
"""

from __future__ import annotations

import io
import os
import tarfile
import time
from collections.abc import Iterable
from pathlib import Path

from ablations.run_folder import CHECKPOINTS, METRICS, RunFolder
from gradlab.files import atomic_write_bytes

__all__ = ["pack_run", "unpack_run", "archive_names", "KEPT_CHECKPOINTS"]

#: Checkpoints a run folder in the sweep keeps (the newest ones): a resume falls back to the older one when the
#: newest does not load.
KEPT_CHECKPOINTS = 2


def pack_run(run_dir: str | os.PathLike, *, checkpoints: int = 1, only: Iterable[str] | None = None) -> bytes:
    """The files of a run folder (or a population folder) as an uncompressed tar archive (checkpoints hardly
    compress).

    Only each run folder's ``checkpoints`` newest checkpoints go in (0: none). ``only``: relative paths to include
    (default: every file). metrics.jsonl is cut after its last complete line: the run may be appending to it.
    """
    run_dir = Path(run_dir)
    if checkpoints < 0:
        raise ValueError(f"checkpoints must be >= 0, got {checkpoints}")
    names = sorted(str(p.relative_to(run_dir)) for p in run_dir.rglob("*") if p.is_file()) if only is None \
        else sorted(set(only))
    kept = {p for folder in _run_folders(names) for p in RunFolder(run_dir / folder).checkpoints()[:checkpoints]}
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for name in names:
            path = run_dir / name
            if Path(name).parent.name == CHECKPOINTS and path not in kept:
                continue
            # a file being written atomically under a temporary name, or a folder's lock (ablations.folder_lock)
            if Path(name).name.startswith("."):
                continue
            try:
                data = path.read_bytes()
            except FileNotFoundError:  # rotated away (an old checkpoint) or not written yet
                continue
            if Path(name).name == METRICS:
                data = data[:data.rfind(b"\n") + 1]
            info = tarfile.TarInfo(name)
            info.size = len(data)
            info.mtime = int(path.stat().st_mtime) if path.exists() else int(time.time())
            tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def unpack_run(data: bytes, run_dir: str | os.PathLike) -> list[str]:
    """Write an archive of :func:`pack_run` into run_dir, each file atomically; returns the names written.

    Files already there and not in the archive stay. Where the archive brings checkpoints of a run folder, its
    newest is that run's state: checkpoints of later iterations (an abandoned timeline: the run resumed from an
    older one) are deleted, and of the rest the ``KEPT_CHECKPOINTS`` newest stay.
    """
    run_dir = Path(run_dir)
    written = []
    with tarfile.open(fileobj=io.BytesIO(data), mode="r") as tar:
        for member in tar.getmembers():
            parts = Path(member.name).parts
            if not member.isfile() or Path(member.name).is_absolute() or ".." in parts:
                raise ValueError(f"run archive: refusing member {member.name!r}")
            src = tar.extractfile(member)
            atomic_write_bytes(run_dir / member.name, src.read() if src else b"")
            written.append(member.name)
    arrived = set(written)
    for name in _run_folders(n for n in written if Path(n).parent.name == CHECKPOINTS):
        folder = RunFolder(run_dir / name)
        checkpoints = folder.checkpoints()
        shipped = [p for p in checkpoints if (Path(name) / CHECKPOINTS / p.name).as_posix() in arrived]
        if not shipped:  # no file of a checkpoint's name (ckpt_<iteration>.pt) came
            continue
        for later in checkpoints[:checkpoints.index(shipped[0])]:
            later.unlink()
        folder.prune_checkpoints(KEPT_CHECKPOINTS)
    return written


def _run_folders(names: Iterable[str]) -> set[str]:
    """The run folders (relative paths, "." for the archive's own) that hold a checkpoint or metrics among
    ``names``: the folder itself for a single run, each member's for a population."""
    out = set()
    for name in names:
        path = Path(name)
        if path.parent.name == CHECKPOINTS:
            out.add(path.parent.parent.as_posix())
        elif path.name == METRICS:
            out.add(path.parent.as_posix())
    return out


def archive_names(data: bytes) -> list[str]:
    """The member names of an archive of :func:`pack_run`."""
    return tarfile.open(fileobj=io.BytesIO(data)).getnames()
