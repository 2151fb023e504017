"""Statistics over seeds for run folders: which arm trains better, with confidence intervals and tests.

An *arm* is a caller-given name for a group of run folders, one per seed (e.g. ``decoupled``, ``full``,
``full-hard``, ``blind``). Every statistic is computed per task, over the arm's seeds, from the deterministic
evaluations a run logs (``eval_return_mean``; runs that predate it have ``eval_return`` on their video iterations,
which is read instead). The definitions are rliable's (Agarwal et al., "Deep RL at the edge of the statistical
precipice", 2021), computed here with numpy so that no resampling library (and none of its pandas) is needed:

* **final return** of a run: the mean of its evaluation returns at the last ``final_evals`` (3) evaluation
  iterations that EVERY run of the comparison has (:func:`common_window`; runs cut at equal modelled time end
  at different iterations per arm, so there: the same iterations within each arm);
* **IQM**: the interquartile mean over seeds (rliable's ``aggregate_iqm``: scipy's 25 % trimmed mean,
  ``floor(n / 4)`` seeds dropped at each end, so 3 seeds give the plain mean, 5 seeds the mean of the middle 3);
* **95 % CI**: the percentile interval of the bootstrap over seeds. Up to ``EXACT_BOOTSTRAP_MAX_N`` seeds it is
  exact: every distinct resample is enumerated with its multinomial probability (C(2n - 1, n) of them: 10 for 3
  seeds, 126 for 5, 6435 for 8), so the interval has no draw noise; beyond, ``reps`` resamples drawn with
  ``numpy.random.default_rng(seed)``. Over 3 seeds the interval is the range [min, max] of the seeds (each
  extreme resample has probability 1/27 > 2.5 %): it excludes 0 exactly when all three agree in sign, which
  happens a quarter of the time with no difference at all. Read it as the range it is;
* **paired difference** against a reference arm: per seed, arm minus reference final return (same seed in both;
  seeds that only one arm has are listed and skipped), how many seeds agree in sign, the mean with its bootstrap
  CI, the two-sided **sign-flip permutation p-value** (exact over all 2^n sign patterns up to
  ``EXACT_SIGN_FLIP_MAX_N`` seeds; its smallest value is 2 / 2^n: 0.25 for 3 seeds, 0.0625 for 5, 0.0078 for 8)
  and the probability of improvement P(arm > reference) (Mann-Whitney U / (n m), ties count 1/2) with a CI
  from each arm resampled independently;
* **Holm's correction** (:func:`correct`): a difference *differs* only where its Holm-adjusted p-value over the
  whole family of paired comparisons (a report: every arm against the reference, every task, every view) is at
  most ``ALPHA``, so that the chance of any false "differs" in the report is at most ``ALPHA``;
* **AUC** (``auc``), the mean return along the evaluation curve, and **collapse rate** (``collapse_rate``), how
  often an evaluation falls below half the run's best so far;
* **equal iterations** and **equal wall-clock** (``task_statistics``): the same statistics on each run's curve
  cut at a common iteration count and at a common training-time budget, where training time is *modelled* from
  each arm's iteration time measured alone (``iter_ms_alone``), never from the run's own ``wall_s``;
* **differences along the budget** (``difference_curves``, ``sign_holds``): the paired difference at every
  evaluation, in iterations and in modelled wall-clock, so that no single cut decides what a curve says;
* **performance profiles** (``performance_profiles``): the fraction of an arm's runs whose final return exceeds
  each threshold, with CIs, as data, and ``plot_performance_profiles`` to draw them;
* **looking probes** (``looking_probes``): the probe iterations where the policy's image sensitivity is above a
  fraction (``LOOKING_FRACTION``) of its first probe's, and the probe statistics over those only;
* **the verdict** (``verdict``): an arm is read against the reference (decoupled) only where the reference beats
  the control that cannot see (blind) after Holm correction (the control rule), and nothing is decided from
  fewer than ``MIN_SEEDS`` paired seeds (the minimum-seeds rule).

Importing this module needs numpy only (no torch, no rliable, no scipy, no pandas): it reads JSON. ``load_arms``
reads folders through ``ablations.run_folder.find_runs``, which imports no torch either; ``curve_of`` takes an
already loaded run.
"""

