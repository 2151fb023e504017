"""Each run's arm, and each arm's iteration time measured alone.

* :func:`arm_names` / :func:`arm_label`: each run's arm. Runs are grouped by mode, raster model, preset and any
  other setting that differs between the given runs and changes what is trained (a population member's
  ``encoder_lr_scale``, a flag that overrides the preset); an arm whose mode, raster model and preset are one of
  :data:`vocabulary.ARMS` is named like it, others by their mode and what sets them apart.
* :func:`iteration_times`: per task, each arm's iteration time measured alone, for the equal-wall-clock view:
  ``--benchmark`` files (``benchmarks/iteration.py`` rows of (task, mode, raster model, iter_ms);
  ``benchmarks/population.py`` single runs, a population of one) when they hold every arm of the task, else
  the runs' own median ``iter_ms`` when no run of the task was a population member (a member's iterations
  are its whole population's); otherwise the view is not available, and the section says why. An arm whose
  actor reads the state vector does not set the view's budget, so without a time of its own it is left out
  of the view, which the others keep.

Everything here reads JSON (no torch).
"""

from __future__ import annotations

import json
import os
import shlex
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from statistics import median

from ablations.reports.parts import (
    is_population_member,
    read_benchmark_json,
    run_device,
    run_median_ms,
)
from ablations.run_folder import Run, is_number
from vocabulary import (
    ARM_ORDER,
    ARMS,
    IMAGELESS_MODES,
    MEMBER_DEFAULTS,
    NOT_ARM_SETTINGS,
    POPULATION_BENCHMARK_ARMS,
    PRESET_RASTER_MODEL,
    STATE_INPUT_MODES,
    arm_of,
)

__all__ = ["arm_names", "arm_label", "in_arm_order", "ArmTime", "IterationTimes", "benchmark_iteration_rows",
           "iteration_times"]

_DEFAULT = "<default>"
#: Settings a benchmark row and the runs must agree on for the row's time to stand for the arm's.
_TIMED_SETTINGS = ("num_envs", "horizon", "image_size", "compile")


# ---------------------------------------------------------------------------------------------------- arms
def _value_text(v) -> str:
    return "/".join(map(str, v)) if isinstance(v, (list, tuple)) else str(v)


def _own_settings(run: Run) -> dict[str, str]:
    """The settings of a run that can set it apart from another of its arm (config values but NOT_ARM_SETTINGS),
    as JSON text; DEFAULT for one its preset supplied (or a flag set to the preset's own value) or at its
    MEMBER_DEFAULTS value."""
    record = run.preset or {}
    from_preset = set(record.get("supplied") or {})
    from_preset |= {k for k, o in (record.get("overridden") or {}).items()
                    if isinstance(o, dict) and o.get("flag") == o.get("preset")}
    own = {}
    for k, v in run.config.items():
        if k in NOT_ARM_SETTINGS:
            continue
        text = json.dumps(v, sort_keys=True)
        default = k in from_preset or (k in MEMBER_DEFAULTS and text == json.dumps(MEMBER_DEFAULTS[k]))
        own[k] = _DEFAULT if default else text
    return own


def arm_names(runs: Sequence[Run]) -> dict[Path, str]:
    """Run folder -> arm name. The arm is (mode, raster model (None for IMAGELESS_MODES), preset) named by
    vocabulary.ARMS where listed, else ``mode (raster model[, preset])`` (the preset where it is not dva); then, in
    brackets, every other setting whose value differs between the runs that record it, as ``key=value``, on the
    runs where it is not the default (the preset's, or MEMBER_DEFAULTS'; a setting with neither is named on
    every run): ``decoupled (encoder_lr_scale=0.1)`` beside ``decoupled``."""
    own = [_own_settings(r) for r in runs]
    keys = sorted({k for o in own for k in o})
    differing = [k for k in keys if len({o[k] for o in own if k in o}) > 1]
    names = {}
    for r, o in zip(runs, own):
        raster = None if r.mode in IMAGELESS_MODES else r.config.get("raster_model")
        preset = r.setting("preset")
        head = arm_of(r.mode, raster, preset)
        parts = []
        if head is None:
            head = r.mode
            parts = [str(raster)] if raster is not None else []
            parts += [str(preset)] if preset not in (None, "dva") else []
        parts += [f"{k}={_value_text(r.config[k])}" for k in differing if o.get(k, _DEFAULT) != _DEFAULT]
        names[r.path] = f"{head} ({', '.join(parts)})" if parts else head
    return names


