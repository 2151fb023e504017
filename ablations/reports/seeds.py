"""Seed statistics of run folders as report sections: which arm trains better, with confidence intervals, and
what the gradient probes say while the policy looks at its image.

``ablate-report`` writes these sections; ``ablate-paper`` can call the same functions (the arms and their
times alone come from :mod:`ablations.reports.arms`):

* :func:`seed_statistics`: per task, :func:`ablations.reports.stats.task_statistics` at equal iterations and equal
  wall-clock with Holm's correction over every task's and view's paired comparisons together, the paired
  differences along the budget, the learning-curve bands, the performance profile, and the verdict
  (:func:`ablations.reports.stats.verdict`): full against decoupled is read only where decoupled beats blind after
  correction (the control rule).
* :func:`seed_section` and :func:`probe_section`: the markdown (figures from :func:`ablations.reports.plot.make_plots`
  and the performance profiles, linked relative to the report's folder).

Everything here reads JSON (no torch).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from statistics import median

import numpy as np

from ablations.reports import stats
from ablations.reports.arms import IterationTimes, arm_label, in_arm_order, iteration_times
from ablations.reports.parts import (
    figure_lines,
    markdown_table,
    report_path,
)
from ablations.reports.seed_figures import draw_difference_curves, draw_learning_curves, plot_performance_profiles
from ablations.reports.style import Floors, PlotResult, arm_styles, group_runs
from ablations.run_folder import Run, is_number
from vocabulary import (
    CONTROL_ARM,
    IMAGELESS_MODES,
    REFERENCE_ARM,
)

__all__ = ["NOT_RANKING", "SEED_FIGURES", "PROBE_FIGURES", "PROBE_KEYS", "TaskSeeds", "seed_statistics",
           "seed_section", "ArmProbes", "arm_probes", "probe_section", "not_ranking_reason", "training_collapse_rate"]

#: Tasks whose returns rank no arms, and why (the zero-action floor from the floors file is quoted beside it).
NOT_RANKING = {"cartpole": "D.Va's cartpole (with springs) ranks no arms: doing nothing already scores high"}
#: make_plots figures shown by the seed section and by the probe section (the other sections leave them out).
SEED_FIGURES = ("eval_return_vs_iter.png",)
PROBE_FIGURES = ("looking.png", "exploration_noise.png", "image_sensitivity.png")
#: Probe statistics of the probe section: metrics key (or a ratio of two) -> column name.
PROBE_KEYS = {
    "cos_full_decoupled": "cos(full, decoupled)",
    "grad_norm_render_term": "render-term norm",
    "cos_hard_soft": "cos(hard, soft)",
    "cos_hard_decoupled": "cos(hard, decoupled)",
    "cos_soft_decoupled": "cos(soft, decoupled)",
    "grad_norm_full_hard/grad_norm_full_soft": "norm hard / norm soft",
}


# ------------------------------------------------------------------------------------------- statistics
@dataclass(frozen=True)
class TaskSeeds:
    """One task's seed statistics: ``stats`` (whole, equal iterations, equal wall-clock when ``times.ms``; their
    paired differences Holm-corrected over every task's and view's together), ``times``, ``verdicts`` (view name
    -> :class:`ablations.reports.stats.Verdict`: "equal iterations", and "equal wall-clock" where available),
    ``profile`` (None without evaluations), ``eval_keys`` (the metrics keys the evaluations came from),
    ``error`` (why nothing could be computed, e.g. two runs of one arm and seed), ``curves`` (the paired
    differences along the budget, :func:`ablations.reports.stats.difference_curves`), ``bands`` (arm -> "evaluation" /
    "training" -> its mean curve with interval, :func:`ablations.reports.stats.mean_band`)."""

    task: str
    stats: stats.TaskStatistics | None
    times: IterationTimes
    verdicts: dict[str, stats.Verdict]
    profile: stats.PerformanceProfile | None
    eval_keys: tuple[str, ...]
    error: str | None = None
    curves: dict[tuple[str, str], stats.DifferenceCurve] = field(default_factory=dict)
    bands: dict[str, dict[str, stats.Band]] = field(default_factory=dict)


def not_ranking_reason(task: str, floors: Floors | None, *, facts: Sequence[str] = ()) -> str | None:
    """Why ``task`` ranks no arms (:data:`NOT_RANKING`), with its zero-action floor from ``floors`` and any further
    ``facts`` in brackets; None for a task that ranks arms."""
    reason = NOT_RANKING.get(task)
    if reason is None:
        return None
    zero = ((floors.of(task) or {}).get("zero") or {}) if floors is not None else {}
    found = []
    if is_number(zero.get("mean")):
        found.append(f"zero action {zero['mean']:.0f}" + (f", {Path(floors.source).name}" if floors.source else ""))
    found += facts
    return reason + (f" ({'; '.join(found)})" if found else "")


def seed_statistics(runs: Sequence[Run], *, label: Callable[[Run], str] | None = None,
                    benchmarks: Sequence[str | os.PathLike] = (), floors: Floors | None = None,
                    reps: int = stats.DEFAULT_REPS, seed: int = stats.DEFAULT_SEED,
                    at_iteration: int | None = None) -> dict[str, TaskSeeds]:
    """Task -> :class:`TaskSeeds` of the runs (arms by ``label``, default :func:`arm_label`), tasks in the order
    of ``tasks.TASKS``. ``floors``: quoted where a task ranks no arms (NOT_RANKING). ``at_iteration``: every
    run read as if it had stopped there (``stats.task_statistics``)."""
    stats.check_at_iteration(at_iteration)  # here: a ValueError inside a task's loop becomes that task's note
    label = label or arm_label(runs)
    runs = in_arm_order(runs, label)
    times = iteration_times(runs, label, benchmarks)
    out = {}
    computed = {}
    for task in dict.fromkeys(t for t, _ in group_runs(runs, label=label)):  # tasks.TASKS' order
        t = times[task]
        keys: tuple[str, ...] = ()
        try:  # a run without a seed, or two runs of one arm and seed: this task says why, the others go on
            curves = [stats.curve_of(r, label(r)) for r in runs if r.task == task]
            keys = tuple(sorted({c.key for c in curves if c.key}))
            ts = stats.task_statistics(curves, iter_ms_alone=t.ms, reps=reps, seed=seed,
                                       at_iteration=at_iteration, not_setting_wall=t.not_setting)[task]
        except ValueError as e:
            out[task] = TaskSeeds(task, None, t, {}, None, keys, error=str(e))
            continue
        computed[task] = (ts, curves, keys)
    # the family of Holm's correction: every paired comparison the section shows, every task and view
    corrected = stats.correct_statistics({task: ts for task, (ts, _, _) in computed.items()})
    for task, (_, curves, keys) in computed.items():
        ts, t = corrected[task], times[task]
        reason = not_ranking_reason(task, floors)
        verdicts = {"equal iterations": stats.verdict(ts.equal_iters, control=CONTROL_ARM, not_ranking=reason)}
        if ts.equal_wall is not None:
            verdicts["equal wall-clock"] = stats.verdict(ts.equal_wall, control=CONTROL_ARM, not_ranking=reason)
        cut = curves if at_iteration is None else stats.truncate_at_iteration(curves, at_iteration)
        profile = stats.performance_profiles(stats.truncate_at_iteration(curves, ts.iteration), reps=reps,
                                             seed=seed).get(task) if keys else None
        diffs = stats.difference_curves(cut, reference=REFERENCE_ARM, iter_ms_alone=t.ms, untimed=ts.untimed_at_wall,
                                        reps=reps, seed=seed) if keys else {}
        task_runs = [r for r in runs if r.task == task]
        bands = {}
        for arm in dict.fromkeys(label(r) for r in task_runs):
            rs = [r for r in task_runs if label(r) == arm]
            until = at_iteration or max((r.metrics[-1]["iter"] for r in rs if r.metrics), default=0)
            evals = [c for c in cut if c.arm == arm and c.returns.size]
            train = [_training_series(r, until) for r in rs]
            bands[arm] = {"evaluation": stats.mean_band([(c.iters, c.returns) for c in evals], reps=reps, seed=seed),
                          "training": stats.mean_band(train, reps=reps, seed=seed)}
        out[task] = TaskSeeds(task, ts, t, verdicts, profile, keys, curves=diffs, bands=bands)
    return {task: out[task] for task in dict.fromkeys(t for t, _ in group_runs(runs, label=label))}


def _training_series(run: Run, until: int) -> tuple[np.ndarray, np.ndarray]:
    """(iterations, training return ``return_mean``) of a run up to ``until``."""
    pts = [(m["iter"], m["return_mean"]) for m in run.metrics if m["iter"] <= until and is_number(m.get("return_mean"))]
    return np.array([p[0] for p in pts], float), np.array([p[1] for p in pts], float)


# ---------------------------------------------------------------------------------------------- markdown
def _est(e: stats.Estimate | None, digits: str = ".4g") -> str:
    if e is None:
        return "-"
    return f"{e.value:{digits}} [{e.ci_low:{digits}}, {e.ci_high:{digits}}]"


def _per_seed(values: dict[int, float]) -> str:
    return ", ".join(f"s{s}: {v:.4g}" for s, v in values.items()) or "-"


def _span(values) -> str:
    vals = sorted(set(values))
    return "-" if not vals else str(vals[0]) if len(vals) == 1 else f"{vals[0]}-{vals[-1]}"


_READING = {"better": "better than decoupled (differs after Holm correction)",
            "worse": "worse than decoupled (differs after Holm correction)",
            "not resolved": f"not resolved (Holm-adjusted p > {stats.ALPHA:g})", "no paired seeds": "no paired seeds",
            "too few seeds": f"too few paired seeds to read (fewer than {stats.MIN_SEEDS})"}


def _interval(e: stats.Estimate) -> str:
    """A mean's interval, said for what it is over few seeds: over 3 the seeds' range."""
    text = _est(e)
    return text + (" (the range of the 3 seeds)" if e.n == 3 and e.exact else "")


def _window_text(a: stats.ArmSummary) -> str:
    if a.window:
        return ", ".join(map(str, a.window))
    return "each run's own last: " + "; ".join(f"s{s}: {', '.join(map(str, w))}" for s, w in a.own_windows.items())


def _view_table(cmp: stats.Comparison, v: stats.Verdict, iters: dict[str, int], exploratory: bool = False
                ) -> list[str]:
    rows = []
    for arm, a in cmp.arms.items():
        d = cmp.differences.get(arm)
        if arm == cmp.reference:
            per, agree, diff, p, holm, prob, reading = "-", "-", "reference", "-", "-", "-", "reference"
        elif d is None or d.mean is None:
            per, agree, diff, p, holm, prob, reading = "-", "-", "no paired seeds", "-", "-", "-", "no paired seeds"
        else:
            per = _per_seed(d.diff)
            agree = f"{d.agree} of {d.mean.n}"
            diff = _interval(d.mean)
            p = f"{d.p_value:.3g}"
            holm = f"{d.p_holm:.3g}" if d.p_holm is not None else "-"
            prob = _est(d.improvement, ".2f") if d.improvement else "-"
            reading = ("control" if arm == v.control else _READING[v.readings[arm]] if arm in v.readings
                       else "cannot be ranked yet" if v.gate is not None else "not ranked")
            if arm == v.control:
                reading += (f" ({_READING['worse' if d.mean.value < 0 else 'better']})" if d.differs(v.alpha)
                            else f" ({_READING['not resolved']})")
            if exploratory:  # a registration decides: no correction over what is shown, no reading
                holm, reading = "-", "exploratory"
        collapse = a.collapse_mean
        evals = (_span(a.evals.values()) if a.evals else "0") + (
            f"; seeds without an evaluation: {', '.join(map(str, a.without_evals))}" if a.without_evals else "")
        rows.append([arm, len(a.final), iters.get(arm, "-"), evals, _window_text(a) if a.final else "-",
                     _est(a.final_iqm), _per_seed(a.final), _est(a.auc_iqm),
                     f"{_est(collapse, '.2f')} (n={collapse.n})" if collapse else "-", per, agree, diff, p, holm,
                     prob, reading])
    return markdown_table(["arm", "seeds", "iterations", "evaluations per run",
                           "evaluation window (iterations averaged)", "evaluation return: IQM [95 % CI]",
                           "evaluation return per seed", "AUC: IQM [95 % CI]", "collapse rate: mean [95 % CI]",
                           "minus decoupled per seed", "seeds agreeing in sign",
                           "minus decoupled: mean [95 % exact bootstrap CI]", "sign-flip p",
                           "Holm-adjusted p", "P(arm > decoupled) [95 % CI]", "reading"], rows)


def _verdict_line(view: str, v: stats.Verdict) -> str:
    if not v.ranks:
        return f"**Verdict ({view}):** {v.reason}."
    readings = "; ".join(f"{arm}: {_READING[r]}" for arm, r in v.readings.items()) or "no other arm"
    return f"**Verdict ({view}):** {v.reason}, so the other arms are read against {v.reference}: {readings}."


def _family_size(seeds: dict[str, TaskSeeds]) -> int:
    return max((d.family or 0 for s in seeds.values() if s.stats for c in (s.stats.equal_iters, s.stats.equal_wall)
                if c is not None for d in c.differences.values()), default=0)


def _budget_lines(s: TaskSeeds, task: str, fig_dir: Path, base: Path, styles, floors: Floors | None
                  ) -> list[str]:
    """The paired differences along the budget (figure and where the sign holds) and the learning curves."""
    out = []
    if s.curves:
        png = draw_difference_curves(task, s.curves, fig_dir / f"difference_vs_budget_{task}.png", styles=styles,
                                     reference=REFERENCE_ARM)
        out += [f"![{task}: paired differences along the budget]({report_path(png, base)})", "",
                f"*{task}: each arm minus {REFERENCE_ARM}, paired by seed, at every evaluation (left: equal "
                "iterations; right, where the arms' times alone are known: equal modelled wall-clock). At each "
                f"budget a run's return is the mean of its last {stats.FINAL_EVALS} evaluations up to it, at the "
                "evaluation iterations its arm's and the reference's runs share. Line: mean; dashed: median; "
                "shaded: the mean's 95 % bootstrap interval (exact), pointwise and not corrected for the many "
                "budgets.*", "",
                "Where the sign holds (pointwise intervals):", ""]
        for axis in ("iteration", "wall-clock"):
            for (_arm, a), dc in s.curves.items():
                if a == axis:
                    out.append(f"- at equal {'iterations' if axis == 'iteration' else 'modelled wall-clock'}: "
                               f"{stats.sign_holds(dc)}.")
        out.append("")
    if s.bands:
        png = draw_learning_curves(task, s.bands, fig_dir / f"learning_curves_{task}.png",
                                   floors=floors.of(task) if floors is not None else None,
                                   styles=styles, exact_max_n=stats.EXACT_BOOTSTRAP_MAX_N)
        out += [f"![{task}: learning curves]({report_path(png, base)})", "",
                f"*{task}: each arm's mean evaluation return (left; the deterministic policy) and training return "
                "(right; the exploring policy's last 100 episodes) over its seeds against iterations, shaded: the "
                "mean's 95 % bootstrap interval where 2 or more runs have the point (a stretch only one run reaches "
                "is dotted); dotted and dash-dotted horizontal lines: the zero- and random-action floors.*", ""]
    return out


def seed_section(runs: Sequence[Run], fig_dir: Path, base: Path, *, label: Callable[[Run], str] | None = None,
                 benchmarks: Sequence[str | os.PathLike] = (), floors: Floors | None = None,
                 plots: PlotResult | None = None, reps: int = stats.DEFAULT_REPS, seed: int = stats.DEFAULT_SEED,
                 computed: dict[str, TaskSeeds] | None = None, at_iteration: int | None = None,
                 heading: str = "## 3. Seed statistics: which arm trains better", exploratory: bool = False
                 ) -> list[str]:
    """The seed-statistics section: the arms, per task the verdict and the tables at equal iterations and equal
    wall-clock, the performance profiles (drawn into ``fig_dir``) and ``plots``' SEED_FIGURES (links relative to
    ``base``, the report's folder). ``computed``: :func:`seed_statistics` of these runs and arguments, when the
    caller has it already (computed with the same ``at_iteration``). ``at_iteration``: the runs read as if they
    had stopped there. ``exploratory``: a registered analysis decides elsewhere in the report, so the tables show
    no Holm-adjusted p-value and no reading, and no verdict line is written."""
    out = [heading, ""]
    if not runs:
        return [*out, "No training runs were given.", ""]
    label = label or arm_label(runs)
    seeds = computed if computed is not None else seed_statistics(runs, label=label, benchmarks=benchmarks,
                                                                  floors=floors, reps=reps, seed=seed,
                                                                  at_iteration=at_iteration)
    if not any(s.eval_keys or s.error for s in seeds.values()):
        return [*out, "No run logged a deterministic evaluation (metrics `eval_return_mean`, every `--eval-every` "
                "iterations): these runs cannot be compared over seeds. Train with `--eval-every K` for this "
                "section.", ""]
    family = _family_size(seeds)
    out += [f"A run's **final return** here is its deterministic **evaluation return** (the policy's mean action "
            "from the fixed evaluation seed) averaged over the last "
            f"{stats.FINAL_EVALS} evaluation iterations that **every run of the comparison** has (at equal "
            "wall-clock, where each arm ends at its own iteration: every run of the arm); the tables name those "
            "iterations. The training return (the exploring policy's last 100 episodes) is a different number and "
            "is labelled as such wherever it appears. Over seeds: the **interquartile mean** (IQM; with 3 seeds "
            "the plain mean, with 5 the mean of the middle 3) with a 95 % percentile bootstrap CI over seeds: "
            f"exact up to {stats.EXACT_BOOTSTRAP_MAX_N} seeds (every distinct resample enumerated with its "
            f"probability), else {reps} resamples from a fixed seed. Over 3 seeds that interval is the seeds' range "
            "[min, max]: it excludes 0 exactly when all three agree in sign, which happens a quarter of the time "
            "with no difference at all.", "",
            f"**Against {REFERENCE_ARM}**, per arm: each seed's difference (the same seed in both arms), how many "
            "seeds agree in sign, the mean with its exact bootstrap CI, the two-sided **sign-flip permutation "
            "p-value** (exact: all 2^n sign patterns; its smallest value is 2/2^n, 0.25 over 3 seeds and 0.0625 "
            f"over 5, so 5 seeds cannot reach p < 0.05), and the **Holm-adjusted p-value** over the family of all "
            f"{family} paired comparisons of this section (every arm against {REFERENCE_ARM}, blind included, on "
            "every task, at equal iterations and at equal wall-clock), at a family-wise level of "
            f"{stats.ALPHA:g}: over {family} comparisons a difference can differ only with at least "
            f"{stats.seeds_to_resolve(max(1, family))} paired seeds, however large it is. A difference **differs "
            f"after Holm correction** where its adjusted p-value is at most {stats.ALPHA:g}, and is **not "
            "resolved** otherwise; the readings say only that. Beside them: "
            f"the probability of improvement P(arm > {REFERENCE_ARM}) on the paired seeds (each arm resampled "
            f"independently, {reps} resamples). **AUC**: the mean height of the evaluation curve (trapezoid over "
            "its span). **Collapse rate**: the fraction of evaluations, after the first positive best, below half "
            "the best so far (defined for runs with such evaluations; n says how many). **Equal iterations**: "
            "every run cut at the fewest iterations any run of the task reached. **Equal wall-clock**: every run "
            "cut at the least training time any run of the task reached, modelled as iterations x its arm's "
            "iteration time measured alone, after a distilled student's expert's training time (compilation, "
            "evaluations and the probes' extra backward left out; a run "
            "on the state vector, a reference, does not set it and is read at its end where it ends sooner); "
            "with equal iterations that is the fastest arm's last iteration. Both cuts are single points of a "
            "curve: the figure of paired differences along the budget shows every evaluation, and the text under "
            "it says where the sign holds.", "",
            *([f"**Read at iteration {at_iteration}** (`--at-iteration`): every run is cut there first, so all "
               "of this section's views end at or before it; a task whose runs all ended sooner is read at their "
               "ends (each verdict names its iteration). The figures of section 2 and the probe section show the "
               "whole runs.", ""] if at_iteration is not None else []),
            f"**The control rule**: an arm is read against {REFERENCE_ARM} only where {REFERENCE_ARM} beats "
            f"{CONTROL_ARM} (the same pixels, never looked at): {REFERENCE_ARM} minus {CONTROL_ARM} positive and "
            f"differing after Holm correction. Otherwise the pixel arms cannot be ranked on that task yet. **The "
            f"minimum-seeds rule**: nothing is decided from fewer than {stats.MIN_SEEDS} paired seeds.", ""]
    if exploratory:
        out += ["**Exploratory**: a registration decides this report's question (the registered analysis above). "
                "This section shows every arm, view and budget without Holm's correction and without verdicts: its "
                "adjusted p-values and readings are left out, and its p-values are pointwise.", ""]
    out += _arms_table(runs, label)
    styles = arm_styles(group_runs(list(runs), label=label))
    for task, s in seeds.items():
        out += [f"### {task}", ""]
        if s.error:
            out += [f"Not computed: {s.error}.", ""]
            continue
        if not s.eval_keys:
            out += ["No run of this task logged a deterministic evaluation (`eval_return_mean`).", ""]
            continue
        if s.eval_keys == ("eval_return",):
            out += ["These runs logged the evaluation return only on their video iterations (`eval_return`, one "
                    "episode): read with care.", ""]
        ts = s.stats
        n = ts.iteration
        out += [*([] if exploratory else [_verdict_line(f"equal iterations, {n}", s.verdicts["equal iterations"]),
                                          ""]),
                f"Equal iterations: every run cut at iteration {n}; its final evaluation return averages the "
                f"evaluations at iterations {_window_text(next(iter(ts.equal_iters.arms.values())))}.", ""]
        out += _view_table(ts.equal_iters, s.verdicts["equal iterations"], dict.fromkeys(ts.equal_iters.arms, n),
                           exploratory)
        out.append("")
        missing = {arm: d.missing for arm, d in ts.equal_iters.differences.items() if d.missing}
        if missing:
            out += ["Seeds without a partner (left out of the paired differences): " + "; ".join(
                f"{arm} against {REFERENCE_ARM}: " + ", ".join(f"{a} {list(v)}" for a, v in m.items())
                for arm, m in missing.items()) + ".", ""]
        out += _swings_lines([r for r in runs if r.task == task], label, n)
        if ts.equal_wall is None:
            out += [f"Equal wall-clock: not available: {s.times.why}.", ""]
        else:
            times = ", ".join(f"{a} {ms:.4g} ms" for a, ms in ts.iter_ms_alone.items())
            ended = ", ".join(ts.ended_before_wall)
            out += [*([] if exploratory else [_verdict_line(f"equal wall-clock, {ts.wall_s:.4g} s",
                                                            s.verdicts["equal wall-clock"]), ""]),
                    f"Equal wall-clock: every run{' of the timed arms' if ts.untimed_at_wall else ''} cut at "
                    f"{ts.wall_s:.4g} s of modelled training time ({times} per "
                    f"iteration; {s.times.why}); each run's final evaluation return averages its arm's last "
                    "common evaluations (the window column)."
                    + (f" The runs of {ended} (the actor on the state vector: a reference, which does "
                       "not set the budget) end sooner and are read at their end: less time than the others, "
                       "never more." if ended else ""), ""]
            out += _view_table(ts.equal_wall, s.verdicts["equal wall-clock"], ts.iters_at_wall or {}, exploratory)
            out.append("")
        out += _budget_lines(s, task, fig_dir, base, styles, floors)
        if s.profile is not None:
            png = plot_performance_profiles(s.profile, fig_dir / f"performance_profile_{task}.png",
                                                  styles=styles)
            out += [f"![{task}: performance profile]({report_path(png, base)})", "",
                    f"*{task}: the fraction of each arm's runs whose final evaluation return (at equal iterations, "
                    f"{n}) exceeds each return (shaded: 95 % bootstrap CI, exact).*", ""]
    if plots is not None:
        out += figure_lines(plots, SEED_FIGURES, base)
    return out


def training_collapse_rate(run: Run, until: int) -> float:
    """``stats.collapse_rate`` of the run's training return (``return_mean``: the last 100 episodes of the
    exploring policy, on every logged iteration up to ``until``): how often training falls below half its best so
    far, the swings that the deterministic evaluation's own collapse rate sets apart from exploration noise."""
    pts = sorted((r["iter"], r["return_mean"]) for r in run.metrics
                 if r["iter"] <= until and is_number(r.get("return_mean")))
    curve = stats.Curve(task=run.task, arm="", seed=0, path=str(run.path), last_iter=until, key="return_mean",
                        iters=np.array([p[0] for p in pts], dtype=np.int64),
                        returns=np.array([p[1] for p in pts], dtype=np.float64))
    return stats.collapse_rate(curve)


