"""The exact sign-flip test by meeting in the middle, against the full enumeration of sign patterns and against
answers known by hand (Hartigan's order statistic of subset means for the inverted interval)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from ablations.reports import stats


def enumerated_p(diffs, alternative="two-sided"):
    """The reference: every one of the 2^n sign patterns as a row of the full sign matrix."""
    d = np.asarray(diffs, dtype=np.float64)
    n = d.size
    tol = 1e-9 * float(np.abs(d).max())
    signs = 1 - 2 * ((np.arange(2 ** n)[:, None] >> np.arange(n)) & 1)
    means = signs @ d / n
    if alternative == "greater":
        return float(np.mean(means >= d.mean() - tol))
    if alternative == "less":
        return float(np.mean(means <= d.mean() + tol))
    return float(np.mean(np.abs(means) >= abs(d.mean()) - tol))


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8, 11, 16])
@pytest.mark.parametrize("alternative", ["two-sided", "greater", "less"])
def test_meet_in_the_middle_equals_the_full_enumeration_up_to_16_seeds(n, alternative):
    rng = np.random.default_rng(n)
    for d in (rng.normal(0.3, 1.0, n), rng.integers(-3, 4, n).astype(float), np.full(n, 2.5)):
        assert stats.sign_flip_p(d, alternative=alternative) == enumerated_p(d, alternative)


def test_known_p_values_by_hand():
    assert stats.sign_flip_p([1, 2, 3, 4, 5], alternative="greater") == 1 / 32
    assert stats.sign_flip_p([1, 2, 3, 4, 5], alternative="less") == 1.0
    # (3, 1, -1): the 8 signed sums are 5, 3, 3, 1, -1, -3, -3, -5; S_obs = 3, so 3 of 8 are >= 3
    assert stats.sign_flip_p([3, 1, -1], alternative="greater") == 3 / 8
    assert stats.sign_flip_p([3, 1, -1], alternative="less") == 7 / 8
    with pytest.raises(ValueError, match="alternative"):
        stats.sign_flip_p([1.0], alternative="bigger")


def test_exact_beyond_16_seeds_every_seed_agreeing_gives_the_smallest_p():
    for n in (17, 24, 31):
        d = np.linspace(1.0, 2.0, n)
        assert stats.sign_flip_p(d) == 2.0 / 2 ** n
        assert stats.sign_flip_p(d, alternative="greater") == 1.0 / 2 ** n
    # one seed of 24 against: the patterns reaching S_obs are the observed one and those flipping only seeds whose
    # sum is at most the dissenting one's magnitude; with the dissenter at -0.5 and the others >= 1: just those
    d = np.concatenate([np.linspace(1.0, 2.0, 23), [-0.5]])
    assert stats.sign_flip_p(d, alternative="greater") == 2 / 2 ** 24


def test_a_count_of_the_full_enumeration_at_20_seeds():
    rng = np.random.default_rng(5)
    d = rng.normal(0.5, 1.0, 20)
    signs = 1 - 2 * ((np.arange(2 ** 20)[:, None] >> np.arange(20)) & 1).astype(np.int8)
    sums = signs @ d
    for t in (0.0, float(d.sum()), 3.0):
        assert stats.sign_flip_count(d, t) == int(np.sum(sums >= t - 1e-9))


def test_forty_seeds_is_exact_and_quick():
    rng = np.random.default_rng(1)
    d = rng.normal(0.4, 1.0, 40)
    p = stats.sign_flip_p(d)
    # exact: a multiple of 2^-40, reproducible without a seed, and the two tails by symmetry
    assert (p * 2 ** 40) == round(p * 2 ** 40)
    assert p == pytest.approx(2 * stats.sign_flip_p(d, alternative="greater"), rel=1e-12)
    # beyond 40 the patterns are drawn
    assert stats.sign_flip_p(np.ones(41), reps=999) == pytest.approx(1 / 1000)


def subset_means(d):
    return np.sort([np.mean(c) for k in range(1, len(d) + 1) for c in itertools.combinations(d, k)])


@pytest.mark.parametrize("alpha", [0.01, 0.05, 0.2])
def test_the_one_sided_interval_is_hartigans_order_statistic(alpha):
    d = np.array([3.1, -0.7, 2.2, 5.0, 1.4, 0.3, 4.4, -1.9, 2.8])
    n = d.size
    k = math.floor(alpha * 2 ** n)
    low, high = stats.sign_flip_interval(d, alpha=alpha, alternative="greater")
    assert high == math.inf and low == pytest.approx(subset_means(d)[k - 1], abs=1e-6)
    low2, high2 = stats.sign_flip_interval(-d, alpha=alpha, alternative="less")
    assert low2 == -math.inf and high2 == pytest.approx(-low, abs=1e-6)


def test_the_two_sided_interval_is_the_set_the_test_does_not_reject():
    rng = np.random.default_rng(3)
    d = rng.normal(1.0, 2.0, 10)
    alpha = 0.05
    low, high = stats.sign_flip_interval(d, alpha=alpha)
    assert low < d.mean() < high
    eps = 1e-6
    assert stats.sign_flip_p(d - (low + eps)) > alpha and stats.sign_flip_p(d - (low - eps)) <= alpha
    assert stats.sign_flip_p(d - (high - eps)) > alpha and stats.sign_flip_p(d - (high + eps)) <= alpha
    # the bounds sit within the tie tolerance (1e-9 of the largest difference) of a subset mean
    # by the subset means: the two-sided bounds are the one-sided ones at alpha / 2 (the test's two tails)
    k = math.floor(alpha / 2 * 2 ** d.size)
    means = subset_means(d)
    assert low == pytest.approx(means[k - 1], abs=1e-6) and high == pytest.approx(means[-k], abs=1e-6)
    # excludes 0 exactly when the test rejects at that level
    t = stats.sign_flip_test(d, alpha=alpha)
    assert t.rejects() == (t.ci_low > 0 or t.ci_high < 0)


def test_too_few_seeds_reject_no_shift_and_the_interval_is_unbounded():
    assert stats.sign_flip_interval([1.0, 2.0, 3.0], alpha=0.05) == (-math.inf, math.inf)
    assert stats.sign_flip_interval([1.0, 2.0, 3.0, 4.0, 5.0], alpha=0.05, alternative="greater")[0] > -math.inf
    with pytest.raises(ValueError, match="alpha"):
        stats.sign_flip_interval([1.0], alpha=1.5)


def test_a_planted_effect_is_found_at_24_seeds_and_noise_is_not():
    rng = np.random.default_rng(0)
    effect = stats.sign_flip_test(rng.normal(1.0, 1.0, 24), alpha=0.01, alternative="greater")
    assert effect.rejects() and effect.ci_low > 0
    noise = stats.sign_flip_test(rng.normal(0.0, 1.0, 24), alpha=0.01)
    assert not noise.rejects() and noise.ci_low < 0 < noise.ci_high