from __future__ import annotations

import functools
import itertools
import math
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

__all__ = ["DEFAULT_REPS", "DEFAULT_SEED", "FINAL_EVALS", "EVAL_KEYS", "Curve", "Estimate", "ArmSummary",
           "PairedDifference", "Comparison", "TaskStatistics", "ProfileCurve", "PerformanceProfile",
           "LookingProbes", "curve_of", "load_arms", "final_return", "auc", "collapse_rate", "iqm_estimate",
           "mean_estimate", "compare", "common_iteration", "truncate_at_iteration", "common_wall_s",
           "truncate_at_wall_s", "check_at_iteration", "task_statistics", "performance_profiles",
           "plot_performance_profiles", "looking_probes", "LOOKING_FRACTION", "BlindPhase", "blind_phase",
           "BLIND_PHASE_ITERS", "Verdict", "Gate", "verdict", "MIN_SEEDS", "ALPHA", "EXACT_BOOTSTRAP_MAX_N",
           "EXACT_SIGN_FLIP_MAX_N", "bootstrap_distribution", "percentile_interval", "sign_flip_p", "holm",
           "correct", "correct_statistics", "common_window", "paired_difference", "DifferenceCurve",
           "difference_curves", "sign_holds", "Band", "mean_band"]

#: Bootstrap resamples per confidence interval where the bootstrap is not enumerated (more seeds than
#: EXACT_BOOTSTRAP_MAX_N), and for the probability of improvement's interval.
DEFAULT_REPS = 2000
#: Seed of the random generator (``numpy.random.default_rng``) of every drawn resample or sign pattern.
DEFAULT_SEED = 0
#: Up to this many seeds a bootstrap interval enumerates every distinct resample (6435 at 8 seeds; 92378 at 10
#: would make a report's thousands of intervals slow for no gain a reader could see).
EXACT_BOOTSTRAP_MAX_N = 8
#: Up to this many paired seeds the sign-flip p-value enumerates every sign pattern (65536 at 16).
EXACT_SIGN_FLIP_MAX_N = 16
#: Family-wise error level of the Holm-corrected verdicts.
ALPHA = 0.05
#: Evaluations averaged into a run's final return.
FINAL_EVALS = 3
#: Metrics keys of the deterministic evaluation return, in order of preference: the mean over the evaluation
#: environments, else the older single-rollout return logged on video iterations.
EVAL_KEYS = ("eval_return_mean", "eval_return")
#: A probe counts as looking when its image sensitivity exceeds this fraction of the run's first probe's (the
#: untrained policy's): the blind phase drops it by orders of magnitude, so the bar needs no precision.
LOOKING_FRACTION = 0.1
#: The minimum-seeds rule: no verdict rests on fewer paired seeds than this. A percentile bootstrap over 1 seed
#: is a point and over 2 excludes zero whenever both agree in sign (half the time under no difference); the
#: sign-flip test cannot go below 0.5 there. Fewer: the table shows the numbers, the verdict says "too few seeds".
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
    return float(np.sum((y[1:] + y[:-1]) * np.diff(x)) / 2.0 / (x[-1] - x[0]))


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
    """A statistic over ``n`` runs (seeds) with its percentile bootstrap confidence interval [ci_low, ci_high]
    (same units as the statistic). ``exact``: the interval is of the exact bootstrap distribution (every
    resample enumerated with its probability; ``reps`` is then the number of distinct resamples), else of
    ``reps`` resamples drawn with ``numpy.random.default_rng(seed)``."""

    value: float
    ci_low: float
    ci_high: float
    n: int
    reps: int
    seed: int
    confidence: float = 0.95
    exact: bool = False

    def excludes(self, x: float) -> bool:
        """Whether the interval lies wholly on one side of ``x``."""
        return self.ci_low > x or self.ci_high < x


