"""One markdown report from whatever measurements exist: ``ablate-report RUN_DIR... --memory DIR --out report.md``.

Sections:
    1. Backward time per iteration (the paper's Table 1): for cartpole, hopper, ant and humanoid, our median
       backward ms of decoupled (D.Va) and full (SHAC through the renderer) and their ratio, beside the
       paper's numbers (RTX 4080), labelled as the paper's. A task or mode without a measurement says
       "not run"; nothing is estimated.
    2. Training curves: the ``ablate-plot`` figures of the given runs, and a table of the runs.
    3. Memory sweeps: the ``ablate-memory`` table(s) and plots.
    4. Provenance: device, versions, dates and the command behind every input, and this report's command.

Where our backward times come from, in order of precedence per (task, mode):
    a benchmark JSON (``--benchmark``), then the runs' summary.json ``median_bwd_ms`` (warm-up and probe
    iterations excluded; recomputed the same way from metrics.jsonl when a run has no summary); several runs
    of one (task, mode) give the median of their medians.

Benchmark JSON (a dedicated timing measurement; the format this module reads)::

    {"date": "...", "command": "...", "device": "cuda", "gpu": "NVIDIA H100 ...", "versions": {"torch": ...},
     "results": [{"task": "ant", "mode": "full", "bwd_ms": 123.4,
                  "num_envs": 64, "horizon": 32, "image_size": 84}, ...]}

A bare list of result objects is accepted too; ``median_bwd_ms`` is accepted for ``bwd_ms``.
The figures are (re)drawn into ``<report folder>/figures/`` so the report folder is self-contained.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path

import tyro

from ablations.plot import FIGURES, Run, find_runs, group_runs, make_plots
from gradlab.timing import median

__all__ = ["ReportConfig", "build_report", "PAPER_TABLE1_MS", "TASKS", "run_bwd_ms", "load_benchmark"]

TASKS = ("cartpole", "hopper", "ant", "humanoid")
#: The paper's Table 1 (D.Va, NeurIPS 2025): backward time per iteration on an RTX 4080, converted from seconds
#: to ms: task -> (D.Va = decoupled, SHAC with rendering = full).
PAPER_TABLE1_MS = {
    "cartpole": (110.0, 360.0),
    "hopper": (190.0, 510.0),
    "ant": (210.0, 580.0),
    "humanoid": (680.0, 1380.0),
}
PAPER_DEVICE = "RTX 4080"
NOT_RUN = "not run"


@dataclass
class ReportConfig:
    """Build one markdown report (Table-1-style backward times, training curves, memory sweep, provenance)."""

    runs: tyro.conf.Positional[tuple[Path, ...]] = ()
    """Run folders written by `ablate` (or folders that hold run folders)."""
    memory: tuple[Path, ...] = ()
    """Folders of `ablate-memory` sweeps (each with memory.csv and memory.json)."""
    benchmark: tuple[Path, ...] = ()
    """Benchmark JSON files with backward times per (task, mode); they take precedence over run summaries."""
    out: Path = Path("report/report.md")
    """The markdown file to write; figures go to figures/ beside it."""
    title: str = "Policy gradients through pixels: full vs decoupled"
    """Title of the report."""


# ---------------------------------------------------------------------------------------------- inputs
def run_bwd_ms(run: Run) -> float | None:
    """A run's median backward ms per iteration: summary.json's, else recomputed from metrics.jsonl.

    The recomputation matches ``ablations.runs``: iterations after ``warmup_iters``, probe iterations (which
    differentiate twice) excluded.
    """
    if run.summary and isinstance(run.summary.get("median_bwd_ms"), (int, float)):
        return float(run.summary["median_bwd_ms"])
    warm = run.config.get("warmup_iters", 2) or 0
    vals = [m["bwd_ms"] for m in run.metrics
            if isinstance(m.get("bwd_ms"), (int, float)) and m.get("iter", 0) > warm and not m.get("probed")]
    return median(vals) if vals else None


def load_benchmark(path: str | os.PathLike) -> tuple[dict, list[dict]]:
    """(metadata, results) of a benchmark JSON; ValueError naming the problem for anything else."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"--benchmark {path}: no such file") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"--benchmark {path}: not valid JSON ({e})") from None
    meta, results = ({}, data) if isinstance(data, list) else (data, data.get("results") if isinstance(data, dict)
                                                               else None)
    if not isinstance(results, list):
        raise ValueError(f"--benchmark {path}: expected a 'results' list of {{task, mode, bwd_ms}} objects")
    out = []
    for i, r in enumerate(results):
        bwd = r.get("bwd_ms", r.get("median_bwd_ms")) if isinstance(r, dict) else None
        if not isinstance(r, dict) or "task" not in r or "mode" not in r or not isinstance(bwd, (int, float)):
            raise ValueError(f"--benchmark {path}: result {i} needs task, mode and a numeric bwd_ms")
        out.append({**r, "bwd_ms": float(bwd)})
    return {k: v for k, v in meta.items() if k != "results"}, out


