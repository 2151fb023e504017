"""The pieces every report section builds with: the facts read off a run (median time per iteration, device,
whether it trained in a population) or a ``--benchmark`` file, markdown tables, links relative to the report's
folder, and a figure's lines. Below :mod:`ablations.reports.seeds` and :mod:`ablations.reports.report`, which both
use them."""

from __future__ import annotations

import json
import os
from pathlib import Path
from statistics import median

from ablations.reports.plot import FIGURES
from ablations.reports.style import PlotResult
from ablations.run_folder import Run, is_number

__all__ = ["NOT_RUN", "run_median_ms", "run_device", "is_population_member", "read_benchmark_json",
           "markdown_table", "ms_text", "report_path", "figure_lines"]

#: What a table says where there is no measurement.
NOT_RUN = "not run"


def run_median_ms(run: Run, key: str) -> float | None:
    """A run's median ``key`` (``bwd_ms``, ``iter_ms``, ...) per iteration: summary.json's ``median_<key>``, else
    recomputed from metrics.jsonl.

    The recomputation matches ``ablations.runs``: iterations after ``warmup_iters``, probe iterations (which
    differentiate twice) excluded.
    """
    if run.summary and is_number(run.summary.get(f"median_{key}")):
        return float(run.summary[f"median_{key}"])
    warm = run.config.get("warmup_iters", 2) or 0
    vals = [m[key] for m in run.metrics if is_number(m.get(key)) and m.get("iter", 0) > warm and not m.get("probed")]
    return median(vals) if vals else None


def run_device(run: Run) -> str:
    """The device a run trained on, as config.json records it (the GPU's name on CUDA)."""
    env = run.environment
    return env.get("gpu") or env.get("device") or run.config.get("device") or "?"


def is_population_member(run: Run) -> bool:
    """Whether the run trained in a population of several members (config.json's "population" record): its
    iteration's times are then the whole population's, not its own."""
    return run.population is not None and len(run.population.get("members") or ()) > 1


def read_benchmark_json(path: str | os.PathLike):
    """The parsed JSON of a ``--benchmark`` file; ValueError naming the flag and file when it is missing or not
    JSON."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"--benchmark {path}: no such file") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"--benchmark {path}: not valid JSON ({e})") from None


def ms_text(v: float | None) -> str:
    """Milliseconds as a table shows them (three significant digits, whole numbers from 100); NOT_RUN for None."""
    if v is None:
        return NOT_RUN
    return f"{v:.0f}" if v >= 100 else f"{v:.1f}" if v >= 10 else f"{v:.3g}"


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return ms_text(v)
    return str(v).replace("|", "\\|").replace("\n", " ")


def markdown_table(header: list[str], rows: list[list]) -> list[str]:
    """Markdown table lines; floats formatted like times, '|' escaped."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return lines


def report_path(target: str | os.PathLike, base: Path) -> str:
    """``target`` relative to ``base`` (the report's folder): a report names no absolute path of the machine that
    wrote it, and its links hold wherever the folders move together."""
    return Path(os.path.relpath(target, base)).as_posix()


def figure_lines(res: PlotResult, names, base: Path) -> list[str]:
    """Markdown for the named figures of a make_plots result (links relative to ``base``), or why one is missing."""
    out = []
    for name in names:
        caption = FIGURES[name]
        if name in res.files:
            out += [f"![{caption}]({report_path(res.files[name], base)})", "", f"*{caption}*", ""]
            out += [f"*{line}.*" for line in res.left_out if line.startswith(f"{name}:")]
            out += [""] if out[-1] != "" else []
        elif name in res.skipped:
            out += [f"*{name} not drawn: {res.skipped[name]}.*", ""]
    return out
