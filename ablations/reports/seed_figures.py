"""The figures of the seed statistics (``ablate-report``'s seed sections): each task's learning curves with the
bootstrap interval of the mean, the paired differences against a reference arm along the training budget, and the
performance profiles. They draw what :mod:`ablations.reports.stats` computes, in the arms' styles of every other
figure (:func:`ablations.reports.style.arm_styles`), into PNGs written atomically."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from ablations.reports.stats import PerformanceProfile
from ablations.reports.style import ArmStyle, draw_band, draw_floor_lines, plain_tick_labels, save_figure

__all__ = ["draw_learning_curves", "draw_difference_curves", "plot_performance_profiles"]


def draw_learning_curves(task: str, bands: dict[str, dict], path: str | os.PathLike, *,
                         floors: dict[str, dict] | None = None, styles: dict[str, ArmStyle] | None = None,
                         confidence: float = 0.95, exact_max_n: int = 10) -> Path:
    """One task's learning curves per arm in two panels, the deterministic **evaluation return** and the
    **training return** (the exploring policy's last 100 episodes), against iterations: arm -> {"evaluation":
    Band, "training": Band} (``ablations.reports.stats.mean_band``), the band the mean's bootstrap interval over seeds
    (shaded where 2 or more runs have the point; a single run's stretch dotted), the zero- and random-action
    floors as horizontal lines; the legend gives each arm's runs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11.0, 3.8), layout="constrained")
    for ax, kind, ylabel in ((axes[0], "evaluation", "evaluation return\n(deterministic policy)"),
                             (axes[1], "training", "training return\n(last 100 episodes, exploring)")):
        for arm, b in bands.items():
            band = b.get(kind)
            if band is not None and band.x.size:
                draw_band(ax, band, (styles or {}).get(arm), f"{arm} (n={int(band.n.max())})")
        draw_floor_lines(ax, floors)
        ax.set_xlabel("iteration")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        plain_tick_labels(ax)
    axes[0].set_title(f"{task}: evaluation return")
    axes[1].set_title(f"{task}: training return")
    fig.suptitle(f"mean over seeds; shaded: {confidence:.0%} bootstrap interval of the mean (exact up to "
                 f"{exact_max_n} seeds)\nwhere 2 or more runs have the point; dotted: a point only one run has",
                 fontsize=8)
    handles, labels = axes[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside right upper", fontsize=8)
    path = Path(path)
    save_figure(fig, path)
    return path


def draw_difference_curves(task: str, curves: dict[tuple[str, str], object], path: str | os.PathLike, *,
                           styles: dict[str, ArmStyle] | None = None, reference: str = "decoupled") -> Path:
    """One task's paired differences against ``reference`` along the training budget
    (``ablations.reports.stats.difference_curves``: (arm, axis) -> DifferenceCurve): a panel in iterations and one in
    modelled wall-clock where given; per arm the mean difference (line), the median (thin, dashed) and the mean's
    interval at each evaluation (shaded), and zero."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes_used = [a for a in ("iteration", "wall-clock") if any(k[1] == a for k in curves)]
    fig, axes = plt.subplots(1, max(len(axes_used), 1), figsize=(5.6 * max(len(axes_used), 1), 3.8), squeeze=False,
                             layout="constrained")
    conf = next(iter(curves.values())).confidence if curves else 0.95
    for ax, axis in zip(axes[0], axes_used):
        for (arm, a), dc in curves.items():
            if a != axis:
                continue
            style = (styles or {}).get(arm)
            look = {"color": style.color} if style is not None else {}
            (line,) = ax.plot(dc.x, dc.mean, lw=1.6, marker="o", ms=3, label=f"{arm} (n={int(dc.n.max())})",
                              gid="mean", ls=style.linestyle if style is not None else "-", **look)
            ax.plot(dc.x, dc.median, lw=0.9, ls="--", color=line.get_color(), gid="median", label=f"_{arm} median")
            ax.fill_between(dc.x, dc.ci_low, dc.ci_high, color=line.get_color(), alpha=0.18, lw=0)
        ax.axhline(0.0, color="0.15", lw=1.0, zorder=1.5)
        ax.set_xlabel("iteration" if axis == "iteration" else "modelled training time [s] (iterations x the arm's "
                      "iteration time alone)")
        ax.set_ylabel(f"final return: arm − {reference}\n(paired by seed)")
        ax.set_title(f"{task}: at equal {'iterations' if axis == 'iteration' else 'wall-clock'}")
        ax.grid(alpha=0.3)
        plain_tick_labels(ax)
    fig.suptitle(f"line: mean paired difference, dashed: median, shaded: {conf:.0%} bootstrap interval of the "
                 "mean\nat each evaluation (pointwise, not corrected for the many budgets)", fontsize=8)
    handles, labels = axes[0][0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside right upper", fontsize=8)
    path = Path(path)
    save_figure(fig, path)
    return path


def plot_performance_profiles(profile: PerformanceProfile, path: str | Path, *,
                              styles: Mapping | None = None) -> Path:
    """Draw one task's profiles (fraction of runs above each threshold, the CI shaded) to a PNG, written
    atomically; the legend sits outside the axes. ``styles``: arm -> ``ablations.reports.style.ArmStyle`` (the arm's
    colour and line style in every other figure); arms it does not name take matplotlib's next colour."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
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
    save_figure(fig, path)
    return path
