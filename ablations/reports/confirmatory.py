"""The registered analysis of a confirmatory experiment (``ablations.registration``) and its planning.

* :func:`hypothesis_pairs`: per hypothesis, the paired differences (seed -> arm minus reference) of the registered
  statistic (``stats.window_statistic``) over given runs;
* :func:`holm_rejects` and :func:`sequential_holm`: Holm's step-down at each look's alpha over the hypotheses not
  rejected at an earlier look (a rejection stands), then the control rule: a comparison counts only where its
  task's gate is rejected;
* :func:`tost_p`: the two one-sided sign-flip tests of equivalence within +-margin;
* :func:`simulate_power` and :func:`plan`: the registered design's power (the probability that a hypothesis is
  rejected by the last look, and at look 1), simulated with normal paired differences of a given mean and SD per
  hypothesis, independent across hypotheses, through the same exact tests and looks; ``ablate-plan`` prints it
  from pilot runs, at the pilot's effect and at the registered smallest effect of interest.

Reads JSON only (no torch).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import groupby
from pathlib import Path

import numpy as np
import tyro

from ablations.registration import Hypothesis, Registration, load_registration, pin, run_arm
from ablations.registration import check_runs as rg_check
from ablations.reports.stats import curve_of, sign_flip_interval, sign_flip_p, window_statistic
from ablations.run_folder import find_runs


# -------------------------------------------------------------------------------------------------- data
def hypothesis_pairs(reg: Registration, runs, seeds: Sequence[int] | None = None) -> dict[str, dict[int, float]]:
    """Hypothesis id -> seed -> arm minus reference of the registered statistic, over the seeds (``seeds``, default
    any) where both arms of the task have a run with an evaluation in the window. Raises ValueError naming the
    runs where one task, arm and seed has two runs."""
    values: dict[tuple[str, str | None, int], object] = {}
    for run in runs:
        key = (run.task, run_arm(run), int(run.seed))
        if key in values:
            raise ValueError(f"two runs of task {key[0]}, arm {key[1]}, seed {key[2]}: {values[key].path} and "
                             f"{run.path}; give one folder a seed")
        values[key] = run
    out = {}
    for h in reg.hypotheses:
        def stat(arm: str, seed: int, h: Hypothesis = h) -> float:
            run = values[(h.task, arm, seed)]
            return window_statistic(curve_of(run, arm), h.statistic.kind, h.statistic.start, h.statistic.end)

        both = sorted({s for (t, a, s) in values if t == h.task and a == h.arm}
                      & {s for (t, a, s) in values if t == h.task and a == h.reference})
        if seeds is not None:
            both = [s for s in both if s in set(seeds)]
        diffs = {s: stat(h.arm, s) - stat(h.reference, s) for s in both}
        out[h.id] = {s: d for s, d in diffs.items() if math.isfinite(d)}
    return out


# ------------------------------------------------------------------------------------------ the decision
def holm_rejects(p_values: Mapping[str, float], alpha: float) -> set[str]:
    """Holm's step-down at family-wise level ``alpha``: with the m p-values sorted ascending, reject while
    p(k) <= alpha / (m - k + 1); NaN p-values are never rejected but count in m (a registered hypothesis without
    data keeps its share)."""
    m = len(p_values)
    order = sorted(p_values, key=lambda k: (math.isnan(p_values[k]), p_values[k]))
    out = set()
    for rank, k in enumerate(order):
        p = p_values[k]
        if math.isnan(p) or p > alpha / (m - rank):
            break
        out.add(k)
    return out


def gated(reg: Registration, rejected: set[str]) -> set[str]:
    """The control rule on Holm's rejections: a comparison stands only where a gate of its task is rejected."""
    open_tasks = {h.task for h in reg.hypotheses if h.role == "gate" and h.id in rejected}
    return {h.id for h in reg.hypotheses if h.id in rejected and (h.role == "gate" or h.task in open_tasks)}


def sequential_holm(reg: Registration, p_by_look: Sequence[Mapping[str, float]]) -> list[set[str]]:
    """The rejections standing after each look given (cumulative, the control rule applied): at look k, Holm at
    the look's alpha over the hypotheses not rejected at an earlier look. Valid for exact p-values
    (Bonferroni over the looks: each look's false rejections have chance at most its alpha)."""
    done: set[str] = set()
    out = []
    for look, ps in zip(reg.looks, p_by_look):
        done |= holm_rejects({k: v for k, v in ps.items() if k not in done}, look.alpha)
        out.append(gated(reg, done))
    return out


