"""``ablate-sweep``: a grid of ``ablate`` runs (tasks x modes x seeds x any ``ablate`` flag) on Ray core.

Each run is one Ray task that starts ``python -m ablations ablate`` as a child process in a scratch folder on
whichever node Ray picked, so a crash, an out-of-memory kill or a bad configuration stays inside that run.
The node needs no filesystem shared with the driver: a small actor pinned to the driver's node (``RunStore``)
receives the run folder packed as a tar archive every time a new checkpoint appears and once at the end, and
writes it under ``<sweep>/runs/<run_id>/``. A retried task (its worker died, or its child was killed by a
signal) asks the store for the latest checkpoint it holds and continues with ``ablate --resume``.

The sweep folder::

    sweep.json                    the manifest (written atomically): grid, and per run its status
                                  (queued / running / done / failed), error, folder, iteration, latest return
    runs/<run_id>/                each run folder as ``ablate`` writes it (config.json, metrics.jsonl,
                                  summary.json, videos/, the two newest checkpoints)
    logs/<run_id>.attempt<N>.log  the child's output of each attempt
    discarded/                    folders of earlier attempts that stopped before any checkpoint (a fresh
                                  start needs an empty folder; nothing is deleted)

A rerun with the same folder skips runs whose summary says they finished, resumes the others from their last
checkpoint and starts the rest from scratch. Library use (the ``ablate-paper`` layer): build a
:class:`SweepConfig` (or :func:`parse_args`), then :func:`run_sweep` returns the manifest; :func:`plan` lists
the runs without starting anything. Both take ``arms``: named sets of ablate flags, each with its own mode,
that replace the modes axis (tasks x arms x seeds x --vary), for comparisons whose sides differ in more than
the mode (the paper's full arm with its own preset beside the soft-rasterizer one).

Each run folder keeps its ``KEPT_CHECKPOINTS`` newest checkpoints, so a resume survives a damaged newest one
(``ablate --resume`` falls back to the next).
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import re
import shutil
import signal
import sys
import tarfile
import tempfile
import time
import uuid
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ablations.runs import check_writable
from gradlab.checkpoint import (
    atomic_write_bytes,
    atomic_write_json,
    latest_checkpoint,
    list_checkpoints,
    prune_checkpoints,
)

__all__ = ["SweepConfig", "RunSpec", "RunStore", "RunProcessDied", "parse_args", "plan", "run_sweep", "dry_run",
           "load_manifest", "pack_run", "unpack_run", "main", "KEPT_CHECKPOINTS"]

MANIFEST = "sweep.json"
#: ``ablate`` flags the sweep sets itself (the grid's own axes, and where each run's folder goes).
#: Each run compiles in its own process (--no-compile-helper): a sweep's concurrent runs already use the cores that
#: a helper process would (ablations/compile_helper.py).
RESERVED = {"task": "--tasks", "mode": "--modes", "seed": "--seeds", "out": "--out", "name": None,
            "resume": None, "progress": None, "compile_helper": None}
#: ``ablate`` arguments every run of a sweep gets
RUN_ARGS = ("--no-progress", "--no-compile-helper")
#: Summary statuses of a run that needs no more work (time_limit: it stopped on the budget it was given).
FINISHED = ("finished", "time_limit")
STATUSES = ("queued", "running", "done", "failed")
#: Checkpoints a run folder in the sweep keeps (the newest ones): a resume falls back to the older one when the
#: newest does not load.
KEPT_CHECKPOINTS = 2
#: Seconds between the worker's looks at its run folder, and between the driver's table updates.
WORKER_POLL_S = 0.5
DRIVER_POLL_S = 1.0


@dataclass
class SweepConfig:
    """Run a grid of `ablate` runs (tasks x modes x seeds x --vary flags) as Ray tasks; rerun to resume."""

    config: Path | None = None
    """TOML file with any of these options (underscores or dashes: tasks, modes, seeds, out, gpus-per-run...),
    a [set] table (flag = value) and a [vary] table (flag = [values]).
    Flags given on the command line win; their --set/--vary entries are added to the file's, key by key."""
    out: Path = Path("sweep")
    """The sweep folder: sweep.json, runs/<run_id>/, logs/. Reuse it to resume the sweep."""
    tasks: tuple[str, ...] = ("cartpole",)
    """Tasks (one grid axis)."""
    modes: tuple[str, ...] = ("full", "decoupled")
    """Gradient modes: full, decoupled, state (one grid axis)."""
    seeds: tuple[int, ...] = (0,)
    """Seeds (one grid axis)."""
    set: tuple[str, ...] = ()
    """ablate flags shared by every run, as FLAG=VALUE (e.g. iters=500 num-envs=64 compile=true;
    list flags: actor-hidden="64 64")."""
    vary: tuple[str, ...] = ()
    """More grid axes over any ablate flag, as FLAG=V1,V2,... (e.g. image-size=64,84 horizon=16,32)."""
    address: str | None = None
    """Ray cluster to join: HOST:PORT, or auto (the cluster `ray start` began on this machine).
    None: RAY_ADDRESS or that cluster when there is one, else a local cluster started for this sweep.
    ray:// (Ray Client) is refused: the driver must run on a node of the cluster, where run folders are collected."""
    num_cpus: int | None = None
    """CPUs of a local cluster started here (None: all); only without --address."""
    num_gpus: int | None = None
    """GPUs of a local cluster started here (None: all detected); only without --address."""
    cpus_per_run: float = 1.0
    """CPUs Ray reserves for each run; its torch CPU threads (OMP_NUM_THREADS) are this, rounded down, at least 1."""
    gpus_per_run: float = 0.0
    """GPUs Ray reserves for each run; fractions share a GPU (0.25: four runs per GPU; Ray does not divide its memory).
    0: the run sees no GPU (CUDA_VISIBLE_DEVICES is emptied) and trains on the CPU."""
    max_retries: int = 3
    """Retries of a run whose worker process died or whose ablate process was killed by a signal.
    Each retry resumes from the last checkpoint the sweep folder holds.
    An ablate error (a bad value, a non-finite loss, out of memory) is not retried: it is recorded."""
    rerun_failed: bool = True
    """On a rerun, start (or resume) runs recorded as failed; --no-rerun-failed leaves them as they are."""
    keep_checkpoints: bool = True
    """Keep each finished run's two newest checkpoints in its folder (--no-keep-checkpoints deletes them once done)."""
    progress: bool = True
    """Live table (tqdm): done / running / failed / queued and each running run's iteration and latest return.
    Either way a line is printed whenever a run changes status."""
    dry_run: bool = False
    """List the runs (and what a rerun would do with each) and exit without starting Ray."""
    kill_once: tuple[str, ...] = ()
    """Fault injection, to test recovery: these runs' Ray workers kill themselves (SIGKILL) once each.
    Each dies right after its first checkpoint has reached the sweep folder, its ablate process with it.
    A marker in <out>/.killed/ (naming that checkpoint) keeps the retry from doing it again."""

    def validate(self) -> None:
        """Checks of the sweep's own options (the runs' flags are checked by :func:`plan`)."""
        for name in ("tasks", "modes", "seeds"):
            if not getattr(self, name):
                raise ValueError(f"--{name} needs at least one value")
            values = list(getattr(self, name))
            if len(set(values)) != len(values):
                raise ValueError(f"--{name} lists a value twice: {values}")
        if self.cpus_per_run <= 0:
            raise ValueError(f"--cpus-per-run must be positive, got {self.cpus_per_run}")
        if self.gpus_per_run < 0:
            raise ValueError(f"--gpus-per-run must be >= 0, got {self.gpus_per_run}")
        if self.gpus_per_run > 1 and self.gpus_per_run != int(self.gpus_per_run):
            raise ValueError(f"--gpus-per-run above 1 must be a whole number, got {self.gpus_per_run}")
        if self.max_retries < 0:
            raise ValueError(f"--max-retries must be >= 0, got {self.max_retries}")
        if self.address is not None and self.address.startswith("ray://"):
            raise ValueError(f"--address {self.address}: Ray Client is not supported; run ablate-sweep on a node "
                             "of the cluster (e.g. through `ray job submit`) with --address auto")
        if self.address is not None and (self.num_cpus is not None or self.num_gpus is not None):
            raise ValueError("--num-cpus/--num-gpus size a local cluster started here; they cannot be used with "
                             "--address")


