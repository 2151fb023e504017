"""The grid: every run of a sweep (:func:`plan`), and the command line one attempt of a run executes.

A run is one point of tasks x modes (or arms) x seeds x ``--vary``; its ``ablate`` arguments are checked by
ablate's own parser and validation before anything starts. :func:`attempt_command` is the one place that turns a
run into the process a worker starts.
"""

from __future__ import annotations

import itertools
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field

import tyro

from ablations.naming import slug, sweep_run_id
from ablations.run_config import RunConfig
from ablations.sweep.config import SweepConfig, flag_args, norm_key, parse_set, parse_vary
from vocabulary import MEMBER_FIELDS, MODES

__all__ = ["RunSpec", "plan", "attempt_command", "RUN_ARGS", "ABLATE"]

#: ``ablate`` arguments every run of a sweep gets
RUN_ARGS = ("--no-progress", "--no-compile-helper")
#: What an attempt runs, after the worker node's Python: ``python -m ablations ablate``.
ABLATE = ("-m", "ablations", "ablate")


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
    #: The settings of this run that are a population member's own (vocabulary.MEMBER_FIELDS: mode, seed and
    #: those its arm or --vary sets), by ablate field name: its ``--member`` entry in a population.
    own: dict = field(default_factory=dict)
    #: ``args`` without the member's own settings: what the members of its population share.
    shared: tuple[str, ...] = ()
    #: Runs with the same group can train in one process: the same value of every other setting, all on the state
    #: vector or none (gradlab.members.check_population).
    group: str = ""


def attempt_command(args: Sequence[str], run_id: str, *, resume: bool, threads: int = 1,
                    program: Sequence[str] | None = None) -> list[str]:
    """The command line of one attempt of a run, started in the attempt's scratch folder.

    A fresh start writes the run folder ``./<run_id>``; a resume continues it (the folder unpacked there) from
    its checkpoint, or from the first iteration where it has none.
    Paths are relative so that the run's recorded command and config name no folder of the worker node.
    ``threads``: the run's torch CPU threads (``--threads``; the sweep's --cpus-per-run, rounded down).
    ``program`` replaces ``python -m ablations ablate`` (a test seam: a stand-in that takes ablate's arguments).
    """
    program = [sys.executable, *ABLATE] if program is None else list(program)
    # --restart: a run retried after it died before its first checkpoint trains again from its first iteration
    # (its old metrics kept beside); one with a checkpoint resumes from it
    where = ["--resume", run_id, "--restart"] if resume else [*args, "--out", ".", "--name", run_id]
    return [*program, *where, *RUN_ARGS, "--threads", str(threads)]


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
            raise ValueError(f"arm {name}: needs a 'mode' ({', '.join(MODES)})")
        unknown = set(arm) - {"mode", "flags", "about"}
        if unknown:
            raise ValueError(f"arm {name}: unknown keys {sorted(unknown)} (mode, flags, about)")
        flags = {norm_key(k, where=f"arm {name} flag {k}"): v for k, v in (arm.get("flags") or {}).items()}
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
    from gradlab.config import ModePlan, check_as_given
    from tasks.command_line import check_argv

    cfg.validate()
    set_table = parse_set(cfg.set) if set_table is None else {norm_key(k, where=f"set {k}"): v
                                                               for k, v in set_table.items()}
    vary_table = parse_vary(cfg.vary) if vary_table is None else {norm_key(k, where=f"vary {k}"): list(v)
                                                                  for k, v in vary_table.items()}
    both = set(set_table) & set(vary_table)
    if both:
        raise ValueError(f"{', '.join(sorted(both))}: given in both --set and --vary")
    for name, values in vary_table.items():
        if len({slug(v) for v in values}) != len(values):
            raise ValueError(f"--vary {name}: values repeat (or differ only in punctuation): {values}")
    shared = [a for name, value in set_table.items() for a in flag_args(name, value)]
    columns = [(None, (mode, {})) for mode in cfg.modes] if arms is None else \
        list(_arm_table(arms, set_table, vary_table).items())
    specs, seen = [], {}
    axes = list(vary_table.items())
    for task, (arm, (mode, arm_flags)), seed in itertools.product(cfg.tasks, columns, cfg.seeds):
        # an arm's flag may name its run's task and seed (ablate-paper's distill arm: its expert's folder)
        arm_flags = {k: v.format(task=task, seed=seed) if isinstance(v, str) else v for k, v in arm_flags.items()}
        for combo in itertools.product(*(values for _, values in axes)):
            flags = {name: value for (name, _), value in zip(axes, combo)}
            run_id = sweep_run_id(task, arm or mode, seed, flags)
            own = {"mode": str(mode), "seed": int(seed),
                   **{k: v for k, v in {**arm_flags, **flags}.items() if k in MEMBER_FIELDS}}
            args = ["--task", str(task), "--mode", str(mode), "--seed", str(seed), *shared,
                    *(a for name, value in arm_flags.items() for a in flag_args(name, value)),
                    *(a for name, value in flags.items() for a in flag_args(name, value))]
            population = ["--task", str(task), *shared,
                          *(a for name, value in {**arm_flags, **flags}.items() if name not in MEMBER_FIELDS
                            for a in flag_args(name, value))]
            try:
                check_argv(RunConfig, [*args, *RUN_ARGS], "ablate")  # what tyro would answer with a box
            except ValueError as e:
                raise ValueError(f"run {run_id}: ablate rejects its flags: {' '.join(args)} ({e})") from None
            try:
                run_cfg = tyro.cli(RunConfig, args=[*args, *RUN_ARGS])
            except SystemExit:
                # tyro has printed what it rejected; name the run and its flags.
                raise ValueError(f"run {run_id}: ablate rejects its flags: {' '.join(args)}") from None
            try:
                run_cfg.validate()
                check_as_given(run_cfg)
            except ValueError as e:
                raise ValueError(f"run {run_id}: {e}") from None
            if run_id in seen:
                raise ValueError(f"runs {seen[run_id]} and {flags} share the folder name {run_id}")
            seen[run_id] = flags
            on_state = ModePlan.of(run_cfg.mode).actor_input == "state"
            group = repr(sorted((k, v) for k, v in vars(run_cfg).items() if k not in MEMBER_FIELDS)) + \
                (" on the state vector" if on_state else "") + (" distill" if run_cfg.mode == "distill" else "")
            specs.append(RunSpec(run_id=run_id, task=str(task), mode=str(mode), seed=int(seed), flags=flags,
                                 args=tuple(args), iters=run_cfg.iters, arm=arm, own=own, shared=tuple(population),
                                 group=group))
    return specs
