"""The run folder: the files one training run writes, and the one module that writes, lists and reads them.

A run folder holds:
    config.json      the resolved configuration (every flag, preset values filled in), what the preset supplied
                     and which flags overrode it, the start time (UTC), the command and the environment (device,
                     versions, CPU threads)
    git.txt          commit, branch, dirty status and diff stat of the code that ran (git.diff: the full diff)
    metrics.jsonl    one JSON object per training iteration, appended as the run goes (a resume sets lines it
                     cannot keep aside in metrics.jsonl.redone-<time> and .damaged-<time>, a --restart the old
                     records in *.before-restart-<time>: nothing is deleted)
    provenance.jsonl one line per start in this folder (the first, each resume, a restart): time, commit, dirty
                     status and a hash of the code (a dirty resume's own diff in git.diff.resume-<time>)
    summary.json     written at the end (or when the run stops on an error or a signal): its status, final and best
                     training and evaluation returns, medians without warm-up, peaks, start-up seconds
    checkpoints/     ckpt_<iter>.pt (the newest few), written atomically; a resume starts from the newest that loads
                     and renames damaged newer ones to ckpt_<iter>.pt.damaged
    videos/          iter_<iter>.mp4 evaluation rollouts of the deterministic policy

:class:`RunFolder` is one folder: a run creates it (or finds it to resume), writes its records, appends metrics
lines, saves and prunes checkpoints and writes videos through it; several runs of one process (a population)
each hold their own. :class:`Run` is a folder's records parsed (:func:`load_run`, :func:`find_runs`) for plots,
reports and statistics.

Reading imports no torch (``ablations.reports`` reads run folders without it); checkpoints and the environment
record import it when they are called.
"""

from __future__ import annotations

import datetime
import itertools
import json
import math
import os
import shutil
import sys
import tempfile
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ablations.folder_lock import LOCK
from ablations.run_records import git_info, git_state
from ablations.tree_hash import tree_hash
from gradlab.files import atomic_write_bytes, atomic_write_json, atomic_write_text

if TYPE_CHECKING:
    import torch

    from gradlab.checkpoint import LoadedCheckpoint

__all__ = ["RunFolder", "Run", "MetricsTail", "load_run", "find_runs", "read_metrics", "check_writable", "thin_copy",
           "evaluation_of", "is_number", "CONFIG", "METRICS",
           "SUMMARY", "CHECKPOINTS", "VIDEOS", "RESUME_FILES", "PROVENANCE", "ABSENT_MEANS", "POPULATION_RECORD",
           "metrics_notes", "say_metrics_notes"]

CONFIG, GIT, GIT_DIFF, METRICS, SUMMARY = "config.json", "git.txt", "git.diff", "metrics.jsonl", "summary.json"
CHECKPOINTS, VIDEOS = "checkpoints", "videos"
#: One JSON line per start of the run in this folder (its first, each resume, a restart): the code that ran.
PROVENANCE = "provenance.jsonl"
#: The record a population folder holds beside its members' run folders (the other folder format: a run alone's
#: folder is a run folder itself).
POPULATION_RECORD = "population.json"
#: What ``ablate --resume`` needs besides a checkpoint (the git records keep a copied folder complete).
RESUME_FILES = (CONFIG, GIT, GIT_DIFF, METRICS, PROVENANCE)
#: What a setting missing from an older config.json means: the behaviour the code had before the setting existed.
#: A resume refuses a folder that lacks any other setting (it would take today's default without a word).
ABSENT_MEANS: dict[str, object] = {
    "precision": "fp32",  # the --precision flag came later; every run before it trained in float32
}