@dataclass(frozen=True)
class RunSpec:
    """One point of the grid: its folder name and the ``ablate`` flags that define it."""

    run_id: str
    task: str
    mode: str
    seed: int
    #: The --vary values of this run, by ablate field name.
    flags: dict = field(default_factory=dict)
    #: ``ablate`` arguments without --out/--name/--progress (the worker adds those).
    args: tuple[str, ...] = ()
    iters: int = 0
    #: The arm this run belongs to (see :func:`plan`), or None in a tasks x modes grid.
    arm: str | None = None


class RunProcessDied(RuntimeError):
    """The ``ablate`` child was killed by a signal (the kernel's OOM killer, a node going away): Ray retries."""


# ---------------------------------------------------------------------------------------------------------
# Command line and TOML


def _field_types() -> dict[str, str]:
    """ablate's field name -> annotation text (``from __future__ import annotations`` keeps them strings)."""
    from ablations.runs import RunConfig

    return {f.name: str(f.type) for f in dataclasses.fields(RunConfig)}


def _norm_key(key: str, *, where: str) -> str:
    name = key.strip().lstrip("-").replace("-", "_")
    types = _field_types()
    if name.startswith("no_") and types.get(name[3:]) == "bool":
        raise ValueError(f"{where}: write {name[3:].replace('_', '-')}=false instead")
    if name not in types:
        raise ValueError(f"{where}: ablate has no flag --{name.replace('_', '-')} (see ablate --help)")
    if name in RESERVED:
        hint = RESERVED[name]
        flag = name.replace("_", "-")
        raise ValueError(f"{where}: the sweep sets --{flag} itself" + (f"; use {hint}" if hint else ""))
    return name


def _flag_args(name: str, value: Any) -> list[str]:
    """``ablate`` arguments for one field value: a TOML value (bool, number, list, string) or a CLI string."""
    flag = "--" + name.replace("_", "-")
    kind = _field_types()[name]
    if kind == "bool":
        if isinstance(value, str):
            low = value.strip().lower()
            if low not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError(f"{flag}: expected true or false, got {value!r}")
            value = low in ("true", "1", "yes")
        return [flag if value else "--no-" + flag[2:]]
    if value is None:
        return [flag, "None"]
    if isinstance(value, (list, tuple)):
        return [flag, *(str(v) for v in value)]
    if "tuple" in kind and isinstance(value, str):
        return [flag, *value.split()]
    return [flag, str(value)]


def _slug(value: Any) -> str:
    text = " ".join(str(v) for v in value) if isinstance(value, (list, tuple)) else str(value)
    return re.sub(r"[^A-Za-z0-9.+]+", "-", text).strip("-") or "none"