def hypothesis_p(h: Hypothesis, diffs: Sequence[float]) -> float:
    """The registered test's exact p-value of one hypothesis (NaN without differences)."""
    return sign_flip_p(diffs, alternative=h.alternative) if len(diffs) else math.nan


def tost_p(diffs: Sequence[float], margin: float) -> float:
    """Two one-sided sign-flip tests of equivalence: H0 mean <= -margin or mean >= +margin; the p-value is the
    larger of the two one-sided ones (equivalence at level a where it is <= a)."""
    d = np.asarray(diffs, dtype=np.float64)
    if d.size == 0:
        return math.nan
    return max(sign_flip_p(d + margin, alternative="greater"), sign_flip_p(d - margin, alternative="less"))


# ------------------------------------------------------------------------------------------------- power
@dataclass(frozen=True)
class Power:
    """One hypothesis's simulated power: ``by_last`` P(rejected by the last look, control rule applied), ``at_first``
    P(rejected at look 1), ``tost`` P(equivalence at the last look's seeds and alpha), None without a margin."""

    by_last: float
    at_first: float
    tost: float | None


def simulate_power(reg: Registration, effects: Mapping[str, tuple[float, float]], *, sims: int = 1000,
                   seed: int = 0) -> dict[str, Power]:
    """Hypothesis id -> :class:`Power` of the registered design where every hypothesis's paired differences are
    independent normal draws with (mean, SD) ``effects[id]`` (return units; a hypothesis missing there is
    drawn with no effect and SD 1 and counts in Holm's m). ``sims`` simulated experiments, each drawing the last
    look's seeds and reading every look at its first seeds, with ``numpy.random.default_rng(seed)``."""
    if sims < 1:
        raise ValueError(f"sims must be at least 1, got {sims}")
    rng = np.random.default_rng(seed)
    n_looks = [len(lk.seeds) for lk in reg.looks]
    hits_last = dict.fromkeys((h.id for h in reg.hypotheses), 0)
    hits_first = dict(hits_last)
    tost_hits = dict(hits_last)
    for _ in range(sims):
        draws = {h.id: rng.normal(*effects.get(h.id, (0.0, 1.0)), size=n_looks[-1]) for h in reg.hypotheses}
        p_by_look = [{h.id: hypothesis_p(h, draws[h.id][:n]) for h in reg.hypotheses} for n in n_looks]
        rejected = sequential_holm(reg, p_by_look)
        for h in reg.hypotheses:
            hits_first[h.id] += h.id in rejected[0]
            hits_last[h.id] += h.id in rejected[-1]
            if h.equivalence_margin is not None:
                tost_hits[h.id] += tost_p(draws[h.id], h.equivalence_margin) <= reg.looks[-1].alpha
    return {h.id: Power(hits_last[h.id] / sims, hits_first[h.id] / sims,
                        tost_hits[h.id] / sims if h.equivalence_margin is not None else None)
            for h in reg.hypotheses}


@dataclass(frozen=True)
class PlanConfig:
    """Plan a registered confirmatory experiment from pilot runs: per hypothesis the pilot's paired effect and SD of
    the registered statistic, and the registered design's power at its looks' seed counts, at the pilot's effect
    and at the registered smallest effect of interest (with the pilot's SD), and of the TOST where a margin is
    registered."""

    registration: Path
    """The registration (preregistration.json, ablations/registration.py); no default, since --pin writes it."""
    runs: tyro.conf.Positional[tuple[Path, ...]] = ()
    """Pilot run folders (or folders that hold them)."""
    sims: int = 1000
    """Simulated experiments per power."""
    seed: int = 0
    """Seed of the simulation's random generator."""
    pin: bool = False
    """Write this copy's training tree hash into the registration's tree_hash (once, before its runs) and stop."""


