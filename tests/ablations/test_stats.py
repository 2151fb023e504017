"""ablations.reports.stats on synthetic run folders whose answers are known by hand."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from ablations.reports import plot, stats
from ablations.reports.stats import Curve

#: Few resamples keep the tests fast; the intervals they check are wide of their bounds at any count.
REPS = 200
#: For tests that check point values only (the bootstrap still runs, so its plumbing is exercised).
FEW = 10


def write_run(root, name, *, task="hopper", mode="decoupled", seed=0, evals=(), last_iter=None, every=10,
              key="eval_return_mean", extra=None):
    """A run folder as `ablate` writes one: config.json and one metrics line per iteration; ``evals`` are the
    evaluation returns at iterations every, 2 every, ... (``key`` names them); ``extra``: iter -> more keys."""
    run = root / name
    run.mkdir(parents=True)
    config = {"task": task, "mode": mode, "seed": seed, "raster_model": None, "preset": "dva",
              "lr_decay_iters": 30000}
    (run / "config.json").write_text(json.dumps({"config": config, "environment": {}}))
    at = {every * (i + 1): r for i, r in enumerate(evals)}
    last_iter = last_iter if last_iter is not None else max(at, default=1)
    lines = []
    for it in range(1, last_iter + 1):
        m = {"iter": it, "wall_s": 0.5 * it, "return_mean": 0.0}
        if it in at:
            m[key] = at[it]
        m.update((extra or {}).get(it, {}))
        lines.append(json.dumps(m))
    (run / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    return run


def curve(returns, *, arm="a", seed=0, task="hopper", iters=None, last_iter=None) -> Curve:
    iters = np.arange(1, len(returns) + 1) * 10 if iters is None else np.asarray(iters)
    return Curve(task=task, arm=arm, seed=seed, path=f"{arm}{seed}", iters=iters.astype(np.int64),
                 returns=np.asarray(returns, dtype=np.float64),
                 last_iter=int(iters[-1]) if last_iter is None and iters.size else (last_iter or 0))


# ------------------------------------------------------------------------------------------ reading runs
def test_load_arms_reads_run_folders_and_the_older_eval_key(tmp_path):
    write_run(tmp_path / "dec", "s0", seed=0, evals=(1.0, 2.0, 3.0), last_iter=35)
    write_run(tmp_path / "dec", "s1", seed=1, evals=(4.0, 5.0), key="eval_return")  # a run from before eval_*
    with open(tmp_path / "dec" / "s1" / "metrics.jsonl", "a") as f:
        f.write('{"iter": 21, "eval_ret')  # a run killed mid-write: the torn line is ignored
    curves = stats.load_arms({"decoupled": [tmp_path / "dec"]})  # a folder of runs stands for all of them
    by_seed = {c.seed: c for c in curves}
    assert sorted(by_seed) == [0, 1] and {c.arm for c in curves} == {"decoupled"}
    c0, c1 = by_seed[0], by_seed[1]
    assert c0.task == "hopper" and c0.key == "eval_return_mean" and c0.last_iter == 35
    np.testing.assert_array_equal(c0.iters, [10, 20, 30])
    np.testing.assert_array_equal(c0.returns, [1.0, 2.0, 3.0])
    assert c1.key == "eval_return" and c1.last_iter == 20
    np.testing.assert_array_equal(c1.returns, [4.0, 5.0])


def test_two_runs_of_one_seed_in_an_arm_are_an_error(tmp_path):
    write_run(tmp_path, "a", seed=3, evals=(1.0,))
    write_run(tmp_path, "b", seed=3, evals=(2.0,))
    with pytest.raises(ValueError, match="two runs of task 'hopper' with seed 3"):
        stats.load_arms({"full": [tmp_path / "a", tmp_path / "b"]})


def test_module_imports_without_torch():
    code = "import sys, ablations.reports.stats; assert 'torch' not in sys.modules, 'torch was imported'"
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)


# ------------------------------------------------------------------------------------ per-run statistics
def test_final_return_is_the_mean_of_the_last_three_evaluations():
    assert stats.final_return(curve([9.0, 1.0, 2.0, 6.0])) == 3.0
    assert stats.final_return(curve([4.0, 8.0])) == 6.0  # fewer than three: all of them
    assert math.isnan(stats.final_return(curve([])))


def test_auc_is_the_trapezoid_mean_over_the_span():
    # (0 + 10) / 2 * 10 + 10 * 20 = 250 over iterations 10..40, a span of 30
    assert stats.auc(curve([0.0, 10.0, 10.0], iters=[10, 20, 40])) == pytest.approx(250 / 30)
    assert stats.auc(curve([5.0, 5.0, 5.0])) == 5.0
    assert stats.auc(curve([7.0])) == 7.0


def test_collapse_rate_counts_evaluations_below_half_the_running_best_after_the_first_positive_best():
    # running best -5 -1 10 10 10 20 20 20; the first positive best is the third; of the five after it,
    # 4 < 10/2 and 9 < 20/2 collapse, 6, 20 and 11 do not
    assert stats.collapse_rate(curve([-5, -1, 10, 4, 6, 20, 9, 11])) == pytest.approx(2 / 5)
    assert stats.collapse_rate(curve([1, 2, 3])) == 0.0
    assert math.isnan(stats.collapse_rate(curve([-3, -2, -1])))  # no positive best
    assert math.isnan(stats.collapse_rate(curve([-3, 5])))  # nothing after it


# ------------------------------------------------------------------------------------------- bootstrap
def test_iqm_of_a_known_set_and_a_deterministic_interval():
    # 8 values: two dropped at each end, the mean of 3, 4, 5, 6
    est = stats.iqm_estimate([7, 1, 100, 3, 2, 6, 4, 5], reps=REPS, seed=4)
    assert est.value == 4.5 and est.n == 8 and est.exact and est.reps == math.comb(15, 8)  # every resample
    assert est.ci_low <= 4.5 <= est.ci_high and est.ci_low < est.ci_high
    assert stats.iqm_estimate([1, 2, 3, 4, 100], reps=REPS).value == 3.0  # 5 values: the middle 3
    assert stats.iqm_estimate([1, 2, 9], reps=REPS).value == 4.0  # 3 values: nothing dropped
    np.random.seed(123)  # noqa: NPY002 (numpy's global state: no statistic here may draw from it)
    before = np.random.get_state()[1].copy()  # noqa: NPY002
    again = stats.iqm_estimate([7, 1, 100, 3, 2, 6, 4, 5], reps=REPS, seed=4)
    assert again == est
    np.testing.assert_array_equal(np.random.get_state()[1], before)  # noqa: NPY002
    assert stats.iqm_estimate([], reps=REPS) is None


def _arm(name, finals, *, task="hopper", seeds=None):
    """Curves whose final return (the mean of the last three) is each of ``finals``."""
    seeds = range(len(finals)) if seeds is None else seeds
    return [curve([0.0, f - 1.0, f, f + 1.0], arm=name, seed=s, task=task) for s, f in zip(seeds, finals)]


FINALS = [120.0, 340.0, 95.0, 410.0, 260.0]


def test_identical_arms_difference_and_improvement_cover_no_effect():
    cmp = stats.compare(_arm("decoupled", FINALS) + _arm("full", FINALS), reps=REPS)
    d = cmp.differences["full"]
    assert d.diff == dict.fromkeys(range(5), 0.0) and d.mean.value == 0.0
    assert d.mean.ci_low <= 0.0 <= d.mean.ci_high
    assert d.improvement.value == 0.5 and d.improvement.ci_low <= 0.5 <= d.improvement.ci_high
    # the same returns dealt to other seeds: the paired differences are non-zero but centre on zero
    d = stats.compare(_arm("decoupled", FINALS) + _arm("full", FINALS[1:] + FINALS[:1]), reps=REPS).differences["full"]
    assert any(v != 0 for v in d.diff.values()) and d.mean.value == pytest.approx(0.0, abs=1e-9)
    assert not d.mean.excludes(0.0) and d.mean.ci_low < 0.0 < d.mean.ci_high
    assert d.improvement.value == 0.5 and not d.improvement.excludes(0.5)


def test_a_shifted_arm_has_a_difference_that_excludes_zero_on_its_side():
    noise = [3.0, -2.0, 5.0, -4.0, 1.0]
    better = [f + 50.0 + e for f, e in zip(FINALS, noise)]
    cmp = stats.compare(_arm("decoupled", FINALS) + _arm("full", better) + _arm("blind", [f - 80 for f in FINALS]),
                        reps=REPS)
    up, down = cmp.differences["full"], cmp.differences["blind"]
    assert up.mean.value == pytest.approx(50.6) and up.mean.ci_low > 0.0 and up.mean.excludes(0.0)
    assert down.mean.value == pytest.approx(-80.0) and down.mean.ci_high < 0.0
    # unpaired, the arms overlap (returns spread 95..410), so rliable's probability is below 1 but above 1/2
    assert 0.5 < up.improvement.value < 1.0 and up.improvement.ci_high >= up.improvement.value
    assert down.improvement.value < 0.5
    assert set(cmp.differences) == {"full", "blind"} and cmp.reference == "decoupled"
    assert cmp.arms["full"].final_iqm.value == pytest.approx(np.mean(sorted(better)[1:4]))


def test_missing_seeds_are_reported_and_skipped():
    curves = _arm("decoupled", [1.0, 2.0, 3.0], seeds=[0, 1, 3]) + _arm("full", [5.0, 7.0, 9.0], seeds=[0, 1, 2])
    curves.append(curve([], arm="full", seed=4, iters=np.array([], np.int64), last_iter=40))  # never evaluated
    cmp = stats.compare(curves, reps=FEW)
    d = cmp.differences["full"]
    assert d.seeds == (0, 1) and d.diff == {0: 4.0, 1: 5.0} and d.mean.n == 2
    assert d.missing == {"full": (2,), "decoupled": (3,)}
    assert cmp.arms["full"].without_evals == (4,) and cmp.arms["full"].seeds == (0, 1, 2)


def test_compare_refuses_mixed_tasks():
    with pytest.raises(ValueError, match="one task"):
        stats.compare(_arm("a", [1.0], task="hopper") + _arm("b", [1.0], task="ant"), reps=FEW)


# ------------------------------------------------------------------------ equal iterations and time
def test_equal_iterations_and_equal_wall_clock_cut_at_the_right_points(tmp_path):
    # decoupled: 100 iterations at 100 ms alone = 10 s; full: 60 iterations at 250 ms = 15 s; evaluations every
    # 10 iterations with return = iteration
    for s in (0, 1):
        write_run(tmp_path / "dec", f"s{s}", seed=s, evals=[float(10 * (i + 1) + s) for i in range(10)])
        write_run(tmp_path / "full", f"s{s}", seed=s, mode="full", evals=[float(10 * (i + 1) + s) for i in range(6)])
    curves = stats.load_arms({"decoupled": [tmp_path / "dec"], "full": [tmp_path / "full"]})
    assert stats.common_iteration(curves) == 60
    ts = stats.task_statistics(curves, iter_ms_alone={"decoupled": 100.0, "full": 250.0}, reps=FEW)["hopper"]
    assert ts.iteration == 60
    # equal iterations: both arms end at 60, final = mean of the returns at 40, 50, 60 (+ seed)
    for arm in ("decoupled", "full"):
        assert ts.equal_iters.arms[arm].final == {0: 50.0, 1: 51.0}
    assert ts.whole.arms["decoupled"].final == {0: 90.0, 1: 91.0}
    # equal wall-clock: 10 s, full's 40 iterations (its evaluations 10..40) against all of decoupled
    assert ts.wall_s == pytest.approx(10.0) and ts.iters_at_wall == {"decoupled": 100, "full": 40}
    assert ts.equal_wall.arms["full"].final == {0: 30.0, 1: 31.0}
    assert ts.equal_wall.arms["decoupled"].final == {0: 90.0, 1: 91.0}
    assert ts.equal_wall.differences["full"].diff == {0: -60.0, 1: -60.0}
    assert stats.task_statistics(curves, reps=FEW)["hopper"].equal_wall is None
    with pytest.raises(ValueError, match="iter_ms_alone has no iteration time for arm 'full'"):
        stats.common_wall_s(curves, {"decoupled": 100.0})


def test_a_distilled_students_expert_time_is_charged_before_its_first_iteration(tmp_path):
    # distill: the student's metrics carry its expert's training time (expert_wall_s, 4 s for seed 0, 6 s for
    # seed 1), charged before its first iteration as the reference charges it; then 100 iterations at 100 ms.
    # decoupled: 100 iterations at 100 ms, nothing charged. Evaluations every 10 iterations, return = iteration.
    for s, charged in ((0, 4.0), (1, 6.0)):
        write_run(tmp_path / "dec", f"s{s}", seed=s, evals=[float(10 * (i + 1)) for i in range(10)])
        write_run(tmp_path / "dis", f"s{s}", seed=s, mode="distill", evals=[float(10 * (i + 1)) for i in range(10)],
                  extra={it: {"expert_wall_s": charged} for it in range(1, 101)})
    curves = stats.load_arms({"decoupled": [tmp_path / "dec"], "distill": [tmp_path / "dis"]})
    assert {(c.arm, c.seed): c.charged_s for c in curves} == {("decoupled", 0): 0.0, ("decoupled", 1): 0.0,
                                                               ("distill", 0): 4.0, ("distill", 1): 6.0}
    ms = {"decoupled": 100.0, "distill": 100.0}
    assert stats.common_wall_s(curves, ms) == pytest.approx(10.0)  # decoupled's end; distill ends at 14 and 16 s
    cut = {(c.arm, c.seed): c.last_iter for c in stats.truncate_at_wall_s(curves, ms, 10.0)}
    assert cut == {("decoupled", 0): 100, ("decoupled", 1): 100, ("distill", 0): 60, ("distill", 1): 40}
    assert [c.last_iter for c in stats.truncate_at_wall_s(curves, ms, 5.0) if c.arm == "distill"] == [10, 0]
    ts = stats.task_statistics(curves, iter_ms_alone=ms, reps=FEW)["hopper"]
    assert ts.equal_iters.differences["distill"].diff == {0: 0.0, 1: 0.0}  # equal iterations charge nothing
    # at 10 s the students reach 60 and 40 iterations; the arm's window is the evaluations both have, 20-40
    assert ts.iters_at_wall == {"decoupled": 100, "distill": 60}
    assert ts.equal_wall.arms["distill"].final == {0: 30.0, 1: 30.0}
    # along the wall-clock, each seed's student is read at its own charged offset: at 10 s, 60 and 40 iterations
    dc = stats.difference_curves(curves, iter_ms_alone=ms, reps=FEW)[("distill", "wall-clock")]
    assert dc.x[0] == pytest.approx(7.0) and dc.x[-1] == pytest.approx(10.0)  # from seed 1's first evaluation
    assert dc.mean[-1] == pytest.approx(((50.0 - 90.0) + (30.0 - 90.0)) / 2)


def test_the_run_that_sets_the_time_budget_keeps_its_last_iteration():
    # 30 x 33.3 ms = 0.999 s sets the budget: its round trip through floating point must not lose iteration 30;
    # the other arm (100 x 20 ms) gets floor(999 / 20) = 49 iterations, its evaluations at 10..40
    slow, fast = curve([1.0, 2.0, 3.0], arm="slow"), curve([5.0] * 10, arm="fast")
    ms = {"slow": 33.3, "fast": 20.0}
    budget = stats.common_wall_s([slow, fast], ms)
    assert budget == pytest.approx(0.999)
    cut_slow, cut_fast = stats.truncate_at_wall_s([slow, fast], ms, budget)
    assert cut_slow.last_iter == 30 and cut_slow.returns.size == 3
    assert cut_fast.last_iter == 49
    np.testing.assert_array_equal(cut_fast.iters, [10, 20, 30, 40])


def test_a_reference_arm_does_not_set_the_wall_clock_budget_and_is_read_at_its_end():
    # state: 100 iterations at 10 ms = 1 s; decoupled 100 x 100 ms = 10 s; full 60 x 250 ms = 15 s. Without the
    # exception the state arm's 1 s would cut every pixel arm at its first evaluations.
    curves = [curve([float(i + s) for i in range(n)], arm=arm, seed=s)
              for arm, n in (("decoupled", 10), ("full", 6), ("state", 10)) for s in range(3)]
    ms = {"decoupled": 100.0, "full": 250.0, "state": 10.0}
    assert stats.common_wall_s(curves, ms) == pytest.approx(1.0)
    assert stats.common_wall_s(curves, ms, not_setting={"state"}) == pytest.approx(10.0)
    assert stats.common_wall_s(curves, ms, not_setting={"decoupled", "full", "state"}) == pytest.approx(1.0)
    ts = stats.task_statistics(curves, iter_ms_alone=ms, reps=FEW, not_setting_wall={"state"})["hopper"]
    assert ts.wall_s == pytest.approx(10.0)
    assert ts.iters_at_wall == {"decoupled": 100, "full": 40, "state": 100} and ts.ended_before_wall == ("state",)
    assert ts.equal_wall.arms["state"].final == ts.whole.arms["state"].final


def test_a_reference_arm_without_a_time_is_left_out_of_equal_wall_clock_only():
    # as above, but the state arm's time alone is not known: the pixel arms keep their budget and cut, state
    # leaves the wall-clock view (and its difference curve along wall-clock) and stays in equal iterations
    curves = [curve([float(i + s) for i in range(n)], arm=arm, seed=s)
              for arm, n in (("decoupled", 10), ("full", 6), ("state", 10)) for s in range(3)]
    ms = {"decoupled": 100.0, "full": 250.0}
    ts = stats.task_statistics(curves, iter_ms_alone=ms, reps=FEW, not_setting_wall={"state"})["hopper"]
    assert ts.wall_s == pytest.approx(10.0) and ts.untimed_at_wall == ("state",)
    assert set(ts.equal_wall.arms) == {"decoupled", "full"} and set(ts.iters_at_wall) == {"decoupled", "full"}
    assert "state" in ts.equal_iters.arms and ts.ended_before_wall == ()
    diffs = stats.difference_curves(curves, iter_ms_alone=ms, untimed=ts.untimed_at_wall, reps=FEW)
    assert set(diffs) == {("full", "iteration"), ("state", "iteration"), ("full", "wall-clock")}
    with pytest.raises(ValueError, match="no iteration time for arm 'state'"):  # not named untimed: an error
        stats.difference_curves(curves, iter_ms_alone=ms, reps=FEW)
    # an arm that sets the budget still needs its time
    with pytest.raises(ValueError, match="no iteration time for arm 'full'"):
        stats.task_statistics(curves, iter_ms_alone={"decoupled": 100.0}, reps=FEW, not_setting_wall={"state"})
    with pytest.raises(ValueError, match="no iteration time for arm 'decoupled'"):
        stats.difference_curves(curves, iter_ms_alone={"full": 250.0}, untimed={"decoupled", "state"}, reps=FEW)


# -------------------------------------------------------------------------------- performance profiles
def test_performance_profile_fractions_and_plot(tmp_path):
    curves = _arm("decoupled", [1.0, 2.0, 3.0, 4.0]) + _arm("full", [3.0, 3.5, 5.0, 6.0])
    prof = stats.performance_profiles(curves, thresholds=[0.0, 2.5, 4.5, 7.0], reps=REPS)["hopper"]
    np.testing.assert_array_equal(prof.arms["decoupled"].fraction, [1.0, 0.5, 0.0, 0.0])
    np.testing.assert_array_equal(prof.arms["full"].fraction, [1.0, 1.0, 0.5, 0.0])
    for p in prof.arms.values():
        assert p.n == 4 and np.all(p.ci_low <= p.fraction) and np.all(p.fraction <= p.ci_high)
    assert prof.arms["decoupled"].ci_low[1] < 0.5 < prof.arms["decoupled"].ci_high[1]
    auto = stats.performance_profiles(curves, points=11, reps=FEW)["hopper"]
    assert auto.thresholds.shape == (11,) and auto.thresholds[0] < 1.0 and auto.thresholds[-1] > 6.0
    png = plot.plot_performance_profiles(prof, tmp_path / "profile.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ------------------------------------------------------------------------------------- looking probes
def _probe(it, f0, f1, cos, **more):
    return {"iter": it, "grad_norm": 1.0, "grad_norm_clipped": 1.0, "image_sensitivity_f0": f0,
            "image_sensitivity_f1": f1, "cos_full_decoupled": cos, "grad_norm_full": 10.0 * cos, **more}


def test_looking_probes_select_by_a_fraction_of_the_first_probe(tmp_path):
    rows = [_probe(10, 3.0, 1.0, 1.0),  # sum 4.0: the initial sensitivity, the bar is 0.4
            {"iter": 11, "grad_norm": 2.0},  # not a probe
            _probe(20, 0.01, 0.0, 0.99),  # blind phase
            _probe(30, 0.3, 0.3, 0.2, grad_norm_render_term=5.0),  # 0.6: looks
            _probe(40, 0.2, 0.1, 0.9),  # 0.3: does not
            _probe(50, 1.0, 1.0, 0.4)]  # 2.0: looks
    write_run(tmp_path, "run", evals=(), last_iter=50, extra={r["iter"]: r for r in rows})
    from ablations.run_folder import read_metrics

    look = stats.looking_probes(read_metrics(tmp_path / "run"))
    assert look.probe_iters == (10, 20, 30, 40, 50) and look.n_probes == 5
    assert look.initial == 4.0 and look.sensitivity[2] == pytest.approx(0.6)
    assert look.looking_iters == (10, 30, 50) and look.n_looking == 3
    assert look.medians["cos_full_decoupled"] == 0.4 and look.counts["cos_full_decoupled"] == 3
    assert look.values["cos_full_decoupled"] == (1.0, 0.2, 0.4)  # the looking probes' own, in iteration order
    assert look.medians["grad_norm_full"] == pytest.approx(4.0)
    assert look.medians["grad_norm_render_term"] == 5.0 and look.counts["grad_norm_render_term"] == 1
    assert "grad_norm_clipped" not in look.medians and "grad_norm" not in look.medians
    # the mean over frames halves every sensitivity and the bar alike; a higher fraction drops probe 30
    assert stats.looking_probes(rows, reduce="mean").looking_iters == (10, 30, 50)
    assert stats.looking_probes(rows, fraction=0.2).looking_iters == (10, 50)
    only = stats.looking_probes(rows, keys=["cos_full_decoupled", "cos_hard_soft"])
    assert only.medians == {"cos_full_decoupled": 0.4, "cos_hard_soft": None}
    none = stats.looking_probes([{"iter": 1, "grad_norm": 1.0}])
    assert none.n_probes == 0 and none.initial is None and none.medians == {}
    with pytest.raises(ValueError, match="reduce"):
        stats.looking_probes(rows, reduce="max")


def test_the_blind_phase_is_how_deep_and_how_long_the_policy_stops_looking():
    # first probe 4.0, bar 0.4: blind at 20 and 40 (lowest 0.04 / 4), looking again at 30; 600 is past the window
    rows = [_probe(10, 3.0, 1.0, 1.0), _probe(20, 0.04, 0.0, 0.9), _probe(30, 1.0, 0.0, 0.5),
            _probe(40, 0.1, 0.1, 0.5), _probe(50, 2.0, 0.0, 0.5), _probe(600, 0.0, 0.0, 0.5)]
    phase = stats.blind_phase(stats.looking_probes(rows))
    assert (phase.within, phase.probes, phase.blind, phase.looks_again_at, phase.last_blind) == (500, 4, 2, 30, 40)
    assert phase.lowest == pytest.approx(0.01)
    # a shorter window stops before the policy looks again; a run that always looks was never blind
    assert stats.blind_phase(stats.looking_probes(rows), within=25).looks_again_at is None
    assert stats.blind_phase(stats.looking_probes(rows), within=25).last_blind == 20
    always = stats.blind_phase(stats.looking_probes([_probe(10, 1.0, 0.0, 1.0), _probe(20, 0.5, 0.0, 1.0)]))
    assert (always.blind, always.looks_again_at, always.last_blind, always.lowest) == (0, None, None, 0.5)
    assert stats.blind_phase(stats.looking_probes([_probe(10, 1.0, 0.0, 1.0)])).lowest is None
    # a first probe of 0 sets no bar: nothing is called blind and there is no ratio
    zero = stats.blind_phase(stats.looking_probes([_probe(10, 0.0, 0.0, 1.0), _probe(20, 0.5, 0.0, 1.0)]))
    assert (zero.probes, zero.blind, zero.lowest) == (1, 0, None)
    with pytest.raises(ValueError, match="within"):
        stats.blind_phase(stats.looking_probes(rows), within=0)


# ------------------------------------------------------------------------------------------------ verdict
DEC8 = [100.0, 200.0, 150.0, 120.0, 180.0, 90.0, 210.0, 160.0]
NOISE8 = [1.0, -2.0, 0.5, 2.0, -1.5, 0.7, -0.4, 1.2]


def test_arms_are_read_against_decoupled_where_decoupled_beats_blind():
    # 8 seeds, all agreeing in sign: sign-flip p = 2 / 2^8 each; Holm over the 4 comparisons: 4 x 2/256 = 0.031
    curves = (_arm("decoupled", DEC8) + _arm("blind", [d - 90.0 + e for d, e in zip(DEC8, NOISE8)])
              + _arm("full-soft", [d + 40.0 + e for d, e in zip(DEC8, NOISE8)])
              + _arm("full-hard", [d - 30.0 - e for d, e in zip(DEC8, NOISE8)])
              + _arm("full-alpha", [d + 10.0 * (-1) ** i for i, d in enumerate(DEC8)]))
    v = stats.verdict(stats.compare(curves, reps=REPS))
    assert v.ranks and v.gate.passed and v.gate.by == "paired difference"
    assert v.gate.paired.value == pytest.approx(90.0 - np.mean(NOISE8)) and v.gate.paired.ci_low > 0
    assert v.gate.p_holm == pytest.approx(4 * 2 / 256)
    assert v.readings == {"full-soft": "better", "full-hard": "worse", "full-alpha": "not resolved"}
    assert "decoupled beats blind" in v.reason and "8 of 8 seeds agree in sign" in v.reason


def test_no_arm_is_ranked_where_decoupled_does_not_beat_blind():
    dec = [100.0, 200.0, 150.0]
    curves = (_arm("decoupled", dec) + _arm("blind", [d + e for d, e in zip(dec, [-40.0, 30.0, 5.0])])
              + _arm("full-soft", [d + 500.0 for d in dec]))  # far better than decoupled: still not read
    v = stats.verdict(stats.compare(curves, reps=REPS))
    assert not v.ranks and not v.gate.passed and v.gate.by is None and v.readings == {}
    assert v.gate.paired.ci_low < 0 < v.gate.paired.ci_high
    assert "cannot be ranked on this task yet" in v.reason


def test_five_seeds_that_all_agree_do_not_pass_the_gate():
    # the exact sign-flip p-value over 5 seeds cannot go below 2 / 32 = 0.0625: however far apart, 5 seeds do not
    # resolve a difference at 0.05, even uncorrected
    dec = DEC8[:5]
    curves = _arm("decoupled", dec) + _arm("blind", [d - 900.0 for d in dec])
    v = stats.verdict(stats.compare(curves, reps=REPS))
    assert v.gate.paired.ci_low > 0 and v.gate.p_holm == pytest.approx(0.0625) and not v.ranks
    assert "5 of 5 seeds agree in sign, sign-flip p = 0.0625" in v.reason


def test_the_gate_needs_paired_seeds():
    # decoupled's seeds 0-2 and blind's 3-5 share none: their IQMs lie far apart, but nothing is paired to test
    curves = _arm("decoupled", [500.0, 510.0, 520.0]) + _arm("blind", [10.0, 20.0, 30.0], seeds=[3, 4, 5])
    v = stats.verdict(stats.compare(curves, reps=REPS))
    assert not v.ranks and v.gate.paired is None and "no decoupled seed has a blind run of the same seed" in v.reason


def test_an_interval_over_fewer_than_three_seeds_decides_nothing():
    # one seed: the bootstrap "interval" is a point; two seeds that agree in sign: an interval above zero that
    # half of all pairs would give with no difference at all. Neither may pass the gate or read an arm.
    for n in (1, 2):
        seeds = list(range(n))
        curves = (_arm("decoupled", [1000.0 + 10 * i for i in seeds], seeds=seeds)
                  + _arm("blind", [10.0 + i for i in seeds], seeds=seeds))
        v = stats.verdict(stats.compare(curves, reps=FEW))
        assert v.gate.paired.ci_low > 0 and v.gate.reference_iqm.ci_low > v.gate.control_iqm.ci_high
        assert not v.ranks and not v.gate.passed and v.gate.by is None and v.readings == {}
        assert f"too few seeds to read decoupled against blind: {n} paired seed(s)" in v.reason
    # the gate passes on eight seeds; an arm with two paired seeds far above decoupled is still not read
    curves = (_arm("decoupled", DEC8) + _arm("blind", [d - 90.0 for d in DEC8])
              + _arm("full-soft", [d + 400.0 for d in DEC8[:2]], seeds=[0, 1])
              + _arm("full-hard", [d + 400.0 for d in DEC8], seeds=range(8)))
    v = stats.verdict(stats.compare(curves, reps=FEW))
    assert v.ranks and v.readings == {"full-soft": "too few seeds", "full-hard": "better"}
    assert stats.MIN_SEEDS == 3


def test_runs_cut_before_their_first_evaluation_say_so():
    curves = [dataclasses.replace(c, iters=c.iters + 100, last_iter=c.last_iter + 100)
              for c in _arm("decoupled", [1.0, 2.0, 3.0]) + _arm("blind", [0.0, 0.5, 1.0])]
    with pytest.raises(ValueError, match=r"no hopper run has an evaluation at or before iteration 50 \(the first "
                                         r"is at 110\): read it later"):
        stats.task_statistics(curves, reps=FEW, at_iteration=50)


def test_equal_wall_clock_is_taken_within_the_cut():
    # decoupled 50 ms, blind 100 ms an iteration; runs of 20 iterations read at 10: the budget is 10 x 50 ms, so
    # decoupled is read at 10 and blind at 5
    curves = [curve([1.0, 2.0, 3.0, 4.0], arm=a, seed=s, iters=[5, 10, 15, 20]) for a in ("decoupled", "blind")
              for s in range(3)]
    ts = stats.task_statistics(curves, reps=FEW, iter_ms_alone={"decoupled": 50.0, "blind": 100.0},
                               at_iteration=10)["hopper"]
    assert ts.iteration == 10 and ts.wall_s == pytest.approx(0.5)
    assert ts.iters_at_wall == {"decoupled": 10, "blind": 5}


def test_a_task_without_blind_or_that_ranks_no_arms_is_not_read():
    curves = _arm("decoupled", [1.0, 2.0, 3.0]) + _arm("full-soft", [9.0, 9.5, 9.9])
    v = stats.verdict(stats.compare(curves, reps=FEW))
    assert not v.ranks and v.gate is None and "no blind run" in v.reason
    curves += _arm("blind", [-50.0, -40.0, -45.0])
    v = stats.verdict(stats.compare(curves, reps=FEW), not_ranking="doing nothing scores high")
    assert not v.ranks and v.reason == "doing nothing scores high" and v.readings == {}


def test_profiles_take_the_arms_styles(tmp_path, monkeypatch):
    from matplotlib.axes import Axes
    from matplotlib.colors import to_rgb

    from ablations.reports.style import ArmStyle

    prof = stats.performance_profiles(_arm("decoupled", [1.0, 2.0]) + _arm("blind", [0.0, 0.5]), reps=FEW)["hopper"]
    seen = {}
    real = Axes.plot

    def spy(ax, *args, **kw):
        seen[kw.get("label")] = (kw.get("color"), kw.get("ls"))
        return real(ax, *args, **kw)

    monkeypatch.setattr(Axes, "plot", spy)
    styles = {"decoupled": ArmStyle((0.1, 0.2, 0.7), (0, (5, 2)), "o")}
    plot.plot_performance_profiles(prof, tmp_path / "p.png", styles=styles)
    assert to_rgb(seen["decoupled (n=2)"][0]) == (0.1, 0.2, 0.7) and seen["decoupled (n=2)"][1] == (0, (5, 2))
    assert seen["blind (n=2)"] == (None, None)  # not named: matplotlib's next colour


# ------------------------------------------------------------------------- exact resampling and correction
def _brute_force_interval(values, confidence=0.95):
    """The percentile interval of the mean over all n^n ordered resamples, each of probability n^-n."""
    means = np.array([np.mean(r) for r in itertools.product(values, repeat=len(values))])
    return stats.percentile_interval(means, np.full(means.size, 1.0 / means.size), confidence)


@pytest.mark.parametrize("values", [[3.0, -1.0, 7.0], [-1546.0, -48.0, -900.0], [0.5, 2.0, 2.0, -4.0],
                                    [1.0, 9.0, -3.0, 4.0, 2.5]])
def test_the_exact_bootstrap_equals_the_enumeration_of_every_ordered_resample(values):
    est = stats.mean_estimate(values)
    assert est.exact and est.reps == math.comb(2 * len(values) - 1, len(values))
    assert (est.ci_low, est.ci_high) == pytest.approx(_brute_force_interval(values))
    _stat, w, exact = stats.bootstrap_distribution(values, lambda rows: rows.mean(axis=1))
    assert exact and w.sum() == pytest.approx(1.0)
    if len(values) == 3:  # each extreme resample has probability 1/27 > 2.5 %: the interval is the range
        assert (est.ci_low, est.ci_high) == (min(values), max(values))


def test_more_seeds_than_the_enumeration_takes_draw_a_stated_number_of_resamples():
    values = list(range(stats.EXACT_BOOTSTRAP_MAX_N + 1))
    est = stats.mean_estimate(values, reps=500, seed=3)
    assert not est.exact and est.reps == 500 and est == stats.mean_estimate(values, reps=500, seed=3)


def test_sign_flip_p_values_are_exact():
    assert stats.sign_flip_p([1, 2, 3, 4, 5]) == 0.0625  # 2 of 32 patterns reach the observed |mean|
    assert stats.sign_flip_p([-4, -1, -2]) == 0.25
    assert stats.sign_flip_p([5.0] * 8) == pytest.approx(2 / 256)
    assert stats.sign_flip_p([1, -1, 2, -2]) == 1.0
    # by hand: d = (3, 1, -1) sums to 3; the 8 signed sums are +-5, +-3, +-3, +-1: |sum| >= 3 in 6 of 8
    assert stats.sign_flip_p([3, 1, -1]) == 0.75
    assert math.isnan(stats.sign_flip_p([]))
    # the same at any scale: the tie tolerance is relative (tiny differences are not all ties)
    assert stats.sign_flip_p([i * 1e-10 for i in range(1, 7)]) == stats.sign_flip_p(list(range(1, 7))) == 2 / 64
    assert stats.sign_flip_p([0.0, 0.0, 0.0]) == 1.0


@pytest.mark.parametrize(("family", "seeds"), [(1, 6), (3, 7), (10, 9), (18, 10)])
def test_seeds_to_resolve_is_the_fewest_with_which_the_strongest_result_survives_holm(family, seeds):
    """Every seed agreeing (the smallest sign-flip p-value), against ``family - 1`` comparisons of p = 1:
    the strongest result differs after Holm correction from the stated number of seeds on, never below it."""
    assert stats.seeds_to_resolve(family) == seeds

    def strongest_differs(n: int) -> bool:
        p = stats.sign_flip_p([1.0 + 0.1 * i for i in range(n)])
        return stats.holm([p] + [1.0] * (family - 1))[0] <= stats.ALPHA

    assert strongest_differs(seeds) and not strongest_differs(seeds - 1)
    with pytest.raises(ValueError, match="at least 1"):
        stats.seeds_to_resolve(0)


def test_holm_adjusts_known_p_values():
    # sorted 0.01, 0.03, 0.04, 0.2 times 4, 3, 2, 1: 0.04, 0.09, 0.08 -> 0.09 (monotone), 0.2
    assert stats.holm([0.01, 0.04, 0.03, 0.2]) == pytest.approx([0.04, 0.09, 0.09, 0.2])
    out = stats.holm([0.5, math.nan, 0.01])  # NaN stays out of the family: m = 2
    assert out[0] == 0.5 and math.isnan(out[1]) and out[2] == pytest.approx(0.02)
    assert stats.holm([0.6, 0.7]) == [1.0, 1.0]


def test_a_clearly_worse_arm_on_eight_seeds_differs_after_correction_and_noise_does_not():
    rng = np.random.default_rng(0)
    dec = list(rng.normal(1000, 200, 8))
    worse = [d - 300 + e for d, e in zip(dec, rng.normal(0, 30, 8))]
    noise = [d + e for d, e in zip(dec, rng.normal(0, 300, 8))]
    blind = [d - 800 + e for d, e in zip(dec, rng.normal(0, 30, 8))]
    cmp = stats.compare(_arm("decoupled", dec) + _arm("blind", blind) + _arm("full", worse) + _arm("noisy", noise))
    (cmp,) = stats.correct([cmp])
    d = cmp.differences["full"]
    assert d.agree == 8 and d.p_value == pytest.approx(2 / 256) and d.family == 3 and d.differs()
    assert not cmp.differences["noisy"].differs() and cmp.differences["noisy"].p_holm > 0.05
    assert stats.verdict(cmp).readings == {"full": "worse", "noisy": "not resolved"}
    # the same comparison in a larger family (the 18 of a three-task report): 18 x 2/256 > 0.05
    (big,) = stats.correct([cmp] * 6)[:1]
    assert big.differences["full"].family == 18 and not big.differences["full"].differs()


def test_every_run_of_a_comparison_averages_the_same_evaluation_iterations():
    # a: evaluations at 1500, 1750, 2000, 2038; b: at 1250, 1500, 1750, 2000: the common last three are
    # 1500, 1750, 2000 for both (not 1750, 2000, 2038 for a)
    a = curve([10.0, 20.0, 30.0, 1000.0], arm="decoupled", iters=[1500, 1750, 2000, 2038])
    b = curve([1.0, 2.0, 3.0, 4.0], arm="full", iters=[1250, 1500, 1750, 2000])
    assert stats.common_window([a, b]) == (1500, 1750, 2000)
    cmp = stats.compare([a, b], reps=FEW)
    assert cmp.arms["decoupled"].final == {0: 20.0} and cmp.arms["full"].final == {0: 3.0}
    assert cmp.arms["full"].window == (1500, 1750, 2000)
    per_arm = stats.compare([a, b], reps=FEW, window="per arm")
    assert per_arm.arms["decoupled"].window == (1750, 2000, 2038)
    # runs that share no evaluation iteration: each its own last three, listed per seed
    c = curve([5.0, 6.0], arm="full", iters=[1, 2])
    cmp = stats.compare([a, c], reps=FEW)
    assert cmp.arms["full"].window == () and cmp.arms["full"].own_windows == {0: (1, 2)}


def test_difference_curves_say_where_the_sign_holds():
    # 8 seeds; full's evaluations equal decoupled's up to iteration 30, then 100 below on every seed
    iters = np.arange(1, 11) * 10
    curves = []
    for s in range(8):
        base = np.linspace(0, 900, 10) + 37.0 * s
        curves.append(curve(base, arm="decoupled", seed=s, iters=iters))
        curves.append(curve(base - np.where(iters > 30, 100.0 + s, 0.0) + (s % 2 - 0.5) * 0.01 * (iters <= 30),
                            arm="full", seed=s, iters=iters))
    dcs = stats.difference_curves(curves, iter_ms_alone={"decoupled": 100.0, "full": 200.0}, final_evals=1)
    dc = dcs[("full", "iteration")]
    assert list(dc.x) == list(iters) and set(dc.n) == {8}
    assert np.all(dc.ci_high[3:] < 0) and not np.any(dc.ci_high[:3] < 0)
    assert stats.sign_holds(dc) == ("full − decoupled < 0 with the interval excluding 0 from iteration 40 on "
                                    "(7 of 10 budgets, iteration 10 to iteration 100)")
    wall = dcs[("full", "wall-clock")]
    # budgets: every evaluation time of either arm from the later first one (2 s) to the shortest run's end
    # (10 s: decoupled at 100 iterations x 0.1 s; full at 100 x 0.2 s = 20 s)
    assert wall.x[0] == pytest.approx(2.0) and wall.x[-1] == pytest.approx(10.0)
    # at 10 s full is at iteration 50 (below decoupled's 50 by 100 + s), decoupled at 100
    assert wall.mean[-1] == pytest.approx(np.mean([(np.linspace(0, 900, 10)[4] - 103.5) - 900]))
    flat = [curve([1.0 + s % 3] * 3, arm="decoupled", seed=s) for s in range(3)]
    flat += [curve([1.0 + (s + 1) % 3] * 3, arm="full", seed=s) for s in range(3)]
    assert "the interval covers 0 at every one of its 3 budget(s)" in stats.sign_holds(
        stats.difference_curves(flat)[("full", "iteration")])


def test_the_statistics_work_where_the_resampling_libraries_cannot_import():
    # arch (rliable's bootstrap) fails to import under pandas 3: blocked here, the statistics still compute
    code = ("import sys; sys.modules.update(dict.fromkeys(['rliable', 'arch', 'pandas'])); "
            "import numpy as np, ablations.reports.stats as s; "
            "c = [s.Curve('t', a, i, '', np.array([10, 20]), np.array([v, v + i]), 20) "
            "for a, v in (('decoupled', 5.0), ('full', 1.0)) for i in range(4)]; "
            "d = s.compare(c).differences['full']; s.performance_profiles(c); "
            "print(d.mean.value, d.p_value, sorted({m.split('.')[0] for m in sys.modules if sys.modules[m]} "
            "& {'rliable', 'arch', 'pandas', 'torch'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "-4.0 0.125 []"


def test_the_iqm_is_rliables():
    rly_metrics = pytest.importorskip("rliable.metrics")
    for values in ([7, 1, 100, 3, 2, 6, 4, 5], [1, 2, 9], [4.0, -2.0, 8.5, 1.0, 3.0]):
        ours = stats.iqm_estimate(values).value
        assert ours == pytest.approx(float(rly_metrics.aggregate_iqm(np.array(values, float).reshape(-1, 1))))