def _split_assign(item: str, *, flag: str) -> tuple[str, str]:
    if "=" not in item:
        raise ValueError(f"{flag} {item!r}: expected FLAG=VALUE")
    key, value = item.split("=", 1)
    if not key.strip():
        raise ValueError(f"{flag} {item!r}: the flag name is empty")
    return key, value


def _set_table(items: Iterable[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        key, value = _split_assign(item, flag="--set")
        out[_norm_key(key, where=f"--set {item}")] = value
    return out


def _vary_table(items: Iterable[str]) -> dict[str, list]:
    out: dict[str, list] = {}
    for item in items:
        key, value = _split_assign(item, flag="--vary")
        values = [v.strip() for v in value.split(",")]
        if any(not v for v in values):
            raise ValueError(f"--vary {item!r}: an empty value (values are separated by commas)")
        out[_norm_key(key, where=f"--vary {item}")] = values
    return out


def _load_toml(path: Path) -> tuple[dict, dict, dict]:
    """(sweep options, [set], [vary]) of a TOML file, keys normalised, unknown keys refused."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        raise ValueError("--config needs Python 3.11 or newer (tomllib)") from None
    try:
        data = tomllib.loads(Path(path).read_text())
    except OSError as e:
        raise ValueError(f"--config {path}: {e.strerror or e}") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"--config {path}: not valid TOML: {e}") from None
    fields = {f.name for f in dataclasses.fields(SweepConfig)} - {"config", "set", "vary"}
    options, set_table, vary_table = {}, {}, {}
    for key, value in data.items():
        name = key.replace("-", "_")
        if name == "set":
            if not isinstance(value, dict):
                raise ValueError(f"--config {path}: [set] must be a table of flag = value")
            set_table = {_norm_key(k, where=f"{path} [set] {k}"): v for k, v in value.items()}
        elif name == "vary":
            if not isinstance(value, dict) or not all(isinstance(v, list) and v for v in value.values()):
                raise ValueError(f"--config {path}: [vary] must be a table of flag = [value, ...]")
            vary_table = {_norm_key(k, where=f"{path} [vary] {k}"): v for k, v in value.items()}
        elif name in fields:
            options[name] = tuple(value) if isinstance(value, list) else value
        else:
            raise ValueError(f"--config {path}: unknown key {key!r} (known: {', '.join(sorted(fields))}, set, vary)")
    if "out" in options:
        options["out"] = Path(options["out"])
    return options, set_table, vary_table


def parse_args(argv: list[str] | None = None) -> tuple[SweepConfig, dict, dict]:
    """(config, set table, vary table) from the command line and the --config file it names."""
    import argparse

    import tyro

    argv = list(sys.argv[1:] if argv is None else argv)
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--config", type=Path, default=None)
    known, _ = pre.parse_known_args(argv)
    options, set_table, vary_table = ({}, {}, {}) if known.config is None else _load_toml(known.config)
    try:
        default = SweepConfig(**options)
    except TypeError as e:
        raise ValueError(f"--config {known.config}: {e}") from None
    cfg = tyro.cli(SweepConfig, args=argv, default=default, description=SweepConfig.__doc__)
    set_table = {**set_table, **_set_table(cfg.set)}
    vary_table = {**vary_table, **_vary_table(cfg.vary)}
    return cfg, set_table, vary_table


# ---------------------------------------------------------------------------------------------------------
# The grid


def _arm_table(arms: dict, set_table: dict, vary_table: dict) -> dict[str, tuple[str, dict]]:
    """{arm name: (mode, {ablate field: value})}, checked: names fit a folder name, flags exist and are not the
    sweep's own, and no flag of an arm is also in --set or --vary."""
    if not arms:
        raise ValueError("arms: give at least one arm (name -> {mode, flags})")
    table = {}
    for name, arm in arms.items():
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9.+-]*", str(name)):
            raise ValueError(f"arm {name!r}: names are letters, digits, '.', '+' and '-' (they name run folders)")
        if not isinstance(arm, dict) or not isinstance(arm.get("mode"), str):
            raise ValueError(f"arm {name}: needs a 'mode' (full, decoupled, state, blind)")
        unknown = set(arm) - {"mode", "flags", "about"}
        if unknown:
            raise ValueError(f"arm {name}: unknown keys {sorted(unknown)} (mode, flags, about)")
        flags = {_norm_key(k, where=f"arm {name} flag {k}"): v for k, v in (arm.get("flags") or {}).items()}
        both = sorted(set(flags) & (set(set_table) | set(vary_table)))
        if both:
            raise ValueError(f"arm {name}: {', '.join(both)} is set by the arm and also by --set/--vary")
        table[str(name)] = (arm["mode"], flags)
    return table


def plan(cfg: SweepConfig, set_table: dict | None = None, vary_table: dict | None = None, *,
         arms: dict | None = None) -> list[RunSpec]:
    """Every run of the grid, checked by ablate's own parser and validation; raises ValueError naming the run.

    ``set_table``/``vary_table`` default to the config's ``--set``/``--vary`` strings. ``arms``
    ({name: {"mode": ..., "flags": {flag: value}}}) replaces the modes axis: the grid is tasks x arms x seeds x
    --vary, run ids ``<task>_<arm>_seed<seed>...``, each run with its arm's mode and flags (after --set).
    """
    import itertools

    import tyro

    from ablations.runs import RunConfig

    cfg.validate()
    set_table = _set_table(cfg.set) if set_table is None else {_norm_key(k, where=f"set {k}"): v
                                                                for k, v in set_table.items()}
    vary_table = _vary_table(cfg.vary) if vary_table is None else {_norm_key(k, where=f"vary {k}"): list(v)
                                                                    for k, v in vary_table.items()}
    both = set(set_table) & set(vary_table)
    if both:
        raise ValueError(f"{', '.join(sorted(both))}: given in both --set and --vary")
    for name, values in vary_table.items():
        if len({_slug(v) for v in values}) != len(values):
            raise ValueError(f"--vary {name}: values repeat (or differ only in punctuation): {values}")
    shared = [a for name, value in set_table.items() for a in _flag_args(name, value)]
    columns = [(None, (mode, {})) for mode in cfg.modes] if arms is None else \
        list(_arm_table(arms, set_table, vary_table).items())
    specs, seen = [], {}
    axes = list(vary_table.items())
    for task, (arm, (mode, arm_flags)), seed in itertools.product(cfg.tasks, columns, cfg.seeds):
        for combo in itertools.product(*(values for _, values in axes)):
            flags = {name: value for (name, _), value in zip(axes, combo)}
            run_id = f"{task}_{arm or mode}_seed{seed}" + "".join(
                f"_{name.replace('_', '-')}{_slug(value)}" for name, value in flags.items())
            args = ["--task", str(task), "--mode", str(mode), "--seed", str(seed), *shared,
                    *(a for name, value in arm_flags.items() for a in _flag_args(name, value)),
                    *(a for name, value in flags.items() for a in _flag_args(name, value))]
            try:
                run_cfg = tyro.cli(RunConfig, args=[*args, *RUN_ARGS])
            except SystemExit:
                # tyro has printed what it rejected; name the run and its flags.
                raise ValueError(f"run {run_id}: ablate rejects its flags: {' '.join(args)}") from None
            try:
                run_cfg.validate()
            except ValueError as e:
                raise ValueError(f"run {run_id}: {e}") from None
            if run_id in seen:
                raise ValueError(f"runs {seen[run_id]} and {flags} share the folder name {run_id}")
            seen[run_id] = flags
            specs.append(RunSpec(run_id=run_id, task=str(task), mode=str(mode), seed=int(seed), flags=flags,
                                 args=tuple(args), iters=run_cfg.iters, arm=arm))
    return specs


# ---------------------------------------------------------------------------------------------------------
# Run folders as tar archives (the only way files travel between a worker and the driver)


def pack_run(run_dir: str | os.PathLike, *, checkpoints: int = 1, only: Iterable[str] | None = None) -> bytes:
    """The files of a run folder as an uncompressed tar archive (checkpoints hardly compress).

    Only the ``checkpoints`` newest checkpoints go in (0: none). ``only``: relative paths to include (default:
    every file). metrics.jsonl is cut after its last complete line: the run may be appending to it.
    """
    run_dir = Path(run_dir)
    if checkpoints < 0:
        raise ValueError(f"checkpoints must be >= 0, got {checkpoints}")
    kept = set(list_checkpoints(run_dir / "checkpoints")[:checkpoints])
    names = sorted(str(p.relative_to(run_dir)) for p in run_dir.rglob("*") if p.is_file()) if only is None \
        else sorted(set(only))
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for name in names:
            path = run_dir / name
            if name.startswith("checkpoints/") and path not in kept:
                continue
            if Path(name).name.startswith("."):  # a file being written atomically under a temporary name
                continue
            try:
                data = path.read_bytes()
            except FileNotFoundError:  # rotated away (an old checkpoint) or not written yet
                continue
            if name == "metrics.jsonl":
                data = data[:data.rfind(b"\n") + 1]
            info = tarfile.TarInfo(name)
            info.size = len(data)
            info.mtime = int(path.stat().st_mtime) if path.exists() else int(time.time())
            tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def unpack_run(data: bytes, run_dir: str | os.PathLike) -> list[str]:
    """Write an archive of :func:`pack_run` into run_dir, each file atomically; returns the names written.

    Files already there and not in the archive stay. When the archive brings checkpoints, its newest is the
    run's state: checkpoints of later iterations (an abandoned timeline: the run resumed from an older one)
    are deleted, and of the rest the ``KEPT_CHECKPOINTS`` newest stay.
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
    folder = run_dir / "checkpoints"
    shipped = [p for p in list_checkpoints(folder) if f"checkpoints/{p.name}" in written]
    if shipped:
        for later in list_checkpoints(folder)[:list_checkpoints(folder).index(shipped[0])]:
            later.unlink()
        prune_checkpoints(folder, keep=KEPT_CHECKPOINTS)
    return written


# ---------------------------------------------------------------------------------------------------------
# The driver-side store (a Ray actor pinned to the driver's node)


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
        return self.root / "runs" / run_id

    def begin(self, run_id: str) -> tuple[int, bytes | None]:
        """A new attempt: (its number, the run folder packed for ``ablate --resume``, or None: start fresh)."""
        attempt = self.attempts.get(run_id, 0) + 1
        self.attempts[run_id] = self.current[run_id] = attempt
        run_dir = self.run_dir(run_id)
        pack = None
        if latest_checkpoint(run_dir / "checkpoints") is not None:
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

    def claim_kill(self, run_id: str, checkpoint: str) -> bool:
        """True once per run id and sweep folder (the --kill-once fault injection); the marker file names the
        checkpoint the run had shipped when it was killed."""
        marker = self.root / ".killed" / run_id
        if marker.exists():
            return False
        atomic_write_bytes(marker, checkpoint.encode())
        return True


# ---------------------------------------------------------------------------------------------------------
# The Ray task: one attempt of one run on a worker node

_STOP_AT_CHECKPOINTS = "ABLATE_SWEEP_STOP_AT_CHECKPOINTS"  # set by the worker for --kill-once runs
#: Run in the child: die with the Ray worker that started it (Linux: PR_SET_PDEATHSIG survives exec), then
#: become ``python -m ablations ablate ...``. Without it a SIGKILLed worker would leave its run training.
_CHILD = f"""
import ctypes, os, signal, sys
parent = int(sys.argv[1])
if sys.platform.startswith("linux"):
    ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))
    if os.getppid() != parent:
        sys.exit("ablate-sweep: the worker that started this run is gone")