def plan(cfg: PlanConfig) -> str:
    """``ablate-plan``'s text: the markdown table of :class:`PlanConfig`, or with ``pin`` the pinned hash."""
    if cfg.pin:
        return f"{cfg.registration}: tree_hash {pin(cfg.registration)}"
    reg = load_registration(cfg.registration)
    if not cfg.runs:
        raise ValueError("give pilot run folders (or --pin to pin the tree hash)")
    pairs = hypothesis_pairs(reg, find_runs(list(cfg.runs)))
    pilot = {k: (float(np.mean(list(v.values()))), float(np.std(list(v.values()), ddof=1)))
             for k, v in pairs.items() if len(v) >= 2}
    at_pilot = simulate_power(reg, pilot, sims=cfg.sims, seed=cfg.seed)
    smallest = {}
    for h in reg.hypotheses:
        if h.id in pilot and h.smallest_effect is not None:
            sign = -1.0 if h.alternative == "less" or (h.alternative == "two-sided" and pilot[h.id][0] < 0) else 1.0
            smallest[h.id] = (sign * h.smallest_effect, pilot[h.id][1])
    at_smallest = simulate_power(reg, {**pilot, **smallest}, sims=cfg.sims, seed=cfg.seed)
    at_zero = simulate_power(reg, {k: (0.0, sd) for k, (_, sd) in pilot.items()}, sims=cfg.sims, seed=cfg.seed)
    looks = ", ".join(f"{len(lk.seeds)} seeds at alpha {lk.alpha:g}" for lk in reg.looks)
    lines = [f"Plan of {reg.path} ({reg.name}): looks {looks}; Holm over {len(reg.hypotheses)} hypotheses at each "
             f"look, a comparison read only where its task's gate is rejected. Power: P(rejected by the last look) "
             f"(at look 1), {cfg.sims} simulated experiments of normal paired differences with the pilot's SD, "
             "independent across hypotheses.", "",
             "| hypothesis | statistic | pilot pairs | pilot mean, SD | power at the pilot's effect | smallest effect "
             "| power there | TOST margin | TOST power at no difference |",
             "|---|---|---|---|---|---|---|---|---|"]
    for h in reg.hypotheses:
        st = f"{h.statistic.kind} {h.statistic.start}-{h.statistic.end}, {h.alternative}"
        if h.id not in pilot:
            lines.append(f"| {h.id} | {st} | {len(pairs[h.id])} | too few pairs for an SD | - | "
                         f"{h.smallest_effect or '-'} | - | {h.equivalence_margin or '-'} | - |")
            continue
        mean, sd = pilot[h.id]
        p, sm, z = at_pilot[h.id], at_smallest[h.id], at_zero[h.id]
        small = (f"{h.smallest_effect:g} | {sm.by_last:.2f} ({sm.at_first:.2f})" if h.smallest_effect is not None
                 else "- | -")
        tost = f"{h.equivalence_margin:g} | {z.tost:.2f}" if z.tost is not None else "- | -"
        lines.append(f"| {h.id} | {st} | {len(pairs[h.id])} | {mean:+.1f}, {sd:.1f} | {p.by_last:.2f} "
                     f"({p.at_first:.2f}) | {small} | {tost} |")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------- the registered report
#: summary.json statuses of a run that failed in training: an outcome, not a gap (the registration's policy).
TRAINING_FAILURES = ("nonfinite",)


def in_family(reg: Registration, run) -> bool:
    """Whether a run is one of the registered family's: a registered task, arm and seed of the last look."""
    return run.task in reg.tasks and run_arm(run) in reg.arms and run.seed in set(reg.looks[-1].seeds)


def _done(reg: Registration, runs) -> set[tuple[str, str, int]]:
    """(task, arm, seed) of every run that trained all the registered iterations or failed in training."""
    done = set()
    for run in runs:
        last = max((r.get("iter", 0) for r in run.metrics), default=0)
        if last >= reg.iterations or (run.summary or {}).get("status") in TRAINING_FAILURES:
            done.add((run.task, run_arm(run), run.seed))
    return done


def _seed_ranges(seeds: Sequence[int]) -> str:
    """``[100, 101, 102, 105]`` -> ``"100-102, 105"``."""
    runs = [list(g) for _, g in groupby(enumerate(sorted(seeds)), key=lambda x: x[1] - x[0])]
    return ", ".join(str(r[0][1]) if len(r) == 1 else f"{r[0][1]}-{r[-1][1]}" for r in runs)