def _swings_lines(runs: Sequence[Run], label: Callable[[Run], str], until: int) -> list[str]:
    rows = []
    for arm, rs in _by_arm(runs, label).items():
        rates = {r.seed: training_collapse_rate(r, until) for r in rs}
        defined = [v for v in rates.values() if not np.isnan(v)]
        rows.append([arm, f"{np.mean(defined):.2f}" if defined else "-",
                     ", ".join(f"s{s}: {'-' if np.isnan(v) else f'{v:.2f}'}" for s, v in rates.items())])
    if not rows:
        return []
    return [f"Swings of the training return up to iteration {until}: the fraction of logged iterations, after the "
            "first positive best, whose training return (last 100 episodes of the exploring policy) is below half "
            "its best so far.", "", *markdown_table(["arm", "training-return collapse rate: mean", "per seed"], rows),
            ""]


def _by_arm(runs: Sequence[Run], label: Callable[[Run], str]) -> dict[str, list[Run]]:
    """Arm -> its runs, arms and runs in :func:`in_arm_order`."""
    by: dict[str, list[Run]] = {}
    for r in in_arm_order(runs, label):
        by.setdefault(label(r), []).append(r)
    return by


def _arms_table(runs: Sequence[Run], label: Callable[[Run], str]) -> list[str]:
    rows = []
    for arm, rs in _by_arm(runs, label).items():
        r0 = rs[0]
        raster = "-" if r0.mode in IMAGELESS_MODES else r0.config.get("raster_model")
        tasks = {}
        for r in rs:
            tasks.setdefault(r.task, []).append(r)
        runs_text = "; ".join(f"{t}: seeds {', '.join(str(r.seed) for r in sorted(x, key=lambda r: str(r.seed)))}, "
                              f"{_span(r.metrics[-1]['iter'] for r in x if r.metrics)} iterations"
                              for t, x in tasks.items())
        rows.append([arm, r0.mode, raster, r0.setting("preset") or "-", runs_text])
    return [*markdown_table(["arm", "mode", "raster model", "preset", "runs"], rows), ""]