if os.environ.pop("{_STOP_AT_CHECKPOINTS}", None):
    # --kill-once: stop after each checkpoint until the worker has seen it (it resumes the run with SIGCONT),
    # so that the injected death comes mid-run even when the whole run is quicker than the worker's poll
    import gradlab.checkpoint, runpy
    save = gradlab.checkpoint.save_checkpoint
    def save_and_stop(*args, **kwargs):
        save(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGSTOP)
    gradlab.checkpoint.save_checkpoint = save_and_stop
    sys.argv = [sys.argv[0], "ablate", *sys.argv[2:]]
    runpy.run_module("ablations", run_name="__main__", alter_sys=True)
else:
    os.execv(sys.executable, [sys.executable, "-m", "ablations", "ablate", *sys.argv[2:]])
"""


def _tail(path: Path, n: int = 30) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


def _error_of(log: Path, returncode: int) -> str:
    """The line ablate's CLI prints for a failure ("error: ..."), else the last lines of the log."""
    lines = _tail(log, 200).splitlines()
    errors = [ln for ln in lines if ln.startswith("error: ")]
    if errors:
        return errors[-1][len("error: "):]
    exc = [ln for ln in lines if re.match(r"^[A-Za-z_][\w.]*(Error|Exception|Exit|Interrupt)\b", ln)]
    return (exc[-1] if exc else " | ".join(lines[-3:]) or "no output") + f" (exit code {returncode})"


