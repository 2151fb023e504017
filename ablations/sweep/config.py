"""The ``ablate-sweep`` options (:class:`SweepConfig`), its TOML file, and ``--set``/``--vary`` as ablate flags."""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import tyro

from ablations.naming import slug
from ablations.run_config import RunConfig
from vocabulary import MODES, TASKS

__all__ = ["SweepConfig", "parse_args", "parse_set", "parse_vary", "norm_key", "flag_args", "slug", "RESERVED",
           "AUTO_PACK_GPU"]

#: ``ablate`` flags the sweep sets itself (the grid's own axes, where each run's folder goes, its CPU threads).
#: Each run compiles in its own process (--no-compile-helper): a sweep's concurrent runs already use the cores that
#: a helper process would (ablations/startup/helpers.py).
RESERVED = {"task": "--tasks", "mode": "--modes", "seed": "--seeds", "out": "--out", "name": None,
            "resume": None, "restart": None, "progress": None, "compile_helper": None, "threads": "--cpus-per-run"}

# --help shows the valid values of the two named axes (the lists every command shares).
_TaskList = Annotated[tuple[str, ...], tyro.conf.arg(metavar="{" + ",".join(TASKS) + "} [...]")]
_ModeList = Annotated[tuple[str, ...], tyro.conf.arg(metavar="{" + ",".join(MODES) + "} [...]")]
_Pack = Annotated[str, tyro.conf.arg(metavar="{auto,N}")]

#: Members per population of ``--pack auto`` on a GPU (why: --pack's help, from BENCHMARKS.md section 7).
AUTO_PACK_GPU = 12


@dataclass
class SweepConfig:
    """Run a grid of `ablate` runs (tasks x modes x seeds x --vary flags) as Ray tasks; rerun to resume."""

    config: Path | None = None
    """TOML file with any of these options (underscores or dashes: tasks, modes, seeds, out, gpus-per-run...),
    a [set] table (flag = value) and a [vary] table (flag = [values]).
    Flags given on the command line win; their --set/--vary entries are added to the file's, key by key."""
    out: Path = Path("sweep")
    """The sweep folder: sweep.json, runs/<run_id>/, logs/. Reuse it to resume the sweep."""
    tasks: _TaskList = ("cartpole",)
    """Tasks (one grid axis)."""
    modes: _ModeList = ("full", "decoupled")
    """Gradient modes (one grid axis)."""
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
    """CPUs each run gets: at most (a node's CPUs / this) runs train on a node at once; its torch CPU threads
    (ablate --threads) are this, rounded down, at least 1."""
    gpus_per_run: float = 0.0
    """GPUs Ray reserves for each run; fractions share a GPU (0.25: four runs per GPU; Ray does not divide its memory).
    0: the run sees no GPU (CUDA_VISIBLE_DEVICES is emptied) and trains on the CPU."""
    pack: _Pack = "1"
    """Grid cells that can share a process (the same task and every setting but a member's own: mode, seed,
    raster model, preset and the other vocabulary.MEMBER_FIELDS) train as populations of at most N members,
    each one `ablate --member ...` process and one Ray task with the resources of one run (--cpus-per-run,
    --gpus-per-run); the members' run folders are runs/<population>/<member>. 1: one run per process. auto: 12
    on GPU runs (--gpus-per-run > 0; what the population benchmark measured at that size: BENCHMARKS.md
    section 7), 1 on the CPU. State runs form
    populations of their own. A population too large for its device's memory fails naming its size: lower N."""
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

    def validate(self) -> None:
        """Checks of the sweep's own options (the runs' flags are checked by :func:`~ablations.sweep.plan`)."""
        for name in ("tasks", "modes", "seeds"):
            if not getattr(self, name):
                raise ValueError(f"--{name} needs at least one value")
            values = list(getattr(self, name))
            if len(set(values)) != len(values):
                raise ValueError(f"--{name} lists a value twice: {values}")
        for name, known in (("tasks", TASKS), ("modes", MODES)):
            unknown = [v for v in getattr(self, name) if v not in known]
            if unknown:
                raise ValueError(f"--{name} {' '.join(map(str, unknown))}: choose from {', '.join(known)}")
        if self.cpus_per_run <= 0:
            raise ValueError(f"--cpus-per-run must be positive, got {self.cpus_per_run}")
        if self.gpus_per_run < 0:
            raise ValueError(f"--gpus-per-run must be >= 0, got {self.gpus_per_run}")
        if self.gpus_per_run > 1 and self.gpus_per_run != int(self.gpus_per_run):
            raise ValueError(f"--gpus-per-run above 1 must be a whole number, got {self.gpus_per_run}")
        if self.max_retries < 0:
            raise ValueError(f"--max-retries must be >= 0, got {self.max_retries}")
        self.pack_size()
        if self.address is not None and self.address.startswith("ray://"):
            raise ValueError(f"--address {self.address}: Ray Client is not supported; run ablate-sweep on a node "
                             "of the cluster (e.g. through `ray job submit`) with --address auto")
        if self.address is not None and (self.num_cpus is not None or self.num_gpus is not None):
            raise ValueError("--num-cpus/--num-gpus size a local cluster started here; they cannot be used with "
                             "--address")

    def pack_size(self) -> int:
        """Most members per population that --pack gives (1: one run per process); ValueError naming the flag."""
        text = str(self.pack).strip().lower()
        if text == "auto":
            return AUTO_PACK_GPU if self.gpus_per_run > 0 else 1
        if not text.isdigit() or int(text) < 1:
            raise ValueError(f"--pack must be auto or a positive whole number, got {self.pack!r}")
        return int(text)


