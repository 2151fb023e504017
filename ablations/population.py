"""The runs of one ``ablate`` process and their folders, prepared before any expensive work (:func:`prepare`),
and what ``ablate`` says when they end (:func:`closing_lines`).

A single run is a population of one. Only its folder differs, at the edge: a run alone keeps the flat run
folder (config.json, metrics.jsonl, ... directly inside), a population of several a population folder holding
``population.json`` (the members' folder names, the command) and one ordinary run folder per member, whose
config.json names the population it ran in: plots, reports and statistics read members as they read single runs.
``ablate --resume`` takes either folder, or a member's.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from ablations.folder_lock import LOCK, FolderLocks
from ablations.naming import claim_folder, folder_name, member_name
from ablations.reports import load_floors
from ablations.run_config import RESUMABLE, AblateConfig, RunConfig, check_shared, default_threads, shac_part
from ablations.run_folder import (
    ABSENT_MEANS,
    POPULATION_RECORD,
    RunFolder,
    check_writable,
    set_aside_damaged_checkpoint,
)
from gradlab import precision
from gradlab.checkpoint import atomic_write_json, checkpoint_path, read_checkpoint
from gradlab.config import SHACConfig
from gradlab.roster import Roster
from gradlab.seeding import resolve_device
from vocabulary import PRESET_FIELDS, PRESETS

__all__ = ["AblateConfig", "POPULATION", "PopulationFolder", "Prepared", "NothingToDo", "prepare", "check_resume",
           "closing_lines", "home_of", "member_name", "is_population"]

#: The record a population folder holds beside its members' run folders.
POPULATION = POPULATION_RECORD


def is_population(path: str | Path) -> bool:
    """Whether ``path`` is a population folder (it holds population.json)."""
    return (Path(path) / POPULATION).is_file()


class PopulationFolder:
    """A population folder: population.json and its members' run folders."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    @classmethod
    def create(cls, parent: Path, name: str, names: list[str]) -> tuple[PopulationFolder, list[RunFolder]]:
        """The new folder ``parent/name`` and a new run folder per member (ValueError if it exists, not empty)."""
        pop = cls(Path(parent) / name)
        check_writable(parent)
        if pop.path.exists() and any(p.name != LOCK for p in pop.path.iterdir()):
            raise ValueError(f"population folder {pop.path} exists and is not empty: pass --resume {pop.path} or "
                             f"another --name")
        folders = [RunFolder.create(pop.path, n) for n in names]
        pop.write_record({"members": names, "command": sys.argv,
                          "created_utc": time.strftime("%Y-%m-%dT%H:%M:%S+00:00", time.gmtime())})
        return pop, folders

    def remove_if_unused(self) -> None:
        """Remove the folder and its population.json when nothing else is left in it (a population that stopped
        before any member wrote its first record: the member folders were removed as empty)."""
        try:
            if any(p.name != POPULATION for p in self.path.iterdir()):  # a lock file: another process holds it
                return
            (self.path / POPULATION).unlink(missing_ok=True)
            self.path.rmdir()
        except OSError:
            pass

    @classmethod
    def of(cls, path: str | Path) -> PopulationFolder | None:
        """The population of ``path``: a population folder, or a member's run folder (its config.json names it);
        None for anything else (a run alone's folder). ValueError for a member's folder whose population folder
        has lost its population.json: resumed alone, the member would draw its action noise from torch's default
        generator instead of the generator its checkpoint holds, an inexact resume, so it is refused."""
        path = Path(path)
        if is_population(path):
            return cls(path)
        try:
            record = RunFolder(path).read_record()
        except ValueError:
            record = {}
        trained_in = record.get("population")
        if not isinstance(trained_in, dict):
            return None
        if is_population(path.parent):
            return cls(path.parent)
        names = trained_in.get("members") if isinstance(trained_in.get("members"), list) else []
        raise ValueError(f"{path} trained as a member of a population of {len(names) or 'several'}, and "
                         f"{path.parent / POPULATION} is gone: alone it would not resume exactly (its action noise "
                         f"comes from a generator of the population's); restore {POPULATION} (its members: "
                         f"{', '.join(map(str, names)) or 'see config.json'}) and resume {path.parent}")

    def write_record(self, record: dict) -> None:
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