@functools.cache
def _multisets(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Every distinct bootstrap resample of n >= 1 values as a sorted index tuple (M, n)
    (``combinations_with_replacement``: M = C(2n - 1, n)) with its probability n! / (prod of the index
    multiplicities!) / n^n: the n^n ordered resamples grouped by the multiset they draw. The rows are sorted,
    so a statistic of sorted values reads them directly."""
    idx = np.array(list(itertools.combinations_with_replacement(range(n), n)), dtype=np.int64)
    counts = np.stack([np.bincount(row, minlength=n) for row in idx])
    factorial = np.array([math.factorial(k) for k in range(n + 1)], dtype=np.float64)
    return idx, math.factorial(n) / factorial[counts].prod(axis=1) / float(n) ** n


def bootstrap_distribution(values: Sequence[float], statistic: Callable[[np.ndarray], np.ndarray], *,
                           reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED) -> tuple[np.ndarray, np.ndarray, bool]:
    """(statistic of each resample, its probability, exact) of the bootstrap of ``values`` (resampled with
    replacement, n of n). Up to ``EXACT_BOOTSTRAP_MAX_N`` values every distinct resample is enumerated with its
    multinomial probability (exact: no draw noise); more values: ``reps`` resamples drawn with
    ``numpy.random.default_rng(seed)``, each of probability 1 / reps. ``statistic`` maps an (M, n) array of
    resamples, each row sorted ascending, to (M,) values."""
    x = np.sort(np.asarray(values, dtype=np.float64))
    n = x.size
    if n <= EXACT_BOOTSTRAP_MAX_N:
        idx, w = _multisets(n)
        return np.asarray(statistic(x[idx]), dtype=np.float64), w, True
    if reps < 1:
        raise ValueError(f"reps must be a positive number of bootstrap resamples, got {reps}")
    draws = np.sort(x[np.random.default_rng(seed).integers(0, n, size=(reps, n))], axis=1)
    return np.asarray(statistic(draws), dtype=np.float64), np.full(reps, 1.0 / reps), False


def percentile_interval(stat: np.ndarray, weights: np.ndarray, confidence: float = 0.95) -> tuple[float, float]:
    """The percentile interval of a weighted bootstrap distribution: the smallest value with at least
    (1 - confidence) / 2 of the probability at or below it, and the largest with as much at or above it (so an
    interval of the negated statistic is the negated interval, and three values give [min, max]: each extreme
    resample has probability 1/27 > 2.5 %)."""
    tail = (1.0 - confidence) / 2.0
    order = np.argsort(stat, kind="stable")
    s, w = stat[order], weights[order]
    below = np.cumsum(w)
    above = np.cumsum(w[::-1])[::-1]
    eps = 1e-12
    lo = s[np.flatnonzero(below >= tail - eps)[0]]
    hi = s[np.flatnonzero(above >= tail - eps)[-1]]
    return float(lo), float(hi)


def _estimate(values: Sequence[float], statistic: Callable[[np.ndarray], np.ndarray], *, reps: int, seed: int,
              confidence: float) -> Estimate:
    x = np.sort(np.asarray(values, dtype=np.float64))
    stat, w, exact = bootstrap_distribution(x, statistic, reps=reps, seed=seed)
    lo, hi = percentile_interval(stat, w, confidence)
    point = float(np.asarray(statistic(x[None, :])).reshape(-1)[0])
    return Estimate(point, lo, hi, int(x.size), int(stat.size), seed, confidence, exact)


def _iqm_rows(rows: np.ndarray) -> np.ndarray:
    """The interquartile mean of each row of sorted values (``rliable.metrics.aggregate_iqm``: scipy's 25 %
    trimmed mean, floor(n / 4) values dropped at each end)."""
    g = rows.shape[1] // 4
    return rows[:, g:rows.shape[1] - g].mean(axis=1)


def iqm_estimate(values: Sequence[float], *, reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED,
                 confidence: float = 0.95) -> Estimate | None:
    """Interquartile mean of per-seed values with its bootstrap CI over seeds; None for no values."""
    if len(values) == 0:
        return None
    return _estimate(values, _iqm_rows, reps=reps, seed=seed, confidence=confidence)


def mean_estimate(values: Sequence[float], *, reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED,
                  confidence: float = 0.95) -> Estimate | None:
    """Mean of per-seed values with its bootstrap CI over seeds; None for no values."""
    if len(values) == 0:
        return None
    return _estimate(values, lambda rows: rows.mean(axis=1), reps=reps, seed=seed, confidence=confidence)


def _improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y) of each row pair (ties count 1/2): rliable's probability of improvement, Mann-Whitney U / (n m)."""
    gt = (x[:, :, None] > y[:, None, :]).mean(axis=(1, 2))
    eq = (x[:, :, None] == y[:, None, :]).mean(axis=(1, 2))
    return gt + 0.5 * eq


def _improvement_estimate(x: Sequence[float], y: Sequence[float], *, reps: int, seed: int,
                          confidence: float) -> Estimate:
    """The probability of improvement P(X > Y) with a percentile bootstrap CI, each sample resampled
    independently (``reps`` draws, ``numpy.random.default_rng(seed)``), as rliable resamples it."""
    if reps < 1:
        raise ValueError(f"reps must be a positive number of bootstrap resamples, got {reps}")
    xa, ya = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    rng = np.random.default_rng(seed)
    xs = xa[rng.integers(0, xa.size, size=(reps, xa.size))]
    ys = ya[rng.integers(0, ya.size, size=(reps, ya.size))]
    lo, hi = percentile_interval(_improvement(xs, ys), np.full(reps, 1.0 / reps), confidence)
    return Estimate(float(_improvement(xa[None], ya[None])[0]), lo, hi, int(xa.size), reps, seed, confidence)


# ------------------------------------------------------------------------------------ tests and correction
def sign_flip_p(diffs: Sequence[float], *, reps: int = 100_000, seed: int = DEFAULT_SEED) -> float:
    """Two-sided paired permutation p-value of the mean difference being 0: under no difference each seed's
    difference is as likely negated, so p = P(|mean of the sign-flipped differences| >= |observed mean|) over
    the 2^n sign patterns, all enumerated up to ``EXACT_SIGN_FLIP_MAX_N`` differences (beyond: ``reps``
    patterns drawn with ``numpy.random.default_rng(seed)``, the observed one counted in). Its smallest value is
    2 / 2^n: 0.25 over 3 seeds, 0.0625 over 5. NaN without differences."""
    d = np.asarray(diffs, dtype=np.float64)
    n = d.size
    if n == 0:
        return math.nan
    observed = abs(d.mean())
    tol = 1e-9 * max(1.0, float(np.abs(d).max()))
    if n <= EXACT_SIGN_FLIP_MAX_N:
        signs = 1 - 2 * ((np.arange(2 ** n)[:, None] >> np.arange(n)) & 1)
        return float(np.mean(np.abs(signs @ d / n) >= observed - tol))
    signs = np.random.default_rng(seed).choice([-1.0, 1.0], size=(reps, n))
    return float((1 + np.sum(np.abs(signs @ d / n) >= observed - tol)) / (reps + 1))


def holm(p_values: Sequence[float]) -> list[float]:
    """Holm's step-down adjusted p-values, in the given order: with the m p-values sorted ascending,
    p_adj(i) = max over j <= i of min(1, (m - j + 1) p(j)). A comparison differs at level alpha (family-wise
    error at most alpha over all m) where its adjusted p-value is <= alpha. NaN p-values stay NaN and do not
    count in m."""
    p = np.asarray(p_values, dtype=np.float64)
    out = np.full(p.shape, np.nan)
    ok = np.flatnonzero(~np.isnan(p))
    m = ok.size
    running = 0.0
    for rank, i in enumerate(ok[np.argsort(p[ok], kind="stable")]):
        running = max(running, min(1.0, (m - rank) * p[i]))
        out[i] = running
    return out.tolist()


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
                            improvement=_improvement_estimate([a[s] for s in seeds], [b[s] for s in seeds], **kw),
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
    _check_unique(curves)
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
        stats = TaskStatistics(task=task, whole=compare(cs, window="per arm", **kw), iteration=n,
                               equal_iters=compare(truncate_at_iteration(cs, n), **kw))
        if iter_ms_alone is not None:
            budget = common_wall_s(cs, iter_ms_alone)
            cut = truncate_at_wall_s(cs, iter_ms_alone, budget)
            ms = _iter_ms(cs, iter_ms_alone)
            stats = replace(stats, wall_s=budget, iter_ms_alone=ms, equal_wall=compare(cut, window="per arm", **kw),
                            iters_at_wall={a: max(c.last_iter for c in cut if c.arm == a) for a in ms})
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
                      iter_ms_alone: Mapping[str, float] | None = None, final_evals: int = FINAL_EVALS,
                      reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED, confidence: float = 0.95
                      ) -> dict[tuple[str, str], DifferenceCurve]:
    """(arm, axis) -> :class:`DifferenceCurve` of every arm against ``reference`` in the curves of ONE task, along
    iterations and, with ``iter_ms_alone`` (arm -> ms per iteration measured alone), along modelled wall-clock.
    An arm without paired seeds, or whose runs share no evaluation iteration with the reference's, has none."""
    tasks = sorted({c.task for c in curves})
    if len(tasks) != 1:
        raise ValueError(f"difference_curves takes the curves of one task, got {tasks or 'none'}")
    by_arm: dict[str, dict[int, Curve]] = {}
    for c in curves:
        if c.returns.size:
            by_arm.setdefault(c.arm, {})[c.seed] = c
    if reference not in by_arm:
        return {}
    ms = _iter_ms([c for c in curves if c.arm in by_arm], iter_ms_alone) if iter_ms_alone is not None else None
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
        if ms is None:
            continue
        own = {}
        for name, cs in ((arm, [runs[s] for s in seeds]), (reference, [ref[s] for s in seeds])):
            it = np.array(sorted(set.intersection(*(set(c.iters.tolist()) for c in cs))), dtype=np.int64)
            own[name] = (it, it * ms[name] / 1e3, {c.seed: _window_means(c, it, final_evals) for c in cs})
        end = min(c.last_iter * ms[c.arm] / 1e3 for c in pair)
        if not (own[arm][0].size and own[reference][0].size):
            continue
        start = max(own[arm][1][0], own[reference][1][0])
        grid = np.unique(np.concatenate([own[arm][1], own[reference][1]]))
        grid = grid[(grid >= start) & (grid <= end * (1 + 1e-12))]
        if not grid.size:
            continue

        def at(name: str, s: int, grid=grid, own=own) -> np.ndarray:
            times, means = own[name][1], own[name][2][s]
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
            idx, w = _multisets(k)
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