def _arm_order(arm: str, mode: str) -> tuple:
    known = list(ARM_ORDER)
    modes = ("decoupled", "full", "state", "blind")
    return (known.index(arm) if arm in known else len(known), modes.index(mode) if mode in modes else len(modes),
            arm)


def in_arm_order(runs: Sequence[Run], label: Callable[[Run], str]) -> list[Run]:
    """The runs sorted by arm (vocabulary.ARM_ORDER, then the other arms by mode and name), then seed."""
    return sorted(runs, key=lambda r: (*_arm_order(label(r), r.mode), str(r.seed), str(r.path)))


def arm_label(runs: Sequence[Run]) -> Callable[[Run], str]:
    """A run's arm (:func:`arm_names` over ``runs``), as the ``label`` of ``make_plots``, ``collect_bwd`` and
    ``runs_table``."""
    names = arm_names(runs)
    return lambda r: names[r.path]


# ---------------------------------------------------------------------------------------- iteration times
@dataclass(frozen=True)
class ArmTime:
    """An arm's iteration time measured alone: ``ms`` per training iteration (plain iterations: no probe, no
    evaluation), where it came from (``source``: a benchmark file's name, or ``runs``), the ``device`` it was
    measured on, and ``n`` (benchmark rows or runs it is the median of)."""

    ms: float
    source: str
    device: str
    n: int


@dataclass(frozen=True)
class IterationTimes:
    """One task's iteration times for the equal-wall-clock view: ``ms`` arm -> milliseconds when every arm has
    one from one kind of source on one device (arms on the state vector may lack one: ``untimed``), else None;
    ``found``: arm -> the time found, where one was; ``why``: where the times come from, or why the view is
    not available (one sentence); ``untimed``: the state-vector arms left out of the view for lack of a time;
    ``not_setting``: the arms on the state vector (``vocabulary.STATE_INPUT_MODES``), which never set the view's
    budget."""

    task: str
    ms: dict[str, float] | None
    found: dict[str, ArmTime]
    why: str
    untimed: tuple[str, ...] = ()
    not_setting: frozenset[str] = frozenset()


def benchmark_iteration_rows(path: str | os.PathLike) -> tuple[str, list[dict]]:
    """(device, rows) of a ``--benchmark`` file's iteration times measured alone: ``benchmarks/iteration.py``
    results (``status`` ok, numeric ``iter_ms``), and ``benchmarks/population.py`` populations of one member
    (its separate runs ran at the same time as each other, so they are not alone; a row's arm is the script's
    member order unless it names its ``mode``; the sizes are read from its recorded command where given there).
    Each row: task, mode, raster_model (None where not recorded), iter_ms, and the ``_TIMED_SETTINGS`` it
    records. ValueError naming the file when it is no benchmark JSON."""
    data = read_benchmark_json(path)
    meta = data if isinstance(data, dict) else {}
    device = str(meta.get("gpu") or meta.get("device") or "?")
    rows = []
    if isinstance(meta.get("rows"), list):  # benchmarks/population.py
        # its rows do not record the sizes; its command does where they were given
        argv = shlex.split(str(meta.get("command") or ""))
        sizes = {k.replace("-", "_"): int(argv[i + 1]) for i, a in enumerate(argv[:-1])
                 if (k := a.removeprefix("--")) in ("num-envs", "horizon", "image-size") and argv[i + 1].isdigit()}
        for r in meta["rows"]:
            if not (isinstance(r, dict) and r.get("kind") == "population" and r.get("members") == 1
                    and r.get("status", "ok") == "ok" and is_number(r.get("iter_ms"))):
                continue
            arm = ARMS[POPULATION_BENCHMARK_ARMS[int(r.get("arm", 0)) % len(POPULATION_BENCHMARK_ARMS)]]
            mode, raster = ((r["mode"], r.get("raster_model")) if isinstance(r.get("mode"), str) else
                            (arm.mode, arm.raster_flag))
            # the benchmark's members train on the default preset: no raster model given is that preset's
            rows.append({"task": r.get("task"), "mode": mode, "raster_model": raster or PRESET_RASTER_MODEL["dva"],
                         "iter_ms": float(r["iter_ms"]), "compile": meta.get("device") != "cpu", **sizes})
        return device, rows
    results = data if isinstance(data, list) else meta.get("results")
    for r in results if isinstance(results, list) else []:
        if isinstance(r, dict) and r.get("status", "ok") == "ok" and is_number(r.get("iter_ms")) and "mode" in r:
            rows.append({"task": r.get("task"), "mode": r["mode"], "raster_model": r.get("raster_model"),
                         "iter_ms": float(r["iter_ms"]), **{k: r[k] for k in _TIMED_SETTINGS if k in r}})
    return device, rows


