"""Statistics over seeds for run folders: which arm trains better, with confidence intervals (issue 36).

An *arm* is a caller-given name for a group of run folders, one per seed (e.g. ``decoupled``, ``full``,
``full-hard``, ``blind``). Every statistic is computed per task, over the arm's seeds, from the deterministic
evaluations a run logs (``eval_return_mean``; runs that predate it have ``eval_return`` on their video iterations,
which is read instead). The statistics are rliable's (Agarwal et al., "Deep RL at the edge of the statistical
precipice", 2021), called as its authors do:

* **final return** of a run: the mean of its last ``final_evals`` (3) evaluations (fewer if it has fewer);
* **IQM**: the interquartile mean over seeds, ``rliable.metrics.aggregate_iqm`` (scipy's 25 % trimmed mean:
  ``floor(n / 4)`` seeds dropped at each end, so 3 seeds give the plain mean, 5 seeds the mean of the middle 3);
* **95 % CI**: percentile stratified bootstrap over seeds (``rliable.library.get_interval_estimates``), ``reps``
  resamples (``DEFAULT_REPS`` = 2000: with 5 seeds there are only 126 distinct resamples, so more reps change
  the interval's ends by less than their own Monte Carlo error). rliable resamples with numpy's *global* random
  state (its ``random_state`` argument does not reach the resampling), so every bootstrap here seeds that state
  with ``seed`` and restores it afterwards: the same input and seed give the same interval, whatever ran before.
  With 3-5 seeds a percentile bootstrap interval is narrower than the true 95 % one; read it as such;
* **paired difference** against a reference arm: per seed, arm minus reference final return (same seed in both;
  seeds that only one arm has are listed and skipped), its mean with a 95 % bootstrap CI over seeds, and
  rliable's **probability of improvement** P(arm > reference) (Mann-Whitney U / (n m), ties count 1/2) on the
  same paired seeds, with rliable's CI (each arm resampled independently);
* **AUC** (``auc``), the mean return along the evaluation curve, and **collapse rate** (``collapse_rate``), how
  often an evaluation falls below half the run's best so far;
* **equal iterations** and **equal wall-clock** (``task_statistics``): the same statistics on each run's curve
  cut at a common iteration count and at a common training-time budget, where training time is *modelled* from
  each arm's iteration time measured alone (``iter_ms_alone``), never from the run's own ``wall_s``;
* **performance profiles** (``performance_profiles``): the fraction of an arm's runs whose final return exceeds
  each threshold, with CIs, as data, and ``plot_performance_profiles`` to draw them;
* **looking probes** (``looking_probes``): the probe iterations where the policy's image sensitivity is above a
  fraction (``LOOKING_FRACTION``) of its first probe's, and the probe statistics over those only;
* **the verdict** (``verdict``): an arm is read against the reference (decoupled) only where the reference beats
  the control that cannot see (blind) with a confidence interval that excludes zero (issue 36), and no interval
  decides anything with fewer than ``MIN_SEEDS`` seeds (see there).

Importing this module needs numpy, scipy and rliable only (no torch): it reads JSON. ``load_arms`` reads folders
through ``ablations.run_folder.find_runs``, which imports no torch either; ``curve_of`` takes an already loaded run.
"""

from __future__ import annotations

import contextlib
import math
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import scipy.integrate
from rliable import library as rly
from rliable import metrics as rly_metrics

__all__ = ["DEFAULT_REPS", "DEFAULT_SEED", "FINAL_EVALS", "EVAL_KEYS", "Curve", "Estimate", "ArmSummary",
           "PairedDifference", "Comparison", "TaskStatistics", "ProfileCurve", "PerformanceProfile",
           "LookingProbes", "curve_of", "load_arms", "final_return", "auc", "collapse_rate", "iqm_estimate",
           "mean_estimate", "compare", "common_iteration", "truncate_at_iteration", "common_wall_s",
           "truncate_at_wall_s", "check_at_iteration", "task_statistics", "performance_profiles",
           "plot_performance_profiles", "looking_probes", "LOOKING_FRACTION", "BlindPhase", "blind_phase",
           "BLIND_PHASE_ITERS", "Verdict", "Gate", "verdict", "MIN_SEEDS"]