class _MetricsTail:
    """The newest complete metrics line of a growing metrics.jsonl, reading only what was appended."""

    def __init__(self, path: Path):
        self.path, self.offset, self.last, self.inode = path, 0, None, None

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


def _run_attempt(spec: dict, store, opts: dict) -> dict:
    """Body of the Ray task: one attempt of one run (fresh or resumed); returns its result for the manifest."""
    import ray

    run_id = spec["run_id"]
    attempt, pack = ray.get(store.begin.remote(run_id))
    base = Path(tempfile.gettempdir()) / "ablate-sweep" / opts["sweep_id"]
    for stale in base.glob(f"{run_id}.attempt*"):  # left by an earlier attempt on this node that was killed
        shutil.rmtree(stale, ignore_errors=True)
    scratch = base / f"{run_id}.attempt{attempt}"
    run_dir = scratch / run_id
    scratch.mkdir(parents=True)
    if pack is not None:
        unpack_run(pack, run_dir)
        args = ["--resume", str(run_dir)]
    else:
        args = [*spec["args"], "--out", str(scratch), "--name", run_id]
    # What the store already holds needs no second trip.
    shipped = latest_checkpoint(run_dir / "checkpoints")
    sent_videos: set[str] = set()
    env = dict(os.environ, OMP_NUM_THREADS=str(max(1, int(opts["cpus_per_run"]))))
    if not opts["gpus_per_run"]:
        env["CUDA_VISIBLE_DEVICES"] = ""
    if run_id in opts["kill_once"]:
        env[_STOP_AT_CHECKPOINTS] = "1"  # see _CHILD
    log = scratch / "ablate.log"
    node = ray.get_runtime_context().get_node_id()
    import platform
    import subprocess

    try:
        with open(log, "wb") as log_f:
            proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(os.getpid()), *args, *RUN_ARGS],
                                    stdout=log_f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        store.report.remote(run_id, attempt, {"status": "running", "node": node, "host": platform.node(),
                                              "resumed": pack is not None})
        metrics = _MetricsTail(run_dir / "metrics.jsonl")
        reported = None
        while True:
            returncode = proc.poll()
            last = metrics.poll()
            if last is not None and last.get("iter") != reported:
                reported = last.get("iter")
                store.report.remote(run_id, attempt, {"iteration": reported,
                                                      "latest_return": last.get("return_mean")})
            ckpt = latest_checkpoint(run_dir / "checkpoints")
            if returncode is None and ckpt is not None and ckpt != shipped:
                # metrics.jsonl gets an iteration's line before its checkpoint: read after seeing the checkpoint,
                # it covers every iteration the checkpoint does.
                videos = _new_videos(run_dir, sent_videos)
                data = pack_run(run_dir, only=[*_RESUME_FILES, *videos, str(ckpt.relative_to(run_dir))])
                if f"checkpoints/{ckpt.name}" in tarfile.open(fileobj=io.BytesIO(data)).getnames():
                    ray.get(store.save.remote(run_id, attempt, data))
                    shipped = ckpt
                    sent_videos.update(videos)
                    if run_id in opts["kill_once"] and ray.get(store.claim_kill.remote(run_id, ckpt.name)):
                        _kill_self_mid_run(store, run_id, attempt, log)
                if run_id in opts["kill_once"]:  # the run stopped itself after this checkpoint (see _CHILD)
                    proc.send_signal(signal.SIGCONT)
            if returncode is not None:
                break
            time.sleep(WORKER_POLL_S)
        ray.get(store.save_log.remote(run_id, attempt, log.read_text(errors="replace")))
        if returncode < 0:
            try:
                name = signal.Signals(-returncode).name
            except ValueError:
                name = str(-returncode)
            raise RunProcessDied(f"ablate was killed by signal {name} on {platform.node()} "
                                 f"(attempt {attempt}); last output: {_tail(log, 3)}")
        summary = {}
        if (run_dir / "summary.json").exists():
            summary = json.loads((run_dir / "summary.json").read_text())
        done = returncode == 0 and summary.get("status") in FINISHED
        rest = [str(p.relative_to(run_dir)) for p in run_dir.rglob("*") if p.is_file()]
        # An unfinished run keeps its checkpoint whatever --keep-checkpoints says: a rerun resumes from it.
        data = pack_run(run_dir, only=[n for n in rest if n not in sent_videos],
                        checkpoints=1 if opts["keep_checkpoints"] or not done else 0)
        ray.get(store.save.remote(run_id, attempt, data))
        last = metrics.poll() or {}
        return {"status": "done" if done else "failed",
                "error": None if done else _error_of(log, returncode),
                "summary_status": summary.get("status"),
                "iteration": summary.get("iterations", last.get("iter")),
                "latest_return": summary.get("final_return", last.get("return_mean")),
                "attempt": attempt, "node": node, "host": platform.node()}
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _kill_self_mid_run(store, run_id: str, attempt: int, log: Path) -> None:
    """--kill-once: SIGKILL this Ray worker, as a node's OOM killer or a lost node would; its child follows."""
    import ray

    note = _tail(log, 10_000) + "\n[ablate-sweep --kill-once: the Ray worker kills itself]\n"
    ray.get(store.save_log.remote(run_id, attempt, note))
    os.kill(os.getpid(), signal.SIGKILL)


