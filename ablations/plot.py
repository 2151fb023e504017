"""Training curves of run folders, per task and mode, mean +- std across seeds: ``ablate-plot RUN_DIR... --out DIR``.

Runs are grouped by (task, mode) from their config.json; each group is one line (colour = mode) in one panel per
task. Curves are aligned on iteration or environment steps and linearly interpolated onto a common grid on the
wall clock (seeds never finish iterations at the same second), over the range every run of the group covers
(no tail averaged over fewer seeds than the legend says). The band is +- one sample standard deviation across
runs (none for a single run). Quantities plotted on a log axis (gradient norms) are averaged in log space: the
line is the geometric mean and the band multiplies/divides by the geometric standard deviation.

Files (PNG, written atomically; a figure without data is skipped and the reason returned):
    return_vs_env_steps.png  return_vs_wall_clock.png  grad_norm.png  cosine_hist.png  cosine_vs_iter.png
    timing.png (forward and backward ms per iteration)  memory.png (peak allocated MB; CPU: saved for backward)
"""

from __future__ import annotations

import io
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tyro

__all__ = ["PlotConfig", "Run", "load_run", "find_runs", "group_runs", "aggregate", "make_plots", "PlotResult",
           "FIGURES",
           "MODE_COLORS"]

#: File name -> caption of every figure ``make_plots`` can write.
FIGURES = {
    "return_vs_env_steps.png": "Return (mean of the last 100 episodes) against environment steps.",
    "return_vs_wall_clock.png": "Return against wall-clock training time (interpolated across seeds).",
    "grad_norm.png": "Actor gradient norm before clipping (log scale; geometric mean x/÷ geometric std).",
    "cosine_hist.png": "Cosine between the full and the decoupled gradient of the same rollout (probe "
                       "iterations, all seeds pooled).",
    "cosine_vs_iter.png": "Cosine(full, decoupled) over training.",
    "timing.png": "Forward (rollout + render + loss) and backward time per iteration (geometric mean across "
                  "seeds; probe iterations, which compute both gradients, left out).",
    "memory.png": "Peak memory per iteration (CUDA: peak allocated; CPU: bytes saved for backward; probe "
                  "iterations left out).",
}
MODE_COLORS = {"full": "tab:red", "decoupled": "tab:blue", "state": "tab:green"}
_TASK_ORDER = ("cartpole", "hopper", "ant", "humanoid")


@dataclass
class PlotConfig:
    """Plot return, gradient norm, cosine(full, decoupled), time and memory of run folders, per task and mode,
    mean +- std across seeds."""

    runs: tyro.conf.Positional[tuple[Path, ...]] = ()
    """Run folders written by `ablate` (a folder holding run folders stands for all of them)."""
    out: Path = Path("plots")
    """Folder for the PNG files."""