#: Bootstrap resamples per confidence interval (see the module docstring for why this many).
DEFAULT_REPS = 2000
#: Seed of numpy's global random state during each bootstrap.
DEFAULT_SEED = 0
#: Evaluations averaged into a run's final return.
FINAL_EVALS = 3
#: Metrics keys of the deterministic evaluation return, in order of preference: the mean over the evaluation
#: environments, else the older single-rollout return logged on video iterations.
EVAL_KEYS = ("eval_return_mean", "eval_return")
#: A probe counts as looking when its image sensitivity exceeds this fraction of the run's first probe's (the
#: untrained policy's): the blind phase (issue 36) drops it by orders of magnitude, so the bar needs no precision.
LOOKING_FRACTION = 0.1
#: The fewest seeds whose interval the verdict reads. A percentile bootstrap over 1 seed is a point and over 2
#: excludes zero whenever both seeds agree in sign (half the time under no difference at all); with 3 it is
#: still only as strict as "all three agree" (a quarter of the time under none), which the module docstring's
#: caveat covers. Fewer seeds than this: the table shows the numbers, the verdict says "too few seeds".
MIN_SEEDS = 3
_SENSITIVITY_KEY = re.compile(r"image_sensitivity_f(\d+)$")


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


# ---------------------------------------------------------------------------------------------------- curves
@dataclass(frozen=True)
class Curve:
    """One run's deterministic evaluation curve.

    ``iters`` (E,) int: the training iterations the evaluations followed (a metrics line's ``iter``: iterations
    done, 1-based); ``returns`` (E,) float: the evaluation return there (undiscounted, deterministic policy);
    ``last_iter``: the run's last metrics line's ``iter`` (how far it trained, evaluated or not); ``key``: the
    metrics key the returns came from (``EVAL_KEYS``), None when the run has no evaluation.
    """

    task: str
    arm: str
    seed: int
    path: str
    iters: np.ndarray
    returns: np.ndarray
    last_iter: int
    key: str | None = None


def curve_of(run, arm: str) -> Curve:
    """The evaluation curve of a loaded run (anything with ``.config`` (config.json's "config" object),
    ``.metrics`` (metrics.jsonl's lines) and ``.path``, e.g. ``ablations.run_folder.Run``), under arm name ``arm``.

    The key is the first of ``EVAL_KEYS`` any line carries; lines without a finite value of it are skipped.
    """
    cfg = run.config
    for k in ("task", "seed"):
        if k not in cfg:
            raise ValueError(f"{run.path}: config.json's config has no {k!r}")
    rows = run.metrics
    key = next((k for k in EVAL_KEYS if any(_number(r.get(k)) for r in rows)), None)
    pts = sorted((r["iter"], r[key]) for r in rows if key is not None and _number(r.get(key)))
    return Curve(task=str(cfg["task"]), arm=arm, seed=int(cfg["seed"]), path=str(run.path),
                 iters=np.array([p[0] for p in pts], dtype=np.int64),
                 returns=np.array([p[1] for p in pts], dtype=np.float64),
                 last_iter=int(max((r["iter"] for r in rows), default=0)), key=key)


def load_arms(arms: Mapping[str, Iterable[str | Path]]) -> list[Curve]:
    """Arm name -> run folders (a folder holding run folders stands for all of them) -> their curves, in the
    given order. Raises ValueError for a folder that is not a run, or two runs of one task, arm and seed."""
    from ablations.run_folder import find_runs

    curves = [curve_of(run, arm) for arm, paths in arms.items() for run in find_runs(list(paths))]
    _check_unique(curves)
    return curves


def _check_unique(curves: Sequence[Curve]) -> None:
    seen: dict[tuple[str, str, int], str] = {}
    for c in curves:
        k = (c.task, c.arm, c.seed)
        if k in seen:
            raise ValueError(f"arm {c.arm!r} has two runs of task {c.task!r} with seed {c.seed}: {seen[k]} and "
                             f"{c.path}; give one folder per seed")
        seen[k] = c.path


# ------------------------------------------------------------------------------------- per-run statistics
def final_return(curve: Curve, final_evals: int = FINAL_EVALS) -> float:
    """Mean of the last ``final_evals`` evaluation returns (all of them when there are fewer); NaN without any."""
    if curve.returns.size == 0:
        return math.nan
    return float(np.mean(curve.returns[-final_evals:]))


