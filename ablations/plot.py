"""Training curves of run folders, per task and mode, mean +- std across seeds: ``ablate-plot RUN_DIR... --out DIR``.

Runs are grouped by task and label from their config.json; each group is one line in one panel per task. The
label is the mode, followed in brackets by the values of ``preset``, ``raster_model`` and ``renderer`` that
differ between the given runs of that mode (``full (hard)`` beside ``full (alpha)``); colour = mode, line
style = the variant within the mode. Curves are aligned on iteration or environment steps and linearly
interpolated onto a common grid on the wall clock (seeds never finish iterations at the same second), over the
range every run of the group covers (no tail averaged over fewer seeds than the legend says). The band is +- one
sample standard deviation across runs (none for a single run). Quantities plotted on a log axis (gradient norms)
are averaged in log space: the line is the geometric mean and the band multiplies/divides by the geometric
standard deviation.

Every return curve has the task's zero-action and random-action return floors beside it as horizontal lines
(``task-floors``' JSON: docs/floors.json of this checkout, or ``--floors FILE``); a task without an entry is
drawn without them and named in one warning.

Files (PNG, written atomically; a figure without data is skipped and the reason returned):
    return_vs_env_steps.png  return_vs_wall_clock.png  return_vs_iter.png  grad_norm.png  cosine_hist.png
    cosine_vs_iter.png  probe_grad_norms.png (full, decoupled and render-term norms of the same rollout)
    render_term_groups.png (the render term by the actor's parameter groups)
    image_sensitivity.png (the policy's sensitivity to each frame of its stack)
    timing.png (forward and backward ms per iteration)  memory.png (peak allocated MB; CPU: saved for backward)
"""

from __future__ import annotations

import io
import json
import math
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tyro

__all__ = ["PlotConfig", "Run", "load_run", "find_runs", "group_runs", "run_labels", "aggregate", "make_plots",
           "PlotResult", "Floors", "load_floors", "FIGURES", "MODE_COLORS", "VARIANT_KEYS", "DEFAULT_FLOORS",
           "RENDER_TERM_GROUPS", "plot_runs"]

#: File name -> caption of every figure ``make_plots`` can write.
FIGURES = {
    "return_vs_env_steps.png": "Return (mean of the last 100 episodes) against environment steps.",
    "return_vs_wall_clock.png": "Return against wall-clock training time (interpolated across seeds).",
    "return_vs_iter.png": "Return against training iterations.",
    "grad_norm.png": "Actor gradient norm before clipping (log scale; geometric mean x/÷ geometric std).",
    "cosine_hist.png": "Cosine between the full and the decoupled gradient of the same rollout (probe "
                       "iterations, all seeds pooled).",
    "cosine_vs_iter.png": "Cosine(full, decoupled) over training.",
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
}
MODE_COLORS = {"full": "tab:red", "decoupled": "tab:blue", "state": "tab:green", "blind": "tab:gray"}
#: Line styles of the variants of one mode (in the order of their labels).
_VARIANT_STYLES = ("-", "--", "-.", ":")
_TASK_ORDER = ("cartpole", "cartpole-swingup", "hopper", "ant", "humanoid")
#: config.json settings that tell runs of one mode apart in labels, when the given runs differ in them.
VARIANT_KEYS = ("preset", "raster_model", "renderer")
#: The actor's parameter groups of the render-term probe (metrics keys grad_norm_render_term_<group>).
RENDER_TERM_GROUPS = ("encoder", "mlp", "log_std")
#: The return floors of this checkout (written by ``task-floors``).
DEFAULT_FLOORS = Path(__file__).resolve().parents[1] / "docs" / "floors.json"
#: Floor policy -> (line style, legend name).
_FLOOR_LINES = {"zero": (":", "zero action"), "random": ("-.", "random action")}


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


@dataclass
class Run:
    """One run folder, parsed."""

    path: Path
    config: dict
    environment: dict
    command: list | None
    summary: dict | None
    metrics: list[dict]
    #: config.json's "preset" record (name, supplied, overridden), when the run has one.
    preset: dict | None = None
    #: config.json's "started_utc", when the run recorded it.
    started_utc: str | None = None

    @property
    def task(self) -> str:
        return str(self.config.get("task"))

    @property
    def mode(self) -> str:
        return str(self.config.get("mode"))

    @property
    def seed(self):
        return self.config.get("seed")

    def setting(self, key: str):
        """A config.json setting (``preset`` falls back to the name in the preset record); None when absent."""
        value = self.config.get(key)
        if value is None and key == "preset" and isinstance(self.preset, dict):
            value = self.preset.get("name")
        return value

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
    preset = data.get("preset") if isinstance(data.get("preset"), dict) else None
    started = data.get("started_utc") if isinstance(data.get("started_utc"), str) else None
    return Run(path=path, config=config, environment=data.get("environment") or {}, command=data.get("command"),
               summary=summary, metrics=read_metrics(path), preset=preset, started_utc=started)


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


