"""Several runs trained in one process (``gradlab.SHAC`` with a list of configs): ``ablate``'s options with several
values, the members they stand for, and the population folder that holds the members' run folders.

``ablate --mode decoupled full blind --seed 0 1 2`` trains the product of the values as one population; with
``--member`` the members are listed one by one instead. The population folder holds ``population.json`` (the
members' folder names, the command) and one ordinary run folder per member, whose config.json names the
population it ran in: plots, reports and statistics read members as they read single runs.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from ablations.run_folder import RunFolder, check_writable
from ablations.runs import RunConfig
from gradlab.config import SHACConfig
from vocabulary import MEMBER_FIELDS, MODES, POPULATION_RECORD, PRESETS, RASTER_MODELS

__all__ = ["AblateConfig", "POPULATION", "PopulationFolder", "member_name", "is_population"]

#: The record a population folder holds beside its members' run folders.
POPULATION = POPULATION_RECORD

_PRODUCT = ("mode", "raster_model", "preset", "seed")


@dataclass
class AblateConfig(RunConfig):
    """Train SHAC on a task with full, decoupled (D.Va), blind or state policy gradients, and measure them.
    Several values of --mode, --seed, --raster-model or --preset train every combination as one population in
    this process (one batched simulation; each member a run of its own, in its own run folder)."""

    mode: tuple[Literal[MODES], ...] = ("decoupled",)
    """full: gradients flow through the rendered images into the robot state; decoupled (D.Va): the image stack is
    detached at the actor's input; state: the actor sees the state vector (upper bound); blind: the decoupled
    visual actor fed a constant black image (the floor any result from pixels must beat). Several: a population."""
    seed: tuple[int, ...] = (0,)
    """One seed for everything of a run (networks, noise, resets); same seed on the CPU, identical metrics.
    Several: a population, one member per seed."""
    raster_model: tuple[Literal[RASTER_MODELS], ...] | None = None
    """The rasterizer's image model, and so the gradient estimator of --mode full: hard (a z-buffer, the paper's
    baseline), softmax or alpha (silhouettes carry gradient); None: the preset's. Several: a population."""
    preset: tuple[Literal[PRESETS], ...] = ("dva",)
    """Hyperparameters every unset setting takes (gradlab/presets.py): dva (D.Va's per-task configs) or
    shac-diffrender (the paper's full-APG baseline: its decay length and the hard rasterizer). Several: a
    population."""
    member: tuple[str, ...] = ()
    """Population members one by one instead of a product: each 'mode=full,seed=0[,raster_model=hard][,preset=P]
    [,other=V]' with settings a member may have of its own (vocabulary.MEMBER_FIELDS); the other flags are the
    population's. Not with several values of --mode, --seed, --raster-model or --preset."""

    def members(self) -> list[RunConfig]:
        """The runs these options stand for: one (a single run), or a population's members; ValueError naming the
        flag for options that do not make one."""
        base = {f.name: getattr(self, f.name) for f in dataclasses.fields(RunConfig) if f.name not in _PRODUCT}
        values = {"mode": self.mode, "seed": self.seed, "preset": self.preset,
                  "raster_model": (None,) if self.raster_model is None else self.raster_model}
        for name, vals in values.items():
            if len(set(vals)) != len(vals):
                raise ValueError(f"--{name.replace('_', '-')} lists a value twice: {' '.join(map(str, vals))}")
        if self.member:
            several = [f"--{k.replace('_', '-')}" for k, v in values.items() if len(v) > 1]
            if several:
                raise ValueError(f"--member lists the members one by one: give {' and '.join(several)} one value")
            one = {k: v[0] for k, v in values.items()}
            return [RunConfig(**{**base, **one, **_member_settings(spec)}) for spec in self.member]
        return [RunConfig(**base, mode=m, raster_model=r, preset=p, seed=s)
                for m, r, p, s in itertools.product(values["mode"], values["raster_model"], values["preset"],
                                                    values["seed"])]


def _member_settings(spec: str) -> dict:
    """'mode=full,seed=0,...' -> {"mode": "full", "seed": 0, ...}, values typed as their settings are."""
    out = {}
    for part in filter(None, (p.strip() for p in spec.split(","))):
        key, sep, raw = part.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or key not in MEMBER_FIELDS:
            raise ValueError(f"--member {spec!r}: {part!r} is not a member's own setting (one of "
                             f"{', '.join(MEMBER_FIELDS)}, as key=value)")
        out[key] = _typed(raw.strip(), RunConfig.__dataclass_fields__[key].default)
    if "mode" not in out:
        raise ValueError(f"--member {spec!r}: every member names its mode (mode=...)")
    return out