def check_writable(folder: str | os.PathLike) -> None:
    """Create ``folder`` if needed and check that a file can be created in it; ValueError naming it if not."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        # A unique name: several runs may start in the same folder at once.
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".write-test.")
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise ValueError(f"output folder {folder} is not writable: {e}") from None


def read_metrics(run_dir: str | os.PathLike) -> list[dict]:
    """The parsed lines of a run folder's metrics.jsonl ([] without one): every line that reads as an iteration's
    record; a torn last line (a run killed mid-write) or a damaged one in the middle is left out, the lines after it
    kept (``ablate --resume`` names and sets aside such lines: :meth:`RunFolder.settle_metrics`)."""
    try:
        data = (Path(run_dir) / METRICS).read_bytes()
    except FileNotFoundError:
        return []
    return [row for _, _, row in _metrics_lines(data)[0] if row is not None]


def metrics_notes(run_dir: str | os.PathLike) -> list[str]:
    """What a reader of a run folder's metrics.jsonl should be told (one line each, [] when nothing): lines it skips
    as damaged, and iterations that appear twice or out of order (two processes that trained into one folder)."""
    path = Path(run_dir) / METRICS
    try:
        lines, _ = _metrics_lines(path.read_bytes())
    except FileNotFoundError:
        return []
    notes = []
    damaged = [n for n, _, row in lines if row is None]
    if damaged:
        notes.append(f"warning: {path}: line(s) {_spans(damaged)} damaged (not a JSON record), skipped")
    its = [row["iter"] for _, _, row in lines if row is not None]
    twice = sorted(it for it, n in Counter(its).items() if n > 1)
    if twice:
        notes.append(f"warning: {path}: iteration(s) {_spans(twice)} appear more than once (two processes trained "
                     f"into this folder?); every copy is read")
    back = [b for a, b in itertools.pairwise(its) if b < a]
    if back:
        notes.append(f"warning: {path}: iterations out of order (iteration {back[0]} after a later one); read sorted "
                     f"by iteration")
    return notes


def say_metrics_notes(runs: list[Run]) -> None:
    """Print each run's :func:`metrics_notes` on stderr, once (``ablate-plot`` and ``ablate-report`` read them)."""
    for run in runs:
        for note in metrics_notes(run.path):
            print(note, file=sys.stderr)


def _metrics_lines(data: bytes) -> tuple[list[tuple[int, bytes, dict | None]], bytes | None]:
    """(the complete lines of metrics.jsonl's bytes as (line number, its bytes without the newline, record or None
    where it does not read as one: not UTF-8, not JSON, not an iteration's object), the last line's bytes when it is
    torn: cut off before its newline and not a record). Lines are kept as bytes so that whatever is set aside or
    kept is what was on disk, byte for byte."""
    lines = data.split(b"\n")
    tail = lines.pop()  # b"" when the file ends with a newline
    out = []
    for n, line in enumerate(lines, 1):
        out.append((n, line, _record(line)))
    torn = None
    if tail:
        row = _record(tail)
        if row is None:
            torn = tail
        else:  # complete but for its newline
            out.append((len(lines) + 1, tail, row))
    return out, torn


def _record(line: bytes) -> dict | None:
    try:
        row = json.loads(line.decode("utf-8"))  # strict: a line that is not UTF-8 is damaged
    except ValueError:  # UnicodeDecodeError and JSONDecodeError are both ValueErrors
        return None
    return row if isinstance(row, dict) and isinstance(row.get("iter"), int) else None


def _shown(line: bytes) -> str:
    """A damaged line's first bytes, for a one-line note (undecodable bytes shown escaped)."""
    return repr(line[:60].decode("utf-8", errors="backslashreplace"))


def _spans(its: list[int]) -> str:
    """Sorted iterations as ranges: [2, 5, 6, 7] -> '2, 5..7'."""
    parts: list[list[int]] = []
    for it in sorted(its):
        if parts and it == parts[-1][1] + 1:
            parts[-1][1] = it
        else:
            parts.append([it, it])
    return ", ".join(str(a) if a == b else f"{a}..{b}" for a, b in parts)


def _stamp() -> str:
    """The UTC time in the names of the files a resume sets aside (sorting as they were made)."""
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%SZ")


def _aside(path: Path, suffix: str) -> Path:
    """The name under which a resume or restart sets ``path`` aside: <name><suffix>, or with -2, -3, ... where
    that exists already (two within one second, a second damaged copy): nothing set aside is ever overwritten."""
    k = 1
    while True:
        aside = path.with_name(path.name + suffix + (f"-{k}" if k > 1 else ""))
        if not aside.exists():
            return aside
        k += 1