def home_of(path: str | Path) -> tuple[list[RunFolder], PopulationFolder | None]:
    """The members' run folders of the runs ``path`` belongs to (a run alone's folder, a population's folder or a
    member's) and their population folder (None: a run alone); ValueError naming what is not readable. The one
    place that tells a run alone's flat folder from a population's."""
    population = PopulationFolder.of(path)
    return ([RunFolder.existing(path)], None) if population is None else (population.members(), population)


# ---------------------------------------------------------------------------------------------- preparing
@dataclass
class Prepared:
    """What :func:`prepare` settled: one entry per member, in the trainer's member order (a single run: one)."""

    cfgs: list[RunConfig]
    #: The members, built once: each trainer config resolved, checked and ordered (what the trainer is built of).
    roster: Roster
    folders: list[RunFolder]
    device: torch.device
    #: The checkpoint states to resume from, one per member; None: a fresh start (or a resume with no checkpoint).
    states: list[dict] | None
    #: The population folder; None: a run alone, whose run folder is the one folder ``ablate`` names.
    population: PopulationFolder | None
    #: The locks of the population folder and every member's folder, held until :meth:`release` (the caller's,
    #: once the last summary is written): one process at a time trains into a folder.
    locks: FolderLocks = dataclasses.field(default_factory=FolderLocks)

    def release(self) -> None:
        """Give up the folders' locks."""
        self.locks.release()

    @property
    def home(self) -> Path:
        """The folder ``ablate`` names (and ``--resume`` takes)."""
        return self.folders[0].path if self.population is None else self.population.path


class NothingToDo(Exception):
    """A resume of a run that has nothing left to train (its message: one line saying so and how to extend it)."""


def prepare(runs: RunConfig | Sequence[RunConfig], *, resume_flags: Collection[str] | None = None) -> Prepared:
    """Validate everything, then create the folders (or find the ones to resume), before any expensive work.

    ``runs``: the members' RunConfigs (one: a single run), or one RunConfig whose ``--resume`` names a run folder,
    a population folder or a member's folder. The configs come back in the trainer's member order, a resume's as
    its folders record them, ``threads`` resolved. ``resume_flags``: the :data:`RESUMABLE` settings a resume takes
    from ``runs`` (the flags given on its command line; None: those that differ from their defaults, for callers
    that cannot tell). ValueError naming the flag for bad input, or for members that cannot share a process;
    NothingToDo for a resume of a finished run."""
    members = [runs] if isinstance(runs, RunConfig) else list(runs)
    locks = FolderLocks()
    try:
        return _prepare(members, resume_flags, locks)
    except BaseException:
        locks.release()
        raise


def _lock(locks: FolderLocks, folders: list[RunFolder], population: PopulationFolder | None) -> None:
    """Lock the population folder (if any) and every member's folder: ``--resume`` takes either."""
    if population is not None:
        locks.acquire([population.path], "population folder")
    locks.acquire([f.path for f in folders], "run folder")


def _prepare(members: list[RunConfig], resume_flags: Collection[str] | None, locks: FolderLocks) -> Prepared:
    """:func:`prepare`, the folders it makes or finds locked in ``locks`` (released by the caller on a refusal)."""
    resume = members[0].resume
    population: PopulationFolder | None = None
    if resume is not None:
        try:
            folders, population = home_of(resume)
            _lock(locks, folders, population)  # before anything in them is read or renamed
        except ValueError as e:
            raise ValueError(f"--resume {resume}: {e}") from None
        members = [_stored_config(f, members[0], resume_flags) for f in folders]
    else:
        if members[0].restart:
            raise ValueError("--restart goes with --resume RUN_FOLDER (a folder that holds no checkpoint)")
        for member in members:
            member.check_run_options()  # the trainer's settings: by the roster, as it resolves them
    check_shared(members)
    roster = Roster.of([shac_part(m) for m in members])
    threads = members[0].threads or default_threads()
    members = [dataclasses.replace(m, threads=threads) for m in roster.arrange(members)]
    try:
        device = resolve_device(members[0].device)
    except ValueError as e:
        raise ValueError(str(e) if str(e).startswith("--device") else f"--device: {e}") from None
    try:
        precision.check(members[0].precision, device)  # a refusal before any folder is made
    except ValueError:
        if resume is None:
            raise
        raise ValueError(f"--resume {resume}: it trains at --precision {members[0].precision}, which needs a CUDA "
                         f"device (it was given --device {members[0].device})") from None
    if resume is not None:
        prepared = Prepared(members, roster, roster.arrange(folders), device, None, population, locks)
        try:
            prepared.states = _resume_states(prepared.folders, device, restart=members[0].restart,
                                             resolved=roster.cfgs)
        except ValueError as e:
            raise ValueError(f"--resume {resume}: {e}") from None
        check_resume(prepared)
        return prepared
    first = members[0]
    if first.name is None:
        check_writable(first.out)
        name = claim_folder(first.out, folder_name(members))
    else:
        name = first.name
    if len(members) == 1:  # the edge: a run alone's folder is the run folder itself
        folders = [RunFolder.create(first.out, name)]
    else:
        population, folders = PopulationFolder.create(first.out, name, [member_name(m, members) for m in members])
    _lock(locks, folders, population)
    return Prepared(members, roster, folders, device, None, population, locks)