def run_labels(runs: list[Run]) -> list[str]:
    """Each run's label: its mode, plus the ``VARIANT_KEYS`` values that differ among the runs of that mode.

    E.g. ``full (hard)`` and ``full (alpha)`` when the full runs differ only in raster_model; a mode whose runs
    agree on every variant key is just its name.
    """
    by_mode: dict[str, list[Run]] = {}
    for r in runs:
        by_mode.setdefault(r.mode, []).append(r)
    varying = {mode: [k for k in VARIANT_KEYS if len({json.dumps(r.setting(k)) for r in rs}) > 1]
               for mode, rs in by_mode.items()}
    labels = []
    for r in runs:
        keys = varying[r.mode]
        labels.append(f"{r.mode} ({', '.join(str(r.setting(k)) for k in keys)})" if keys else r.mode)
    return labels


def group_runs(runs: list[Run], *, label: Callable[[Run], str] | None = None) -> dict[tuple[str, str], list[Run]]:
    """{(task, label): runs}, tasks in the paper's order, then modes full, decoupled, state, blind.

    ``label``: a run's group label; default :func:`run_labels` (the mode, with its variant where runs differ).
    """
    labels = [label(r) for r in runs] if label is not None else run_labels(runs)
    groups: dict[tuple[str, str], list[Run]] = {}
    for r, lab in zip(runs, labels):
        groups.setdefault((r.task, lab), []).append(r)

    def order(k: tuple[str, str]) -> tuple:
        t, lab = k
        m = groups[k][0].mode
        return (_TASK_ORDER.index(t) if t in _TASK_ORDER else 99, t,
                list(MODE_COLORS).index(m) if m in MODE_COLORS else 99, m, lab)

    return {k: sorted(groups[k], key=lambda r: (str(r.seed), str(r.path))) for k in sorted(groups, key=order)}


def _styles(groups: dict[tuple[str, str], list[Run]]) -> dict[str, tuple[str | None, str]]:
    """label -> (colour of its mode, line style of its variant within the mode), the same in every panel."""
    by_mode: dict[str, list[str]] = {}
    for (_, lab), rs in groups.items():
        labs = by_mode.setdefault(rs[0].mode, [])
        if lab not in labs:
            labs.append(lab)
    return {lab: (MODE_COLORS.get(mode), _VARIANT_STYLES[i % len(_VARIANT_STYLES)])
            for mode, labs in by_mode.items() for i, lab in enumerate(labs)}


# ---------------------------------------------------------------------------------------------- floors
@dataclass
class Floors:
    """Zero- and random-action return floors per task, and the file they came from."""

    source: Path | None
    #: task -> {"zero": {"mean", "std", "episodes", ...}, "random": {...}}
    tasks: dict[str, dict] = field(default_factory=dict)

    def of(self, task: str) -> dict[str, dict] | None:
        """{policy: stats} of the task's floors, or None when the file has no entry for it."""
        entry = self.tasks.get(task)
        return {k: entry[k] for k in _FLOOR_LINES if k in entry} if entry else None

    def missing_message(self, task: str) -> str:
        where = str(self.source) if self.source else "no floors file"
        return (f"no return floor for task {task!r} ({where}): its return curves are drawn without the zero- and "
                f"random-action lines; measure them with `task-floors --tasks {task}`")


