"""The run store: the sweep folder's ``runs/`` and ``logs/``, and what the sweep decides from a run folder.

:class:`RunStore` lives on the driver's node (a Ray actor pinned there); workers send it run folders packed by
:mod:`ablations.sweep.transfer`. Run folders are read and written through ``ablations.run_folder``, on the driver's
copy and on a worker's scratch copy alike.
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

from ablations.run_folder import RunFolder
from ablations.sweep.transfer import KEPT_CHECKPOINTS, pack_run, unpack_run
from gradlab.checkpoint import atomic_write_bytes

__all__ = ["RunStore", "FINISHED", "run_path", "run_state"]

#: Summary statuses of a run that needs no more work (time_limit: it stopped on the budget it was given).
FINISHED = ("finished", "time_limit")


def run_path(sweep_dir: str | os.PathLike, run_id: str) -> Path:
    """Where the sweep folder keeps a run's folder."""
    return Path(sweep_dir) / "runs" / run_id


def run_state(run_dir: Path, iters: int) -> str:
    """What a (re)run must do with a run of ``iters`` iterations: 'done' (its summary says so), 'resume' (it has
    a checkpoint) or 'start'."""
    folder = RunFolder(run_dir)
    summary = folder.read_summary() or {}
    if summary.get("status") in FINISHED and (summary.get("iterations", 0) >= iters
                                              or summary.get("status") == "time_limit"):
        return "done"
    return "resume" if folder.newest_checkpoint() is not None else "start"


class RunStore:
    """Receives run folders from the workers and writes them under ``<sweep>/runs``; hands out resume state.

    Every attempt of a run gets a number from :meth:`begin`; writes of an older attempt (a worker that died
    while its message was in flight) are refused, so a retry never sees its folder go back in time.
    """

    def __init__(self, sweep_dir: str, attempts: dict[str, int]):
        self.root = Path(sweep_dir)
        self.attempts = dict(attempts)
        self.current: dict[str, int] = {}
        self.progress: dict[str, dict] = {}

    def run_dir(self, run_id: str) -> Path:
        return run_path(self.root, run_id)

    def begin(self, run_id: str) -> tuple[int, bytes | None]:
        """A new attempt: (its number, the run folder packed for ``ablate --resume``, or None: start fresh)."""
        attempt = self.attempts.get(run_id, 0) + 1
        self.attempts[run_id] = self.current[run_id] = attempt
        run_dir = self.run_dir(run_id)
        pack = None
        if RunFolder(run_dir).newest_checkpoint() is not None:
            pack = pack_run(run_dir, checkpoints=KEPT_CHECKPOINTS,
                            only=[str(p.relative_to(run_dir)) for p in run_dir.rglob("*")
                                  if p.is_file() and not p.relative_to(run_dir).parts[0] == "videos"])
        elif run_dir.exists() and any(run_dir.iterdir()):
            # ablate starts only in an empty folder; keep what the earlier attempt left.
            dest = self.root / "discarded" / f"{run_id}.attempt{attempt - 1}.{time.strftime('%Y%m%d-%H%M%S')}"
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.move(str(run_dir), str(dest))
        self.progress[run_id] = {"status": "running", "attempt": attempt, "started": time.time()}
        return attempt, pack

    def save(self, run_id: str, attempt: int, data: bytes) -> bool:
        """Merge a worker's archive into the run folder; False (nothing written) for a stale attempt."""
        if self.current.get(run_id) != attempt:
            return False
        unpack_run(data, self.run_dir(run_id))
        return True

    def save_log(self, run_id: str, attempt: int, text: str) -> None:
        path = self.root / "logs" / f"{run_id}.attempt{attempt}.log"
        atomic_write_bytes(path, text.encode(errors="replace"))

    def report(self, run_id: str, attempt: int, info: dict) -> None:
        if self.current.get(run_id) == attempt:
            self.progress.setdefault(run_id, {}).update(info)

    def snapshot(self) -> dict[str, dict]:
        return {k: {**v, "attempts": self.attempts.get(k, 0)} for k, v in self.progress.items()}