def _typed(raw: str, default):
    if raw.lower() == "none":
        return None
    if isinstance(default, bool):
        return raw.lower() in ("1", "true", "yes")
    if isinstance(default, tuple):  # e.g. betas=0.7/0.95
        return tuple(float(x) for x in raw.split("/"))
    for kind in (int, float):
        try:
            return kind(raw)
        except ValueError:
            pass
    return raw


def member_name(cfg: RunConfig, members: list[RunConfig]) -> str:
    """A member's run folder name: task, mode, the member settings that differ between members and that it sets
    (a raster model or preset by its name, another setting as name-value), seed; e.g. ``hopper_full_hard_seed0``
    beside ``hopper_full_seed0``."""
    from ablations.sweep.config import slug
    varying = [k for k in MEMBER_FIELDS if k not in ("mode", "seed")
               and len({repr(getattr(c, k)) for c in members}) > 1 and getattr(cfg, k) is not None]
    # values as the sweep writes them into folder names (a tuple such as betas: "betas0.5-0.9", not "(0.5, 0.9)")
    labels = [str(getattr(cfg, k)) if k in ("raster_model", "preset")
              else f"{k.replace('_', '-')}{slug(getattr(cfg, k))}" for k in varying]
    return "_".join([cfg.task, cfg.mode, *labels, f"seed{cfg.seed}"])


def is_population(path: str | Path) -> bool:
    """Whether ``path`` is a population folder (it holds population.json)."""
    return (Path(path) / POPULATION).is_file()