def set_aside_damaged_checkpoint(path: Path, why: str, resuming_from: Path) -> None:
    """Rename a checkpoint that does not load to <name>.damaged (never over an earlier one) and say so on stderr,
    naming the checkpoint the resume takes instead."""
    aside = _aside(path, ".damaged")
    os.replace(path, aside)
    print(f"warning: checkpoint {path} is damaged ({why}); renamed to {aside.name}, resuming from "
          f"{resuming_from.name}", file=sys.stderr)


def evaluation_of(row: dict) -> tuple[float, float] | None:
    """(mean, std) of the deterministic evaluation return a metrics line holds, or None: ``eval_return_mean`` and
    ``eval_return_std`` over the evaluation's episodes, or ``eval_return`` with std NaN (lines that have only
    that, logged with the videos)."""
    mean = row.get("eval_return_mean", row.get("eval_return"))
    if not is_number(mean):
        return None
    std = row.get("eval_return_std")
    return float(mean), float(std) if is_number(std) and "eval_return_mean" in row else math.nan


def is_number(v) -> bool:
    """A finite int or float (not a bool): a metrics value that can be plotted or compared."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


# ---------------------------------------------------------------------------------------------- the folder
class RunFolder:
    """One run folder (``path``): create or find it, write its records, metrics, checkpoints and videos, read
    them back. Every file but metrics.jsonl is written atomically (a reader or a killed run sees the old file or
    the new one), readable as the umask allows."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"RunFolder({str(self.path)!r})"

    # ------------------------------------------------------------------ create or find
    @classmethod
    def create(cls, parent: str | os.PathLike, name: str) -> RunFolder:
        """A new run folder ``parent/name`` (created, writable); ValueError when it exists with files in it."""
        folder = cls(Path(parent) / name)
        check_writable(parent)
        if folder.path.exists() and any(p.name != LOCK for p in folder.path.iterdir()):
            raise ValueError(f"run folder {folder.path} exists and is not empty: pass --resume {folder.path} or "
                             f"another --name")
        check_writable(folder.path)
        return folder

    @classmethod
    def existing(cls, path: str | os.PathLike) -> RunFolder:
        """The run folder at ``path`` (to resume or add to); ValueError when it has no config.json."""
        folder = cls(path)
        if not folder.path.exists():
            raise ValueError(f"{folder.path}: no such folder")
        if not folder.path.is_dir():
            raise ValueError(f"{folder.path} is a file, not a run folder (give the folder that holds config.json)")
        if not folder.config_path.exists():
            raise ValueError(f"{folder.path}: no config.json there (not a run folder)")
        check_writable(folder.path)
        return folder

    def remove_if_empty(self) -> None:
        """Remove the folder when nothing was written into it (a run that stopped before its first record)."""
        try:
            self.path.rmdir()
        except OSError:
            pass

    # ------------------------------------------------------------------ paths
    @property
    def config_path(self) -> Path:
        return self.path / CONFIG

    @property
    def metrics_path(self) -> Path:
        return self.path / METRICS

    @property
    def summary_path(self) -> Path:
        return self.path / SUMMARY

    @property
    def checkpoint_dir(self) -> Path:
        return self.path / CHECKPOINTS

    @property
    def video_dir(self) -> Path:
        return self.path / VIDEOS

    # ------------------------------------------------------------------ write
    def write_config(self, record: dict) -> None:
        """config.json: ``record`` holds "config" (every setting) and what else the run records about itself."""
        atomic_write_json(self.config_path, record)

    def write_git(self, repo: Path | None = None) -> None:
        """git.txt (and git.diff when the tree differs from its commit) of the source tree at ``repo`` (default:
        this checkout)."""
        text, diff = git_info(repo)
        atomic_write_text(self.path / GIT, text)
        if diff:
            atomic_write_text(self.path / GIT_DIFF, diff)

    def append_metrics(self, row: dict) -> None:
        """One metrics line, handed to the operating system before this returns: a killed process loses none.
        Its way to the disk is forced where it matters, before the checkpoint (:meth:`save_checkpoint`) or summary
        that covers it, once for every line since, rather than a disk round trip a line and a member."""
        with open(self.metrics_path, "a") as f:
            f.write(json.dumps(row) + "\n")

    def sync_metrics(self) -> None:
        """Force the metrics lines written so far to the disk."""
        if self.metrics_path.exists():
            with open(self.metrics_path, "rb") as f:
                os.fsync(f.fileno())

    def settle_metrics(self, upto_iter: int) -> list[str]:
        """Before a resume from the checkpoint of iteration ``upto_iter``: metrics.jsonl keeps every readable line
        of an iteration up to it, as it was written; the lines after it (iterations the resume trains again) go to
        metrics.jsonl.redone-<time>, lines that do not read as a record to metrics.jsonl.damaged-<time> (both
        written before metrics.jsonl is replaced: a kill in between loses nothing); a torn last line is dropped.
        Returns one line per thing done or found (for stderr): each damaged line, the lines set aside, the torn
        line, a missing file and iterations up to ``upto_iter`` with no line."""
        path, notes = self.metrics_path, []
        if not path.exists():
            if upto_iter:
                notes.append(f"warning: {path} is missing: iterations 1..{upto_iter} have no metrics (plots and "
                             f"reports of this run start at iteration {upto_iter + 1})")
            return notes
        lines, torn = _metrics_lines(path.read_bytes())
        kept = [(n, line, row) for n, line, row in lines if row is not None and row["iter"] <= upto_iter]
        later = [(n, line, row) for n, line, row in lines if row is not None and row["iter"] > upto_iter]
        damaged = [(n, line) for n, line, row in lines if row is None]
        stamp = _stamp()
        if damaged:
            aside = _aside(path, f".damaged-{stamp}")
            atomic_write_bytes(aside, b"".join(line + b"\n" for _, line in damaged))
            for n, line in damaged[:5]:
                notes.append(f"warning: {path} line {n} is damaged (not a JSON record: {_shown(line)}); moved to "
                             f"{aside.name}")
            if len(damaged) > 5:
                notes.append(f"warning: {path}: {len(damaged) - 5} more damaged lines moved to {aside.name}")
        if later:
            aside = _aside(path, f".redone-{stamp}")
            atomic_write_bytes(aside, b"".join(line + b"\n" for _, line, _ in later))
            notes.append(f"note: {path}: the lines of iteration(s) {_spans([r['iter'] for _, _, r in later])} come "
                         f"after the checkpoint of iteration {upto_iter} and are trained again; the old lines are "
                         f"kept in {aside.name}")
        if torn is not None:
            notes.append(f"note: {path}: its last line was cut off mid-write (the run was killed while writing it); "
                         f"dropped: {_shown(torn)}")
        missing = sorted(set(range(1, upto_iter + 1)) - {row["iter"] for _, _, row in kept})
        if missing:
            notes.append(f"warning: {path} has no line for iteration(s) {_spans(missing)} (plots and reports of "
                         f"this run show a gap there)")
        if damaged or later or torn is not None:
            atomic_write_bytes(path, b"".join(line + b"\n" for _, line, _ in kept))
        return notes

    def set_aside_for_restart(self) -> list[str]:
        """Before a run trains again from iteration 1 in this folder (``--restart``: no checkpoint a resume could
        take): its metrics.jsonl, summary.json, videos/ and checkpoints/ (a population's member can hold one the
        others do not have) renamed to <name>.before-restart-<time>; one line per name. Its config.json and
        git.txt are then written anew by the restart."""
        stamp, notes = _stamp(), []
        for path in (self.metrics_path, self.summary_path, self.video_dir, self.checkpoint_dir, self.config_path,
                     self.path / GIT, self.path / GIT_DIFF):
            if path.exists() and (path.is_dir() or path.stat().st_size):
                aside = _aside(path, f".before-restart-{stamp}")
                os.replace(path, aside)
                notes.append(f"note: --restart: {path} kept as {aside.name}")
        return notes

    def append_provenance(self, event: str, iteration: int, repo: Path | None = None) -> dict:
        """One line of provenance.jsonl for this start of the run (``event``: "start", "resume" or "restart", from
        the checkpoint of ``iteration``; 0: from the first): the UTC time, the commit and whether the tree was
        dirty (None where there is no repository), and the training tree's hash (``ablations.tree_hash``, as
        config.json records it: comparable across copies without a repository). A dirty resume or restart keeps
        its own diff beside, git.diff.<event>-<time> (the first start's is git.diff). Returns the line's record."""
        repo = repo or Path(__file__).resolve().parents[1]
        commit, dirty, diff = git_state(repo)
        entry = {"event": event, "iteration": iteration,
                 "utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                 "commit": commit or os.environ.get("PIXELGRAD_COMMIT"), "dirty": dirty,
                 "tree_hash": tree_hash(repo).value}
        if dirty and event != "start":
            aside = _aside(self.path / GIT_DIFF, f".{event}-{_stamp()}")
            atomic_write_text(aside, diff)
            entry["diff"] = aside.name
        with open(self.path / PROVENANCE, "a") as f:
            f.write(json.dumps(entry) + "\n")
        return entry

    def read_provenance(self) -> list[dict]:
        """provenance.jsonl's records, oldest first ([] for a folder written before it existed)."""
        try:
            data = (self.path / PROVENANCE).read_bytes()
        except FileNotFoundError:
            return []
        out = []
        for line in data.split(b"\n"):
            try:
                row = json.loads(line.decode("utf-8"))
            except ValueError:
                continue
            if isinstance(row, dict):
                out.append(row)
        return out

    def write_summary(self, summary: dict) -> None:
        self.sync_metrics()  # the lines it sums up first
        atomic_write_json(self.summary_path, summary)

    def write_video(self, iteration: int, frames: list[np.ndarray], fps: int = 60) -> Path | None:
        """videos/iter_<iteration>.mp4 of frames (H, W, 3) uint8 RGB (mp4v), written under a temporary name and
        renamed; None (nothing written) without frames."""
        import cv2

        if not frames:
            return None
        path = self.video_dir / f"iter_{iteration:06d}.mp4"
        h, w = frames[0].shape[:2]
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.stem}.tmp.mp4")
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
        if not writer.isOpened():
            raise RuntimeError(f"OpenCV could not open an MP4 writer for {path}")
        for f in frames:
            writer.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
        writer.release()
        os.replace(tmp, path)
        return path

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self, iteration: int, state: dict) -> Path:
        """checkpoints/ckpt_<iteration>.pt; returns its path. Older ones stay until :meth:`prune_checkpoints`
        (a population prunes once every member's new one is written)."""
        from gradlab.checkpoint import checkpoint_path, save_checkpoint

        path = checkpoint_path(self.checkpoint_dir, iteration)
        self.sync_metrics()  # the lines it covers first: a resume truncates the metrics to the checkpoint
        save_checkpoint(path, state)
        return path

    def checkpoints(self) -> list[Path]:
        """The checkpoint files, newest (highest iteration) first."""
        from gradlab.checkpoint import list_checkpoints

        return list_checkpoints(self.checkpoint_dir)

    def checkpoint_iterations(self) -> set[int]:
        """The iterations this folder holds a checkpoint of."""
        from gradlab.checkpoint import checkpoint_iteration

        return {checkpoint_iteration(p) for p in self.checkpoints()}

    def newest_checkpoint(self) -> Path | None:
        found = self.checkpoints()
        return found[0] if found else None

    def prune_checkpoints(self, keep: int) -> None:
        from gradlab.checkpoint import prune_checkpoints

        prune_checkpoints(self.checkpoint_dir, keep=keep)

    def drop_checkpoints(self) -> None:
        """Delete every checkpoint (a finished run that keeps none)."""
        shutil.rmtree(self.checkpoint_dir, ignore_errors=True)

    def load_checkpoint(self, device: torch.device | str = "cpu") -> LoadedCheckpoint | None:
        """The newest checkpoint that loads (None: the folder has none at all, so a resume starts from the first
        iteration). Damaged newer ones are reported on stderr and renamed aside (``.damaged`` appended), so that
        they no longer count among the newest when the resumed run prunes, and stay for inspection. ValueError
        when every checkpoint is damaged."""
        from gradlab.checkpoint import NoReadableCheckpointError, load_newest_readable

        if not self.checkpoints():
            return None
        try:
            loaded = load_newest_readable(self.checkpoint_dir, map_location=device)
        except NoReadableCheckpointError as e:
            raise ValueError(str(e)) from None
        for path, why in loaded.damaged:
            set_aside_damaged_checkpoint(path, why, loaded.path)
        return loaded

    # ------------------------------------------------------------------ read
    def read_record(self) -> dict:
        """config.json as a dict with a "config" object; ValueError naming the file when it is missing, does not
        parse or was not written by ``ablate``."""
        path = self.config_path
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise ValueError(f"{self.path} is not a run folder: it has no config.json (expected config.json, "
                             f"metrics.jsonl, summary.json as written by `ablate`)") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise ValueError(f"{path} cannot be read ({type(e).__name__}: {e})") from None
        if not isinstance(data, dict) or not isinstance(data.get("config"), dict):
            raise ValueError(f"{path} has no 'config' object: not written by `ablate`")
        return data

    def read_metrics(self) -> list[dict]:
        return read_metrics(self.path)

    def read_summary(self) -> dict | None:
        """summary.json, or None when there is none (yet) or it does not parse (it is
        written atomically, so a file that does not parse is not the run's)."""
        try:
            data = json.loads(self.summary_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            return None
        return data if isinstance(data, dict) else None

    def videos(self) -> list[Path]:
        """The evaluation videos, oldest first."""
        return sorted(self.video_dir.glob("iter_*.mp4"))


class MetricsTail:
    """The newest complete line of a growing metrics.jsonl, reading only what was appended since the last look."""

    def __init__(self, path: str | os.PathLike):
        self.path, self.offset, self.last, self.inode = Path(path), 0, None, None

    def poll(self) -> dict | None:
        try:
            with open(self.path, "rb") as f:
                st = os.fstat(f.fileno())
                if st.st_ino != self.inode or st.st_size < self.offset:  # rewritten (a resume truncates it)
                    self.inode, self.offset = st.st_ino, 0
                f.seek(self.offset)
                chunk = f.read()
        except FileNotFoundError:
            return self.last
        end = chunk.rfind(b"\n")
        if end >= 0:
            self.offset += end + 1
            for line in reversed(chunk[:end].splitlines()):
                try:
                    self.last = json.loads(line)
                    break
                except json.JSONDecodeError:
                    continue
        return self.last


# ---------------------------------------------------------------------------------------------- reading
@dataclass
class Run:
    """One run folder's records, parsed (:func:`load_run`)."""

    path: Path
    config: dict
    environment: dict
    command: list | None
    summary: dict | None
    metrics: list[dict]
    #: config.json's "preset" record (name, supplied, overridden), when the run has one.
    preset: dict | None = None
    #: config.json's "started_utc", when the run recorded it.
    started_utc: str | None = None
    #: config.json's "population" record (its folder and members), when the run trained in one.
    population: dict | None = None
    #: config.json's "tree_hash" (``ablations.tree_hash``): the training tree's hash, when the run recorded it.
    tree_hash: str | None = None

    @property
    def task(self) -> str:
        return str(self.config.get("task"))

    @property
    def mode(self) -> str:
        return str(self.config.get("mode"))

    @property
    def seed(self):
        return self.config.get("seed")

    def setting(self, key: str):
        """A config.json setting (``preset`` falls back to the name in the preset record); None when absent."""
        value = self.config.get(key)
        if value is None and key == "preset" and isinstance(self.preset, dict):
            value = self.preset.get("name")
        return value

    def series(self, x: str, y: str, *, skip_probed: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) of the iterations where both are finite numbers, sorted by x; ``skip_probed`` leaves out
        probe iterations (they differentiate twice, so their times and memory are not the mode's)."""
        pts = [(r[x], r[y]) for r in self.metrics if is_number(r.get(x)) and is_number(r.get(y))
               and not (skip_probed and r.get("probed"))]
        pts.sort()
        return np.array([p[0] for p in pts], float), np.array([p[1] for p in pts], float)

    def evaluations(self, x: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, mean, std) of the deterministic evaluations (:func:`evaluation_of`), sorted by x; std is NaN where a
        line has no spread over episodes."""
        pts = sorted((r[x], *ev) for r in self.metrics if is_number(r.get(x)) and (ev := evaluation_of(r)) is not None)
        return tuple(np.array([p[i] for p in pts], float) for i in range(3))  # type: ignore[return-value]


def load_run(path: str | os.PathLike) -> Run:
    """Parse a run folder; ValueError with the reason if it is not one."""
    folder = RunFolder(path)
    if not folder.path.exists():
        raise ValueError(f"{folder.path}: no such folder")
    if not folder.path.is_dir():
        raise ValueError(f"{folder.path} is a file, not a run folder (give the folder that holds config.json)")
    data = folder.read_record()
    config = data["config"]
    for k in ("task", "mode"):
        if k not in config:
            raise ValueError(f"{folder.config_path}: config has no {k!r}")
    preset = data.get("preset") if isinstance(data.get("preset"), dict) else None
    started = data.get("started_utc") if isinstance(data.get("started_utc"), str) else None
    population = data.get("population") if isinstance(data.get("population"), dict) else None
    tree = data.get("tree_hash") if isinstance(data.get("tree_hash"), str) else None
    return Run(path=folder.path, config=config, environment=data.get("environment") or {},
               command=data.get("command"), summary=folder.read_summary(), metrics=folder.read_metrics(),
               preset=preset, started_utc=started, population=population, tree_hash=tree)


def find_runs(paths: list[str | os.PathLike] | tuple) -> list[Run]:
    """Runs of the given folders; a folder that is not a run stands for every run folder below it, at any depth
    (an experiment's folder of populations, each a folder of member runs), in path order.

    Raises ValueError when no path is given, or a path is neither a run nor holds one.
    """
    if not paths:
        raise ValueError("no run folders given (pass one or more folders written by `ablate`)")
    runs: list[Run] = []
    for p in paths:
        p = Path(p)
        if p.is_dir() and not (p / CONFIG).exists():
            below = _runs_below(p)
            if below:
                runs.extend(load_run(c) for c in below)
                continue
        runs.append(load_run(p))
    return runs


def _runs_below(folder: Path) -> list[Path]:
    """The run folders (holding config.json) below ``folder``, sorted; a run's own subfolders are not searched."""
    found = []
    for child in sorted(c for c in folder.iterdir() if c.is_dir()):
        found.extend([child] if (child / CONFIG).exists() else _runs_below(child))
    return found



def thin_copy(src: str | os.PathLike, dst: str | os.PathLike, *, every: int) -> RunFolder:
    """A copy of the run folder ``src`` at ``dst`` small enough to keep in a repository: its records (config.json,
    git.txt, summary.json), videos, and the metrics lines of every ``every``-th iteration, every probe, every
    evaluation and the last iteration (what plots, reports and statistics read, a comparison at equal iterations
    up to where the run ended); no checkpoints, no git.diff. Returns the copy."""
    if every < 1:
        raise ValueError(f"every must be a positive integer, got {every}")
    source, copy = RunFolder.existing(src), RunFolder(dst)
    copy.path.mkdir(parents=True, exist_ok=True)
    for name in (CONFIG, GIT, SUMMARY):
        if (source.path / name).exists():
            shutil.copy2(source.path / name, copy.path / name)
    for video in source.videos():
        copy.video_dir.mkdir(exist_ok=True)
        shutil.copy2(video, copy.video_dir / video.name)
    rows = source.read_metrics()
    kept = [r for i, r in enumerate(rows) if r["iter"] % every == 0 or r.get("probed") or evaluation_of(r) is not None
            or i == len(rows) - 1]
    atomic_write_text(copy.metrics_path, "".join(json.dumps(r) + "\n" for r in kept))
    return copy
