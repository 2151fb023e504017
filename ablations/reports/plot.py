"""Training curves of run folders, per task and mode, mean +- std across seeds: ``ablate-plot RUN_DIR... --out DIR``.

Runs are grouped by task and label from their config.json; each group (an "arm") is one line in one panel per
task. The label is the mode, followed in brackets by the values of ``preset``, ``raster_model`` and ``renderer``
that differ between the given runs of that mode (``full (hard)`` beside ``full (alpha)``). Every arm has a style
of its own, the same in every figure: a colour (its mode's, a darker or lighter shade for a further variant of
the mode), a line style and a marker, so no two arms look alike and a line lying exactly under another still
shows through the other's dashes and markers. Series with few points (probe iterations, every K-th) are marked
at every point; denser ones at about a dozen points, shifted per arm. One legend per figure, right of the panels;
it gives each arm's number of runs n (per panel, left to right, where the panels differ: ``n=2/1``).

Curves are aligned on iteration or environment steps and linearly interpolated onto a common grid on the wall
clock (seeds never finish iterations at the same second). Every run is drawn over its own range: where all of an
arm's runs cover the x the arm's line is full, where fewer do (runs of different lengths) it goes on thin and
dotted with "n=k" where the count changes. The band is +- one sample standard deviation across the runs at that
point, drawn where 2 or more cover it. An arm with two runs of one task and seed is not averaged (one seed would
count twice): ``ablate-plot`` refuses it with one error line naming the runs, a report leaves that arm out of its
figures and names it; any arm a figure cannot draw (no data for it) is named in one line per figure.
Quantities plotted on a log axis (gradient norms, 1 - cosine) are averaged in log space: the
line is the geometric mean and the band multiplies/divides by the geometric standard deviation. Linear axes
print plain tick values (no offset such as ``1e-5+9.9999e-1``).

Return figures draw the training return (mean of the last 100 episodes, lines) and the deterministic evaluation
return (metrics ``eval_return_mean`` +- ``eval_return_std`` over its episodes; ``eval_return`` alone in older
runs) of every run as star markers in the arm's colour, and the task's zero-action and random-action return
floors as labelled horizontal lines (``task-floors``' JSON: docs/floors.json of this checkout, or ``--floors
FILE``); a task without an entry is drawn without them and named in one warning.

Files (PNG, written atomically, with fixed metadata so that unchanged data gives the same bytes; a figure without
data is skipped and the reason returned):
    return_vs_env_steps.png  return_vs_wall_clock.png  return_vs_iter.png  grad_norm.png  cosine_hist.png
    cosine_vs_iter.png  probe_grad_norms.png (full, decoupled and render-term norms of the same rollout)
    render_term_groups.png (the render term by the actor's parameter groups)
    image_sensitivity.png (the policy's sensitivity to each frame of its stack)
    eval_return_vs_iter.png (the deterministic evaluation return, every seed and the mean)
    exploration_noise.png (mean exp(log_std))  looking.png (image sensitivity relative to the first probe, with
    the bar above which the policy counts as looking: ``ablations.reports.stats.LOOKING_FRACTION``)
    timing.png (forward and backward ms per iteration)  memory.png (peak allocated MB; CPU: saved for backward)

:func:`build_figures` returns the matplotlib Figures without writing them (to inspect or restyle them);
:func:`make_plots` writes them.
"""


from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from ablations.reports.seed_figures import plot_performance_profiles
from ablations.reports.stats import LOOKING_FRACTION, looking_probes
from ablations.reports.style import (
    FLOOR_LINES,
    MARKERS,
    Aggregate,
    FigureSet,
    Floors,
    PlotResult,
    aggregate,
    arm_styles,
    group_runs,
    load_floors,
    plain_tick_labels,
    save_figure,
)
from ablations.run_folder import Run, find_runs, is_number, say_metrics_notes

# plot_performance_profiles (ablations.reports.seed_figures) is importable from here beside the other figures.
__all__ = ["PlotConfig", "make_plots", "build_figures", "FIGURES", "RENDER_TERM_GROUPS", "plot_runs",
           "plot_performance_profiles"]

_EVAL = ("Stars: the deterministic evaluation return of each run (bar: +- std over its evaluation episodes, "
         "where recorded); dotted and dash-dotted lines: the zero- and random-action return floors.")
