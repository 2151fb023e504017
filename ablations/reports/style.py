"""What every figure of the reports shares: runs grouped by task and arm with their labels, each arm's colour,
line style and marker (the same in every figure), the return floors, the mean +- std across runs, and how a figure
is saved (an 80-dpi palette PNG with fixed metadata, so unchanged data gives the same bytes)."""

from __future__ import annotations

import io
import json
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ablations.run_folder import Run, is_number
from gradlab.files import atomic_write_bytes
from vocabulary import TASKS

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["group_runs", "run_labels", "ArmStyle", "arm_styles", "MODE_COLORS", "VARIANT_KEYS", "Floors",
           "load_floors", "DEFAULT_FLOORS", "Aggregate", "aggregate", "PlotResult", "FigureSet", "PNG_METADATA",
           "FIGURE_DPI", "png_bytes", "save_figure", "MARKERS", "FLOOR_LINES", "draw_floor_lines", "draw_band",
           "plain_tick_labels"]


MODE_COLORS = {"full": "tab:red", "decoupled": "tab:blue", "state": "tab:green", "blind": "tab:gray"}
#: Colours of modes MODE_COLORS does not name, in the order they appear.
_OTHER_COLORS = ("tab:purple", "tab:brown", "tab:olive", "tab:cyan", "tab:pink", "tab:orange")
#: Line styles of the arms, in group order: dash patterns (on, off, ... in line widths) told apart at a glance.
_LINESTYLES = ("-", (0, (5, 2)), (0, (1, 1.5)), (0, (6, 2, 1.5, 2)), (0, (2.5, 1.5)), (0, (8, 2, 1.5, 2, 1.5, 2)),
               (0, (11, 3)), (0, (3, 1.5, 1, 1.5, 1, 1.5)), (0, (1.5, 3.5)), (0, (8, 1.5, 3, 1.5)))
#: Markers of the arms (hollow, so a marker under another shows); the evaluation star is none of them.
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<", ">", "h")
#: config.json settings that tell runs of one mode apart in labels, when the given runs differ in them.
VARIANT_KEYS = ("preset", "raster_model", "renderer")
#: The return floors of this checkout (written by ``task-floors``).
DEFAULT_FLOORS = Path(__file__).resolve().parents[2] / "docs" / "floors.json"
#: Floor policy -> (line style, name on the line).
FLOOR_LINES = {"zero": (":", "zero action"), "random": ("-.", "random action")}


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
    """{(task, label): runs}, tasks in the order of ``tasks.TASKS``, then modes full, decoupled, state, blind.

    ``label``: a run's group label; default :func:`run_labels` (the mode, with its variant where runs differ).
    """
    labels = [label(r) for r in runs] if label is not None else run_labels(runs)
    groups: dict[tuple[str, str], list[Run]] = {}
    for r, lab in zip(runs, labels):
        groups.setdefault((r.task, lab), []).append(r)

    def order(k: tuple[str, str]) -> tuple:
        t, lab = k
        m = groups[k][0].mode
        return (TASKS.index(t) if t in TASKS else 99, t,
                list(MODE_COLORS).index(m) if m in MODE_COLORS else 99, m, lab)

    return {k: sorted(groups[k], key=lambda r: (str(r.seed), str(r.path))) for k in sorted(groups, key=order)}


class ArmStyle(NamedTuple):
    """How one arm is drawn in every figure: an RGB colour, a matplotlib line style and a marker."""

    color: tuple[float, float, float]
    linestyle: str | tuple
    marker: str


def _shade(color, variant: int) -> tuple[float, float, float]:
    """The mode's colour for its first variant; then alternately darker and lighter, further each time."""
    from matplotlib.colors import to_rgb

    rgb = np.array(to_rgb(color))
    if variant == 0:
        return tuple(float(c) for c in rgb)
    step = (variant + 1) // 2
    target, t = (0.0, min(0.3 * step, 0.7)) if variant % 2 else (1.0, min(0.4 * step, 0.75))
    return tuple(float(c) for c in rgb + (target - rgb) * t)