def _setting(d: dict) -> str:
    parts = []
    if d.get("num_envs") and d.get("horizon"):
        parts.append(f"{d['num_envs']}x{d['horizon']}")
    if d.get("image_size"):
        parts.append(f"{d['image_size']}px")
    return " ".join(parts) or "?"


def _run_device(run: Run) -> str:
    env = run.environment
    return env.get("gpu") or env.get("device") or run.config.get("device") or "?"


@dataclass
class Cell:
    """Our backward time for one (task, mode) and where it came from."""

    ms: float
    n: int
    source: str
    setting: str
    device: str


def collect_bwd(runs: list[Run], benchmarks: list[tuple[Path, dict, list[dict]]]) -> dict[tuple[str, str], Cell]:
    """Our backward-time cells keyed by (task, mode): benchmarks first, then runs (see the module docstring)."""
    cells: dict[tuple[str, str], Cell] = {}
    for path, meta, results in benchmarks:
        by_key: dict[tuple[str, str], list[dict]] = {}
        for r in results:
            by_key.setdefault((r["task"], r["mode"]), []).append(r)
        for key, rs in by_key.items():
            if key in cells:
                continue  # the first benchmark given wins
            settings = sorted({_setting(r) for r in rs})
            cells[key] = Cell(ms=median([r["bwd_ms"] for r in rs]), n=len(rs), source=f"benchmark {path.name}",
                              setting=" / ".join(settings), device=str(meta.get("gpu") or meta.get("device") or "?"))
    for (task, mode), rs in group_runs(runs).items():
        if (task, mode) in cells:
            continue
        vals = [(v, r) for r in rs if (v := run_bwd_ms(r)) is not None]
        if not vals:
            continue
        settings = sorted({_setting(r.config) for _, r in vals})
        devices = sorted({_run_device(r) for _, r in vals})
        cells[(task, mode)] = Cell(ms=median([v for v, _ in vals]), n=len(vals), source="runs",
                                   setting=" / ".join(settings), device=" / ".join(devices))
    return cells


# ---------------------------------------------------------------------------------------------- formatting
def _ms(v: float | None) -> str:
    if v is None:
        return NOT_RUN
    return f"{v:.0f}" if v >= 100 else f"{v:.1f}" if v >= 10 else f"{v:.3g}"


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return _ms(v)
    return str(v).replace("|", "\\|").replace("\n", " ")