# ----------------------------------------------------------------------------------------------- probes
@dataclass(frozen=True)
class ArmProbes:
    """One arm's probe statistics on one task over the probes where its policy looks: ``looking`` / ``probes``
    per seed, ``medians`` PROBE_KEYS key -> median pooled over every seed's looking probes (None without any),
    ``counts`` how many probes that pooled, ``all_cos``: the median cos(full, decoupled) over every probe (to
    set beside the looking one); ``blind``: per seed, its blind phase (``stats.blind_phase``)."""

    task: str
    arm: str
    looking: dict[int, int]
    probes: dict[int, int]
    medians: dict[str, float | None]
    counts: dict[str, int]
    all_cos: float | None
    blind: dict[int, stats.BlindPhase] = field(default_factory=dict)


def _with_ratios(rows: list[dict]) -> list[dict]:
    """Metrics lines with the PROBE_KEYS ratios ``a/b`` added where both are positive numbers."""
    ratios = [k for k in PROBE_KEYS if "/" in k]
    out = []
    for row in rows:
        extra = {}
        for k in ratios:
            a, b = (row.get(x) for x in k.split("/"))
            if is_number(a) and is_number(b) and b > 0:
                extra[k] = a / b
        out.append({**row, **extra} if extra else row)
    return out


def arm_probes(runs: Sequence[Run], *, label: Callable[[Run], str] | None = None,
               fraction: float = stats.LOOKING_FRACTION) -> list[ArmProbes]:
    """Per (task, arm) with probes, :class:`ArmProbes` (looking: ``stats.looking_probes`` with ``fraction``)."""
    label = label or arm_label(runs)
    groups: dict[tuple[str, str], list[Run]] = {}
    for r in in_arm_order(runs, label):
        groups.setdefault((r.task, label(r)), []).append(r)
    out = []
    for (task, arm), rs in groups.items():
        looks = {r.seed: stats.looking_probes(_with_ratios(r.metrics), fraction=fraction, keys=list(PROBE_KEYS))
                 for r in rs}
        if not any(look.n_probes for look in looks.values()):
            continue
        pooled = {k: [v for look in looks.values() for v in look.values.get(k, ())] for k in PROBE_KEYS}
        every = [m["cos_full_decoupled"] for r in rs for m in r.metrics if is_number(m.get("cos_full_decoupled"))]
        out.append(ArmProbes(task, arm, {s: look.n_looking for s, look in looks.items()},
                             {s: look.n_probes for s, look in looks.items()},
                             {k: float(median(v)) if v else None for k, v in pooled.items()},
                             {k: len(v) for k, v in pooled.items()}, float(median(every)) if every else None,
                             {s: stats.blind_phase(look) for s, look in looks.items() if look.n_probes}))
    return out