def arm_styles(groups: dict[tuple[str, str], list[Run]]) -> dict[str, ArmStyle]:
    """label -> :class:`ArmStyle`, the same in every panel and figure, no two alike.

    Colour: the mode's (MODE_COLORS; others get a colour of their own), shaded per variant of the mode. Line
    style and marker: one per arm in group order; past ten arms the pairs still differ.
    """
    labels: list[str] = []
    by_mode: dict[str, list[str]] = {}
    for (_, lab), rs in groups.items():
        if lab not in labels:
            labels.append(lab)
            by_mode.setdefault(rs[0].mode, []).append(lab)
    others = iter(_OTHER_COLORS * (1 + len(by_mode) // len(_OTHER_COLORS)))
    colors = {}
    for mode, labs in by_mode.items():
        base = MODE_COLORS.get(mode) or next(others)
        colors.update({lab: _shade(base, i) for i, lab in enumerate(labs)})
    n = len(_LINESTYLES)
    return {lab: ArmStyle(colors[lab], _LINESTYLES[i % n], MARKERS[(i + i // n) % len(MARKERS)])
            for i, lab in enumerate(labels)}


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
        return {k: entry[k] for k in FLOOR_LINES if k in entry} if entry else None

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
        ok = isinstance(entry, dict) and any(k in entry for k in FLOOR_LINES) and all(
            isinstance(entry[k], dict) and is_number(entry[k].get("mean")) for k in FLOOR_LINES if k in entry)
        if not ok:
            raise ValueError(f"--floors {path}: task {task!r} needs zero/random objects with a numeric 'mean'")
    return Floors(source=path, tasks=tasks)


class Aggregate(NamedTuple):
    """Several runs' curves on one x grid: ``centre`` +- ``low``/``high`` (one sample standard deviation; the
    centre itself where fewer than 2 runs have the point) and ``n``, how many runs cover each x."""

    x: np.ndarray
    centre: np.ndarray
    low: np.ndarray
    high: np.ndarray
    n: np.ndarray


def aggregate(series: list[tuple[np.ndarray, np.ndarray]], *, log: bool = False) -> Aggregate | None:
    """Mean and +-1 std band of several (x, y) curves over the range ANY of them covers, with the number of runs
    at each point.

    The grid is every x of every curve; at each, the curves whose own range [first x, last x] covers it are
    linearly interpolated onto it (exact where a curve has a point) and averaged, so runs of different lengths
    are each drawn over their own range and ``n`` says how many stand behind each point. None without any
    point. ``log``: average log10(y) (y <= 0 dropped): geometric mean and geometric-std band.
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
    grid = np.unique(np.concatenate([x for x, _ in clean]))
    ys = np.stack([np.where((grid >= x[0]) & (grid <= x[-1]), np.interp(grid, x, y), np.nan) for x, y in clean])
    n = np.sum(~np.isnan(ys), axis=0)
    mean = np.nanmean(ys, axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # one run at a point: no spread there
        std = np.where(n > 1, np.nanstd(ys, axis=0, ddof=1), 0.0)
    low, high = mean - std, mean + std
    if log:
        return Aggregate(grid, 10**mean, 10**low, 10**high, n)
    return Aggregate(grid, mean, low, high, n)


@dataclass
class PlotResult:
    """What ``make_plots`` wrote, what it skipped (file name -> reason), what it warned about, and what it left
    out (one line each: arms a figure could not draw, runs that share a seed)."""

    files: dict[str, Path] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    left_out: list[str] = field(default_factory=list)


@dataclass
class FigureSet:
    """The figures of :func:`build_figures` (file name -> matplotlib Figure, in drawing order), the figures
    without data (file name -> reason), the warnings (tasks without floors), what was left out (one line each)
    and what each figure drew (``drawn``). ``close()`` frees the figures."""

    figures: dict[str, Figure] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    left_out: list[str] = field(default_factory=list)
    #: file name -> {(task, arm): (first x, last x, most runs at a point)} of every arm line drawn
    drawn: dict[str, dict[tuple[str, str], tuple[float, float, int]]] = field(default_factory=dict)

    def close(self) -> None:
        import matplotlib.pyplot as plt

        for fig in self.figures.values():
            plt.close(fig)


#: PNG metadata of every figure: a fixed Software entry and no date, so that a figure whose data did not change
#: is byte for byte the same file (matplotlib writes its version otherwise).
PNG_METADATA = {"Software": "pixelgrad ablations"}
#: Figures are line plots on a white ground: 80 dpi and a 256-colour palette keep them legible at a quarter of
#: the bytes of a 110-dpi RGBA file, so that the shipped reports fit the repository's size budget
#: (docs/design.md, "Shipped run data").
FIGURE_DPI = 80


def png_bytes(fig, *, dpi: int = FIGURE_DPI) -> bytes:
    """``fig`` as palette PNG bytes, deterministic (no date, fixed Software entry, no dithering); closes ``fig``."""
    import matplotlib.pyplot as plt
    from PIL import Image, PngImagePlugin

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight", metadata=PNG_METADATA)
    plt.close(fig)
    image = Image.open(buf).convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    info = PngImagePlugin.PngInfo()
    for key, value in PNG_METADATA.items():
        info.add_text(key, value)
    out = io.BytesIO()
    image.save(out, format="png", optimize=True, pnginfo=info)
    return out.getvalue()


def save_figure(fig, path: Path) -> None:
    """The figure as a PNG at ``path`` (:func:`png_bytes`), written atomically; the figure is closed."""
    atomic_write_bytes(path, png_bytes(fig))


def draw_floor_lines(ax, floors: dict[str, dict] | None) -> None:
    """The task's return floors (policy -> its statistics) as labelled horizontal lines on ``ax``."""
    for policy, st in (floors or {}).items():
        style, name = FLOOR_LINES[policy]
        ax.axhline(st["mean"], color="0.15", ls=style, lw=1.0, zorder=1.5, label=f"{name} floor ({st['mean']:.4g})",
                   gid=f"floor:{policy}")


def draw_band(ax, band, style: ArmStyle | None, label: str, *, lw: float = 1.6) -> None:
    """A band's mean line (solid where 2 or more runs have the point, thin dotted where only one does) and its
    interval shaded where it exists."""
    look = {"color": style.color} if style is not None else {}
    many = band.n >= 2
    (line,) = ax.plot(band.x, np.where(many, band.mean, np.nan), lw=lw, label=label, gid="mean",
                      ls=style.linestyle if style is not None else "-", **look)
    if not many.all():
        ax.plot(band.x, np.where(~many, band.mean, np.nan), lw=0.8, ls=":", color=line.get_color(),
                marker=".", ms=3, gid="single run", label=f"_{label} (1 run)")
    ax.fill_between(band.x, band.ci_low, band.ci_high, where=many, color=line.get_color(), alpha=0.18, lw=0)


def plain_tick_labels(ax) -> None:
    """Plain tick labels on linear axes: no offset such as ``1e-5+9.9999e-1`` above the ticks."""
    from matplotlib.ticker import ScalarFormatter

    for axis in (ax.xaxis, ax.yaxis):
        fmt = axis.get_major_formatter()
        if isinstance(fmt, ScalarFormatter):
            fmt.set_useOffset(False)