#: What ``ablate --resume`` needs besides the checkpoint (git.* keep the folder complete if the driver's is all).
_RESUME_FILES = ("config.json", "git.txt", "git.diff", "metrics.jsonl")


def _new_videos(run_dir: Path, sent: set[str]) -> list[str]:
    """Evaluation videos not shipped yet (small: they ride along with the checkpoints)."""
    return [n for n in (str(p.relative_to(run_dir)) for p in sorted((run_dir / "videos").glob("*.mp4")))
            if n not in sent]


# ---------------------------------------------------------------------------------------------------------
# The manifest


def load_manifest(out: str | os.PathLike) -> dict | None:
    """The sweep folder's sweep.json, or None when there is none yet."""
    path = Path(out) / MANIFEST
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not valid JSON ({e}); written atomically, it was edited by hand") from None


def _run_state(out: Path, spec: RunSpec) -> str:
    """What a (re)run must do with a run: 'done' (its summary says so), 'resume' (a checkpoint) or 'start'."""
    run_dir = out / "runs" / spec.run_id
    try:
        summary = json.loads((run_dir / "summary.json").read_text())
    except (OSError, json.JSONDecodeError):
        summary = {}
    if summary.get("status") in FINISHED and (summary.get("iterations", 0) >= spec.iters
                                              or summary.get("status") == "time_limit"):
        return "done"
    return "resume" if latest_checkpoint(run_dir / "checkpoints") is not None else "start"


def _new_record(spec: RunSpec) -> dict:
    return {"task": spec.task, "mode": spec.mode, "arm": spec.arm, "seed": spec.seed, "flags": spec.flags,
            "args": list(spec.args), "iters": spec.iters, "folder": f"runs/{spec.run_id}", "status": "queued",
            "error": None, "iteration": None, "latest_return": None, "attempts": 0, "resumed": False, "node": None,
            "host": None, "updated": None}


def _prepare_manifest(cfg: SweepConfig, specs: list[RunSpec], set_table: dict, vary_table: dict,
                      argv: list[str] | None, arms: dict | None = None) -> tuple[dict, list[RunSpec]]:
    """The manifest to start from (existing runs checked against the grid) and the runs to launch."""
    out = Path(cfg.out)
    manifest = load_manifest(out) or {"version": 1, "id": uuid.uuid4().hex[:12],
                                      "created": time.strftime("%Y-%m-%dT%H:%M:%S"), "runs": {}}
    runs = manifest["runs"]
    for spec in specs:
        old = runs.get(spec.run_id)
        if old is not None and old.get("args") != list(spec.args):
            raise ValueError(f"{out / MANIFEST}: run {spec.run_id} was made with the flags {' '.join(old['args'])}, "
                             f"this sweep gives it {' '.join(spec.args)}; use another --out for a different sweep")
    todo = []
    for spec in specs:
        rec = runs.setdefault(spec.run_id, _new_record(spec))
        state = _run_state(out, spec)
        if state == "done":
            rec.update(status="done", error=None)
        elif rec["status"] == "failed" and not cfg.rerun_failed:
            continue
        else:
            rec.update(status="queued", resumed=state == "resume")
            todo.append(spec)
    manifest["sweep"] = {"tasks": list(cfg.tasks), "modes": list(cfg.modes), "seeds": list(cfg.seeds),
                         "set": {k: v for k, v in set_table.items()}, "vary": {k: v for k, v in vary_table.items()},
                         "cpus_per_run": cfg.cpus_per_run, "gpus_per_run": cfg.gpus_per_run,
                         "max_retries": cfg.max_retries}
    if arms is not None:
        manifest["sweep"]["arms"] = arms
    manifest["command"] = ["ablate-sweep", *(sys.argv[1:] if argv is None else argv)]
    return manifest, todo


def _write_manifest(out: Path, manifest: dict) -> None:
    counts = {s: 0 for s in STATUSES}
    for rec in manifest["runs"].values():
        counts[rec["status"]] = counts.get(rec["status"], 0) + 1
    manifest["counts"] = counts
    manifest["updated"] = time.strftime("%Y-%m-%dT%H:%M:%S")
    atomic_write_json(out / MANIFEST, manifest)


