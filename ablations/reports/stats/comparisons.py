"""Arms compared per task: summaries, paired differences against a reference with Holm's correction, the
equal-iterations and equal-wall-clock views, differences along the budget, learning-curve bands and performance
profiles.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ablations.reports.stats.curves import (
    FINAL_EVALS,
    Curve,
    auc,
    check_unique,
    collapse_rate,
    final_return,
    is_finite_number,
)
from ablations.reports.stats.estimates import (
    ALPHA,
    DEFAULT_REPS,
    DEFAULT_SEED,
    EXACT_BOOTSTRAP_MAX_N,
    MIN_SEEDS,
    Estimate,
    holm,
    improvement_estimate,
    iqm_estimate,
    mean_estimate,
    multisets,
    percentile_interval,
    sign_flip_p,
)


# ------------------------------------------------------------------------------------------- comparison
@dataclass(frozen=True)
class ArmSummary:
    """One arm on one task. Per-seed dicts (seed -> value) hold the runs with at least one evaluation:
    ``final`` (the mean of the evaluation returns at the ``window`` iterations: the final return), ``auc``
    (``auc``), ``collapse`` (``collapse_rate``; NaN where undefined), ``evals`` (evaluations in the curve). Over
    seeds: ``final_iqm`` and ``auc_iqm`` (IQM with CI, return units), ``collapse_mean`` (mean of the defined rates
    with CI; None when none is defined). ``window``: the evaluation iterations every run's final return averages
    (the same for every run it compares; empty when the runs share none and each took its own last ones, which
    ``own_windows`` then lists per seed). ``without_evals``: seeds whose curve has no evaluation, left out of
    everything."""

    arm: str
    final: dict[int, float]
    auc: dict[int, float]
    collapse: dict[int, float]
    evals: dict[int, int]
    final_iqm: Estimate | None
    auc_iqm: Estimate | None
    collapse_mean: Estimate | None
    without_evals: tuple[int, ...] = ()
    window: tuple[int, ...] = ()
    own_windows: dict[int, tuple[int, ...]] = field(default_factory=dict)

    @property
    def seeds(self) -> tuple[int, ...]:
        return tuple(self.final)


@dataclass(frozen=True)
class PairedDifference:
    """``arm`` against ``reference`` on the seeds both have: ``diff`` (seed -> arm minus reference final
    return), ``mean`` (their mean with a bootstrap CI over seeds: exact up to ``EXACT_BOOTSTRAP_MAX_N`` seeds),
    ``agree`` (how many seeds' differences have the sign of the mean), ``p_value`` (the two-sided sign-flip
    permutation p-value, :func:`sign_flip_p`), ``p_holm`` (Holm-adjusted over the report's family of paired
    comparisons, :func:`correct`; None until corrected) and ``family`` (the number of comparisons that
    correction took together), ``improvement`` (the probability that the arm's final return exceeds the
    reference's, with its CI). ``missing``: arm name -> seeds that arm has and the other lacks (skipped).
    ``mean``, ``improvement`` and ``p_value`` are None without a paired seed."""

    arm: str
    reference: str
    diff: dict[int, float]
    mean: Estimate | None
    improvement: Estimate | None
    missing: dict[str, tuple[int, ...]] = field(default_factory=dict)
    agree: int = 0
    p_value: float | None = None
    p_holm: float | None = None
    family: int | None = None

    @property
    def seeds(self) -> tuple[int, ...]:
        return tuple(self.diff)

    def differs(self, alpha: float = ALPHA) -> bool:
        """Whether the difference is resolved after Holm correction: at least ``MIN_SEEDS`` paired seeds and a
        Holm-adjusted p-value <= ``alpha``."""
        return (self.mean is not None and self.mean.n >= MIN_SEEDS and self.p_holm is not None
                and self.p_holm <= alpha)


@dataclass(frozen=True)
class Comparison:
    """The arms of one task on the given curves: ``arms`` (name -> ArmSummary, in the curves' order) and
    ``differences`` (name -> PairedDifference against ``reference``, every arm but the reference; empty when
    the reference is not among the arms). ``window``: ``"common"`` (every run's final return over the same
    evaluation iterations) or ``"per arm"`` (the same iterations within each arm: runs cut at equal modelled
    time end at different iterations per arm)."""

    task: str
    reference: str | None
    arms: dict[str, ArmSummary]
    differences: dict[str, PairedDifference]
    final_evals: int
    window: str = "common"


def common_window(curves: Sequence[Curve], final_evals: int = FINAL_EVALS) -> tuple[int, ...]:
    """The last ``final_evals`` iterations at which every curve with an evaluation has one (fewer where they
    share fewer; empty where they share none)."""
    sets = [set(c.iters.tolist()) for c in curves if c.returns.size]
    if not sets:
        return ()
    shared = sorted(set.intersection(*sets))
    return tuple(int(i) for i in shared[-final_evals:])


def _windowed(curve: Curve, window: tuple[int, ...], final_evals: int) -> tuple[float, tuple[int, ...]]:
    """(final return, the iterations it averages): the mean at ``window`` where given, else the curve's own
    last ``final_evals``."""
    if window:
        at = np.isin(curve.iters, window)
        return float(np.mean(curve.returns[at])), window
    return final_return(curve, final_evals), tuple(int(i) for i in curve.iters[-final_evals:])


def _arm_summary(arm: str, curves: Sequence[Curve], *, final_evals: int, window: tuple[int, ...], reps: int,
                 seed: int, confidence: float) -> ArmSummary:
    evaluated = sorted((c for c in curves if c.returns.size), key=lambda c: c.seed)
    finals = {c.seed: _windowed(c, window, final_evals) for c in evaluated}
    final = {s: v for s, (v, _) in finals.items()}
    areas = {c.seed: auc(c) for c in evaluated}
    collapse = {c.seed: collapse_rate(c) for c in evaluated}
    defined = [v for v in collapse.values() if not math.isnan(v)]
    kw = dict(reps=reps, seed=seed, confidence=confidence)
    return ArmSummary(arm=arm, final=final, auc=areas, collapse=collapse,
                      evals={c.seed: int(c.returns.size) for c in evaluated},
                      final_iqm=iqm_estimate(list(final.values()), **kw),
                      auc_iqm=iqm_estimate(list(areas.values()), **kw),
                      collapse_mean=mean_estimate(defined, **kw),
                      without_evals=tuple(sorted(c.seed for c in curves if not c.returns.size)),
                      window=window, own_windows={} if window else {s: w for s, (_, w) in finals.items()})


def paired_difference(arm: str, reference: str, a: Mapping[int, float], b: Mapping[int, float], *,
                      reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED,
                      confidence: float = 0.95) -> PairedDifference:
    """``arm`` minus ``reference`` over the seeds both have (``a``, ``b``: seed -> value): the per-seed
    differences, their mean with its bootstrap CI, how many agree in sign with it, the sign-flip p-value and the
    probability of improvement."""
    seeds = sorted(set(a) & set(b))
    missing = {name: tuple(sorted(set(x) - set(y))) for name, x, y in ((arm, a, b), (reference, b, a))}
    missing = {k: v for k, v in missing.items() if v}
    diff = {s: a[s] - b[s] for s in seeds}
    kw = dict(reps=reps, seed=seed, confidence=confidence)
    if not seeds:
        return PairedDifference(arm=arm, reference=reference, diff=diff, mean=None, improvement=None,
                                missing=missing)
    d = np.array(list(diff.values()))
    sign = np.sign(d.mean())
    return PairedDifference(arm=arm, reference=reference, diff=diff, mean=mean_estimate(d, **kw),
                            improvement=improvement_estimate([a[s] for s in seeds], [b[s] for s in seeds], **kw),
                            missing=missing, agree=int(np.sum(np.sign(d) == sign)) if sign else 0,
                            p_value=sign_flip_p(d, seed=seed))


def compare(curves: Sequence[Curve], *, reference: str | None = "decoupled", final_evals: int = FINAL_EVALS,
            reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED, confidence: float = 0.95,
            window: str = "common") -> Comparison:
    """Arm summaries and paired differences against ``reference`` of curves of ONE task (as given: cut them
    first for equal iterations or wall-clock, or use ``task_statistics``). ``window``: ``"common"``: every
    run's final return is the mean of the last ``final_evals`` evaluations at iterations every run has
    (:func:`common_window`); ``"per arm"``: the same, within each arm. The p-values are not yet corrected
    (:func:`correct`)."""
    if final_evals < 1:
        raise ValueError(f"final_evals must be >= 1, got {final_evals}")
    if window not in ("common", "per arm"):
        raise ValueError(f"window must be 'common' or 'per arm', got {window!r}")
    tasks = sorted({c.task for c in curves})
    if len(tasks) != 1:
        raise ValueError(f"compare takes the curves of one task, got {tasks or 'none'}")
    check_unique(curves)
    by_arm: dict[str, list[Curve]] = {}
    for c in curves:
        by_arm.setdefault(c.arm, []).append(c)
    kw = dict(reps=reps, seed=seed, confidence=confidence)
    shared = common_window(curves, final_evals)
    arms = {a: _arm_summary(a, cs, final_evals=final_evals, window=common_window(cs, final_evals)
                            if window == "per arm" else shared, **kw) for a, cs in by_arm.items()}
    differences = {}
    if reference in arms:
        ref = arms[reference]
        differences = {a: paired_difference(a, reference, s.final, ref.final, **kw) for a, s in arms.items()
                       if a != reference}
    return Comparison(task=tasks[0], reference=reference, arms=arms, differences=differences,
                      final_evals=final_evals, window=window)


def correct(comparisons: Sequence[Comparison], *, alpha: float = ALPHA) -> list[Comparison]:
    """The comparisons with every paired difference's ``p_holm`` and ``family`` set: Holm's correction over all
    paired differences with a p-value in all the given comparisons together (the family: every paired
    comparison a report makes, every task and view), so that the chance of any false "differs" among them is at
    most ``alpha``."""
    del alpha  # the adjusted p-values do not depend on it; ``PairedDifference.differs`` reads them at alpha
    keys = [(i, a) for i, c in enumerate(comparisons) for a, d in c.differences.items() if d.p_value is not None]
    adjusted = holm([comparisons[i].differences[a].p_value for i, a in keys])
    out = list(comparisons)
    for (i, a), p in zip(keys, adjusted):
        c = out[i]
        out[i] = replace(c, differences={**c.differences, a: replace(c.differences[a], p_holm=p, family=len(keys))})
    return out


# ------------------------------------------------------------------------ equal iterations, equal time
def common_iteration(curves: Sequence[Curve]) -> int:
    """The iteration count every run reached: the minimum over the runs of their last ``iter``."""
    if not curves:
        raise ValueError("no runs to compare")
    return min(c.last_iter for c in curves)


def truncate_at_iteration(curves: Sequence[Curve], iteration: int) -> list[Curve]:
    """Each curve cut to its evaluations at iterations <= ``iteration`` (and its last_iter to at most it)."""
    out = []
    for c in curves:
        keep = c.iters <= iteration
        out.append(replace(c, iters=c.iters[keep], returns=c.returns[keep], last_iter=min(c.last_iter, iteration)))
    return out


def _iter_ms(curves: Sequence[Curve], iter_ms_alone: Mapping[str, float]) -> dict[str, float]:
    ms = {}
    for arm in dict.fromkeys(c.arm for c in curves):
        if arm not in iter_ms_alone:
            raise ValueError(f"iter_ms_alone has no iteration time for arm {arm!r} (give every compared arm's "
                             f"milliseconds per iteration measured alone)")
        v = iter_ms_alone[arm]
        if not is_finite_number(v) or v <= 0:
            raise ValueError(f"iter_ms_alone[{arm!r}] must be a positive number of milliseconds, got {v!r}")
        ms[arm] = float(v)
    return ms


def _end_s(curve: Curve, ms: Mapping[str, float], iteration: int | None = None) -> float:
    """The modelled training time [s] at the end of ``iteration`` (default: the curve's last) of ``curve``:
    what was charged to it before its first iteration plus that many iterations of its arm alone."""
    return curve.charged_s + (curve.last_iter if iteration is None else iteration) * ms[curve.arm] / 1e3


def common_wall_s(curves: Sequence[Curve], iter_ms_alone: Mapping[str, float], *,
                  not_setting: Collection[str] = ()) -> float:
    """The training-time budget every run reached, in seconds: the minimum over the runs of
    charged_s + last_iter x iter_ms_alone[arm] / 1000 (``Curve.charged_s``: a distilled student's expert's
    training time, else 0). The time is *modelled*: each arm's iteration time measured alone
    (a benchmark's ms per iteration of that arm as the only work on its device), never a run's logged
    ``wall_s``, which for a population member is the whole population's time and includes compilation. So
    it leaves out what the measurement alone left out (typically compilation, evaluation rollouts, and the
    extra backward of probe iterations if the benchmark's time excludes them).

    ``not_setting``: arms whose runs do not set the budget (a reference trained on another input, such as the
    state vector, whose cheap iterations would otherwise end every comparison early); a cut at the budget
    reads such a run at its end when it ends sooner, so it is given less time, never more. Ignored when it
    names every arm."""
    if not curves:
        raise ValueError("no runs to compare")
    ms = _iter_ms(curves, iter_ms_alone)
    setting = [c for c in curves if c.arm not in not_setting] or list(curves)
    return min(_end_s(c, ms) for c in setting)


def truncate_at_wall_s(curves: Sequence[Curve], iter_ms_alone: Mapping[str, float], wall_s: float) -> list[Curve]:
    """Each curve cut to the iterations its arm completes within ``wall_s`` seconds of modelled training time
    (iteration i ends at charged_s + i x iter_ms_alone[arm] / 1000 s; see ``common_wall_s``); a run charged more
    than ``wall_s`` keeps no iteration."""
    ms = _iter_ms(curves, iter_ms_alone)
    # a relative tolerance so that the run that sets the budget keeps its own last iteration despite rounding
    return [truncate_at_iteration([c], max(0, math.floor((wall_s - c.charged_s) * 1e3 / ms[c.arm] * (1 + 1e-12))))[0]
            for c in curves]


def check_at_iteration(at_iteration: int | None) -> None:
    """ValueError unless ``at_iteration`` is None or a positive integer (an iteration to read runs at)."""
    if at_iteration is not None and (isinstance(at_iteration, bool) or not isinstance(at_iteration, int)
                                     or at_iteration < 1):
        raise ValueError(f"at_iteration must be a positive number of iterations, got {at_iteration!r}")


@dataclass(frozen=True)
class TaskStatistics:
    """One task's comparison three ways: ``whole`` (every run's whole curve), ``equal_iters`` (curves cut at
    ``iteration``, the common iteration count), ``equal_wall`` (curves cut at ``wall_s`` seconds of modelled
    training time, each arm at ``iters_at_wall[arm]`` iterations, from ``iter_ms_alone``; None when no
    iteration times were given)."""

    task: str
    whole: Comparison
    iteration: int
    equal_iters: Comparison
    wall_s: float | None = None
    iters_at_wall: dict[str, int] | None = None
    iter_ms_alone: dict[str, float] | None = None
    equal_wall: Comparison | None = None
    #: Arms that did not set the wall-clock budget and whose runs all ended before it (read at their ends).
    ended_before_wall: tuple[str, ...] = ()
    #: Arms that do not set the budget and have no time in ``iter_ms_alone``: left out of ``equal_wall``.
    untimed_at_wall: tuple[str, ...] = ()


def task_statistics(curves: Sequence[Curve], *, reference: str | None = "decoupled",
                    iter_ms_alone: Mapping[str, float] | None = None, final_evals: int = FINAL_EVALS,
                    reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED, confidence: float = 0.95,
                    at_iteration: int | None = None, not_setting_wall: Collection[str] = ()
                    ) -> dict[str, TaskStatistics]:
    """Task -> its ``TaskStatistics`` (tasks in the curves' order). Equal iterations and equal wall-clock are
    taken over all runs of the task, every arm together. ``iter_ms_alone``: arm -> milliseconds per training
    iteration of that arm measured alone (population members share a process, so their own ``wall_s`` is not
    their arm's time). ``at_iteration``: every curve is cut there first (to read longer runs at an earlier
    point: all three views then end at or before it). ``not_setting_wall``: arms that do not set the
    wall-clock budget (``common_wall_s``'s ``not_setting``); such an arm missing from ``iter_ms_alone`` is left
    out of the equal-wall-clock view (``untimed_at_wall``), every other arm needs a time."""
    check_at_iteration(at_iteration)
    kw = dict(reference=reference, final_evals=final_evals, reps=reps, seed=seed, confidence=confidence)
    out = {}
    for task in dict.fromkeys(c.task for c in curves):
        cs = [c for c in curves if c.task == task]
        if at_iteration is not None:
            evaluated = [c for c in cs if len(c.iters)]
            cs = truncate_at_iteration(cs, at_iteration)
            if evaluated and not any(len(c.iters) for c in cs):
                raise ValueError(f"no {task} run has an evaluation at or before iteration {at_iteration} (the "
                                 f"first is at {min(int(c.iters[0]) for c in evaluated)}): read it later")
        n = common_iteration(cs)
        stats = TaskStatistics(task=task, whole=compare(cs, window="per arm", **kw), iteration=n,
                               equal_iters=compare(truncate_at_iteration(cs, n), **kw))
        if iter_ms_alone is not None:
            untimed = tuple(a for a in dict.fromkeys(c.arm for c in cs)
                            if a in not_setting_wall and a not in iter_ms_alone)
            timed = [c for c in cs if c.arm not in untimed]
            budget = common_wall_s(timed, iter_ms_alone, not_setting=not_setting_wall)
            cut = truncate_at_wall_s(timed, iter_ms_alone, budget)
            ms = _iter_ms(timed, iter_ms_alone)
            ended = tuple(a for a in ms if a in not_setting_wall
                          and all(_end_s(c, ms) < budget for c in timed if c.arm == a))
            stats = replace(stats, wall_s=budget, iter_ms_alone=ms, equal_wall=compare(cut, window="per arm", **kw),
                            iters_at_wall={a: max(c.last_iter for c in cut if c.arm == a) for a in ms},
                            ended_before_wall=ended, untimed_at_wall=untimed)
        out[task] = stats
    return out


def correct_statistics(per_task: Mapping[str, TaskStatistics], *, views: Sequence[str] = ("equal_iters",
                                                                                            "equal_wall")
                       ) -> dict[str, TaskStatistics]:
    """``per_task`` with Holm's correction (:func:`correct`) over every paired comparison of the given views of
    every task together: the family a report that shows those views makes."""
    slots = [(task, v) for task, ts in per_task.items() for v in views if getattr(ts, v) is not None]
    fixed = correct([getattr(per_task[t], v) for t, v in slots])
    out = dict(per_task)
    for (t, v), c in zip(slots, fixed):
        out[t] = replace(out[t], **{v: c})
    return out


# ------------------------------------------------------------------------------- differences along the budget
@dataclass(frozen=True)
class DifferenceCurve:
    """``arm`` minus ``reference`` (per seed, paired) at every training budget ``x`` where both arms' runs have
    an evaluation: ``axis`` ``"iteration"`` (x: iterations) or ``"wall-clock"`` (x: seconds of modelled training
    time). At each budget every run's return is the mean of its last ``final_evals`` evaluations up to it, at the
    evaluation iterations that every run of its arm and of the reference share (``"wall-clock"``: of its arm);
    ``n`` paired seeds, their ``mean`` and ``median`` difference, the mean's percentile bootstrap interval
    [``ci_low``, ``ci_high``] (exact up to ``EXACT_BOOTSTRAP_MAX_N`` seeds), ``agree`` (seeds with the mean's
    sign) and the sign-flip ``p_value``: pointwise, not corrected for the many budgets."""

    task: str
    arm: str
    reference: str
    axis: str
    x: np.ndarray
    n: np.ndarray
    mean: np.ndarray
    median: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray
    agree: np.ndarray
    p_value: np.ndarray
    final_evals: int
    confidence: float = 0.95


def _window_means(c: Curve, shared: np.ndarray, final_evals: int) -> np.ndarray:
    """The curve's mean over the last ``final_evals`` of ``shared`` (sorted iterations it has) up to each."""
    at = {int(i): float(r) for i, r in zip(c.iters, c.returns)}
    vals = np.array([at[int(i)] for i in shared])
    csum = np.concatenate([[0.0], np.cumsum(vals)])
    j = np.arange(1, len(vals) + 1)
    start = np.maximum(0, j - final_evals)
    return (csum[j] - csum[start]) / (j - start)


def difference_curves(curves: Sequence[Curve], *, reference: str = "decoupled",
                      iter_ms_alone: Mapping[str, float] | None = None, untimed: Collection[str] = (),
                      final_evals: int = FINAL_EVALS, reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED,
                      confidence: float = 0.95) -> dict[tuple[str, str], DifferenceCurve]:
    """(arm, axis) -> :class:`DifferenceCurve` of every arm against ``reference`` in the curves of ONE task, along
    iterations and, with ``iter_ms_alone`` (arm -> ms per iteration measured alone), along modelled wall-clock;
    every arm needs a time there but those named in ``untimed`` (``TaskStatistics.untimed_at_wall``), which have
    no wall-clock curve. An arm without paired seeds, or whose runs share no evaluation iteration with the
    reference's, has none."""
    tasks = sorted({c.task for c in curves})
    if len(tasks) != 1:
        raise ValueError(f"difference_curves takes the curves of one task, got {tasks or 'none'}")
    by_arm: dict[str, dict[int, Curve]] = {}
    for c in curves:
        if c.returns.size:
            by_arm.setdefault(c.arm, {})[c.seed] = c
    if reference not in by_arm:
        return {}
    ms = None
    if iter_ms_alone is not None:
        ms = _iter_ms([c for c in curves if c.arm in by_arm and (c.arm not in untimed or c.arm == reference)],
                      iter_ms_alone)
    out = {}

    def point_stats(rows: list[np.ndarray]) -> dict[str, np.ndarray]:
        cols: dict[str, list] = {k: [] for k in ("n", "mean", "median", "ci_low", "ci_high", "agree", "p_value")}
        for d in rows:
            e = mean_estimate(d, reps=reps, seed=seed, confidence=confidence)
            sign = np.sign(d.mean())
            for k, v in (("n", d.size), ("mean", e.value), ("median", float(np.median(d))), ("ci_low", e.ci_low),
                         ("ci_high", e.ci_high), ("agree", int(np.sum(np.sign(d) == sign)) if sign else 0),
                         ("p_value", sign_flip_p(d, seed=seed))):
                cols[k].append(v)
        return {k: np.asarray(v) for k, v in cols.items()}

    ref = by_arm[reference]
    for arm, runs in by_arm.items():
        seeds = sorted(set(runs) & set(ref))
        if arm == reference or not seeds:
            continue
        pair = [runs[s] for s in seeds] + [ref[s] for s in seeds]
        shared = np.array(sorted(set.intersection(*(set(c.iters.tolist()) for c in pair))), dtype=np.int64)
        if shared.size:
            diffs = np.stack([_window_means(runs[s], shared, final_evals) - _window_means(ref[s], shared, final_evals)
                              for s in seeds], axis=1)
            out[(arm, "iteration")] = DifferenceCurve(tasks[0], arm, reference, "iteration", shared.astype(float),
                                                      final_evals=final_evals, confidence=confidence,
                                                      **point_stats(list(diffs)))
        if ms is None or arm not in ms:
            continue
        # per seed, the modelled times of the evaluations every seed of the arm has (a run's charged time,
        # a distilled student's expert's, differs by seed)
        own = {}
        for name, cs in ((arm, [runs[s] for s in seeds]), (reference, [ref[s] for s in seeds])):
            it = np.array(sorted(set.intersection(*(set(c.iters.tolist()) for c in cs))), dtype=np.int64)
            own[name] = (it, {c.seed: c.charged_s + it * ms[name] / 1e3 for c in cs},
                         {c.seed: _window_means(c, it, final_evals) for c in cs})
        end = min(_end_s(c, ms) for c in pair)
        if not (own[arm][0].size and own[reference][0].size):
            continue
        start = max(float(t[0]) for name in (arm, reference) for t in own[name][1].values())
        grid = np.unique(np.concatenate([t for name in (arm, reference) for t in own[name][1].values()]))
        grid = grid[(grid >= start) & (grid <= end * (1 + 1e-12))]
        if not grid.size:
            continue

        def at(name: str, s: int, grid=grid, own=own) -> np.ndarray:
            times, means = own[name][1][s], own[name][2][s]
            return means[np.searchsorted(times, grid * (1 + 1e-12), side="right") - 1]

        diffs = np.stack([at(arm, s) - at(reference, s) for s in seeds], axis=1)
        out[(arm, "wall-clock")] = DifferenceCurve(tasks[0], arm, reference, "wall-clock", grid,
                                                   final_evals=final_evals, confidence=confidence,
                                                   **point_stats(list(diffs)))
    return out


@dataclass(frozen=True)
class Band:
    """An arm's mean curve over its runs: at each ``x`` where any run has a value, ``n`` runs, their ``mean`` and
    the mean's percentile bootstrap interval [``ci_low``, ``ci_high``] over runs (exact up to
    ``EXACT_BOOTSTRAP_MAX_N``; NaN where fewer than 2 runs have a value: one run has no interval)."""

    x: np.ndarray
    n: np.ndarray
    mean: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray


def mean_band(series: Sequence[tuple[np.ndarray, np.ndarray]], *, reps: int = DEFAULT_REPS,
              seed: int = DEFAULT_SEED, confidence: float = 0.95) -> Band:
    """:class:`Band` of runs' (x, y) series, each run counted at its own x values only (no interpolation: a
    point's n is how many runs have it)."""
    table: dict[float, list[float]] = {}
    for x, y in series:
        for xi, yi in zip(np.asarray(x, float), np.asarray(y, float)):
            if math.isfinite(yi):
                table.setdefault(float(xi), []).append(float(yi))
    xs = np.array(sorted(table))
    n = np.array([len(table[x]) for x in xs], dtype=np.int64)
    mean = np.array([np.mean(table[x]) for x in xs])
    lo, hi = np.full(xs.size, np.nan), np.full(xs.size, np.nan)
    for k in sorted(set(n.tolist()) - {1}):
        rows = np.flatnonzero(n == k)
        vals = np.sort(np.array([table[xs[i]] for i in rows]), axis=1)
        if k <= EXACT_BOOTSTRAP_MAX_N:
            idx, w = multisets(k)
            stat = vals[:, idx].mean(axis=2)
        else:
            draws = np.random.default_rng(seed).integers(0, k, size=(reps, k))
            stat, w = vals[:, draws].mean(axis=2), np.full(reps, 1.0 / reps)
        for j, i in enumerate(rows):
            lo[i], hi[i] = percentile_interval(stat[j], w, confidence)
    return Band(xs, n, mean, lo, hi)


def sign_holds(dc: DifferenceCurve) -> str:
    """Where along the budget the interval of ``dc`` excludes 0, as one clause: ``full − decoupled < 0 with the
    interval excluding 0 from iteration 1500 on (7 of 12 evaluation points)``; segments of consecutive budgets
    with the same side, the last one "on" where it reaches the last budget."""
    unit = (lambda v: f"iteration {v:.0f}", lambda a, b: f"iterations {a:.0f}-{b:.0f}") if dc.axis == "iteration" \
        else (lambda v: f"{v:.0f} s", lambda a, b: f"{a:.0f}-{b:.0f} s")
    side = np.where(dc.ci_low > 0, 1, np.where(dc.ci_high < 0, -1, 0))
    name = f"{dc.arm} − {dc.reference}"
    span = f"{unit[0](dc.x[0])} to {unit[0](dc.x[-1])}" if dc.x.size > 1 else unit[0](dc.x[0])
    if not np.any(side):
        return (f"{name}: the interval covers 0 at every one of its {dc.x.size} budget(s) ({span}; "
                f"{int(dc.n.min())}-{int(dc.n.max())} paired seeds)" if dc.n.min() != dc.n.max() else
                f"{name}: the interval covers 0 at every one of its {dc.x.size} budget(s) ({span}; "
                f"{int(dc.n[0])} paired seeds)")
    parts = []
    for sgn in (-1, 1):
        segs, i = [], 0
        while i < side.size:
            if side[i] == sgn:
                j = i
                while j + 1 < side.size and side[j + 1] == sgn:
                    j += 1
                segs.append((i, j))
                i = j + 1
            else:
                i += 1
        if not segs:
            continue
        texts = [f"from {unit[0](dc.x[i])} on" if j == side.size - 1 and i > 0 else
                 "at every budget" if j == side.size - 1 else
                 f"at {unit[0](dc.x[i])}" if i == j else f"at {unit[1](dc.x[i], dc.x[j])}" for i, j in segs]
        count = int(np.sum(side == sgn))
        parts.append(f"{name} {'<' if sgn < 0 else '>'} 0 with the interval excluding 0 {', '.join(texts)} "
                     f"({count} of {side.size} budgets, {span})")
    return "; ".join(parts)


# ---------------------------------------------------------------------------------- performance profiles
@dataclass(frozen=True)
class ProfileCurve:
    """One arm's profile: ``fraction`` (T,) of its runs whose final return exceeds each threshold, with
    ``ci_low`` / ``ci_high`` (T,) from the stratified bootstrap; ``n`` runs."""

    fraction: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray
    n: int


@dataclass(frozen=True)
class PerformanceProfile:
    """One task's performance profiles (rliable's score distributions of the final return): ``thresholds``
    (T,) in return units, ``arms`` name -> ProfileCurve; CIs at ``confidence``."""

    task: str
    thresholds: np.ndarray
    arms: dict[str, ProfileCurve]
    reps: int
    seed: int
    final_evals: int
    confidence: float = 0.95


def performance_profiles(curves: Sequence[Curve], *, thresholds: Sequence[float] | None = None, points: int = 101,
                         final_evals: int = FINAL_EVALS, reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED,
                         confidence: float = 0.95) -> dict[str, PerformanceProfile]:
    """Task -> performance profile of the final returns (rliable's score distributions: the fraction of an arm's
    runs above each threshold, with the exact percentile bootstrap CI of that fraction: a binomial), per task
    because raw returns of different tasks do not share a scale; the final returns over the evaluation iterations
    every run of the task shares (:func:`common_window`).
    ``thresholds`` default: ``points`` evenly spaced from 5 % of the range below the task's lowest final return
    to 5 % above its highest. Runs without an evaluation are left out."""
    out = {}
    for task in dict.fromkeys(c.task for c in curves):
        finals: dict[str, list[float]] = {}
        window = common_window([c for c in curves if c.task == task], final_evals)
        for c in curves:
            if c.task == task and c.returns.size:
                finals.setdefault(c.arm, []).append(_windowed(c, window, final_evals)[0])
        if not finals:
            continue
        if thresholds is None:
            lo, hi = min(map(min, finals.values())), max(map(max, finals.values()))
            pad = 0.05 * (hi - lo) if hi > lo else max(1.0, 0.05 * abs(hi))
            taus = np.linspace(lo - pad, hi + pad, points)
        else:
            taus = np.asarray(thresholds, dtype=np.float64)
        arms = {}
        for a, v in finals.items():
            x = np.asarray(v, dtype=np.float64)
            n = x.size
            # a resample's fraction above tau is Binomial(n, k / n) / n, k the runs above tau: its bootstrap
            # distribution is exact for any n, no resample drawn
            fractions = np.arange(n + 1) / n
            bounds = []
            for k in (x[:, None] > taus[None, :]).sum(axis=0):
                pmf = np.array([math.comb(n, j) * (k / n) ** j * (1 - k / n) ** (n - j) for j in range(n + 1)])
                bounds.append(percentile_interval(fractions, pmf, confidence))
            bounds = np.array(bounds)
            arms[a] = ProfileCurve(np.mean(x[:, None] > taus[None, :], axis=0), bounds[:, 0], bounds[:, 1], n)
        out[task] = PerformanceProfile(task=task, thresholds=taus, arms=arms, reps=reps, seed=seed,
                                       final_evals=final_evals, confidence=confidence)
    return out
