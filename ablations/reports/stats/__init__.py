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
  ``EXACT_SIGN_FLIP_MAX_N`` (40) seeds, counted by meeting in the middle; its smallest value is 2 / 2^n: 0.25
  for 3 seeds, 0.0625 for 5, 0.0078 for 8; :func:`sign_flip_test` also one-sided, with the confidence set
  inverted from the same test at the level given)
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
  each threshold, with CIs, as data (``ablations.reports.seed_figures.plot_performance_profiles`` draws them);
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

from ablations.reports.stats.comparisons import (
    ArmSummary,
    Band,
    Comparison,
    DifferenceCurve,
    PairedDifference,
    PerformanceProfile,
    ProfileCurve,
    TaskStatistics,
    check_at_iteration,
    common_iteration,
    common_wall_s,
    common_window,
    compare,
    correct,
    correct_statistics,
    difference_curves,
    mean_band,
    paired_difference,
    performance_profiles,
    sign_holds,
    task_statistics,
    truncate_at_iteration,
    truncate_at_wall_s,
)
from ablations.reports.stats.curves import (
    EVAL_KEYS,
    FINAL_EVALS,
    Curve,
    auc,
    collapse_rate,
    curve_of,
    final_return,
    load_arms,
    window_statistic,
)
from ablations.reports.stats.estimates import (
    ALPHA,
    DEFAULT_REPS,
    DEFAULT_SEED,
    EXACT_BOOTSTRAP_MAX_N,
    EXACT_SIGN_FLIP_MAX_N,
    MIN_SEEDS,
    Estimate,
    SignFlipTest,
    bootstrap_distribution,
    holm,
    iqm_estimate,
    mean_estimate,
    percentile_interval,
    seeds_to_resolve,
    sign_flip_count,
    sign_flip_interval,
    sign_flip_p,
    sign_flip_test,
)
from ablations.reports.stats.probes import (
    BLIND_PHASE_ITERS,
    LOOKING_FRACTION,
    BlindPhase,
    LookingProbes,
    blind_phase,
    looking_probes,
)
from ablations.reports.stats.verdicts import Gate, Verdict, verdict

__all__ = ["DEFAULT_REPS", "DEFAULT_SEED", "FINAL_EVALS", "EVAL_KEYS", "Curve", "Estimate", "ArmSummary",
           "PairedDifference", "Comparison", "TaskStatistics", "ProfileCurve", "PerformanceProfile", "LookingProbes",
           "curve_of", "load_arms", "window_statistic", "final_return", "auc", "collapse_rate", "iqm_estimate",
           "mean_estimate",
           "compare", "common_iteration", "truncate_at_iteration", "common_wall_s", "truncate_at_wall_s",
           "check_at_iteration", "task_statistics", "performance_profiles", "looking_probes", "LOOKING_FRACTION",
           "BlindPhase", "blind_phase", "BLIND_PHASE_ITERS", "Verdict", "Gate", "verdict", "MIN_SEEDS", "ALPHA",
           "EXACT_BOOTSTRAP_MAX_N", "EXACT_SIGN_FLIP_MAX_N", "bootstrap_distribution", "percentile_interval",
           "sign_flip_p", "sign_flip_count", "sign_flip_interval", "sign_flip_test", "SignFlipTest",
           "seeds_to_resolve", "holm", "correct", "correct_statistics", "common_window",
           "paired_difference", "DifferenceCurve", "difference_curves", "sign_holds", "Band", "mean_band"]