@dataclass
class Run:
    """One run folder, parsed."""

    path: Path
    config: dict
    environment: dict
    command: list | None
    summary: dict | None
    metrics: list[dict]

    @property
    def task(self) -> str:
        return str(self.config.get("task"))

    @property
    def mode(self) -> str:
        return str(self.config.get("mode"))

    @property
    def seed(self):
        return self.config.get("seed")

    def series(self, x: str, y: str, *, skip_probed: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) of the iterations where both are finite numbers, sorted by x; ``skip_probed`` leaves out
        probe iterations (they differentiate twice, so their times and memory are not the mode's)."""
        pts = [(r[x], r[y]) for r in self.metrics if _num(r.get(x)) and _num(r.get(y))
               and not (skip_probed and r.get("probed"))]
        pts.sort()
        return np.array([p[0] for p in pts], float), np.array([p[1] for p in pts], float)


def _num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def load_run(path: str | os.PathLike) -> Run:
    """Parse a run folder (see ablations/runs.py); ValueError with the reason if it is not one."""
    from ablations.runs import read_metrics

    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: no such folder")
    if not path.is_dir():
        raise ValueError(f"{path} is a file, not a run folder (give the folder that holds config.json)")
    cfg_path = path / "config.json"
    if not cfg_path.exists():
        raise ValueError(f"{path} is not a run folder: it has no config.json (expected config.json, "
                         f"metrics.jsonl, summary.json as written by `ablate`)")
    try:
        data = json.loads(cfg_path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{cfg_path} is not valid JSON: {e}") from None
    if not isinstance(data, dict) or not isinstance(data.get("config"), dict):
        raise ValueError(f"{cfg_path} has no 'config' object: not written by `ablate`")
    config = data["config"]
    for k in ("task", "mode"):
        if k not in config:
            raise ValueError(f"{cfg_path}: config has no {k!r}")
    summary = None
    if (path / "summary.json").exists():
        try:
            summary = json.loads((path / "summary.json").read_text())
        except json.JSONDecodeError:
            summary = None  # summary.json is written atomically: unreadable means a foreign file; ignore it
    return Run(path=path, config=config, environment=data.get("environment") or {}, command=data.get("command"),
               summary=summary, metrics=read_metrics(path))


def find_runs(paths: list[str | os.PathLike] | tuple) -> list[Run]:
    """Runs of the given folders; a folder that is not a run but holds run folders stands for all of them.

    Raises ValueError when no path is given, or a path is neither a run nor a parent of runs.
    """
    if not paths:
        raise ValueError("no run folders given (pass one or more folders written by `ablate`)")
    runs: list[Run] = []
    for p in paths:
        p = Path(p)
        if p.is_dir() and not (p / "config.json").exists():
            children = sorted(c for c in p.iterdir() if c.is_dir() and (c / "config.json").exists())
            if children:
                runs.extend(load_run(c) for c in children)
                continue
        runs.append(load_run(p))
    return runs


def group_runs(runs: list[Run]) -> dict[tuple[str, str], list[Run]]:
    """{(task, mode): runs}, tasks in the paper's order, modes full, decoupled, state."""
    groups: dict[tuple[str, str], list[Run]] = {}
    for r in runs:
        groups.setdefault((r.task, r.mode), []).append(r)

    def order(k: tuple[str, str]) -> tuple:
        t, m = k
        return (_TASK_ORDER.index(t) if t in _TASK_ORDER else 99, t,
                list(MODE_COLORS).index(m) if m in MODE_COLORS else 99, m)

    return {k: sorted(groups[k], key=lambda r: (str(r.seed), str(r.path))) for k in sorted(groups, key=order)}


def aggregate(series: list[tuple[np.ndarray, np.ndarray]], *, log: bool = False
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Mean and +-1 std band of several (x, y) curves on a common x grid.

    The grid is every x of every curve inside the range all curves cover; each curve is linearly interpolated
    onto it (exact where a curve has a point). Returns (x, centre, low, high), or None when the curves share no
    range. ``log``: average log10(y) (y <= 0 dropped): geometric mean and geometric-std band.
    """
    clean = []
    for x, y in series:
        if log:
            keep = y > 0
            x, y = x[keep], np.log10(y[keep])
        if len(x):
            clean.append((x, y))
    if not clean:
        return None
    lo = max(x[0] for x, _ in clean)
    hi = min(x[-1] for x, _ in clean)
    if lo > hi:
        return None
    grid = np.unique(np.concatenate([x[(x >= lo) & (x <= hi)] for x, _ in clean]))
    ys = np.stack([np.interp(grid, x, y) for x, y in clean])
    mean = ys.mean(0)
    std = ys.std(0, ddof=1) if len(clean) > 1 else np.zeros_like(mean)
    low, high = mean - std, mean + std
    if log:
        return grid, 10**mean, 10**low, 10**high
    return grid, mean, low, high


@dataclass
class PlotResult:
    """What ``make_plots`` wrote and what it skipped (file name -> reason)."""

    files: dict[str, Path] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)


def _save(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    from gradlab.checkpoint import atomic_write_bytes

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def make_plots(runs: list[Run], out: str | os.PathLike) -> PlotResult:
    """Write the FIGURES that the runs have data for into ``out``; see the module docstring."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    if not runs:
        raise ValueError("no runs to plot")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    groups = group_runs(runs)
    tasks = list(dict.fromkeys(t for t, _ in groups))
    result = PlotResult()

    def label(mode: str, rs: list[Run]) -> str:
        return f"{mode} (n={len(rs)})"

    def panels(nrows: int = 1):
        fig, axes = plt.subplots(nrows, len(tasks), figsize=(4.6 * len(tasks), 3.4 * nrows), squeeze=False,
                                 layout="constrained")
        return fig, axes

    def curve_figure(name: str, x: str, y: str, *, xlabel: str, ylabel: str, log: bool = False,
                     modes: tuple[str, ...] | None = None, skip_probed: bool = False) -> None:
        fig, axes = panels()
        drawn = False
        for col, task in enumerate(tasks):
            ax = axes[0][col]
            for (t, mode), rs in groups.items():
                if t != task or (modes is not None and mode not in modes):
                    continue
                agg = aggregate([r.series(x, y, skip_probed=skip_probed) for r in rs], log=log)
                if agg is None:
                    continue
                gx, c, lo, hi = agg
                color = MODE_COLORS.get(mode)
                ax.plot(gx, c, color=color, label=label(mode, rs), lw=1.4)
                if len(rs) > 1:
                    ax.fill_between(gx, lo, hi, color=color, alpha=0.2, lw=0)
                drawn = True
            ax.set_title(task)
            ax.set_xlabel(xlabel)
            if log:
                ax.set_yscale("log")
            ax.grid(True, alpha=0.3)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=8)
        axes[0][0].set_ylabel(ylabel)
        if not drawn:
            plt.close(fig)
            result.skipped[name] = f"no run has both {x} and {y}"
            return
        _save(fig, out / name)
        result.files[name] = out / name

    curve_figure("return_vs_env_steps.png", "env_steps", "return_mean", xlabel="environment steps",
                 ylabel="return (last 100 episodes)")
    curve_figure("return_vs_wall_clock.png", "wall_s", "return_mean", xlabel="wall clock [s]",
                 ylabel="return (last 100 episodes)")
    curve_figure("grad_norm.png", "iter", "grad_norm", xlabel="iteration", ylabel="actor gradient norm (pre-clip)",
                 log=True)
    curve_figure("cosine_vs_iter.png", "iter", "cos_full_decoupled", xlabel="iteration",
                 ylabel="cos(full, decoupled)", modes=("full", "decoupled"))

    # Cosine histogram: every probe of every seed pooled (the distribution, not a curve).
    fig, axes = panels()
    drawn = False
    bins = np.linspace(-1, 1, 41)
    for col, task in enumerate(tasks):
        ax = axes[0][col]
        for (t, mode), rs in groups.items():
            vals = [v for r in rs for v in r.series("iter", "cos_full_decoupled")[1]] if t == task else []
            if not vals:
                continue
            # Outlines, not filled bars: the two modes' histograms overlap.
            ax.hist(np.clip(vals, -1, 1), bins=bins, color=MODE_COLORS.get(mode), histtype="step", lw=1.6,
                    label=f"{mode} (n={len(rs)}, {len(vals)} probes)")
            drawn = True
        ax.set_title(task)
        ax.set_xlabel("cos(full, decoupled)")
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(True, alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    axes[0][0].set_ylabel("probe iterations")
    if drawn:
        _save(fig, out / "cosine_hist.png")
        result.files["cosine_hist.png"] = out / "cosine_hist.png"
    else:
        plt.close(fig)
        result.skipped["cosine_hist.png"] = "no run has probe iterations (cos_full_decoupled)"

    # Timing: forward and backward per iteration, two rows.
    fig, axes = panels(2)
    drawn = False
    for row, (key, name) in enumerate((("fwd_ms", "forward"), ("bwd_ms", "backward"))):
        for col, task in enumerate(tasks):
            ax = axes[row][col]
            spans: list[float] = []
            for (t, mode), rs in groups.items():
                if t != task:
                    continue
                agg = aggregate([r.series("iter", key, skip_probed=True) for r in rs], log=True)
                if agg is None:
                    continue
                gx, c, lo, hi = agg
                spans += [float(c.min()), float(c.max())]
                ax.plot(gx, c, color=MODE_COLORS.get(mode), label=label(mode, rs), lw=1.2)
                if len(rs) > 1:
                    ax.fill_between(gx, lo, hi, color=MODE_COLORS.get(mode), alpha=0.2, lw=0)
                drawn = True
            if spans and min(spans) > 0 and max(spans) >= 10 * min(spans):
                ax.set_yscale("log")  # warm-up and full vs decoupled often differ by decades; else linear
            ax.set_title(f"{task}: {name}")
            ax.set_xlabel("iteration")
            ax.grid(True, which="both", alpha=0.3)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=8)
        axes[row][0].set_ylabel(f"{name} [ms]")
    if drawn:
        _save(fig, out / "timing.png")
        result.files["timing.png"] = out / "timing.png"
    else:
        plt.close(fig)
        result.skipped["timing.png"] = "no run has fwd_ms/bwd_ms"

    # Memory: CUDA peak allocated where any run has it, else what autograd saved (the CPU-visible quantity).
    has_alloc = any(_num(m.get("peak_alloc_mb")) for r in runs for m in r.metrics)
    key, ylabel = ("peak_alloc_mb", "peak allocated [MB] (CUDA)") if has_alloc else \
        ("saved_mb", "saved for backward [MB]")
    curve_figure("memory.png", "iter", key, xlabel="iteration", ylabel=ylabel, skip_probed=True)
    return result
