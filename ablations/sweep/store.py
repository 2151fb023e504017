"""The run store: the sweep folder's ``runs/`` and ``logs/``, and what the sweep decides from a run folder.

:class:`RunStore` lives on the driver's node (a Ray actor pinned there); workers send it job folders (a run
folder, or a population folder with its members' run folders) packed by :mod:`ablations.sweep.transfer`. Run
folders are read and written through ``ablations.run_folder``, on the driver's copy and on a worker's scratch copy
alike.
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

from ablations.run_folder import POPULATION_RECORD, VIDEOS, RunFolder
from ablations.sweep.transfer import KEPT_CHECKPOINTS, pack_run, unpack_run
from gradlab.files import atomic_write_bytes

__all__ = ["RunStore", "FINISHED", "run_path", "run_state", "job_state", "resumable", "common_checkpoint"]

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


def common_checkpoint(folders: list[RunFolder]) -> int | None:
    """The newest iteration of which every run folder has a checkpoint (a population resumes from it); None if
    there is none."""
    have = [f.checkpoint_iterations() for f in folders]
    common = set.intersection(*have) if have else set()
    return max(common) if common else None


def job_state(job_dir: Path, members: list[str] | tuple[str, ...], iters: int) -> str:
    """What a (re)run must do with a job (its folder and its runs' folders in it, ``("",)`` for a run alone):
    'done' (every run's summary says so), 'resume' (``ablate --resume`` finds a checkpoint of one iteration in
    every run folder, and a population its record) or 'start'."""
    if all(run_state(job_dir / m, iters) == "done" for m in members):
        return "done"
    return "resume" if resumable(job_dir, members) else "start"


def resumable(job_dir: Path, members: list[str] | tuple[str, ...]) -> bool:
    """Whether ``ablate --resume`` can continue the job in ``job_dir``: a checkpoint of one iteration in every run
    folder, and a population's record."""
    population = tuple(members) != ("",)
    folders = [RunFolder(job_dir / m) for m in members]
    return common_checkpoint(folders) is not None and (not population or (job_dir / POPULATION_RECORD).is_file())


class RunStore:
    """Receives job folders from the workers and writes them under ``<sweep>/runs``; hands out resume state.

    Every attempt of a job gets a number from :meth:`begin`; writes of an older attempt (a worker that died
    while its message was in flight) are refused, so a retry never sees its folder go back in time.
    """

    def __init__(self, sweep_dir: str, attempts: dict[str, int]):
        self.root = Path(sweep_dir)
        self.attempts = dict(attempts)
        self.current: dict[str, int] = {}
        self.progress: dict[str, dict] = {}
        self.stop_level = 0

    def stop(self, level: int = 1) -> None:
        """The driver's stop request (Ctrl-C): 1, each attempt's ablate gets a SIGINT (it checkpoints once its
        iteration ends); 2, a second one at once (it stops, keeping the last finished iteration)."""
        self.stop_level = max(self.stop_level, level)

    def stopping(self) -> int:
        """The stop request the workers act on: 0 (none), 1 or 2 (see :meth:`stop`)."""
        return self.stop_level

    def run_dir(self, run_id: str) -> Path:
        return run_path(self.root, run_id)

    def begin(self, run_id: str, members: tuple[str, ...] | list[str] = ("",)) -> tuple[int, bytes | None]:
        """A new attempt of a job (``run_id``: its folder name; ``members``: its runs' folders in it, ``("",)``
        for a run alone): (its number, the job folder packed for ``ablate --resume``, or None: start fresh)."""
        attempt = self.attempts.get(run_id, 0) + 1
        self.attempts[run_id] = self.current[run_id] = attempt
        run_dir = self.run_dir(run_id)
        pack = None
        if resumable(run_dir, members):
            pack = pack_run(run_dir, checkpoints=KEPT_CHECKPOINTS,
                            only=[str(p.relative_to(run_dir)) for p in run_dir.rglob("*")
                                  if p.is_file() and VIDEOS not in p.relative_to(run_dir).parts[:-1]])
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
        """Progress of a job's attempt: its status, node, and ``runs`` ({run id: iteration, latest return})."""
        if self.current.get(run_id) == attempt:
            progress = self.progress.setdefault(run_id, {})
            runs = progress.setdefault("runs", {})
            for rid, row in (info.get("runs") or {}).items():
                runs.setdefault(rid, {}).update(row)
            progress.update({k: v for k, v in info.items() if k != "runs"})

    def snapshot(self) -> dict[str, dict]:
        return {k: {**v, "attempts": self.attempts.get(k, 0)} for k, v in self.progress.items()}