def auc(curve: Curve) -> float:
    """Area under the evaluation curve divided by its span: the trapezoid integral of the return over training
    iterations, from the first evaluation to the last, over (last - first) iterations. Units: return (the curve's
    mean height, so curves of different lengths compare); the one evaluation's return when there is one; NaN
    without any."""
    x, y = curve.iters.astype(np.float64), curve.returns
    if y.size == 0:
        return math.nan
    if y.size == 1 or x[-1] == x[0]:
        return float(y[-1])
    return float(scipy.integrate.trapezoid(y, x) / (x[-1] - x[0]))


def collapse_rate(curve: Curve) -> float:
    """Fraction of evaluations that collapse: with returns r_1..r_E in iteration order and the running best
    b_i = max(r_1, .., r_i), let k be the first index with b_k > 0 (the first positive best; half of a
    non-positive best is no bar). The rate is |{i > k : r_i < b_i / 2}| / (E - k): of the evaluations after
    the first positive best, those below half of the best so far. NaN when no best is positive or no
    evaluation follows it."""
    r = curve.returns
    best = np.maximum.accumulate(r) if r.size else r
    positive = np.flatnonzero(best > 0)
    if positive.size == 0 or positive[0] == r.size - 1:
        return math.nan
    after = slice(positive[0] + 1, None)
    return float(np.mean(r[after] < 0.5 * best[after]))


# -------------------------------------------------------------------------------------------- bootstrap
@dataclass(frozen=True)
class Estimate:
    """A statistic over ``n`` runs (seeds) with its bootstrap confidence interval [ci_low, ci_high] (same units
    as the statistic); ``reps`` resamples, numpy's global state seeded with ``seed``."""

    value: float
    ci_low: float
    ci_high: float
    n: int
    reps: int
    seed: int
    confidence: float = 0.95

    def excludes(self, x: float) -> bool:
        """Whether the interval lies wholly on one side of ``x``."""
        return self.ci_low > x or self.ci_high < x


@contextlib.contextmanager
def _numpy_global_seed(seed: int):
    """rliable's bootstraps draw from numpy's global random state: seed it for the block, then put it back."""
    # the legacy global-state API on purpose: it is the state rliable's resampling draws from
    state = np.random.get_state()  # noqa: NPY002
    np.random.seed(seed)  # noqa: NPY002
    try:
        yield
    finally:
        np.random.set_state(state)  # noqa: NPY002


def _interval(scores, func: Callable, *, reps: int, seed: int, confidence: float, n: int) -> Estimate:
    """``func``'s point estimate and stratified-bootstrap CI of ``scores`` (an (n, 1) array, or a list of
    arrays resampled independently), through ``rliable.library.get_interval_estimates``."""
    if reps < 1:
        raise ValueError(f"reps must be a positive number of bootstrap resamples, got {reps}")
    with _numpy_global_seed(seed):
        point, ci = rly.get_interval_estimates({"x": scores}, func, reps=reps, confidence_interval_size=confidence)
    lo, hi = np.asarray(ci["x"], dtype=np.float64).reshape(2)
    return Estimate(float(np.asarray(point["x"]).reshape(())), float(lo), float(hi), n, reps, seed, confidence)


def _scores(values: Sequence[float]) -> np.ndarray:
    """rliable's score matrix (runs x tasks): one task."""
    return np.asarray(values, dtype=np.float64).reshape(-1, 1)


def iqm_estimate(values: Sequence[float], *, reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED,
                 confidence: float = 0.95) -> Estimate | None:
    """Interquartile mean of per-seed values with its stratified-bootstrap CI; None for no values."""
    if len(values) == 0:
        return None
    return _interval(_scores(values), lambda s: np.array([rly_metrics.aggregate_iqm(s)]), reps=reps, seed=seed,
                     confidence=confidence, n=len(values))


def mean_estimate(values: Sequence[float], *, reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED,
                  confidence: float = 0.95) -> Estimate | None:
    """Mean of per-seed values with its bootstrap CI over seeds; None for no values."""
    if len(values) == 0:
        return None
    return _interval(_scores(values), lambda s: np.array([rly_metrics.aggregate_mean(s)]), reps=reps, seed=seed,
                     confidence=confidence, n=len(values))


def _improvement_estimate(x: Sequence[float], y: Sequence[float], *, reps: int, seed: int,
                          confidence: float) -> Estimate:
    """rliable's probability of improvement P(X > Y) with its CI (each sample resampled independently)."""
    return _interval([_scores(x), _scores(y)], rly_metrics.probability_of_improvement, reps=reps, seed=seed,
                     confidence=confidence, n=len(x))


