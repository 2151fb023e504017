"""memory_peak.png and memory_bwd.png: memory and backward time against scene size, one line per setting."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from ablations.memory.config import SWEPT_MODES
from gradlab.files import atomic_write_bytes

__all__ = ["plot_sweep", "sweep_figures"]

#: Line style per mode; the marker tells the vertices per mesh apart (the colour's shade does too).
_MODE_LINES = {"full": "-", "decoupled": "--"}
_VERTS_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "h")


def _x_of(rows: list[dict]) -> tuple[str, Callable[[dict], float | None], bool]:
    """x axis: total scene faces when every measured row knows them, else extra vertices (meshes x verts)."""
    if all(r.get("scene_faces") for r in rows if r["status"] == "ok"):
        return "scene faces (robot + extra meshes)", lambda r: r.get("scene_faces"), True
    return "extra mesh vertices (meshes x vertices per mesh)", lambda r: r["meshes"] * r["verts_per_mesh"], False


def _spans_decade(values) -> bool:
    """True when the positive values cover a factor of 10 or more (a log axis is then worth it)."""
    v = [x for x in values if isinstance(x, (int, float)) and x > 0]
    return bool(v) and max(v) >= 10 * min(v)


def plot_sweep(rows: list[dict], out: str | os.PathLike) -> list[Path]:
    """memory_peak.png and memory_bwd.png (:func:`sweep_figures`) written into ``out``; returns the files
    written (none without ok rows)."""
    from ablations.reports.style import png_bytes
    written = []
    for name, fig in sweep_figures(rows).items():
        atomic_write_bytes(Path(out) / name, png_bytes(fig))
        written.append(Path(out) / name)
    return written


def sweep_figures(rows: list[dict]) -> dict:
    """{"memory_peak.png": Figure, "memory_bwd.png": Figure} from sweep rows; {} without ok rows.

    One line per (mode, vertices per mesh): colour = the mode's (full red, decoupled blue, as in ablate-plot),
    darker for more vertices; line style = the mode; marker = the vertices per mesh. The robot-only point
    (0 meshes) starts every line of its mode. Out-of-memory and timed-out points are crosses at the top edge
    (their x known when the worker counted the scene first). One legend per figure, right of the panels.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.transforms import blended_transform_factory

    ok = [r for r in rows if r["status"] == "ok"]
    if not ok:
        return {}
    xlabel, xf, logx = _x_of(rows)
    cuda = any(r.get("peak_alloc_mb") is not None for r in ok)
    panels = [("peak_alloc_mb", "peak allocated [MB] (CUDA)")] if cuda else []
    panels.append(("saved_mb", "saved for backward per window [MB]"))
    if not cuda:
        panels.append(("max_rss_mb", "peak process RSS [MB] (CPU)"))
    panels = [(k, label) for k, label in panels if any(r.get(k) is not None for r in ok)]
    verts = sorted({r["verts_per_mesh"] for r in rows if r["meshes"] > 0})
    modes = [m for m in SWEPT_MODES if any(r["mode"] == m for r in rows)]
    # Colour = mode (as in ablate-plot: full red, decoupled blue), darker = more vertices per mesh.
    ramps = {"full": plt.get_cmap("Reds"), "decoupled": plt.get_cmap("Blues")}

    def color(mode: str, v: int):
        i = verts.index(v) if v in verts else len(verts) - 1
        return ramps.get(mode, plt.get_cmap("Greys"))(0.45 + 0.5 * i / max(len(verts) - 1, 1))

    task = rows[0]["task"]
    renderer = rows[0].get("renderer") or "soft"  # one per sweep (a FIXED column)
    figures = {}

    def lines(ax, key: str) -> None:
        drawn = False
        for mode in modes:
            base = [r for r in ok if r["mode"] == mode and r["meshes"] == 0 and r.get(key) is not None]
            for v in verts or [0]:
                pts = base + [r for r in ok if r["mode"] == mode and r["meshes"] > 0 and r["verts_per_mesh"] == v
                              and r.get(key) is not None]
                pts = sorted((xf(r), r[key]) for r in pts if xf(r) is not None)
                if not pts:
                    continue
                marker = _VERTS_MARKERS[verts.index(v) % len(_VERTS_MARKERS)] if v in verts else "o"
                name = mode if renderer == "soft" else f"{mode} ({renderer})"
                label = f"{name}, {v} verts/mesh" if verts else name
                ax.plot([p[0] for p in pts], [p[1] for p in pts], ls=_MODE_LINES.get(mode, "-"), marker=marker,
                        color=color(mode, v), label=label, ms=4.5)
                drawn = True
        trans = blended_transform_factory(ax.transData, ax.transAxes)
        failed = [r for r in rows if r["status"] in ("oom", "timeout")]
        unknown, labelled = [], set()
        for r in failed:
            x = xf(r)
            if x is None:
                unknown.append(f"{r['mode']} m{r['meshes']} v{r['verts_per_mesh']}")
                continue
            ax.plot([x], [0.97], "x", color=color(r["mode"], r["verts_per_mesh"]), transform=trans, ms=8, mew=2,
                    label=None if r["status"] in labelled else r["status"], clip_on=False)
            labelled.add(r["status"])
        if unknown:
            ax.text(0.01, 0.01, "oom/timeout, size unknown: " + ", ".join(unknown), transform=ax.transAxes,
                    fontsize=7, va="bottom")
        # Log axes where the data span a decade or more (scene sizes usually do); on a narrow span a log axis
        # only makes the tick labels unreadable.
        if logx and _spans_decade([xf(r) for r in ok]):
            ax.set_xscale("log")
        elif not logx:
            ax.set_xscale("symlog")
        if drawn and _spans_decade([r.get(key) for r in ok]):
            ax.set_yscale("log")  # only with data on it: an empty log axis cannot place its ticks
        ax.set_xlabel(xlabel)
        ax.grid(True, which="both", alpha=0.3)

    def legend(fig, ax) -> None:
        """The lines' legend right of the panels (the first panel has every line), the figure widened by it."""
        handles, labels = ax.get_legend_handles_labels()
        leg = fig.legend(handles, labels, loc="outside right center", fontsize=7)  # clear of the title
        fig.set_figwidth(fig.get_figwidth() + leg.get_window_extent(fig.canvas.get_renderer()).width / fig.dpi)

    setting = (f"{task}, {ok[0]['num_envs']} envs x {ok[0]['horizon']} steps, {ok[0]['image_size']} px, "
               f"{ok[0]['device']}" + (f" ({ok[0]['gpu']})" if ok[0].get("gpu") else ""))
    if panels:
        fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.2), squeeze=False,
                                 layout="constrained")
        for ax, (key, label) in zip(axes[0], panels):
            lines(ax, key)
            ax.set_ylabel(label)
        legend(fig, axes[0][0])
        fig.suptitle(f"Memory vs scene size: {setting}", fontsize=10)
        figures["memory_peak.png"] = fig

    fig, ax = plt.subplots(figsize=(5.5, 4.2), layout="constrained")
    lines(ax, "bwd_ms")
    ax.set_ylabel("backward per iteration [ms] (median)")
    legend(fig, ax)
    fig.suptitle(f"Backward time vs scene size: {setting}", fontsize=9)  # over the legend too
    figures["memory_bwd.png"] = fig
    return figures