def _stored_config(folder: RunFolder, overrides: RunConfig, given: Collection[str] | None = None) -> RunConfig:
    """The RunConfig of a run folder's config.json with what a resume may change taken from ``overrides`` (the
    settings in ``given``; None: those that differ from their defaults); a damaged or foreign file is named in a
    ValueError."""
    try:
        stored = folder.read_record()["config"]
    except ValueError as e:
        raise ValueError(f"--resume {folder.path}: {e}; it is the record of the run's settings, restore it (e.g. "
                         f"from a copy) to resume") from None
    fields = {f.name for f in dataclasses.fields(RunConfig)}
    unknown = sorted(set(stored) - fields)
    if unknown:
        raise ValueError(f"--resume {folder.path}: {folder.config_path} records setting(s) this version does not "
                         f"know: {', '.join(unknown)}; resume it with the code that wrote it (git.txt, "
                         f"provenance.jsonl name it)")
    # set by the resume itself (where it runs, how long, what it prints), never needed from the file
    by_resume = {*RESUMABLE, "out", "name", "resume", "restart", "progress"}
    missing = sorted(fields - set(stored) - by_resume - set(ABSENT_MEANS))
    if missing:
        raise ValueError(f"--resume {folder.path}: {folder.config_path} has no {', '.join(missing)}: a resume "
                         f"would take today's default{'s' if len(missing) > 1 else ''} for the run's own "
                         f"setting{'s' if len(missing) > 1 else ''} without a word; restore it from the run's "
                         f"command (config.json's \"command\") or start a new run")
    stored = {**{k: v for k, v in ABSENT_MEANS.items() if k not in stored}, **stored}
    for k in ("actor_hidden", "critic_hidden", "betas"):
        if stored.get(k) is not None:
            stored[k] = tuple(stored[k])
    if stored.get("preset") not in PRESETS and all(stored.get(k) is not None for k in PRESET_FIELDS):
        # config.json holds every value a preset supplied, so a run whose preset has no table here (an older
        # folder's) resumes with exactly its values, under the default preset's name
        print(f"note: --resume {folder.path}: preset {stored.get('preset')!r} has no table here; the run resumes "
              f"with the values its config.json records (as --preset {RunConfig.preset} with them set)",
              file=sys.stderr)
        stored["preset"] = RunConfig.preset
    stored["out"] = Path(stored.get("out", folder.path.parent))
    stored.update(resume=folder.path, progress=overrides.progress, restart=overrides.restart)
    defaults = RunConfig()
    for k in RESUMABLE:
        if (k in given) if given is not None else getattr(overrides, k) != getattr(defaults, k):
            stored[k] = getattr(overrides, k)
    try:
        cfg = RunConfig(**stored)
        cfg.validate()
    except (TypeError, ValueError) as e:
        raise ValueError(f"--resume {folder.path}: {folder.config_path}: {e}") from None
    return cfg


#: The settings a checkpoint's recorded config must share with its folder's config.json: a checkpoint of another
#: run (another mode, task or network shape, copied in) would not load into this run's trainer.
CHECKPOINT_IDENTITY = ("task", "mode", "seed", "num_envs", "horizon", "image_size", "frames", "actor_hidden",
                       "critic_hidden", "raster_model")


def _not_this_runs(state: dict, resolved: SHACConfig | None) -> str | None:
    """Why a checkpoint dict cannot be this run's (None: it can): no iteration, or a recorded config that
    differs from config.json's (``resolved``: its trainer settings, resolved) in :data:`CHECKPOINT_IDENTITY`."""
    if isinstance(state.get("iteration"), bool) or not isinstance(state.get("iteration"), int):
        return "holds no 'iteration' entry: not a checkpoint written by ablate"
    recorded = state.get("config")
    if resolved is None or not isinstance(recorded, dict):
        return None
    ours = dataclasses.asdict(resolved)
    for k in CHECKPOINT_IDENTITY:
        theirs, mine = recorded.get(k), ours.get(k)
        if k in recorded and (list(theirs) if isinstance(theirs, (list, tuple)) else theirs) != \
                (list(mine) if isinstance(mine, (list, tuple)) else mine):
            return f"a checkpoint of another run: its {k} is {theirs!r}, config.json's {mine!r}"
    return None