# ---------------------------------------------------------------------------------------------------------
# The live table


def _fmt_return(value: Any) -> str:
    return "-" if value is None else f"{value:.4g}"


class _Table:
    """A tqdm bar of finished runs (counts by status in its postfix) and one bar per running run."""

    def __init__(self, manifest: dict, todo: list[RunSpec], *, enabled: bool):
        self.enabled = enabled
        self.manifest = manifest
        self.iters = {s.run_id: s.iters for s in todo}
        self.bars: dict[str, Any] = {}
        self.free: list[int] = []
        self.last_status: dict[str, str] = {}
        self.main = None
        if enabled:
            from tqdm.auto import tqdm

            self.tqdm = tqdm
            self.main = tqdm(total=len(manifest["runs"]), desc="sweep", unit="run", dynamic_ncols=True, position=0)
        self.update()

    def _print(self, text: str) -> None:
        if self.enabled:
            self.tqdm.write(text)
        else:
            print(text, flush=True)

    def counts(self) -> dict[str, int]:
        counts = {s: 0 for s in STATUSES}
        for rec in self.manifest["runs"].values():
            counts[rec["status"]] += 1
        return counts

    def update(self) -> None:
        runs = self.manifest["runs"]
        for run_id, rec in runs.items():
            status, before = rec["status"], self.last_status.get(run_id)
            if status != before:
                self.last_status[run_id] = status
                if before is not None or status in ("done", "failed"):
                    extra = f"  error: {rec['error']}" if rec.get("error") else ""
                    it = f"{rec.get('iteration') or 0}/{rec.get('iters')}"
                    self._print(f"{status:8s} {run_id}  it {it}  return {_fmt_return(rec.get('latest_return'))}"
                                f"  attempts {rec.get('attempts')}{extra}")
            if not self.enabled:
                continue
            bar = self.bars.get(run_id)
            if status == "running":
                if bar is None:
                    pos = self.free.pop(0) if self.free else len(self.bars) + 1
                    bar = self.bars[run_id] = self.tqdm(total=self.iters.get(run_id, rec.get("iters")), desc=run_id,
                                                        unit="it", position=pos, leave=False, dynamic_ncols=True)
                    bar.pos_ = pos
                bar.n = rec.get("iteration") or 0
                bar.set_postfix(ret=_fmt_return(rec.get("latest_return")), refresh=False)
                bar.refresh()
            elif bar is not None:
                self.free.append(bar.pos_)
                self.free.sort()
                bar.close()
                del self.bars[run_id]
        if self.main is not None:
            c = self.counts()
            self.main.n = c["done"] + c["failed"]
            self.main.set_postfix_str(" ".join(f"{k} {v}" for k, v in c.items()), refresh=False)
            self.main.refresh()

    def close(self) -> None:
        for bar in self.bars.values():
            bar.close()
        if self.main is not None:
            self.main.close()


# ---------------------------------------------------------------------------------------------------------
# The driver


def _ray_init(cfg: SweepConfig) -> bool:
    """Connect to (or start) the cluster unless this process already is; True when this call did it."""
    import logging

    import ray

    if ray.is_initialized():
        return False
    kwargs: dict[str, Any] = dict(address=cfg.address, include_dashboard=False, logging_level=logging.WARNING,
                                  log_to_driver=False)
    if cfg.num_cpus is not None:
        kwargs["num_cpus"] = cfg.num_cpus
    if cfg.num_gpus is not None:
        kwargs["num_gpus"] = cfg.num_gpus
    try:
        ray.init(**kwargs)
    except ConnectionError as e:
        raise ValueError(f"--address {cfg.address}: cannot join the Ray cluster: {e}") from None
    return True


def _check_resources(cfg: SweepConfig) -> None:
    """Refuse a sweep that no node could ever schedule (Ray would wait for ever)."""
    import ray

    nodes = [n for n in ray.nodes() if n.get("Alive")]
    cpus = max((n["Resources"].get("CPU", 0) for n in nodes), default=0)
    gpus = max((n["Resources"].get("GPU", 0) for n in nodes), default=0)
    if cfg.cpus_per_run > cpus:
        raise ValueError(f"--cpus-per-run {cfg.cpus_per_run}: no node of the cluster has that many (largest: {cpus})")
    if cfg.gpus_per_run > gpus:
        raise ValueError(f"--gpus-per-run {cfg.gpus_per_run}: no node of the cluster has that many GPUs "
                         f"(largest: {gpus})")


def _describe_failure(exc: BaseException) -> str:
    cause = getattr(exc, "cause", None)
    if isinstance(cause, BaseException):
        exc = cause
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".strip()[:2000]