#: File name -> caption of every figure ``make_plots`` can write.
FIGURES = {
    "return_vs_env_steps.png": "Training return (mean of the last 100 episodes) against environment steps. " + _EVAL,
    "return_vs_wall_clock.png": "Training return against wall-clock training time (interpolated across seeds). "
                                + _EVAL,
    "return_vs_iter.png": "Training return against training iterations. " + _EVAL,
    "grad_norm.png": "Actor gradient norm before clipping (log scale; geometric mean x/÷ geometric std).",
    "cosine_hist.png": "1 - cosine between the full and the decoupled gradient of the same rollout (log scale: "
                       "0 is the same direction, 1 orthogonal, 2 opposite; probe iterations, all seeds pooled).",
    "cosine_vs_iter.png": "1 - cos(full, decoupled) over training (log scale; geometric mean x/÷ geometric std).",
    "probe_grad_norms.png": "Norms of the full and the decoupled actor gradient of the same rollout, and of the "
                            "render term (full minus decoupled: the path through the renderer), on probe "
                            "iterations (log scale).",
    "render_term_groups.png": "The render term's norm by the actor's parameter groups (encoder, MLP, log-std; "
                              "their squares sum to the total's), on probe iterations (log scale).",
    "image_sensitivity.png": "How much the policy's mean action depends on each frame of its stack (oldest "
                             "first): norm of d(sum of mean actions)/d(frame), averaged over environments, on "
                             "probe iterations (log scale).",
    "timing.png": "Forward (rollout + render + loss) and backward time per iteration (geometric mean across "
                  "seeds; probe iterations, which compute both gradients, left out).",
    "memory.png": "Peak memory per iteration (CUDA: peak allocated; CPU: bytes saved for backward; probe "
                  "iterations left out).",
    "eval_return_vs_iter.png": "Deterministic evaluation return (the policy's mean action from the fixed "
                               "evaluation seed) against training iterations: thin lines each seed, the thick "
                               "line the mean across seeds (+- one standard deviation shaded).",
    "exploration_noise.png": "Exploration noise: the policy's mean standard deviation exp(log_std) per "
                             "iteration (mean +- one standard deviation across seeds).",
    "looking.png": "Image sensitivity (summed over the frames) relative to the run's first probe, on probe "
                   "iterations (log scale; geometric mean x/÷ geometric std across seeds). Below the dashed "
                   "line the policy does not look at its image (the blind phase); probe statistics marked "
                   "'looking' count only the probes above it.",
}

_EVAL_MARKER = "*"
#: Series with at most this many points are marked at every point (probe iterations); denser ones about every
#: ``len / _MARKS``-th point.
_MARK_ALL = 30
_MARKS = 12
#: 1 - cos below float64's resolution near 1 (rounding can even make it negative) is drawn at this value.
_COS_FLOOR = float(np.finfo(np.float64).eps)
#: The actor's parameter groups of the render-term probe (metrics keys grad_norm_render_term_<group>).
RENDER_TERM_GROUPS = ("encoder", "mlp", "log_std")


@dataclass
class PlotConfig:
    """Plot return, gradient norm, cosine(full, decoupled), time and memory of run folders, per task and mode,
    mean +- std across seeds."""

    runs: tyro.conf.Positional[tuple[Path, ...]] = ()
    """Run folders written by `ablate` (a folder holding run folders stands for all of them)."""
    out: Path = Path("plots")
    """Folder for the PNG files."""
    floors: Path | None = None
    """task-floors JSON with the zero- and random-action return floors; None: docs/floors.json of this checkout."""


def _frame_keys(runs: list[Run]) -> list[str]:
    """The image_sensitivity_f<i> keys present in the runs, by frame index."""
    keys = {k for r in runs for m in r.metrics for k in m if k.startswith("image_sensitivity_f")}
    return sorted(keys, key=lambda k: int(k.rsplit("f", 1)[1]) if k.rsplit("f", 1)[1].isdigit() else 99)


def _relative_sensitivity(run: Run) -> tuple[np.ndarray, np.ndarray]:
    """(probe iterations, image sensitivity summed over the frames / the first probe's) of a run."""
    look = looking_probes(run.metrics, keys=())
    if not look.n_probes or not look.initial:
        return np.array([]), np.array([])
    return np.array(look.probe_iters, float), np.array(look.sensitivity) / look.initial