def _blind_count(b: stats.BlindPhase) -> str:
    # a first probe of 0 sets no bar (lowest is None): nothing can be called blind or looking
    return f"-/{b.probes}" if b.lowest is None else f"{b.blind}/{b.probes}"


def _looks_again(b: stats.BlindPhase) -> str:
    if b.lowest is None:
        return "no bar (first probe 0)"
    if not b.blind:
        return "never blind"
    return str(b.looks_again_at) if b.looks_again_at is not None else f"still blind at its last probe ({b.last_blind})"


def _blind_phase_lines(found: Sequence[ArmProbes], fraction: float) -> list[str]:
    """The blind-phase table: per arm, how deep and how long its policies stopped looking early in training."""
    rows = []
    for p in found:
        phases = {s: b for s, b in p.blind.items() if b.probes}
        if not phases:
            continue
        lowest = [b.lowest for b in phases.values() if b.lowest is not None]
        rows.append([p.task, p.arm, ", ".join(f"s{s}: {_blind_count(b)}" for s, b in phases.items()),
                     (f"{median(lowest):.2g} " if lowest else "- ") + "(" + ", ".join(
                         f"s{s}: {'-' if b.lowest is None else f'{b.lowest:.2g}'}" for s, b in phases.items()) + ")",
                     ", ".join(f"s{s}: {_looks_again(b)}" for s, b in phases.items()),
                     ", ".join(f"s{s}: {'-' if b.last_blind is None else b.last_blind}" for s, b in phases.items())])
    if not rows:
        return []
    return [f"**The blind phase** (the first {stats.BLIND_PHASE_ITERS} iterations, probes after the first): on how "
            f"many probes the policy did not look (sensitivity at most {fraction:g} x the first probe's), the lowest "
            "sensitivity relative to the first probe (median over seeds, then each seed), the probe at which it first "
            "looked again, and its last blind probe (it may look again and stop once more).", "",
            *markdown_table(["task", "arm", "blind probes / probes", "lowest sensitivity / first",
                             "looks again at iteration", "last blind probe"], rows), ""]