def _matches(row: dict, task: str, runs: list[Run]) -> bool:
    first = runs[0]
    if row["task"] != task or row["mode"] != first.mode:
        return False
    if first.mode not in IMAGELESS_MODES and row["raster_model"] != first.config.get("raster_model"):
        return False
    return all(row[k] == first.config[k] for k in _TIMED_SETTINGS if k in row and k in first.config)


def iteration_times(runs: Sequence[Run], label: Callable[[Run], str],
                    benchmarks: Sequence[str | os.PathLike] = ()) -> dict[str, IterationTimes]:
    """Task -> :class:`IterationTimes` of its arms (``label``: a run's arm). Per arm, the first benchmark file
    with a matching row (same task, mode, raster model where the mode renders, and the settings both record;
    the median of its matching rows); else the median of its runs' median ``iter_ms`` when none of them is a
    population member. The times are used when every arm of the task has a benchmark time, all on one device,
    or else every arm has a time from its runs, all on one device; in both, an arm whose runs all read the
    state vector (``vocabulary.STATE_INPUT_MODES``: it does not set the budget) may lack one and is then left
    out of the view (``IterationTimes.untimed``)."""
    loaded = [(Path(b), *benchmark_iteration_rows(b)) for b in benchmarks]
    groups: dict[str, dict[str, list[Run]]] = {}
    for r in runs:
        groups.setdefault(r.task, {}).setdefault(label(r), []).append(r)
    out = {}
    for task, arms in groups.items():
        bench, own, why_not = {}, {}, {}
        for arm, rs in arms.items():
            for path, device, rows in loaded:
                hits = [row["iter_ms"] for row in rows if _matches(row, task, rs)]
                if hits:
                    bench[arm] = ArmTime(median(hits), f"benchmark {path.name}", device, len(hits))
                    break
            alone = [r for r in rs if not is_population_member(r)]
            times = [(t, r) for r in alone if (t := run_median_ms(r, "iter_ms")) is not None]
            if times:
                own[arm] = ArmTime(median(t for t, _ in times), "runs", " / ".join(sorted({run_device(r) for _, r in
                                                                                           times})), len(times))
            elif arm not in bench:
                why_not[arm] = ("trained as population members (a member's iter_ms is its whole population's)"
                                if len(alone) < len(rs) else "no iter_ms logged")
        found = {**own, **bench}
        on_state = frozenset(arm for arm, rs in arms.items() if all(r.mode in STATE_INPUT_MODES for r in rs))
        ms, why, untimed = None, "", ()
        # a kind of source with every arm first; then one that lacks only state-vector arms
        for kind, times, may_lack in (("benchmark", bench, set()), ("runs", own, set()),
                                      ("benchmark", bench, on_state), ("runs", own, on_state)):
            if may_lack:  # a state arm timed on another device than the others counts as lacking a time
                others = {t.device for a, t in times.items() if a not in may_lack}
                times = {a: t for a, t in times.items() if a not in may_lack or {t.device} == others}
            lacking = [a for a in arms if a not in times]
            if set(lacking) - may_lack or len(lacking) == len(arms):
                continue
            devices = {t.device for t in times.values()}
            if len(devices) > 1:
                why = f"the arms' {kind} times were measured on different devices ({', '.join(sorted(devices))})"
                continue
            ms = {a: t.ms for a, t in times.items()}
            sources = sorted({t.source for t in times.values()})
            why = (f"iteration times measured alone from {', '.join(sources)} on {devices.pop()}"
                   + ("" if kind == "benchmark" else " (each run's median iter_ms without warm-up and probe "
                      "iterations; alone only if nothing else shared its device, which a run folder does not "
                      "record)"))
            untimed = tuple(lacking)
            for a in untimed:
                why += (f"; {a} left out: no time measured alone at its runs' settings, "
                        + (why_not.get(a) or f"its only time is from {found[a].source} on {found[a].device}"))
            break
        if ms is None and not why:
            reasons: dict[str, list[str]] = {}
            for a in arms:
                if a in why_not:
                    reasons.setdefault(why_not[a], []).append(a)
            parts = [f"{', '.join(a)}: {why}" for why, a in reasons.items()] or [
                "the arms' times come from different kinds of source (" + ", ".join(
                    f"{a}: {found[a].source}" for a in arms) + ")"]
            why = ("no iteration time measured alone for every arm: " + "; ".join(parts)
                   + " (give --benchmark files of benchmarks/iteration.py or benchmarks/population.py)")
        out[task] = IterationTimes(task, ms, found, why, untimed, on_state)
    return out
