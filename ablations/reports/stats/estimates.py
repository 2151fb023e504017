"""The bootstrap over seeds, the sign-flip test and Holm's correction (the package docstring defines them).
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

#: Bootstrap resamples per confidence interval where the bootstrap is not enumerated (more seeds than
#: EXACT_BOOTSTRAP_MAX_N), and for the probability of improvement's interval.
DEFAULT_REPS = 2000
#: Seed of the random generator (``numpy.random.default_rng``) of every drawn resample or sign pattern.
DEFAULT_SEED = 0
#: Up to this many seeds a bootstrap interval enumerates every distinct resample (6435 at 8 seeds; 92378 at 10
#: would make a report's thousands of intervals slow for no gain a reader could see).
EXACT_BOOTSTRAP_MAX_N = 8
#: Up to this many paired seeds the sign-flip p-value counts every sign pattern (2^40 at 40, by meeting in the
#: middle: two halves of 2^20 signed sums).
EXACT_SIGN_FLIP_MAX_N = 40
#: Family-wise error level of an exploratory report's Holm-corrected verdicts (a default: every function that
#: decides takes ``alpha``; a registration states its own).
ALPHA = 0.05
#: The minimum-seeds rule: no verdict rests on fewer paired seeds than this. A percentile bootstrap over 1 seed
#: is a point and over 2 excludes zero whenever both agree in sign (half the time under no difference); the
#: sign-flip test cannot go below 0.5 there. Fewer: the table shows the numbers, the verdict says "too few seeds".
MIN_SEEDS = 3


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
def multisets(n: int) -> tuple[np.ndarray, np.ndarray]:
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
        idx, w = multisets(n)
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


def improvement_estimate(x: Sequence[float], y: Sequence[float], *, reps: int, seed: int,
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
def sign_flip_p(diffs: Sequence[float], *, reps: int = 100_000, seed: int = DEFAULT_SEED,
                alternative: str = "two-sided") -> float:
    """Paired permutation p-value of the mean difference being 0: under no difference each seed's difference is
    as likely negated, so over the 2^n sign patterns, with S the sum of the sign-flipped differences and S_obs
    the observed sum: ``"two-sided"`` P(|S| >= |S_obs|), ``"greater"`` P(S >= S_obs) (the alternative: mean > 0),
    ``"less"`` P(S <= S_obs). Exact up to ``EXACT_SIGN_FLIP_MAX_N`` differences: every pattern counted, by
    meeting in the middle (:func:`sign_flip_count`); beyond, ``reps`` patterns drawn with
    ``numpy.random.default_rng(seed)``, the observed one counted in. The smallest two-sided value is 2 / 2^n:
    0.25 over 3 seeds, 0.0625 over 5; one-sided 1 / 2^n. NaN without differences."""
    alternatives = ("two-sided", "greater", "less")
    if alternative not in alternatives:
        raise ValueError(f"alternative must be one of {', '.join(alternatives)}, got {alternative!r}")
    d = np.asarray(diffs, dtype=np.float64)
    n = d.size
    if n == 0:
        return math.nan
    total = float(d.sum())
    tol = n * 1e-9 * float(np.abs(d).max())  # relative: a pattern ties the observed sum only to rounding
    if n <= EXACT_SIGN_FLIP_MAX_N:
        if alternative == "greater":
            return sign_flip_count(d, total - tol) / 2.0 ** n
        if alternative == "less":
            return sign_flip_count(-d, -total - tol) / 2.0 ** n
        t = abs(total) - tol
        if t <= 0:
            return 1.0
        # the signed sums are symmetric (negating a pattern negates its sum exactly): P(S <= -t) = P(S >= t)
        return 2 * sign_flip_count(d, t) / 2.0 ** n
    sums = np.random.default_rng(seed).choice([-1.0, 1.0], size=(reps, n)) @ d
    hits = {"two-sided": np.abs(sums) >= abs(total) - tol, "greater": sums >= total - tol,
            "less": sums <= total + tol}[alternative]
    return float((1 + np.sum(hits)) / (reps + 1))


def signed_sums(x: np.ndarray) -> np.ndarray:
    """All 2^k sums of +-x_i of k values (2^k,), unsorted (pattern negation negates a sum exactly)."""
    sums = np.zeros(1)
    for v in np.asarray(x, dtype=np.float64):
        sums = np.concatenate([sums + v, sums - v])
    return sums


def sign_flip_count(d: Sequence[float], threshold: float) -> int:
    """How many of the 2^n sign patterns s give sum_i s_i d_i >= ``threshold``, counted exactly by meeting in the
    middle: the 2^(n/2) signed sums of each half, one half sorted, and for every sum a of the other the sums
    b >= threshold - a found with ``searchsorted``: O(2^(n/2) n) time and memory (n = 40: two arrays of 2^20)
    where the full sign matrix is 2^n x n."""
    x = np.asarray(d, dtype=np.float64)
    half = x.size // 2
    a, b = signed_sums(x[:half]), np.sort(signed_sums(x[half:]))
    return int(b.size * a.size - np.searchsorted(b, threshold - a, side="left").sum())


def sign_flip_interval(diffs: Sequence[float], *, alpha: float, alternative: str = "two-sided"
                       ) -> tuple[float, float]:
    """The confidence set of the mean difference at level 1 - ``alpha`` inverted from the same sign-flip test
    (:func:`sign_flip_p`): every shift delta whose test of ``diffs - delta`` does not reject, p > alpha. For
    ``"greater"`` it is [low, inf), low the k-th smallest of the 2^n - 1 subset means with k = floor(alpha 2^n)
    (Hartigan's order statistic); ``"less"`` (-inf, high]; ``"two-sided"`` [low, high]. The p-value is monotone
    in delta on each side of the mean, so each bound is found by bisection (to 1e-12 of the differences' range);
    a bound is infinite where no shift is rejected (2^-n > alpha one-sided, 2^(1-n) > alpha two-sided). The
    two-sided bounds are the one-sided ones at alpha / 2 (the test's tails are symmetric). Exact (no draw) up to
    ``EXACT_SIGN_FLIP_MAX_N`` differences; each bisection step is one count, so at 24 seeds an interval takes
    milliseconds, at 40 about a minute."""
    d = np.asarray(diffs, dtype=np.float64)
    if d.size == 0:
        return math.nan, math.nan
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    mean = float(d.mean())
    span = float(d.max() - d.min()) or max(1.0, abs(mean))

    def bound(test: str, outer: float) -> float:
        """The bound between ``outer`` (rejected, or none is) and the mean (never rejected)."""
        if sign_flip_p(d - outer, alternative=test) > alpha:
            return -math.inf if outer < mean else math.inf
        inside, out = mean, outer
        while abs(inside - out) > 1e-12 * span:
            mid = 0.5 * (inside + out)
            if sign_flip_p(d - mid, alternative=test) > alpha:
                inside = mid
            else:
                out = mid
        return inside

    low_out, high_out = float(d.min()) - span, float(d.max()) + span
    if alternative == "greater":
        return bound("greater", low_out), math.inf
    if alternative == "less":
        return -math.inf, bound("less", high_out)
    if alternative != "two-sided":
        raise ValueError(f"alternative must be one of two-sided, greater, less, got {alternative!r}")
    return bound("two-sided", low_out), bound("two-sided", high_out)


@dataclass(frozen=True)
class SignFlipTest:
    """The exact sign-flip test of paired differences at level ``alpha``: ``n`` differences, their ``mean``,
    ``p_value`` (:func:`sign_flip_p` with ``alternative``) and the confidence set [``ci_low``, ``ci_high``]
    inverted from the same test at the same level (:func:`sign_flip_interval`; one-sided: one bound infinite).
    ``exact``: every sign pattern counted (n <= ``EXACT_SIGN_FLIP_MAX_N``)."""

    n: int
    mean: float
    p_value: float
    ci_low: float
    ci_high: float
    alpha: float
    alternative: str
    exact: bool

    def rejects(self, alpha: float | None = None) -> bool:
        """Whether the p-value is at most ``alpha`` (default: the level it was made at)."""
        return self.p_value <= (self.alpha if alpha is None else alpha)


def sign_flip_test(diffs: Sequence[float], *, alpha: float, alternative: str = "two-sided") -> SignFlipTest:
    """:class:`SignFlipTest` of ``diffs`` at level ``alpha``."""
    d = np.asarray(diffs, dtype=np.float64)
    lo, hi = sign_flip_interval(d, alpha=alpha, alternative=alternative)
    return SignFlipTest(n=int(d.size), mean=float(d.mean()) if d.size else math.nan,
                        p_value=sign_flip_p(d, alternative=alternative), ci_low=lo, ci_high=hi, alpha=alpha,
                        alternative=alternative, exact=d.size <= EXACT_SIGN_FLIP_MAX_N)


def seeds_to_resolve(family: int, *, alpha: float = ALPHA) -> int:
    """The fewest paired seeds with which a comparison can differ after Holm correction over ``family``
    comparisons, under the exact sign-flip test (:func:`sign_flip_p`): even with every seed agreeing, its
    p-value is 2 / 2^n, which Holm's first step holds to alpha / family. At 0.05: 6 seeds for one comparison,
    9 for 10, 10 for 18."""
    if family < 1:
        raise ValueError(f"family must be at least 1, got {family}")
    n = 1
    while 2.0 / 2 ** n * family > alpha:
        n += 1
    return n


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