class PopulationFolder:
    """A population folder: population.json and its members' run folders."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    @classmethod
    def create(cls, parent: Path, name: str, members: list[RunConfig], names: list[str]) -> tuple:
        """The new folder ``parent/name`` and a new run folder per member (ValueError if it exists, not empty)."""
        pop = cls(Path(parent) / name)
        check_writable(parent)
        if pop.path.exists() and any(pop.path.iterdir()):
            raise ValueError(f"population folder {pop.path} exists and is not empty: pass --resume {pop.path} or "
                             f"another --name")
        folders = [RunFolder.create(pop.path, n) for n in names]
        pop.write_record({"members": names, "command": sys.argv,
                          "created_utc": time.strftime("%Y-%m-%dT%H:%M:%S+00:00", time.gmtime())})
        return pop, folders

    @classmethod
    def of(cls, path: str | Path) -> PopulationFolder:
        """The population of ``path``: a population folder, or a member's run folder (its config.json names it)."""
        path = Path(path)
        if is_population(path):
            return cls(path)
        try:
            record = RunFolder(path).read_record()
        except ValueError:
            record = {}
        if isinstance(record.get("population"), dict) and is_population(path.parent):
            return cls(path.parent)
        raise ValueError(f"{path} is not a population folder (no {POPULATION})")

    def write_record(self, record: dict) -> None:
        from gradlab.checkpoint import atomic_write_json

        atomic_write_json(self.path / POPULATION, record)

    def read_record(self) -> dict:
        try:
            record = json.loads((self.path / POPULATION).read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise ValueError(f"{self.path / POPULATION} cannot be read ({type(e).__name__}: {e})") from None
        if not isinstance(record, dict) or not isinstance(record.get("members"), list):
            raise ValueError(f"{self.path / POPULATION} lists no members")
        return record

    def members(self) -> list[RunFolder]:
        return [RunFolder.existing(self.path / name) for name in self.read_record()["members"]]


def is_member(path: str | Path) -> bool:
    """Whether ``path`` (a ``--resume`` folder) belongs to a population: its folder, or a member's run folder."""
    try:
        PopulationFolder.of(path)
    except ValueError:
        return False
    return True


def prepare(cfg) -> tuple[list[RunConfig], list[RunFolder], object, list[dict] | None, PopulationFolder]:
    """A population's settings checked and its folders made (or found, to resume), before any expensive work.

    ``cfg``: the members' RunConfigs, or a RunConfig whose ``--resume`` names a population (or a member of one).
    Returns the members' configs and run folders in the trainer's member order, the device, the checkpoint states
    to resume from (None: a fresh start; a resume from the newest iteration every member has a checkpoint of) and
    the population folder. ValueError naming the flag for members that cannot share a process."""
    from ablations.runs import _stored_config, default_threads, shac_part
    from gradlab import precision
    from gradlab.seeding import resolve_device
    from gradlab.shac import check_population, population_order

    if isinstance(cfg, RunConfig):
        home = PopulationFolder.of(cfg.resume)
        try:
            folders = home.members()
        except ValueError as e:
            raise ValueError(f"--resume {cfg.resume}: {e}") from None
        members = [_stored_config(f, cfg) for f in folders]
    else:
        members, home, folders = list(cfg), None, []
        for member in members:
            member.validate()
    _check_members(members)
    check_population([_resolved(m) for m in members])
    order = population_order([shac_part(m) for m in members])
    members = [members[i] for i in order]
    threads = members[0].threads or default_threads()
    members = [dataclasses.replace(m, threads=threads) for m in members]
    device = resolve_device(members[0].device)
    precision.check(members[0].precision, device)  # a refusal before any folder is made
    if home is not None:
        from ablations.runs import check_resume

        folders = [folders[i] for i in order]
        states = _common_checkpoint(folders, device)
        check_resume(folders, members[0], None if states is None else states[0])
        return members, folders, device, states, home
    if members[0].restart:
        raise ValueError("--restart goes with --resume RUN_FOLDER (a folder that holds no checkpoint)")
    first = members[0]
    names = [member_name(m, members) for m in members]
    name = first.name or f"{first.task}_population{len(members)}_{time.strftime('%Y%m%d-%H%M%S')}"
    home, folders = PopulationFolder.create(first.out, name, members, names)
    return members, folders, device, None, home


def _resolved(cfg: RunConfig):
    from ablations.runs import shac_part
    from gradlab.config import resolve_config

    return resolve_config(shac_part(cfg))


def _check_members(members: list[RunConfig]) -> None:
    """Run options (not trainer settings) that a population's members must share, named as flags."""
    trainer_fields = {f.name for f in dataclasses.fields(SHACConfig)}
    for name in (f.name for f in dataclasses.fields(RunConfig)):
        if name in trainer_fields or name in ("resume", "name", "restart"):
            continue
        values = {repr(getattr(m, name)) for m in members}
        if len(values) > 1:
            raise ValueError(f"the members of one population share --{name.replace('_', '-')}, got "
                             f"{' and '.join(sorted(values))}")


def _common_checkpoint(folders: list[RunFolder], device) -> list[dict] | None:
    """Every member's state at the newest iteration all of them have a readable checkpoint of; None where no
    member has one (the population starts over in its folders, with --restart where it trained before); ValueError
    naming the folders otherwise."""
    from gradlab.checkpoint import checkpoint_path, load_checkpoint

    have = [f.checkpoint_iterations() for f in folders]
    if not any(have):
        return None
    for iteration in sorted(set.intersection(*have), reverse=True):
        try:
            return [load_checkpoint(checkpoint_path(f.checkpoint_dir, iteration), map_location=device)
                    for f in folders]
        except Exception as e:  # a damaged file: an older iteration every member has
            print(f"warning: a checkpoint of iteration {iteration} does not load ({type(e).__name__}); trying an "
                  f"older one", file=sys.stderr)
    raise ValueError(f"the members of {folders[0].path.parent} have no checkpoint of one iteration in common "
                     f"({', '.join(f'{f.path.name}: {sorted(h)}' for f, h in zip(folders, have))})")


def closing_lines(path: str | Path, *, floors=None) -> list[str]:
    """What ``ablate`` prints when a population ends: per member its status, final training return and last
    deterministic evaluation return, the task's floors, the population folder and the command that resumes it."""
    from ablations.reports import load_floors

    home = PopulationFolder(Path(path).resolve())
    rows = [(f.path.name, f.read_summary() or {}) for f in home.members()]
    width = max(len(name) for name, _ in rows)

    def value(v) -> str:
        return "-" if v is None else f"{v:.1f}"

    lines = [f"population of {len(rows)} ({home.path}):",
             f"  {'member':{width}}  {'status':11} {'iters':>6} {'training return':>16} {'evaluation return':>18}"]
    for name, s in rows:
        lines.append(f"  {name:{width}}  {s.get('status', 'no summary'):11} {s.get('iterations', 0):>6} "
                     f"{value(s.get('final_return')):>16} {value(s.get('final_eval_return')):>18}")
    task = next((s.get("task") for _, s in rows if s.get("task")), None)
    floors = floors or load_floors()
    known = floors.of(task) or {} if task else {}
    if known:
        parts = [f"{policy} action {stats['mean']:.1f}" for policy, stats in known.items()]
        lines.append(f"  floors: {', '.join(parts)}  ({floors.source})")
    interrupted = any(s.get("status") == "interrupted" for _, s in rows)
    lines.append(f"  resume: ablate --resume {home.path}" + ("" if interrupted else " --iters N  (to train longer)"))
    lost = sorted({s["lost"] for _, s in rows if s.get("lost")})
    lines += [f"  lost: {text} (every member)" if len(rows) > 1 else f"  lost: {text}" for text in lost]
    return lines