#: Iterations from the start over which ``blind_phase`` looks for the blind phase (the first 500).
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
    paired difference reference minus control is above zero and differs after Holm correction
    (:meth:`PairedDifference.differs`); ``by`` is then ``"paired difference"``, else None. ``paired``: reference
    minus control final return over the paired seeds (None without any), ``p_holm`` its Holm-adjusted p-value;
    ``reference_iqm`` / ``control_iqm``: the arms' IQMs, shown beside it; ``why``: one sentence."""

    passed: bool
    by: str | None
    paired: Estimate | None
    reference_iqm: Estimate | None
    control_iqm: Estimate | None
    why: str
    p_holm: float | None = None


@dataclass(frozen=True)
class Verdict:
    """How one task's arms may be read against the reference. ``ranks``: whether they may; ``reason``: why (or
    why not), one sentence; ``gate``: the reference against the control (None when the task does not rank arms
    or an arm is missing); ``readings``: arm -> ``"better"``, ``"worse"`` (the paired difference differs after
    Holm correction, on that side), ``"not resolved"`` (it does not), ``"too few seeds"`` (fewer than
    ``MIN_SEEDS`` paired seeds) or ``"no paired seeds"``; empty unless ``ranks``. ``alpha``: the family-wise
    level."""

    task: str
    reference: str
    control: str
    ranks: bool
    reason: str
    gate: Gate | None
    readings: dict[str, str]
    alpha: float = ALPHA