def look_progress(reg: Registration, runs, look: int = 0) -> list[str]:
    """Markdown lines saying which registered runs of a look are done, per task and arm (the seeds; no
    statistic of a registered hypothesis is shown before its look is complete). ``runs``: the family's runs,
    already checked against the registration (:func:`registered_section` refuses any that differ)."""
    done, seeds = _done(reg, runs), reg.looks[look].seeds
    n = sum((t, a, s) in done for t in reg.tasks for a in reg.arms for s in seeds)
    lines = [f"Look {look + 1}: {n} of {len(reg.tasks) * len(reg.arms) * len(seeds)} registered runs done "
             f"(trained all {reg.iterations} iterations, or failed in training), each passing the "
             "registration's checks.", "", "| task | arm | seeds done | seeds to run |", "|---|---|---|---|"]
    for t in reg.tasks:
        for a in reg.arms:
            have = [s for s in seeds if (t, a, s) in done]
            rest = [s for s in seeds if (t, a, s) not in done]
            lines.append(f"| {t} | {a} | {_seed_ranges(have) or '-'} | {_seed_ranges(rest) or '-'} |")
    return [*lines, ""]


def latest_complete_look(reg: Registration, runs) -> int | None:
    """The index of the latest look whose every registered task, arm and seed has a run that trained all the
    registered iterations or failed in training (:data:`TRAINING_FAILURES`); None when look 1 is not complete."""
    done = _done(reg, runs)
    complete = None
    for k, look in enumerate(reg.looks):
        if all((t, a, s) in done for t in reg.tasks for a in reg.arms for s in look.seeds):
            complete = k
    return complete


def registered_section(reg: Registration, runs) -> list[str]:
    """The registered analysis as markdown lines: the family at the latest complete look (each earlier look's
    rejections standing), per hypothesis the seeds, the mean with its sign-flip interval at the look's Holm level
    for it, the seeds agreeing, the exact p-value and the verdict. Raises ValueError naming every registered run
    whose tree hash or registered fields differ."""
    family = [r for r in runs if in_family(reg, r)]
    problems = rg_check(reg, family)
    if problems:
        raise ValueError(f"{len(problems)} run(s) differ from the registration {reg.path}:\n" + "\n".join(problems))
    out = ["## The registered analysis", ""]
    k = latest_complete_look(reg, family)
    if k is None:
        return [*out, f"Look 1 ({len(reg.looks[0].seeds)} seeds) is not complete: no registered hypothesis is "
                "tested yet. Everything below is exploratory.", "", *look_progress(reg, family)]
    p_by_look, pairs_by_look = [], []
    for look in reg.looks[:k + 1]:
        pairs = hypothesis_pairs(reg, family, seeds=look.seeds)
        pairs_by_look.append(pairs)
        p_by_look.append({h.id: hypothesis_p(h, list(pairs[h.id].values())) for h in reg.hypotheses})
    rejected = sequential_holm(reg, p_by_look)
    look = reg.looks[k]
    out += [f"Registration `{reg.path}` ({reg.name}), tree `{reg.tree_hash}`. Look {k + 1} of {len(reg.looks)} is "
            f"the latest complete one ({len(look.seeds)} seeds, alpha {look.alpha:g}); at each look Holm ran over "
            "the hypotheses not rejected before, a comparison counting only where its task's gate is rejected. "
            "Intervals: inverted from the same sign-flip test at alpha / (hypotheses tested at that look).", ""]
    rows = []
    open_at_k = [h for h in reg.hypotheses if h.id not in (rejected[k - 1] if k else set())]
    for h in reg.hypotheses:
        d = list(pairs_by_look[k][h.id].values())
        if not d:
            rows.append(f"| {h.id} | {h.arm} - {h.reference} | {h.alternative} | 0 | - | - | - | not tested |")
            continue
        lo, hi = sign_flip_interval(d, alpha=look.alpha / max(1, len(open_at_k)), alternative=h.alternative)
        mean = float(np.mean(d))
        agree = int(np.sum(np.sign(d) == np.sign(mean)))
        at = next((i for i, r in enumerate(rejected) if h.id in r), None)
        verdict = (f"rejected at look {at + 1}" if at is not None else
                   "not read: its task's gate is not rejected" if h.role == "comparison" and
                   h.id in holm_rejects({x.id: p_by_look[k][x.id] for x in open_at_k}, look.alpha) else
                   "not rejected (not equivalence)")
        rows.append(f"| {h.id} | {h.arm} - {h.reference} | {h.alternative} | {len(d)} | {mean:+.1f} "
                    f"[{lo:.1f}, {hi:.1f}] | {agree} of {len(d)} | {p_by_look[k][h.id]:.3g} | {verdict} |")
    out += ["| hypothesis | difference | sided | seeds | mean [interval] | seeds agreeing | exact p | verdict |",
            "|---|---|---|---|---|---|---|---|", *rows, ""]
    return out