def load_floors(path: str | os.PathLike | None = None) -> Floors:
    """The floors of a ``task-floors`` JSON file; None: docs/floors.json of this checkout (no floors, and no
    error, when that file is missing). ValueError naming the file when a given one is missing or malformed."""
    default = path is None
    path = Path(DEFAULT_FLOORS if default else path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        if default:
            return Floors(source=None)
        raise ValueError(f"--floors {path}: no such file (write it with task-floors --out {path})") from None
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"--floors {path}: cannot be read ({e})") from None
    tasks = data.get("tasks") if isinstance(data, dict) else None
    if not isinstance(tasks, dict):
        raise ValueError(f"--floors {path}: expected a 'tasks' object as task-floors writes it")
    for task, entry in tasks.items():
        ok = isinstance(entry, dict) and any(k in entry for k in _FLOOR_LINES) and all(
            isinstance(entry[k], dict) and _num(entry[k].get("mean")) for k in _FLOOR_LINES if k in entry)
        if not ok:
            raise ValueError(f"--floors {path}: task {task!r} needs zero/random objects with a numeric 'mean'")
    return Floors(source=path, tasks=tasks)


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
    """What ``make_plots`` wrote, what it skipped (file name -> reason) and what it warned about."""

    files: dict[str, Path] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def _save(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    from gradlab.checkpoint import atomic_write_bytes

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def _frame_keys(runs: list[Run]) -> list[str]:
    """The image_sensitivity_f<i> keys present in the runs, by frame index."""
    keys = {k for r in runs for m in r.metrics for k in m if k.startswith("image_sensitivity_f")}
    return sorted(keys, key=lambda k: int(k.rsplit("f", 1)[1]) if k.rsplit("f", 1)[1].isdigit() else 99)


def make_plots(runs: list[Run], out: str | os.PathLike, *, floors: Floors | None = None,
               label: Callable[[Run], str] | None = None) -> PlotResult:
    """Write the FIGURES that the runs have data for into ``out``; see the module docstring.

    floors: the return floors (None: :func:`load_floors`'s default file); label: a run's group label (None:
    :func:`run_labels`). A task without floors is named once in ``PlotResult.warnings`` and a UserWarning.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    if not runs:
        raise ValueError("no runs to plot")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    floors = load_floors() if floors is None else floors
    groups = group_runs(runs, label=label)
    styles = _styles(groups)
    tasks = list(dict.fromkeys(t for t, _ in groups))
    result = PlotResult()
    for task in tasks:
        if floors.of(task) is None:
            msg = floors.missing_message(task)
            result.warnings.append(msg)
            warnings.warn(msg, UserWarning, stacklevel=2)

    def legend_label(lab: str, rs: list[Run]) -> str:
        return f"{lab} (n={len(rs)})"

    def panels(nrows: int = 1):
        fig, axes = plt.subplots(nrows, len(tasks), figsize=(4.6 * len(tasks), 3.4 * nrows), squeeze=False,
                                 layout="constrained")
        return fig, axes

    def floor_lines(ax, task: str) -> None:
        for policy, stats in (floors.of(task) or {}).items():
            style, name = _FLOOR_LINES[policy]
            ax.axhline(stats["mean"], color="0.35", ls=style, lw=1.1, label=f"{name} floor ({stats['mean']:.4g})")

    def band(ax, gx, c, lo, hi, rs, lab, *, color=None, ls=None, name=None) -> None:
        col, style = styles[lab]
        ax.plot(gx, c, color=color or col, ls=ls or style, label=name or legend_label(lab, rs), lw=1.4)
        if len(rs) > 1:
            ax.fill_between(gx, lo, hi, color=color or col, alpha=0.2, lw=0)

    def finish(ax, task: str, xlabel: str, *, log: bool = False, title: str | None = None) -> None:
        ax.set_title(title or task)
        ax.set_xlabel(xlabel)
        if log:
            ax.set_yscale("log")
        ax.grid(True, alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)

    def curve_figure(name: str, x: str, y: str, *, xlabel: str, ylabel: str, log: bool = False,
                     modes: tuple[str, ...] | None = None, skip_probed: bool = False,
                     with_floors: bool = False) -> None:
        fig, axes = panels()
        drawn = False
        for col, task in enumerate(tasks):
            ax = axes[0][col]
            ax.set_title(task)
            for (t, lab), rs in groups.items():
                if t != task or (modes is not None and rs[0].mode not in modes):
                    continue
                agg = aggregate([r.series(x, y, skip_probed=skip_probed) for r in rs], log=log)
                if agg is None:
                    continue
                band(ax, *agg, rs, lab)
                drawn = True
            if with_floors:
                floor_lines(ax, task)
            finish(ax, task, xlabel, log=log)
        axes[0][0].set_ylabel(ylabel)
        if not drawn:
            plt.close(fig)
            result.skipped[name] = f"no run has both {x} and {y}"
            return
        _save(fig, out / name)
        result.files[name] = out / name

    def multi_figure(name: str, keys: dict[str, str], *, ylabel: str, why: str) -> None:
        """One panel per task; one line per (group, key): colour = key, line style = the group's."""
        present = [k for k in keys if any(_num(m.get(k)) for r in runs for m in r.metrics)]
        if not present:
            result.skipped[name] = why
            return
        colors = dict(zip(present, ("tab:purple", "tab:orange", "tab:cyan", "tab:olive", "tab:brown", "tab:pink")))
        fig, axes = panels()
        for col, task in enumerate(tasks):
            ax = axes[0][col]
            for (t, lab), rs in groups.items():
                if t != task:
                    continue
                for k in present:
                    agg = aggregate([r.series("iter", k) for r in rs], log=True)
                    if agg is not None:
                        band(ax, *agg, rs, lab, color=colors[k], name=f"{keys[k]}: {legend_label(lab, rs)}")
            finish(ax, task, "iteration", log=True)
        axes[0][0].set_ylabel(ylabel)
        _save(fig, out / name)
        result.files[name] = out / name

    returns = "return (last 100 episodes)"
    curve_figure("return_vs_env_steps.png", "env_steps", "return_mean", xlabel="environment steps", ylabel=returns,
                 with_floors=True)
    curve_figure("return_vs_wall_clock.png", "wall_s", "return_mean", xlabel="wall clock [s]", ylabel=returns,
                 with_floors=True)
    curve_figure("return_vs_iter.png", "iter", "return_mean", xlabel="iteration", ylabel=returns, with_floors=True)
    curve_figure("grad_norm.png", "iter", "grad_norm", xlabel="iteration", ylabel="actor gradient norm (pre-clip)",
                 log=True)
    curve_figure("cosine_vs_iter.png", "iter", "cos_full_decoupled", xlabel="iteration",
                 ylabel="cos(full, decoupled)", modes=("full", "decoupled"))
    multi_figure("probe_grad_norms.png", {"grad_norm_full": "full", "grad_norm_decoupled": "decoupled",
                                          "grad_norm_render_term": "render term"},
                 ylabel="gradient norm (same rollout)", why="no run has probe iterations (grad_norm_full)")
    multi_figure("render_term_groups.png", {f"grad_norm_render_term_{g}": g for g in RENDER_TERM_GROUPS},
                 ylabel="render-term norm", why="no run has the render term by parameter group "
                                               "(grad_norm_render_term_encoder/_mlp/_log_std)")
    frame_keys = _frame_keys(runs)
    n = len(frame_keys)
    multi_figure("image_sensitivity.png",
                 {k: f"frame {k.rsplit('f', 1)[1]}" + (" (oldest)" if i == 0 and n > 1 else
                                                       " (newest)" if i == n - 1 and n > 1 else "")
                  for i, k in enumerate(frame_keys)},
                 ylabel="|d mean action / d frame|", why="no run has image_sensitivity_f<i>")

    # Cosine histogram: every probe of every seed pooled (the distribution, not a curve).
    fig, axes = panels()
    drawn = False
    bins = np.linspace(-1, 1, 41)
    for col, task in enumerate(tasks):
        ax = axes[0][col]
        for (t, lab), rs in groups.items():
            vals = [v for r in rs for v in r.series("iter", "cos_full_decoupled")[1]] if t == task else []
            if not vals:
                continue
            # Outlines, not filled bars: the modes' histograms overlap.
            color, style = styles[lab]
            ax.hist(np.clip(vals, -1, 1), bins=bins, color=color, ls=style, histtype="step", lw=1.6,
                    label=f"{lab} (n={len(rs)}, {len(vals)} probes)")
            drawn = True
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        finish(ax, task, "cos(full, decoupled)")
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
            for (t, lab), rs in groups.items():
                if t != task:
                    continue
                agg = aggregate([r.series("iter", key, skip_probed=True) for r in rs], log=True)
                if agg is None:
                    continue
                spans += [float(agg[1].min()), float(agg[1].max())]
                band(ax, *agg, rs, lab)
                drawn = True
            # warm-up and full vs decoupled often differ by decades; else linear
            log = bool(spans) and min(spans) > 0 and max(spans) >= 10 * min(spans)
            finish(ax, task, "iteration", log=log, title=f"{task}: {name}")
            ax.grid(True, which="both", alpha=0.3)
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


def plot_runs(cfg: PlotConfig) -> PlotResult:
    """``ablate-plot``: the runs of ``cfg.runs`` drawn into ``cfg.out`` with the floors of ``cfg.floors``."""
    return make_plots(find_runs(list(cfg.runs)), cfg.out, floors=load_floors(cfg.floors))