def _table(header: list[str], rows: list[list]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return lines


def _mtime(p: Path) -> str:
    try:
        return _dt.datetime.fromtimestamp(p.stat().st_mtime).astimezone().isoformat(timespec="seconds")
    except OSError:
        return "?"


def _command(cmd) -> str:
    if isinstance(cmd, (list, tuple)):
        return shlex.join(str(c) for c in cmd)
    return str(cmd) if cmd else "(not recorded)"


def _commit(run: Run) -> str:
    try:
        first = (run.path / "git.txt").read_text().splitlines()[0]
    except (OSError, IndexError):
        return "?"
    return first.split()[1][:12] if first.startswith("commit ") and len(first.split()) > 1 else first[:40]


def _rel(target: Path, base: Path) -> str:
    return Path(os.path.relpath(target, base)).as_posix()


# ---------------------------------------------------------------------------------------------- sections
def _table1(cells: dict[tuple[str, str], Cell]) -> list[str]:
    out = ["## 1. Backward time per iteration (Table 1)", "",
           "Median backward time of one SHAC iteration (one window of `horizon` steps for `num_envs` "
           "environments), in ms. **Ours** is measured by this toolkit (CUDA-synchronised timers, warm-up "
           "excluded); **paper** is D.Va's Table 1 (NeurIPS 2025, "
           f"{PAPER_DEVICE}), converted from seconds, quoted for comparison and not measured here. The "
           "reference implementation's timers do not synchronise CUDA, so its times may not include all "
           "asynchronous GPU work. Absolute times depend on the device and the sizes; compare the ratios.", ""]
    header = ["task", "ours: decoupled (D.Va) [ms]", "ours: full [ms]", "ours: full / decoupled",
              "ours: setting (envs x steps, image), device, source",
              f"paper ({PAPER_DEVICE}): D.Va [ms]", f"paper ({PAPER_DEVICE}): SHAC with rendering [ms]",
              "paper: ratio"]
    rows = []
    extra = sorted({t for t, _ in cells if t not in TASKS})
    for task in (*TASKS, *extra):
        dec, full = cells.get((task, "decoupled")), cells.get((task, "full"))
        if dec and full:
            ratio = f"{full.ms / dec.ms:.2f}x" if dec.setting == full.setting and dec.ms > 0 else \
                "n/a (settings differ)"
        else:
            ratio = NOT_RUN
        info = []
        for name, c in (("decoupled", dec), ("full", full)):
            if c:
                info.append(f"{name}: {c.setting}, {c.device}, {c.source} (n={c.n})")
        paper = PAPER_TABLE1_MS.get(task)
        rows.append([task, _ms(dec.ms if dec else None), _ms(full.ms if full else None), ratio,
                     "; ".join(info) or NOT_RUN,
                     _ms(paper[0]) if paper else "-", _ms(paper[1]) if paper else "-",
                     f"{paper[1] / paper[0]:.2f}x" if paper else "-"])
    out += _table(header, rows)
    state = sorted(t for t, m in cells if m == "state")
    if state:
        out += ["", "State-policy runs (no rendering) have backward times too: "
                + ", ".join(f"{t} {_ms(cells[(t, 'state')].ms)} ms" for t in state) + "."]
    return [*out, ""]


def _curves(runs: list[Run], fig_dir: Path, base: Path) -> list[str]:
    out = ["## 2. Training curves", ""]
    if not runs:
        return [*out, "No training runs were given.", ""]
    res = make_plots(runs, fig_dir)
    out += ["Per task and mode, mean +- one standard deviation across seeds (n in the legends).", ""]
    for name, caption in FIGURES.items():
        if name in res.files:
            out += [f"![{caption}]({_rel(res.files[name], base)})", "", f"*{caption}*", ""]
        elif name in res.skipped:
            out += [f"*{name} not drawn: {res.skipped[name]}.*", ""]
    out += ["### Runs", ""]
    rows = []
    for (_task, _mode), rs in group_runs(runs).items():
        for r in rs:
            s = r.summary or {}
            last = r.metrics[-1] if r.metrics else {}
            peak = s.get("peak_alloc_mb")
            rows.append([r.path.name, r.task, r.mode, r.seed, s.get("status", "no summary"),
                         s.get("iterations", last.get("iter")), s.get("env_steps", last.get("env_steps")),
                         s.get("final_return", last.get("return_mean")), s.get("median_fwd_ms"), run_bwd_ms(r),
                         peak if peak is not None else s.get("median_saved_mb"),
                         "alloc" if peak is not None else "saved" if s.get("median_saved_mb") is not None else ""])
    out += _table(["run", "task", "mode", "seed", "status", "iterations", "env steps", "final return",
                   "median fwd [ms]", "median bwd [ms]", "memory [MB]", "memory kind"], rows)
    out += ["", "memory kind: alloc = CUDA peak allocated; saved = median bytes saved for backward (CPU runs)."]
    return [*out, ""]


def _memory(sweeps: list[Path], fig_dir: Path, base: Path) -> list[str]:
    from ablations.memory import plot_sweep, read_csv

    out = ["## 3. Memory sweep", ""]
    if not sweeps:
        return [*out, "No memory sweep was given (`ablate-memory`).", ""]
    for i, folder in enumerate(sweeps):
        rows = read_csv(folder / "memory.csv")
        task = rows[0]["task"] if rows else "?"
        out += [f"### {task} ({folder})", ""]
        if not rows:
            out += ["The sweep has no finished point yet.", ""]
            continue
        r0 = rows[0]
        out += [f"{r0['num_envs']} envs x {r0['horizon']} steps, {r0['image_size']} px, device {r0['device']}"
                + (f" ({r0['gpu']})" if r0.get("gpu") else "") + f", {r0['warmup_iters']} warm-up + "
                f"{r0['iters']} measured iterations per point, one process per point. Times are medians [ms]; "
                "memory [MB] is the maximum over the measured iterations (CUDA peaks are empty on the CPU).", ""]
        table = [[r["mode"], r["meshes"], r["verts_per_mesh"], r.get("scene_faces"), r.get("scene_verts"),
                  r.get("fwd_ms"), r.get("bwd_ms"), r.get("peak_alloc_mb"), r.get("peak_reserved_mb"),
                  r.get("saved_mb"), r["status"] + (f": {r['error']}" if r.get("error") else "")] for r in rows]
        out += _table(["mode", "meshes", "verts/mesh", "faces", "vertices", "fwd [ms]", "bwd [ms]",
                       "peak alloc [MB]", "peak reserved [MB]", "saved [MB]", "status"], table)
        out.append("")
        sub = fig_dir / f"memory_{i}_{task}"
        for f in plot_sweep(rows, sub):
            out += [f"![{f.stem} ({task})]({_rel(f, base)})", ""]
    return out


def _provenance(runs: list[Run], sweeps: list[Path], benchmarks: list[tuple[Path, dict, list[dict]]]) -> list[str]:
    out = ["## 4. Provenance", "", f"Report written {_dt.datetime.now().astimezone().isoformat(timespec='seconds')} "
           f"by `{_command(sys.argv)}`.", ""]
    if runs:
        out += ["### Runs", ""]
        rows = []
        for r in sorted(runs, key=lambda r: str(r.path)):
            env = r.environment
            versions = ", ".join(f"{k} {env[k]}" for k in ("python", "torch", "cuda", "mujoco",
                                                             "pytorch_kinematics") if env.get(k))
            rows.append([str(r.path), _run_device(r), versions, _commit(r), _mtime(r.path / "config.json"),
                         _mtime(r.path / "summary.json") if (r.path / "summary.json").exists() else "-",
                         f"`{_command(r.command)}`"])
        out += _table(["run", "device", "versions", "commit", "started (config.json)", "ended (summary.json)",
                       "command"], rows)
        out.append("")
    for folder in sweeps:
        try:
            meta = json.loads((folder / "memory.json").read_text())
        except (OSError, json.JSONDecodeError):
            meta = {}
        env = meta.get("environment") or {}
        out += [f"### Memory sweep {folder}", "",
                f"- dates: started {meta.get('started', '?')}, last point {meta.get('updated', '?')}",
                f"- device: {env.get('gpu') or env.get('device') or '?'}; versions: "
                + (", ".join(f"{k} {env[k]}" for k in ("python", "torch", "cuda", "mujoco") if env.get(k)) or "?")]
        for c in meta.get("commands", []):
            out.append(f"- command ({c.get('started', '?')}): `{_command(c.get('argv'))}`")
        out.append("")
    for path, meta, _ in benchmarks:
        out += [f"### Benchmark {path}", "",
                f"- date: {meta.get('date', _mtime(path) + ' (file time)')}",
                f"- device: {meta.get('gpu') or meta.get('device') or '?'}; versions: "
                f"{meta.get('versions') or '?'}",
                f"- command: `{_command(meta.get('command'))}`", ""]
    return out


# ---------------------------------------------------------------------------------------------- the report
def build_report(cfg: ReportConfig) -> Path:
    """Write the report (and its figures) and return its path; ValueError on bad or missing input."""
    if not cfg.runs and not cfg.memory and not cfg.benchmark:
        raise ValueError("nothing to report: give run folders, --memory SWEEP_DIR and/or --benchmark FILE.json")
    runs = find_runs(list(cfg.runs)) if cfg.runs else []
    sweeps = []
    for m in cfg.memory:
        m = Path(m)
        if not (m / "memory.csv").exists():
            raise ValueError(f"--memory {m}: no memory.csv there (not an ablate-memory output folder)")
        sweeps.append(m)
    benchmarks = [(Path(b), *load_benchmark(b)) for b in cfg.benchmark]

    out = Path(cfg.out)
    if out.suffix.lower() != ".md":
        raise ValueError(f"--out {out}: the report is a markdown file; give a path ending in .md")
    base = out.parent
    fig_dir = base / "figures"
    try:
        fig_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"cannot create {fig_dir}: {e}") from None

    lines = [f"# {cfg.title}", ""]
    inputs = []
    if runs:
        inputs.append(f"{len(runs)} run folder(s)")
    if sweeps:
        inputs.append(f"{len(sweeps)} memory sweep(s)")
    if benchmarks:
        inputs.append(f"{len(benchmarks)} benchmark file(s)")
    lines += [f"Built from {', '.join(inputs)}. Sections without inputs say so; no number here is estimated.", ""]
    lines += _table1(collect_bwd(runs, benchmarks))
    lines += _curves(runs, fig_dir, base)
    lines += _memory(sweeps, fig_dir, base)
    lines += _provenance(runs, sweeps, benchmarks)

    from gradlab.checkpoint import atomic_write_text

    atomic_write_text(out, "\n".join(lines).rstrip() + "\n")
    return out