# ------------------------------------------------------------------------------------------- comparison
@dataclass(frozen=True)
class ArmSummary:
    """One arm on one task. Per-seed dicts (seed -> value) hold the runs with at least one evaluation:
    ``final`` (mean of the last ``final_evals`` evaluation returns), ``auc`` (``auc``), ``collapse``
    (``collapse_rate``; NaN where undefined), ``evals`` (evaluations in the curve). Over seeds: ``final_iqm``
    and ``auc_iqm`` (IQM with CI, return units), ``collapse_mean`` (mean of the defined rates with CI; None when
    none is defined). ``without_evals``: seeds whose curve has no evaluation, left out of everything."""

    arm: str
    final: dict[int, float]
    auc: dict[int, float]
    collapse: dict[int, float]
    evals: dict[int, int]
    final_iqm: Estimate | None
    auc_iqm: Estimate | None
    collapse_mean: Estimate | None
    without_evals: tuple[int, ...] = ()

    @property
    def seeds(self) -> tuple[int, ...]:
        return tuple(self.final)


@dataclass(frozen=True)
class PairedDifference:
    """``arm`` against ``reference`` on the seeds both have: ``diff`` (seed -> arm minus reference final
    return), ``mean`` (their mean with a bootstrap CI over seeds), ``improvement`` (rliable's probability that
    the arm's final return exceeds the reference's, with its CI). ``missing``: arm name -> seeds that arm has
    and the other lacks (skipped). ``mean`` and ``improvement`` are None without a paired seed."""

    arm: str
    reference: str
    diff: dict[int, float]
    mean: Estimate | None
    improvement: Estimate | None
    missing: dict[str, tuple[int, ...]] = field(default_factory=dict)

    @property
    def seeds(self) -> tuple[int, ...]:
        return tuple(self.diff)


@dataclass(frozen=True)
class Comparison:
    """The arms of one task on the given curves: ``arms`` (name -> ArmSummary, in the curves' order) and
    ``differences`` (name -> PairedDifference against ``reference``, every arm but the reference; empty when
    the reference is not among the arms)."""

    task: str
    reference: str | None
    arms: dict[str, ArmSummary]
    differences: dict[str, PairedDifference]
    final_evals: int


def _arm_summary(arm: str, curves: Sequence[Curve], *, final_evals: int, reps: int, seed: int,
                 confidence: float) -> ArmSummary:
    evaluated = sorted((c for c in curves if c.returns.size), key=lambda c: c.seed)
    final = {c.seed: final_return(c, final_evals) for c in evaluated}
    areas = {c.seed: auc(c) for c in evaluated}
    collapse = {c.seed: collapse_rate(c) for c in evaluated}
    defined = [v for v in collapse.values() if not math.isnan(v)]
    kw = dict(reps=reps, seed=seed, confidence=confidence)
    return ArmSummary(arm=arm, final=final, auc=areas, collapse=collapse,
                      evals={c.seed: int(c.returns.size) for c in evaluated},
                      final_iqm=iqm_estimate(list(final.values()), **kw),
                      auc_iqm=iqm_estimate(list(areas.values()), **kw),
                      collapse_mean=mean_estimate(defined, **kw),
                      without_evals=tuple(sorted(c.seed for c in curves if not c.returns.size)))


def _paired(arm: ArmSummary, ref: ArmSummary, *, reps: int, seed: int, confidence: float) -> PairedDifference:
    seeds = sorted(set(arm.final) & set(ref.final))
    missing = {name: tuple(sorted(set(a.final) - set(b.final))) for name, a, b in
               ((arm.arm, arm, ref), (ref.arm, ref, arm))}
    missing = {k: v for k, v in missing.items() if v}
    diff = {s: arm.final[s] - ref.final[s] for s in seeds}
    kw = dict(reps=reps, seed=seed, confidence=confidence)
    improvement = None
    if seeds:
        improvement = _improvement_estimate([arm.final[s] for s in seeds], [ref.final[s] for s in seeds], **kw)
    return PairedDifference(arm=arm.arm, reference=ref.arm, diff=diff, mean=mean_estimate(list(diff.values()), **kw),
                            improvement=improvement, missing=missing)