def probe_section(runs: Sequence[Run], base: Path, *, label: Callable[[Run], str] | None = None,
                  plots: PlotResult | None = None, fraction: float = stats.LOOKING_FRACTION,
                  heading: str = "## 4. Gradient probes where the policy looks") -> list[str]:
    """The probe statistics over looking probes (:func:`arm_probes`) and ``plots``' PROBE_FIGURES (links
    relative to ``base``)."""
    out = [heading, ""]
    found = arm_probes(runs, label=label, fraction=fraction) if runs else []
    if not found:
        return [*out, "No run has probe iterations with image sensitivity (`image_sensitivity_f<i>`; full and "
                "decoupled runs with --cosine-every > 0 log them).", ""]
    out += ["On probe iterations the trainer computes the full gradient (through the renderer) and the decoupled "
            "one (the image input detached) of the same rollout, and for full runs also the full gradient through "
            "the other raster model (hard against soft). A probe counts here when the policy looks at its image: "
            f"its image sensitivity (|d mean action / d frame| summed over the frames) is above {fraction:g} x the "
            "run's first probe's (the untrained policy's). Medians pool the looking probes of every seed (n: how "
            "many carried the value); the last column sets the cosine over every probe beside it.", ""]
    rows = []
    for p in found:
        counts = ", ".join(f"s{s}: {p.looking[s]}/{p.probes[s]}" for s in p.looking)
        cells = [f"{p.medians[k]:.3g} (n={p.counts[k]})" if p.medians[k] is not None else "-" for k in PROBE_KEYS]
        rows.append([p.task, p.arm, f"{sum(p.looking.values())}/{sum(p.probes.values())} ({counts})", *cells,
                     f"{p.all_cos:.3g}" if p.all_cos is not None else "-"])
    out += markdown_table(["task", "arm", "looking probes / probes", *(f"median {c}" for c in PROBE_KEYS.values()),
                           "median cos(full, decoupled), every probe"], rows)
    out.append("")
    out += _blind_phase_lines(found, fraction)
    if plots is not None:
        out += figure_lines(plots, PROBE_FIGURES, base)
    return out