def _negated(e: Estimate) -> Estimate:
    """The estimate of minus the statistic: a percentile bootstrap of a mean flips exactly under negation."""
    return replace(e, value=-e.value, ci_low=-e.ci_high, ci_high=-e.ci_low)


def _ci(e: Estimate) -> str:
    return f"{e.value:.4g} [{e.ci_low:.4g}, {e.ci_high:.4g}]"


def _test_text(d: PairedDifference) -> str:
    """``3 of 5 seeds agree in sign, sign-flip p = 0.0625, Holm-adjusted p = 1 (18 comparisons)``."""
    text = f"{d.agree} of {d.mean.n} seeds agree in sign, sign-flip p = {d.p_value:.3g}"
    if d.p_holm is not None:
        text += f", Holm-adjusted p = {d.p_holm:.3g} ({d.family} comparison{'s' if d.family != 1 else ''})"
    return text


def verdict(cmp: Comparison, *, control: str = "blind", not_ranking: str | None = None,
            alpha: float = ALPHA) -> Verdict:
    """The control rule: the arms of ``cmp`` are read against its reference (decoupled) only where the reference
    beats ``control`` (blind: the same pixels, never looked at), i.e. reference minus control differs after Holm
    correction and is positive; otherwise pixels have not yet been shown to help on this task and the arms
    cannot be ranked. Each arm's reading follows its own Holm-corrected paired difference. A comparison not yet
    corrected (:func:`correct`) is corrected here over its own paired differences alone. The minimum-seeds rule
    holds throughout: fewer than ``MIN_SEEDS`` paired seeds decide nothing. ``not_ranking``: a reason the task
    ranks no arms whatever the numbers (a task that doing nothing solves)."""
    ref = cmp.reference or "reference"
    if not_ranking is not None:
        return Verdict(cmp.task, ref, control, False, not_ranking, None, {}, alpha)
    missing = [a for a in (ref, control) if a not in cmp.arms or cmp.arms[a].final_iqm is None]
    if missing:
        return Verdict(cmp.task, ref, control, False, f"the arms cannot be ranked: no {' and no '.join(missing)} "
                       "run with an evaluation to hold them against", None, {}, alpha)
    if any(d.p_value is not None and d.p_holm is None for d in cmp.differences.values()):
        cmp = correct([cmp])[0]
    r, c = cmp.arms[ref].final_iqm, cmp.arms[control].final_iqm
    d = cmp.differences[control]
    paired = _negated(d.mean) if d.mean is not None else None
    iqms = f"IQMs {_ci(r)} (n={r.n}) and {_ci(c)} (n={c.n})"
    if paired is None:
        why = f"no {ref} seed has a {control} run of the same seed to pair with ({iqms})"
    elif paired.n < MIN_SEEDS:
        why = (f"too few seeds to read {ref} against {control}: {paired.n} paired seed(s), and no verdict rests on "
               f"fewer than {MIN_SEEDS} ({ref} minus {control} {_ci(paired)})")
    elif d.differs(alpha) and paired.value > 0:
        why = f"{ref} beats {control}: {ref} minus {control} {_ci(paired)}, {_test_text(d)} <= {alpha:g}"
    elif d.differs(alpha):
        why = f"{control} beats {ref}: {ref} minus {control} {_ci(paired)}, {_test_text(d)} <= {alpha:g}"
    else:
        why = (f"{ref} is not shown to beat {control} after Holm correction: {ref} minus {control} {_ci(paired)}, "
               f"{_test_text(d)} > {alpha:g}")
    passed = paired is not None and paired.n >= MIN_SEEDS and d.differs(alpha) and paired.value > 0
    gate = Gate(passed, "paired difference" if passed else None, paired, r, c, why, d.p_holm)
    if not passed:
        return Verdict(cmp.task, ref, control, False, f"{why}; the pixel arms cannot be ranked on this task yet",
                       gate, {}, alpha)
    readings = {}
    for arm, diff in cmp.differences.items():
        if arm == control:
            continue
        m = diff.mean
        readings[arm] = ("no paired seeds" if m is None else "too few seeds" if m.n < MIN_SEEDS
                         else ("better" if m.value > 0 else "worse") if diff.differs(alpha) else "not resolved")
    return Verdict(cmp.task, ref, control, True, why, gate, readings, alpha)