def _markevery(points: int, arm: int, arms: int):
    """Every point of a sparse series; about ``_MARKS`` of a dense one, shifted per arm so that the markers of
    lines lying on each other fall on different points."""
    if points <= _MARK_ALL:
        return None
    step = math.ceil(points / _MARKS)
    return (arm * step // max(arms, 1)) % step, step


#: Colours of the quantities of a multi-quantity figure (probe norms, render-term groups, frames).
_QUANTITY_COLORS = ("tab:purple", "tab:orange", "tab:cyan", "tab:olive", "tab:brown", "tab:pink")


class _Drawer:
    """Draws the FIGURES of some runs into a FigureSet; one method per kind of figure."""

    def __init__(self, runs: list[Run], floors: Floors, label: Callable[[Run], str] | None, *,
                 shared_seed: str = "leave out"):
        self.runs = runs
        self.floors = floors
        self.out = FigureSet()
        self.figure = ""
        self.groups = group_runs(runs, label=label)
        for (task, lab), rs in list(self.groups.items()):
            if shared_seed == "keep newest":
                self.groups[(task, lab)] = self._newest_per_seed(task, lab, rs)
                continue
            seen: dict[str, Run] = {}
            for r in rs:
                if str(r.seed) in seen:
                    msg = (f"arm {lab!r} has two runs of task {task!r} with seed {r.seed}: {seen[str(r.seed)].path} "
                           f"and {r.path}; give one folder per seed")
                    if shared_seed == "refuse":
                        raise ValueError(msg)
                    # as the seed statistics do: an arm whose runs share a seed is not averaged as seeds
                    self.out.left_out.append(f"left out of every figure: {msg}")
                    del self.groups[(task, lab)]
                    break
                seen[str(r.seed)] = r
        self.styles = arm_styles(self.groups)
        self.arm_index = {lab: i for i, lab in enumerate(self.styles)}
        self.runs = [r for rs in self.groups.values() for r in rs]
        self.tasks = list(dict.fromkeys(t for t, _ in self.groups))

    def _newest_per_seed(self, task: str, lab: str, rs: list[Run]) -> list[Run]:
        """One run per seed: the one that started last (config.json's started_utc, then the folder's path); each
        other one is named in ``left_out`` (a seed counted twice would be averaged as two seeds)."""
        by_seed: dict[str, list[Run]] = {}
        for r in rs:
            by_seed.setdefault(str(r.seed), []).append(r)
        kept = []
        for seed, same in by_seed.items():
            newest = max(same, key=lambda r: (r.started_utc or "", str(r.path)))
            kept.append(newest)
            for r in same:
                if r is not newest:
                    self.out.left_out.append(f"left out of every figure: {r.path} (arm {lab!r} of task {task!r} has "
                                             f"another run of seed {seed}, {newest.path}, started later; it is drawn)")
        return [r for r in rs if any(r is k for k in kept)]

    # ------------------------------------------------------------------------------------------ pieces
    def panels(self, nrows: int = 1):
        import matplotlib.pyplot as plt

        return plt.subplots(nrows, len(self.tasks), figsize=(4.6 * len(self.tasks), 3.4 * nrows), squeeze=False,
                            layout="constrained")

    def arms_of(self, task: str, modes: tuple[str, ...] | None = None):
        """(label, runs) of the task's arms, optionally only those of ``modes``."""
        for (t, lab), rs in self.groups.items():
            if t == task and (modes is None or rs[0].mode in modes):
                yield lab, rs

    def band(self, ax, agg: Aggregate, rs: list[Run], lab: str, *, task: str, color=None,
             marker: str | None = None, lw: float = 1.5, ms: float = 4.5) -> None:
        """The aggregated curve of an arm in its style (``color``/``marker`` replace the arm's): the full line
        where the most runs cover the x, a thin dotted one where fewer do (runs of different lengths, each over
        its own range), "n=k" where the count changes, and the +-1 std band where 2 or more runs cover it."""
        gx, centre, low, high, n = agg
        style = self.styles[lab]
        color = style.color if color is None else color
        most = int(n.max())
        full = n == most
        if not full.all():
            ax.plot(gx, centre, color=color, ls=":", lw=max(lw * 0.6, 0.8), label=f"_{lab} (fewer runs)",
                    gid="fewer runs")
            change = [i for i in range(len(n)) if i == 0 or n[i] != n[i - 1]]
            for i in change:
                ax.annotate(f"n={int(n[i])}", (gx[i], centre[i]), xytext=(2, 3), textcoords="offset points",
                            fontsize=6, color=color, gid="count")
        ax.plot(gx, np.where(full, centre, np.nan), color=color, ls=style.linestyle, lw=lw,
                marker=marker or style.marker, ms=ms, mfc="none", mew=1.1,
                markevery=_markevery(len(gx), self.arm_index[lab], len(self.styles)), label=lab, gid="arm")
        if most > 1:
            ax.fill_between(gx, low, high, where=n >= 2, color=color, alpha=0.15, lw=0)
        drawn = self.out.drawn.setdefault(self.figure, {})
        lo_x, hi_x, k = drawn.get((task, lab), (float(gx[0]), float(gx[-1]), most))
        drawn[(task, lab)] = (min(lo_x, float(gx[0])), max(hi_x, float(gx[-1])), max(k, most))

    def leave_out(self, missing: list[str], why: str) -> None:
        """One line naming the arms the current figure could not draw, and why."""
        if missing:
            self.out.left_out.append(f"{self.figure}: left out {', '.join(missing)} ({why})")

    def arm_handle(self, lab: str, *, color=None, marker: bool = True):
        from matplotlib.lines import Line2D

        style = self.styles[lab]
        return Line2D([], [], color=style.color if color is None else color, ls=style.linestyle, lw=1.5,
                      marker=style.marker if marker else None, ms=4.5, mfc="none", mew=1.1)

    def arm_label(self, lab: str, runs: dict[str, int], probes: dict[str, int] | None = None) -> str:
        """``decoupled (n=2)`` from {task: runs drawn}; where the panels differ, their numbers left to right:
        ``decoupled (n=2/1)``; ``probes``: {task: probe iterations pooled}, added the same way."""

        def per_panel(values: dict[str, int]) -> str:
            nums = [values[t] for t in self.tasks if t in values]
            return str(nums[0]) if len(set(nums)) == 1 else "/".join(map(str, nums))

        return f"{lab} (n={per_panel(runs)}" + (f", {per_panel(probes)} probes)" if probes else ")")

    @staticmethod
    def legend(fig, handles: list, labels: list[str], *, title: str | None = None) -> None:
        """One legend for the figure, right of its panels; the figure is widened by the legend's width, so the
        panels keep theirs."""
        if any(ln.get_gid() == "fewer runs" for ax in fig.axes for ln in ax.lines):
            from matplotlib.lines import Line2D

            handles = [*handles, Line2D([], [], color="0.35", ls=":", lw=0.9)]
            labels = [*labels, "dotted: fewer of the arm's runs\ncover it (n where it changes)"]
        leg = fig.legend(handles, labels, loc="outside right upper", fontsize=8, title=title, title_fontsize=8,
                         alignment="left", handlelength=3.2)
        width = leg.get_window_extent(fig.canvas.get_renderer()).width / fig.dpi
        fig.set_figwidth(fig.get_figwidth() + width + 0.15)

    def floor_lines(self, ax, task: str) -> None:
        """The task's floors as horizontal lines, named in the margin right of the panel, where no data lies
        (the higher one's name above its line, the lower one's below)."""
        floors = self.floors.of(task) or {}
        top = max((s["mean"] for s in floors.values()), default=0.0)
        for policy, stats in floors.items():
            style, name = FLOOR_LINES[policy]
            y = stats["mean"]
            ax.axhline(y, color="0.15", ls=style, lw=1.0, zorder=1.5, label=f"{name} floor ({y:.4g})",
                       gid=f"floor:{policy}")
            above = y == top
            ax.annotate(f"{name}\nfloor {y:.4g}", xy=(1.0, y), xycoords=("axes fraction", "data"),
                        xytext=(3, 1 if above else -1), textcoords="offset points", ha="left",
                        va="bottom" if above else "top", fontsize=7, color="0.15", annotation_clip=False)

    def evaluations(self, ax, task: str, x: str) -> dict[str, int]:
        """Every run's deterministic evaluations as stars in its arm's colour (+- std over the evaluation's
        episodes, where recorded); returns {arm: number of runs drawn}."""
        drawn: dict[str, int] = {}
        for lab, rs in self.arms_of(task):
            color = self.styles[lab].color
            for r in rs:
                ex, ey, es = r.evaluations(x)
                if not len(ex):
                    continue
                yerr = np.nan_to_num(es) if np.isfinite(es).any() else None
                bars = ax.errorbar(ex, ey, yerr=yerr, ls="none", marker=_EVAL_MARKER, ms=11, color=color, mec="k",
                                   mew=0.6, elinewidth=1.2, capsize=3, zorder=3, label=f"_evaluation {lab}")
                bars.lines[0].set_gid("evaluation")
                drawn[lab] = drawn.get(lab, 0) + 1
        return drawn

    def finish(self, ax, title: str, xlabel: str, *, log: bool = False) -> None:
        ax.set_title(title)
        ax.set_xlabel(xlabel)
        if log:
            ax.set_yscale("log")
        ax.grid(True, alpha=0.3)
        plain_tick_labels(ax)

    def keep(self, name: str, fig, drawn: bool, why: str) -> None:
        if drawn:
            self.out.figures[name] = fig
        else:
            import matplotlib.pyplot as plt

            plt.close(fig)
            self.out.skipped[name] = why

    # ------------------------------------------------------------------------------------------ figures
    def curves(self, name: str, x: str, y: str, *, xlabel: str, ylabel: str, log: bool = False,
               modes: tuple[str, ...] | None = None, skip_probed: bool = False, returns: bool = False,
               transform: Callable[[np.ndarray], np.ndarray] | None = None,
               series_of: Callable[[Run], tuple[np.ndarray, np.ndarray]] | None = None, each_run: bool = False,
               floors: bool | None = None, hline: tuple[float, str] | None = None) -> None:
        """One line per arm and panel per task; ``returns``: with every run's evaluations and the floors.
        ``series_of``: a run's (x, y) instead of its metrics ``x`` and ``y``; ``each_run``: every run's own curve
        too, thin, under the arm's; ``floors``: the return floors (default: with ``returns``); ``hline``: a
        dashed reference line (y, its legend text)."""
        from matplotlib.lines import Line2D

        self.figure = name
        fig, axes = self.panels()
        drawn: dict[str, dict[str, int]] = {}
        missing: list[str] = []
        evaluated = False
        for col, task in enumerate(self.tasks):
            ax = axes[0][col]
            for lab, rs in self.arms_of(task, modes):
                series = [series_of(r) if series_of else r.series(x, y, skip_probed=skip_probed) for r in rs]
                series = [(sx, transform(sy)) for sx, sy in series] if transform else series
                agg = aggregate(series, log=log)
                if agg is not None:
                    if each_run:
                        for sx, sy in series:
                            ax.plot(sx, sy, color=self.styles[lab].color, lw=0.8, alpha=0.45, marker=".", ms=3,
                                    label=f"_run {lab}", gid="run")
                    self.band(ax, agg, rs, lab, task=task, lw=2.2 if each_run else 1.5)
                    drawn.setdefault(lab, {})[task] = len(rs)
                else:
                    missing.append(f"{task} {lab}")
            if returns:
                for lab, n in self.evaluations(ax, task, x).items():
                    drawn.setdefault(lab, {}).setdefault(task, n)
                    evaluated = True
            if returns if floors is None else floors:
                self.floor_lines(ax, task)
            if hline is not None:
                ax.axhline(hline[0], color="0.15", ls="--", lw=1.0, zorder=1.5, gid="reference")
            self.finish(ax, task, xlabel, log=log)
        axes[0][0].set_ylabel(ylabel)
        labs = [lab for lab in self.styles if lab in drawn]
        handles = [self.arm_handle(lab) for lab in labs]
        labels = [self.arm_label(lab, drawn[lab]) for lab in labs]
        if evaluated:
            handles += [Line2D([], [], color="0.35", lw=1.5),
                        Line2D([], [], ls="none", marker=_EVAL_MARKER, ms=11, color="0.6", mec="k", mew=0.6)]
            labels += ["line: training return (last 100 episodes)", "star: deterministic evaluation (each run)"]
        if each_run:
            handles.append(Line2D([], [], color="0.35", lw=0.8, alpha=0.45, marker=".", ms=3))
            labels.append("thin: each seed")
        if hline is not None:
            handles.append(Line2D([], [], color="0.15", ls="--", lw=1.0))
            labels.append(hline[1])
        if drawn:
            self.legend(fig, handles, labels)
            self.leave_out(missing, f"no run of theirs has both {x} and {y}")
        self.keep(name, fig, bool(drawn), f"no run has both {x} and {y}")

    def quantities(self, name: str, keys: dict[str, str], *, ylabel: str, why: str) -> None:
        """One panel per task, one line per (arm, metrics key): colour and marker = the key, line style = the
        arm's; the first key's line and markers are the widest, so a later one lying on it leaves it visible at
        its edges."""
        from matplotlib.lines import Line2D

        present = [k for k in keys if any(is_number(m.get(k)) for r in self.runs for m in r.metrics)]
        if not present:
            self.out.skipped[name] = why
            return
        colors = dict(zip(present, _QUANTITY_COLORS * len(present)))
        markers = dict(zip(present, MARKERS * len(present)))
        self.figure = name
        fig, axes = self.panels()
        drawn: dict[str, dict[str, int]] = {}
        missing: list[str] = []
        for col, task in enumerate(self.tasks):
            ax = axes[0][col]
            for lab, rs in self.arms_of(task):
                for i, k in enumerate(present):
                    agg = aggregate([r.series("iter", k) for r in rs], log=True)
                    if agg is not None:
                        self.band(ax, agg, rs, lab, task=task, color=colors[k], marker=markers[k],
                                  lw=max(3.2 - i, 1.2), ms=max(7.0 - 1.5 * i, 4.5))
                        drawn.setdefault(lab, {})[task] = len(rs)
                if task not in drawn.get(lab, {}):
                    missing.append(f"{task} {lab}")
            self.finish(ax, task, "iteration", log=True)
        axes[0][0].set_ylabel(ylabel)
        if drawn:
            handles = [Line2D([], [], color=colors[k], lw=1.5, marker=markers[k], ms=4.5, mfc="none", mew=1.1)
                       for k in present]
            handles += [self.arm_handle(lab, color="0.2", marker=False) for lab in self.styles if lab in drawn]
            labels = [keys[k] for k in present]
            labels += [self.arm_label(lab, drawn[lab]) for lab in self.styles if lab in drawn]
            self.legend(fig, handles, labels, title="colour and marker: quantity\nline style: runs")
            self.leave_out(missing, why.replace("no run has", "no run of theirs has"))
        self.keep(name, fig, bool(drawn), why)

    def cosine_hist(self) -> None:
        """1 - cos of every probe of every seed pooled (the distribution, not a curve), two bins per decade."""
        self.figure = "cosine_hist.png"
        fig, axes = self.panels()
        values = {(t, lab): np.clip(1.0 - np.concatenate([r.series("iter", "cos_full_decoupled")[1] for r in rs]),
                                    _COS_FLOOR, None) for (t, lab), rs in self.groups.items()}
        values = {k: v for k, v in values.items() if len(v)}
        drawn: dict[str, dict[str, int]] = {}
        probes: dict[str, dict[str, int]] = {}
        if values:
            lo = math.floor(math.log10(min(float(v.min()) for v in values.values())))
            hi = math.log10(max(2.0, *(float(v.max()) for v in values.values())))
            bins = np.logspace(lo, hi, max(2 * math.ceil(hi - lo), 8) + 1)  # two bins per decade
        for col, task in enumerate(self.tasks):
            ax = axes[0][col]
            for lab, rs in self.arms_of(task):
                if (task, lab) not in values:
                    continue
                style = self.styles[lab]
                # Outlines, not filled bars: the arms' histograms overlap.
                ax.hist(values[task, lab], bins=bins, color=style.color, ls=style.linestyle, histtype="step",
                        lw=1.6, label=lab)
                drawn.setdefault(lab, {})[task] = len(rs)
                probes.setdefault(lab, {})[task] = len(values[task, lab])
            ax.set_xscale("log")
            from matplotlib.ticker import MaxNLocator

            ax.yaxis.set_major_locator(MaxNLocator(integer=True))
            self.finish(ax, task, "1 - cos(full, decoupled)  (0: same direction, 1: orthogonal)")
        axes[0][0].set_ylabel("probe iterations")
        if drawn:
            labs = [lab for lab in self.styles if lab in drawn]
            self.legend(fig, [self.arm_handle(lab, marker=False) for lab in labs],
                        [self.arm_label(lab, drawn[lab], probes[lab]) for lab in labs])
            self.leave_out([f"{t} {lab}" for t, lab in self.groups if (t, lab) not in values],
                           "no probe iterations: runs of modes that render nothing have none")
        self.keep("cosine_hist.png", fig, bool(drawn), "no run has probe iterations (cos_full_decoupled)")

    def timing(self) -> None:
        """Forward and backward time per iteration, two rows; a log axis where a panel spans a decade."""
        self.figure = "timing.png"
        fig, axes = self.panels(2)
        drawn: dict[str, dict[str, int]] = {}
        for row, (key, name) in enumerate((("fwd_ms", "forward"), ("bwd_ms", "backward"))):
            for col, task in enumerate(self.tasks):
                ax = axes[row][col]
                spans: list[float] = []
                for lab, rs in self.arms_of(task):
                    agg = aggregate([r.series("iter", key, skip_probed=True) for r in rs], log=True)
                    if agg is None:
                        continue
                    spans += [float(agg[1].min()), float(agg[1].max())]
                    self.band(ax, agg, rs, lab, task=task)
                    drawn.setdefault(lab, {})[task] = len(rs)
                # warm-up and full vs decoupled often differ by decades; else linear
                log = bool(spans) and min(spans) > 0 and max(spans) >= 10 * min(spans)
                self.finish(ax, f"{task}: {name}", "iteration", log=log)
                ax.grid(True, which="both", alpha=0.3)
            axes[row][0].set_ylabel(f"{name} [ms]")
        if drawn:
            labs = [lab for lab in self.styles if lab in drawn]
            self.legend(fig, [self.arm_handle(lab) for lab in labs], [self.arm_label(lab, drawn[lab]) for lab in labs])
            self.leave_out([f"{t} {lab}" for t, lab in self.groups if t not in drawn.get(lab, {})],
                           "no run of theirs has fwd_ms/bwd_ms")
        self.keep("timing.png", fig, bool(drawn), "no run has fwd_ms/bwd_ms")

    def all(self) -> FigureSet:
        returns = "return"
        for name, x, xlabel in (("return_vs_env_steps.png", "env_steps", "environment steps"),
                                ("return_vs_wall_clock.png", "wall_s", "wall clock [s]"),
                                ("return_vs_iter.png", "iter", "iteration")):
            self.curves(name, x, "return_mean", xlabel=xlabel, ylabel=returns, returns=True)
        self.curves("grad_norm.png", "iter", "grad_norm", xlabel="iteration", ylabel="actor gradient norm (pre-clip)",
                    log=True)
        self.curves("cosine_vs_iter.png", "iter", "cos_full_decoupled", xlabel="iteration",
                    ylabel="1 - cos(full, decoupled)\n(0: same direction, 1: orthogonal)", modes=("full", "decoupled"),
                    log=True, transform=lambda cos: np.clip(1.0 - cos, _COS_FLOOR, None))
        self.quantities("probe_grad_norms.png", {"grad_norm_full": "full gradient",
                                                 "grad_norm_decoupled": "decoupled gradient",
                                                 "grad_norm_render_term": "render term"},
                        ylabel="gradient norm (same rollout)", why="no run has probe iterations (grad_norm_full)")
        self.quantities("render_term_groups.png", {f"grad_norm_render_term_{g}": g for g in RENDER_TERM_GROUPS},
                        ylabel="render-term norm", why="no run has the render term by parameter group "
                                                       "(grad_norm_render_term_encoder/_mlp/_log_std)")
        frame_keys = _frame_keys(self.runs)
        n = len(frame_keys)
        self.quantities("image_sensitivity.png",
                        {k: f"frame {k.rsplit('f', 1)[1]}" + (" (oldest)" if i == 0 and n > 1 else
                                                              " (newest)" if i == n - 1 and n > 1 else "")
                         for i, k in enumerate(frame_keys)},
                        ylabel="|d mean action / d frame|", why="no run has image_sensitivity_f<i>")
        self.curves("eval_return_vs_iter.png", "iter", "eval_return", xlabel="iteration",
                    ylabel="evaluation return\n(deterministic policy)", series_of=lambda r: r.evaluations("iter")[:2],
                    each_run=True, floors=True)
        self.curves("exploration_noise.png", "iter", "action_std", xlabel="iteration",
                    ylabel="exploration noise\n(mean exp(log_std))")
        self.curves("looking.png", "iter", "image_sensitivity", xlabel="iteration",
                    ylabel="image sensitivity /\nits first probe's", log=True, series_of=_relative_sensitivity,
                    hline=(LOOKING_FRACTION, f"looking bar: {LOOKING_FRACTION:g} x the first probe's"))
        self.cosine_hist()
        self.timing()
        # Memory: CUDA peak allocated where any run has it, else what autograd saved (the CPU-visible quantity).
        has_alloc = any(is_number(m.get("peak_alloc_mb")) for r in self.runs for m in r.metrics)
        key, ylabel = ("peak_alloc_mb", "peak allocated [MB] (CUDA)") if has_alloc else \
            ("saved_mb", "saved for backward [MB]")
        self.curves("memory.png", "iter", key, xlabel="iteration", ylabel=ylabel, skip_probed=True)
        return self.out


def build_figures(runs: list[Run], *, floors: Floors | None = None, label: Callable[[Run], str] | None = None,
                  shared_seed: str = "leave out") -> FigureSet:
    """The FIGURES that the runs have data for, as matplotlib Figures (not written; close them with
    ``FigureSet.close``); see the module docstring.

    floors: the return floors (None: :func:`load_floors`'s default file); label: a run's group label (None:
    :func:`run_labels`). A task without floors is named once in ``FigureSet.warnings`` and a UserWarning.
    shared_seed: what to do with an arm that has two runs of one task and seed (averaging them would count one
    seed twice): ``"leave out"`` that arm, named in ``FigureSet.left_out`` (as the seed statistics leave it
    out), ``"refuse"``: ValueError naming the two runs, or ``"keep newest"``: of each seed the run that started
    last, the others named in ``FigureSet.left_out``. Whatever else a figure leaves out is named there too.
    """
    import matplotlib

    matplotlib.use("Agg")
    if shared_seed not in ("leave out", "refuse", "keep newest"):
        raise ValueError(f"shared_seed must be 'leave out', 'refuse' or 'keep newest', got {shared_seed!r}")
    if not runs:
        raise ValueError("no runs to plot")
    floors = load_floors() if floors is None else floors
    drawer = _Drawer(runs, floors, label, shared_seed=shared_seed)
    if not drawer.groups:
        raise ValueError("nothing to plot: " + "; ".join(drawer.out.left_out))
    for task in drawer.tasks:
        if floors.of(task) is None:
            msg = floors.missing_message(task)
            drawer.out.warnings.append(msg)
            warnings.warn(msg, UserWarning, stacklevel=2)
    return drawer.all()


def make_plots(runs: list[Run], out: str | os.PathLike, *, floors: Floors | None = None,
               label: Callable[[Run], str] | None = None, shared_seed: str = "leave out") -> PlotResult:
    """Write the FIGURES that the runs have data for into ``out`` (:func:`build_figures`' arguments)."""
    figures = build_figures(runs, floors=floors, label=label, shared_seed=shared_seed)
    out = Path(out)
    result = PlotResult(skipped=figures.skipped, warnings=figures.warnings, left_out=figures.left_out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        for name, fig in figures.figures.items():
            save_figure(fig, out / name)
            result.files[name] = out / name
    finally:
        figures.close()
    return result


def plot_runs(cfg: PlotConfig) -> PlotResult:
    """``ablate-plot``: the runs of ``cfg.runs`` drawn into ``cfg.out`` with the floors of ``cfg.floors``; of runs
    that share an arm, a task and a seed (the same command run twice) the one that started last is drawn, the others
    named as left out (the seed statistics of ``ablate-report`` refuse them)."""
    if Path(cfg.out).exists() and not Path(cfg.out).is_dir():
        raise ValueError(f"--out {cfg.out} is a file: give the folder the figures go in")
    runs = find_runs(list(cfg.runs))
    say_metrics_notes(runs)  # damaged lines skipped, iterations twice or out of order
    return make_plots(runs, cfg.out, floors=load_floors(cfg.floors), shared_seed="keep newest")