def compare(curves: Sequence[Curve], *, reference: str | None = "decoupled", final_evals: int = FINAL_EVALS,
            reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED, confidence: float = 0.95) -> Comparison:
    """Arm summaries and paired differences against ``reference`` of curves of ONE task (as given: cut them
    first for equal iterations or wall-clock, or use ``task_statistics``)."""
    if final_evals < 1:
        raise ValueError(f"final_evals must be >= 1, got {final_evals}")
    tasks = sorted({c.task for c in curves})
    if len(tasks) != 1:
        raise ValueError(f"compare takes the curves of one task, got {tasks or 'none'}")
    _check_unique(curves)
    by_arm: dict[str, list[Curve]] = {}
    for c in curves:
        by_arm.setdefault(c.arm, []).append(c)
    kw = dict(reps=reps, seed=seed, confidence=confidence)
    arms = {a: _arm_summary(a, cs, final_evals=final_evals, **kw) for a, cs in by_arm.items()}
    differences = {}
    if reference in arms:
        differences = {a: _paired(s, arms[reference], **kw) for a, s in arms.items() if a != reference}
    return Comparison(task=tasks[0], reference=reference, arms=arms, differences=differences,
                      final_evals=final_evals)


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
        if not _number(v) or v <= 0:
            raise ValueError(f"iter_ms_alone[{arm!r}] must be a positive number of milliseconds, got {v!r}")
        ms[arm] = float(v)
    return ms


def common_wall_s(curves: Sequence[Curve], iter_ms_alone: Mapping[str, float]) -> float:
    """The training-time budget every run reached, in seconds: the minimum over the runs of
    last_iter x iter_ms_alone[arm] / 1000. The time is *modelled*: each arm's iteration time measured alone
    (a benchmark's ms per iteration of that arm as the only work on its device), never a run's logged
    ``wall_s``, which for a population member is the whole population's time and includes compilation. So
    it leaves out what the measurement alone left out (typically compilation, evaluation rollouts, and the
    extra backward of probe iterations if the benchmark's time excludes them)."""
    if not curves:
        raise ValueError("no runs to compare")
    ms = _iter_ms(curves, iter_ms_alone)
    return min(c.last_iter * ms[c.arm] / 1e3 for c in curves)


def truncate_at_wall_s(curves: Sequence[Curve], iter_ms_alone: Mapping[str, float], wall_s: float) -> list[Curve]:
    """Each curve cut to the iterations its arm completes within ``wall_s`` seconds of modelled training time
    (iteration i ends at i x iter_ms_alone[arm] / 1000 s; see ``common_wall_s``)."""
    ms = _iter_ms(curves, iter_ms_alone)
    # a relative tolerance so that the run that sets the budget keeps its own last iteration despite rounding
    return [truncate_at_iteration([c], math.floor(wall_s * 1e3 / ms[c.arm] * (1 + 1e-12)))[0] for c in curves]


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


def task_statistics(curves: Sequence[Curve], *, reference: str | None = "decoupled",
                    iter_ms_alone: Mapping[str, float] | None = None, final_evals: int = FINAL_EVALS,
                    reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED, confidence: float = 0.95,
                    at_iteration: int | None = None) -> dict[str, TaskStatistics]:
    """Task -> its ``TaskStatistics`` (tasks in the curves' order). Equal iterations and equal wall-clock are
    taken over all runs of the task, every arm together. ``iter_ms_alone``: arm -> milliseconds per training
    iteration of that arm measured alone (population members share a process, so their own ``wall_s`` is not
    their arm's time). ``at_iteration``: every curve is cut there first (to read longer runs at an earlier
    point: all three views then end at or before it)."""
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
        stats = TaskStatistics(task=task, whole=compare(cs, **kw), iteration=n,
                               equal_iters=compare(truncate_at_iteration(cs, n), **kw))
        if iter_ms_alone is not None:
            budget = common_wall_s(cs, iter_ms_alone)
            cut = truncate_at_wall_s(cs, iter_ms_alone, budget)
            ms = _iter_ms(cs, iter_ms_alone)
            stats = replace(stats, wall_s=budget, iter_ms_alone=ms, equal_wall=compare(cut, **kw),
                            iters_at_wall={a: max(c.last_iter for c in cut if c.arm == a) for a in ms})
        out[task] = stats
    return out


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
    """Task -> performance profile of the final returns (``rliable.library.create_performance_profile``), per
    task because raw returns of different tasks do not share a scale. ``thresholds`` default: ``points`` evenly
    spaced from 5 % of the range below the task's lowest final return to 5 % above its highest. Runs without
    an evaluation are left out."""
    out = {}
    for task in dict.fromkeys(c.task for c in curves):
        finals: dict[str, list[float]] = {}
        for c in curves:
            if c.task == task and c.returns.size:
                finals.setdefault(c.arm, []).append(final_return(c, final_evals))
        if not finals:
            continue
        if thresholds is None:
            lo, hi = min(map(min, finals.values())), max(map(max, finals.values()))
            pad = 0.05 * (hi - lo) if hi > lo else max(1.0, 0.05 * abs(hi))
            taus = np.linspace(lo - pad, hi + pad, points)
        else:
            taus = np.asarray(thresholds, dtype=np.float64)
        with _numpy_global_seed(seed):
            frac, cis = rly.create_performance_profile({a: _scores(v) for a, v in finals.items()}, taus, reps=reps,
                                                       confidence_interval_size=confidence)
        arms = {a: ProfileCurve(np.asarray(frac[a], np.float64), np.asarray(cis[a][0], np.float64),
                                np.asarray(cis[a][1], np.float64), len(finals[a])) for a in finals}
        out[task] = PerformanceProfile(task=task, thresholds=taus, arms=arms, reps=reps, seed=seed,
                                       final_evals=final_evals, confidence=confidence)
    return out