def _resume_states(folders: list[RunFolder], device: torch.device, *, restart: bool = False,
                   resolved: Sequence[SHACConfig] | None = None) -> list[dict] | None:
    """Every member's checkpoint state of the newest iteration all of them hold a readable checkpoint of; None
    where none holds one (the runs start over in their folders, with --restart where they trained before).
    Damaged newer files are named on stderr and renamed aside (``.damaged`` appended), so that they no longer
    count among the newest when the resumed run prunes, and stay for inspection; when no iteration is left,
    None with ``restart`` (its checkpoints are then set aside with the rest), else ValueError naming every file
    that did not load, or each member's iterations, and --restart. ``resolved``: the members' trainer settings
    (config.json's, resolved), which each checkpoint's own record must match (:func:`_not_this_runs`); a
    checkpoint that does not counts as damaged."""
    have = [f.checkpoint_iterations() for f in folders]
    if not any(have):
        return None
    damaged: list[tuple[Path, str]] = []
    for iteration in sorted(set.intersection(*have), reverse=True):
        states = []
        for k, folder in enumerate(folders):
            path = checkpoint_path(folder.checkpoint_dir, iteration)
            state, why = read_checkpoint(path, map_location=device)
            if state is not None and (why := _not_this_runs(state, None if resolved is None else resolved[k])):
                state = None
            if state is None:
                damaged.append((path, why))
                break
            states.append(state)
        else:
            for path, why in damaged:
                set_aside_damaged_checkpoint(path, why, checkpoint_path(folders[0].checkpoint_dir, iteration))
            return states
    if restart:
        return None
    where = folders[0].checkpoint_dir if len(folders) == 1 else f"the members of {folders[0].path.parent}"
    listed = "; ".join(f"{p} ({why})" for p, why in damaged) or ", ".join(
        f"{f.path.name}: {sorted(h)}" for f, h in zip(folders, have))
    raise ValueError(f"no readable checkpoint of one iteration in common in {where}: {listed}; add --restart to "
                     f"train it again from iteration 1 in this folder (what it holds is kept beside it as "
                     f"*.before-restart-<time>)")


def check_resume(prepared: Prepared) -> None:
    """What a resume of the prepared runs from their checkpoint states would do, decided before any work:
    NothingToDo when they are finished (their iterations done or their time budget spent); ValueError when there
    is no checkpoint but there are iterations a start from iteration 1 would train again, unless --restart asks
    for it."""
    folders, cfg, where = prepared.folders, prepared.cfgs[0], prepared.home
    state = None if prepared.states is None else prepared.states[0]
    if state is not None:
        it = state["iteration"]
        if it >= cfg.iters:
            raise NothingToDo(f"{where} is finished at iteration {it} (--iters {cfg.iters}): nothing to do; to train "
                              f"it longer: ablate --resume {where} --iters M  (M > {it})")
        if cfg.time_limit_min is not None and state["wall_s"] >= 60.0 * cfg.time_limit_min:
            raise NothingToDo(f"{where} has used its --time-limit-min {cfg.time_limit_min:g} at iteration {it} "
                              f"({state['wall_s'] / 60:.2f} min of training): nothing to do; to train it longer: "
                              f"ablate --resume {where} --time-limit-min M  (M > {state['wall_s'] / 60:.2f})")
        return
    trained = max((max([r["iter"] for r in f.read_metrics()] or [0]) for f in folders), default=0)
    summaries = [f.read_summary() or {} for f in folders]
    trained = max([trained] + [s.get("iterations") or 0 for s in summaries if isinstance(s.get("iterations"), int)])
    if trained == 0 or cfg.restart:
        return
    if all(s.get("status") in ("finished", "time_limit") for s in summaries):
        raise NothingToDo(f"{where} is finished at iteration {trained} and keeps no checkpoint (deleted since): "
                          f"nothing to resume from; --restart trains it again from iteration 1")
    raise ValueError(f"--resume {where}: no checkpoint to resume from, but {trained} iteration(s) trained (it "
                     f"stopped before its first checkpoint, --checkpoint-every {cfg.checkpoint_every}); add --restart "
                     f"to train it again from iteration 1 in this folder (the old metrics.jsonl, summary.json and "
                     f"videos are kept beside it as *.before-restart-<time>)")