# ---------------------------------------------------------------------------------------------------------
# ablate flags as --set / --vary / TOML entries


def _field_types() -> dict[str, str]:
    """ablate's field name -> annotation text (``from __future__ import annotations`` keeps them strings)."""
    return {f.name: str(f.type) for f in dataclasses.fields(RunConfig)}


def norm_key(key: str, *, where: str) -> str:
    """An ablate flag as its field name (``--num-envs`` -> ``num_envs``); ValueError naming ``where`` for a flag
    ablate lacks or one the sweep sets itself."""
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


def flag_args(name: str, value: Any) -> list[str]:
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


def _split_assign(item: str, *, flag: str) -> tuple[str, str]:
    if "=" not in item:
        raise ValueError(f"{flag} {item!r}: expected FLAG=VALUE")
    key, value = item.split("=", 1)
    if not key.strip():
        raise ValueError(f"{flag} {item!r}: the flag name is empty")
    return key, value


def parse_set(items: Iterable[str]) -> dict[str, Any]:
    """``--set FLAG=VALUE ...`` as {ablate field: value string}."""
    out: dict[str, Any] = {}
    for item in items:
        key, value = _split_assign(item, flag="--set")
        out[norm_key(key, where=f"--set {item}")] = value
    return out


def parse_vary(items: Iterable[str]) -> dict[str, list]:
    """``--vary FLAG=V1,V2 ...`` as {ablate field: [value strings]}."""
    out: dict[str, list] = {}
    for item in items:
        key, value = _split_assign(item, flag="--vary")
        values = [v.strip() for v in value.split(",")]
        if any(not v for v in values):
            raise ValueError(f"--vary {item!r}: an empty value (values are separated by commas)")
        out[norm_key(key, where=f"--vary {item}")] = values
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
    options, set_entries, vary_entries = {}, {}, {}
    for key, value in data.items():
        name = key.replace("-", "_")
        if name == "set":
            if not isinstance(value, dict):
                raise ValueError(f"--config {path}: [set] must be a table of flag = value")
            set_entries = {norm_key(k, where=f"{path} [set] {k}"): v for k, v in value.items()}
        elif name == "vary":
            if not isinstance(value, dict) or not all(isinstance(v, list) and v for v in value.values()):
                raise ValueError(f"--config {path}: [vary] must be a table of flag = [value, ...]")
            vary_entries = {norm_key(k, where=f"{path} [vary] {k}"): v for k, v in value.items()}
        elif name in fields:
            options[name] = tuple(value) if isinstance(value, list) else value
        else:
            raise ValueError(f"--config {path}: unknown key {key!r} (known: {', '.join(sorted(fields))}, set, vary)")
    if "out" in options:
        options["out"] = Path(options["out"])
    if "pack" in options:  # pack = 12 or pack = "auto"
        options["pack"] = str(options["pack"])
    return options, set_entries, vary_entries


def _config_file(argv: list[str]) -> Path | None:
    """The ``--config`` file the command line names (``--config FILE`` or ``--config=FILE``), read before the other
    flags because its values are their defaults."""
    for i, arg in enumerate(argv):
        if arg == "--config" and i + 1 < len(argv):
            return Path(argv[i + 1])
        if arg.startswith("--config="):
            return Path(arg.split("=", 1)[1])
    return None


def parse_args(argv: list[str] | None = None) -> tuple[SweepConfig, dict, dict]:
    """(config, set table, vary table) from the command line and the --config file it names."""
    from ablations.cli import parse

    argv = list(sys.argv[1:] if argv is None else argv)
    config = _config_file(argv)
    options, set_entries, vary_entries = ({}, {}, {}) if config is None else _load_toml(config)
    try:
        default = SweepConfig(**options)
    except TypeError as e:
        raise ValueError(f"--config {config}: {e}") from None
    cfg = parse(SweepConfig, argv, default=default, prog="ablate-sweep")
    return cfg, {**set_entries, **parse_set(cfg.set)}, {**vary_entries, **parse_vary(cfg.vary)}