def plot_performance_profiles(profile: PerformanceProfile, path: str | Path, *,
                              styles: Mapping | None = None) -> Path:
    """Draw one task's profiles (fraction of runs above each threshold, the CI shaded) to a PNG, written
    atomically; the legend sits outside the axes. ``styles``: arm -> ``ablations.plot.ArmStyle`` (the arm's colour
    and line style in every other figure); arms it does not name take matplotlib's next colour."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ablations.plot import _save

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for arm, p in profile.arms.items():
        style = (styles or {}).get(arm)
        look = {"color": style.color, "ls": style.linestyle} if style is not None else {}
        (line,) = ax.plot(profile.thresholds, p.fraction, label=f"{arm} (n={p.n})", lw=1.6, **look)
        ax.fill_between(profile.thresholds, p.ci_low, p.ci_high, color=line.get_color(), alpha=0.2, linewidth=0)
    ax.set_xlabel(f"final evaluation return (mean of the last {profile.final_evals})")
    ax.set_ylabel("fraction of runs above")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"{profile.task}: performance profile (shaded: {profile.confidence:.0%} CI, "
                 f"{profile.reps} bootstrap resamples)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    path = Path(path)
    _save(fig, path)
    return path


# ------------------------------------------------------------------------------------------ looking probes
@dataclass(frozen=True)
class LookingProbes:
    """A run's probe iterations split by whether the policy looks at its image.

    ``probe_iters`` / ``sensitivity`` (P,): every probe (a metrics line with ``image_sensitivity_f<i>``) and its
    image sensitivity (the sum or mean over frames, ``reduce``, of |d mean action / d frame|); ``initial``: the
    first probe's; ``looking_iters``: the probes with sensitivity > ``fraction`` x ``initial``. ``medians``:
    probe key -> median over the looking probes that carry it (None when none does), ``counts``: how many did,
    ``values``: probe key -> those values in iteration order (to pool the probes of several seeds).
    """

    fraction: float
    reduce: str
    initial: float | None
    probe_iters: tuple[int, ...]
    sensitivity: tuple[float, ...]
    looking_iters: tuple[int, ...]
    medians: dict[str, float | None]
    counts: dict[str, int]
    values: dict[str, tuple[float, ...]] = field(default_factory=dict)

    @property
    def n_probes(self) -> int:
        return len(self.probe_iters)

    @property
    def n_looking(self) -> int:
        return len(self.looking_iters)


def _is_probe_statistic(key: str) -> bool:
    """The probe's cosines and gradient norms (gradlab.shac's probe keys), not the every-iteration norms."""
    return key.startswith("cos_") or (key.startswith("grad_norm_") and key != "grad_norm_clipped")


def looking_probes(metrics: Sequence[Mapping], *, fraction: float = LOOKING_FRACTION, reduce: str = "sum",
                   keys: Sequence[str] | None = None) -> LookingProbes:
    """Where a run's policy looks at its image, and its probe statistics there.

    A probe is a metrics line with finite ``image_sensitivity_f0 .. f{k-1}``; its sensitivity is their sum
    (``reduce="sum"``) or mean (``"mean"``). The policy looks on a probe whose sensitivity exceeds ``fraction``
    of the first probe's (the untrained policy's). ``keys``: the probe statistics to take the median of over
    the looking probes; None: every ``cos_*`` and ``grad_norm_*`` key those probes carry (the cosine of full
    and decoupled, the gradient norms, the render term and its groups), except ``grad_norm_clipped``.
    """
    if not (_number(fraction) and fraction >= 0):
        raise ValueError(f"fraction must be a number >= 0, got {fraction!r}")
    if reduce not in ("sum", "mean"):
        raise ValueError(f"reduce must be 'sum' or 'mean', got {reduce!r}")
    probes = []
    for row in sorted(metrics, key=lambda r: r["iter"]):
        frames = [v for k, v in row.items() if _SENSITIVITY_KEY.match(k)]
        if frames and all(_number(v) for v in frames):
            probes.append((row, float(np.sum(frames) if reduce == "sum" else np.mean(frames))))
    initial = probes[0][1] if probes else None
    looking = [row for row, s in probes if s > fraction * initial] if probes else []
    if keys is None:
        keys = sorted({k for row in looking for k in row if _is_probe_statistic(k)})
    medians, counts, values = {}, {}, {}
    for k in keys:
        vals = [float(row[k]) for row in looking if _number(row.get(k))]
        medians[k] = float(np.median(vals)) if vals else None
        counts[k] = len(vals)
        values[k] = tuple(vals)
    return LookingProbes(fraction=float(fraction), reduce=reduce, initial=initial,
                         probe_iters=tuple(int(r["iter"]) for r, _ in probes),
                         sensitivity=tuple(s for _, s in probes),
                         looking_iters=tuple(int(r["iter"]) for r in looking), medians=medians, counts=counts,
                         values=values)


#: Iterations from the start over which ``blind_phase`` looks for the blind phase (issue 36 measures the first 500).
BLIND_PHASE_ITERS = 500


@dataclass(frozen=True)
class BlindPhase:
    """How far and how long a run's policy stops looking at its image early in training (the blind phase): over
    the probes after the first up to iteration ``within``: ``probes`` of them, ``blind`` where the policy does not
    look (sensitivity at most ``fraction`` x the first probe's), ``lowest`` the lowest sensitivity relative to the
    first probe's (None without such probes, or when the first probe is 0 and sets no bar); ``looks_again_at`` the
    first probe after a blind one where it looks again (None when it never stopped looking or is still blind at
    its last probe in the window); ``last_blind`` the last blind probe (None without any): a policy may look again
    and stop once more."""

    within: int
    probes: int
    blind: int
    lowest: float | None
    looks_again_at: int | None
    last_blind: int | None = None


def blind_phase(looking: LookingProbes, *, within: int = BLIND_PHASE_ITERS) -> BlindPhase:
    """:class:`BlindPhase` of a run's probes (``looking``: :func:`looking_probes` of its metrics)."""
    if not (isinstance(within, int) and within > 0):
        raise ValueError(f"within must be a positive integer, got {within!r}")
    early = [(i, s) for i, s in zip(looking.probe_iters[1:], looking.sensitivity[1:]) if i <= within]
    if not early or not looking.initial:
        return BlindPhase(within, len(early), 0, None, None)
    threshold = looking.fraction * looking.initial
    blind = [s <= threshold for _, s in early]
    again = None
    if any(blind):
        first_blind = blind.index(True)
        again = next((i for (i, _), b in zip(early[first_blind:], blind[first_blind:]) if not b), None)
    last = max((i for (i, _), b in zip(early, blind) if b), default=None)
    return BlindPhase(within, len(early), sum(blind), min(s for _, s in early) / looking.initial, again, last)


# ------------------------------------------------------------------------------------------------ verdict
@dataclass(frozen=True)
class Gate:
    """Whether the reference arm beats the control (decoupled against blind) on one task: ``passed`` when the
    paired difference reference minus control has a CI above zero, or the reference's IQM CI lies wholly above
    the control's; ``by`` names which (``"paired difference"``, ``"IQMs"``), None when neither. ``paired``:
    reference minus control final return over the paired seeds (None without any); ``why``: one sentence."""

    passed: bool
    by: str | None
    paired: Estimate | None
    reference_iqm: Estimate | None
    control_iqm: Estimate | None
    why: str


@dataclass(frozen=True)
class Verdict:
    """How one task's arms may be read against the reference. ``ranks``: whether they may; ``reason``: why (or
    why not), one sentence; ``gate``: the reference against the control (None when the task does not rank arms
    or an arm is missing); ``readings``: arm -> ``"better"``, ``"worse"`` (the paired difference's CI excludes
    zero on that side), ``"not resolved"`` (it covers zero), ``"too few seeds"`` (fewer than ``MIN_SEEDS``
    paired seeds) or ``"no paired seeds"``; empty unless ``ranks``."""

    task: str
    reference: str
    control: str
    ranks: bool
    reason: str
    gate: Gate | None
    readings: dict[str, str]


def _negated(e: Estimate) -> Estimate:
    """The estimate of minus the statistic: a percentile bootstrap of a mean flips exactly under negation."""
    return replace(e, value=-e.value, ci_low=-e.ci_high, ci_high=-e.ci_low)


def _ci(e: Estimate) -> str:
    return f"{e.value:.4g} [{e.ci_low:.4g}, {e.ci_high:.4g}]"


def verdict(cmp: Comparison, *, control: str = "blind", not_ranking: str | None = None) -> Verdict:
    """The rule of issue 36: the arms of ``cmp`` are read against its reference (decoupled) only where the
    reference beats ``control`` (blind: the same pixels, never looked at) with a CI that excludes zero, of the
    paired difference or of the IQMs (see ``Gate``); otherwise pixels have not yet been shown to help on this
    task and the arms cannot be ranked. ``not_ranking``: a reason the task ranks no arms whatever the numbers
    (a task that doing nothing solves)."""
    ref = cmp.reference or "reference"
    if not_ranking is not None:
        return Verdict(cmp.task, ref, control, False, not_ranking, None, {})
    missing = [a for a in (ref, control) if a not in cmp.arms or cmp.arms[a].final_iqm is None]
    if missing:
        return Verdict(cmp.task, ref, control, False, f"the arms cannot be ranked: no {' and no '.join(missing)} "
                       "run with an evaluation to hold them against", None, {})
    r, c = cmp.arms[ref].final_iqm, cmp.arms[control].final_iqm
    d = cmp.differences[control].mean
    paired = _negated(d) if d is not None else None
    if paired is not None and paired.n >= MIN_SEEDS and paired.ci_low > 0:
        by = "paired difference"
        why = (f"{ref} beats {control}: {ref} minus {control}, mean over {paired.n} paired seeds "
               f"{_ci(paired)}, CI above zero")
    elif min(r.n, c.n) >= MIN_SEEDS and r.ci_low > c.ci_high:
        by = "IQMs"
        why = f"{ref} beats {control}: IQM {_ci(r)} (n={r.n}) wholly above {_ci(c)} (n={c.n})"
    elif min(r.n, c.n) < MIN_SEEDS:  # neither path has the seeds (paired ones are never more than either arm's)
        by = None
        why = (f"too few seeds to read {ref} against {control}: {r.n} and {c.n} seed(s), an interval over fewer "
               f"than {MIN_SEEDS} decides nothing")
    else:
        by = None
        few = paired is not None and paired.n < MIN_SEEDS
        why = (f"{ref} does not beat {control} with a CI that excludes zero: "
               + (f"{ref} minus {control} {_ci(paired)} over {paired.n} paired seeds"
                  + (f" (fewer than {MIN_SEEDS}: not read)" if few else "") + "; " if paired else "")
               + f"IQMs {_ci(r)} (n={r.n}) and {_ci(c)} (n={c.n})")
    gate = Gate(by is not None, by, paired, r, c, why)
    if not gate.passed:
        return Verdict(cmp.task, ref, control, False, f"{why}; the pixel arms cannot be ranked on this task yet",
                       gate, {})
    readings = {}
    for arm, diff in cmp.differences.items():
        if arm == control:
            continue
        m = diff.mean
        readings[arm] = ("no paired seeds" if m is None else "too few seeds" if m.n < MIN_SEEDS
                         else "better" if m.ci_low > 0 else "worse" if m.ci_high < 0 else "not resolved")
    return Verdict(cmp.task, ref, control, True, why, gate, readings)