# ---------------------------------------------------------------------------------------------- the end
def closing_lines(path: str | Path, *, floors=None) -> list[str]:
    """What ``ablate`` prints when its runs end: how each ended, its final training return and last deterministic
    evaluation return (a run alone in full, a population's members in a table), the task's zero- and
    random-action floors (``floors``: an ``ablations.reports.Floors``; default docs/floors.json of this checkout),
    the absolute folder and the command that resumes it, and what a stop lost."""
    folders, population = home_of(Path(path).resolve())
    summaries = [f.read_summary() or {} for f in folders]
    task = next((s.get("task") for s in summaries if s.get("task")), "?")
    if population is None:
        lines = _run_lines(summaries[0])
        folder = f"  run folder         {folders[0].path}"
    else:
        lines = _member_table([f.path.name for f in folders], summaries, population.path)
        folder = f"  population folder  {population.path}"
    alone = summaries[0].get("final_eval_return") if population is None else None
    lines += _floor_lines(task, floors or load_floors(), alone)
    where = folders[0].path if population is None else population.path
    interrupted = any(s.get("status") == "interrupted" for s in summaries)
    lines += [folder, f"  resume             ablate --resume {where}"
              + ("" if interrupted else " --iters N  (to train longer)")]
    lost = sorted({s["lost"] for s in summaries if s.get("lost")})  # last, where it is seen: what a resume redoes
    lines += [f"  lost               {text}" + (" (every member)" if len(folders) > 1 else "") for text in lost]
    return lines


def _value(v) -> str:
    return "-" if v is None else f"{v:.1f}"


def _run_lines(s: dict) -> list[str]:
    """A run alone's ending: its status and length, training return, last evaluation return."""
    lines = [f"{s.get('task', '?')}/{s.get('mode', '?')} seed {s.get('seed', '?')}: {s.get('status', 'no summary')} "
             f"after {s.get('iterations', 0)} iterations ({s.get('env_steps', 0)} environment steps, "
             f"{s.get('wall_s', 0.0):.0f} s of training)" + (f"; {s['error']}" if s.get("error") else ""),
             f"  training return    {_value(s.get('final_return')):>9}  (mean of the last 100 finished training "
             f"episodes, exploring policy)"]
    ev, std = s.get("final_eval_return"), s.get("final_eval_std")
    if ev is None:
        lines.append("  evaluation return          -  (none yet: --eval-every or --video-every sets how often)")
    else:
        spread = f" +- {std:.1f}" if std is not None else ""
        lines.append(f"  evaluation return  {_value(ev):>9}{spread}  (deterministic policy, at iteration "
                     f"{s.get('final_eval_iter')})")
    return lines


def _member_table(names: list[str], summaries: list[dict], home: Path) -> list[str]:
    """A population's ending: per member its status, iterations, training and last evaluation return."""
    width = max(len(name) for name in names)
    lines = [f"population of {len(names)} ({home}):",
             f"  {'member':{width}}  {'status':11} {'iters':>6} {'training return':>16} {'evaluation return':>18}"]
    for name, s in zip(names, summaries):
        lines.append(f"  {name:{width}}  {s.get('status', 'no summary'):11} {s.get('iterations', 0):>6} "
                     f"{_value(s.get('final_return')):>16} {_value(s.get('final_eval_return')):>18}")
    return lines


def _floor_lines(task: str, floors, ev: float | None) -> list[str]:
    """The task's floors, and where the evaluation return ``ev`` (a run alone's) lies against them."""
    known = floors.of(task) or {}
    if not known:
        return [f"  floors             none for {task} ({floors.source or 'no floors file'}; "
                f"task-floors --tasks {task} measures them)"]
    parts = [f"{policy} action {known[policy]['mean']:.1f}" for policy in ("zero", "random") if policy in known]
    lines = [f"  floors             {', '.join(parts)}  ({floors.source})"]
    if ev is not None:
        sides = [f"{'above' if ev > stats['mean'] else 'below'} the {policy}-action floor"
                 for policy, stats in known.items()]
        lines.append(f"  the evaluation return is {' and '.join(sides)}")
    return lines