def run_sweep(cfg: SweepConfig, set_table: dict | None = None, vary_table: dict | None = None, *,
              argv: list[str] | None = None, arms: dict | None = None) -> dict:
    """Run (or resume) the sweep; returns the final manifest. Bad input raises ValueError before any run.

    ``arms``: see :func:`plan`. Uses the Ray connection of this process when there is one (it is left open),
    else joins or starts the cluster that ``cfg.address`` names and shuts the connection down at the end.
    """
    specs = plan(cfg, set_table, vary_table, arms=arms)
    set_table = _set_table(cfg.set) if set_table is None else set_table
    vary_table = _vary_table(cfg.vary) if vary_table is None else vary_table
    out = Path(cfg.out).resolve()
    check_writable(out)
    manifest, todo = _prepare_manifest(cfg, specs, set_table, vary_table, argv, arms)
    unknown = sorted(set(cfg.kill_once) - {s.run_id for s in specs})
    if unknown:
        raise ValueError(f"--kill-once {' '.join(unknown)}: no such run in this sweep")
    _write_manifest(out, manifest)
    if not todo:
        return manifest

    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    started_here = _ray_init(cfg)
    table = None
    pending: dict = {}
    try:
        _check_resources(cfg)
        runs = manifest["runs"]
        store = ray.remote(RunStore).options(
            num_cpus=0, max_concurrency=1,
            scheduling_strategy=NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False),
        ).remote(str(out), {k: r.get("attempts", 0) for k, r in runs.items()})
        task = ray.remote(_run_attempt).options(num_cpus=cfg.cpus_per_run, num_gpus=cfg.gpus_per_run,
                                                max_retries=cfg.max_retries, retry_exceptions=[RunProcessDied])
        opts = {"sweep_id": manifest["id"], "gpus_per_run": cfg.gpus_per_run, "cpus_per_run": cfg.cpus_per_run,
                "keep_checkpoints": cfg.keep_checkpoints, "kill_once": list(cfg.kill_once)}
        for spec in todo:
            pending[task.remote(dataclasses.asdict(spec), store, opts)] = spec.run_id
        table = _Table(manifest, todo, enabled=cfg.progress)
        last_write = time.monotonic()
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=DRIVER_POLL_S)
            changed = False
            for run_id, info in ray.get(store.snapshot.remote()).items():
                rec = runs[run_id]
                if rec["status"] in ("done", "failed") and info.get("attempts", 0) <= rec.get("attempts", 0):
                    continue
                new = {k: info[k] for k in ("iteration", "latest_return", "node", "host", "attempts", "resumed")
                       if k in info}
                if info.get("status") == "running" and rec["status"] == "queued":
                    new["status"] = "running"
                if any(rec.get(k) != v for k, v in new.items()):
                    rec.update(new, updated=time.strftime("%Y-%m-%dT%H:%M:%S"))
                    changed = changed or "status" in new
            for ref in ready:
                run_id = pending.pop(ref)
                rec = runs[run_id]
                try:
                    result = ray.get(ref)
                except ray.exceptions.RayError as e:
                    # Retries are spent (a worker death, a killed ablate) or the task itself broke.
                    tries = max(rec.get("attempts") or 0, 1)
                    result = {"status": "failed", "error": f"{_describe_failure(e)} (attempt {tries}, "
                                                           f"--max-retries {cfg.max_retries})"}
                rec.update({k: v for k, v in result.items() if k in ("status", "error", "iteration", "latest_return",
                                                                     "node", "host", "summary_status")},
                           updated=time.strftime("%Y-%m-%dT%H:%M:%S"))
                rec["attempts"] = max(rec.get("attempts", 0), result.get("attempt", 0))
                if rec["status"] == "done" and not cfg.keep_checkpoints:
                    shutil.rmtree(out / rec["folder"] / "checkpoints", ignore_errors=True)
                changed = True
            if changed or time.monotonic() - last_write > 10 * DRIVER_POLL_S:
                _write_manifest(out, manifest)
                last_write = time.monotonic()
            table.update()
        snap = ray.get(store.snapshot.remote())
        for run_id, info in snap.items():
            runs[run_id]["attempts"] = max(runs[run_id].get("attempts", 0), info.get("attempts", 0))
    except KeyboardInterrupt:
        # Unfinished runs go back to queued: a rerun resumes them from the checkpoints the folder holds.
        for run_id in pending.values():
            manifest["runs"][run_id]["status"] = "queued"
        raise
    finally:
        if table is not None:
            table.close()
        _write_manifest(out, manifest)
        if started_here:
            ray.shutdown()
    return manifest


def dry_run(cfg: SweepConfig, set_table: dict | None = None, vary_table: dict | None = None, *,
            arms: dict | None = None) -> list[str]:
    """Print (and return) one line per run, with what a (re)run would do with it; starts nothing."""
    specs = plan(cfg, set_table, vary_table, arms=arms)
    out = Path(cfg.out)
    manifest = load_manifest(out) or {"runs": {}}
    lines = []
    for spec in specs:
        state = _run_state(out, spec)
        if state != "done" and manifest["runs"].get(spec.run_id, {}).get("status") == "failed" \
                and not cfg.rerun_failed:
            state = "failed (left)"
        lines.append(f"{state:8s} {spec.run_id}: ablate {' '.join(spec.args)}")
    lines.append(f"{len(specs)} runs; {cfg.cpus_per_run} CPU and {cfg.gpus_per_run} GPU each")
    for line in lines:
        print(line)
    return lines


def main(argv: list[str] | None = None) -> None:
    """``ablate-sweep --tasks cartpole hopper --modes full decoupled --seeds 0 1 2 --vary image-size=64,84``."""
    try:
        cfg, set_table, vary_table = parse_args(argv)
        if cfg.dry_run:
            dry_run(cfg, set_table, vary_table)
            return
        manifest = run_sweep(cfg, set_table, vary_table, argv=argv)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    except KeyboardInterrupt:
        print(f"interrupted; rerun the same command to resume ({Path(cfg.out) / MANIFEST})", file=sys.stderr)
        raise SystemExit(130) from None
    counts = manifest["counts"]
    print(f"{Path(cfg.out) / MANIFEST}: " + ", ".join(f"{n} {s}" for s, n in counts.items()))
    for run_id, rec in manifest["runs"].items():
        if rec["status"] == "failed":
            print(f"failed {run_id}: {rec['error']}", file=sys.stderr)
    if counts.get("failed"):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
