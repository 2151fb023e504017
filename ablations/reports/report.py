"""One markdown report from whatever measurements exist: ``ablate-report RUN_DIR... --memory DIR --out report.md``.

Sections:
    1. Backward time per iteration (the paper's Table 1): for cartpole, hopper, ant and humanoid, our median
       backward ms of decoupled (D.Va) and full (SHAC through the renderer) and their ratio, beside the
       paper's numbers (ablations/reports/paper_numbers.json, with its citation), labelled as the paper's. A task or
       mode without a measurement says "not run"; nothing is estimated. Runs of one mode that differ in
       preset, raster model or renderer are told apart (``full (hard)``), one row per full variant.
    2. Training curves: the ``ablate-plot`` figures of the given runs (return curves with the zero- and
       random-action floors), the floors table, and a table of the runs. Runs are grouped by arm
       (:func:`ablations.reports.arms.arm_label`: ``decoupled``, ``full-soft``, ``full-hard-dva``, ...).
    3. Seed statistics (:func:`ablations.reports.seeds.seed_section`): per task and arm the IQM of the final evaluation
       return (every run over the same evaluation iterations) with 95 % CIs, paired differences against
       decoupled (per seed, seeds agreeing in sign, exact bootstrap interval, exact sign-flip p-value, Holm's
       correction over every comparison of the report) with the probability of improvement, AUC and collapse
       rate, at equal iterations and (from iteration times measured alone) at equal wall-clock; the verdict by
       the control rule (arms are ranked only where decoupled beats blind after correction); the paired
       differences along the budget, learning curves with intervals, performance profiles and the evaluation
       curves. Runs without deterministic evaluations are said to have none.
    4. Gradient probes where the policy looks (:func:`ablations.reports.seeds.probe_section`): medians of the cosines
       and norms over the probes whose image sensitivity shows the policy looking, how many counted, and the
       exploration-noise and image-sensitivity figures.
    5. Memory sweeps: the ``ablate-memory`` table(s) and plots.
    6. Provenance: device, versions, dates and the command behind every input, and this report's command.
       A run's start and end are config.json's ``started_utc`` and summary.json's ``ended_utc``; runs that
       did not record them show the files' modification times, marked "(file time)" (a copy or a checkout
       changes those).

The sections are functions (``table1_section``, ``curves_section`` = ``figure_lines`` + ``floors_section`` +
``runs_table``, ``ablations.reports.seeds.seed_section``, ``ablations.reports.seeds.probe_section``, ``memory_section``,
``provenance_section``) that ``ablate-paper`` composes into its report.

Where our backward times come from, in order of precedence per (task, mode):
    a benchmark JSON (``--benchmark``), then the runs' summary.json ``median_bwd_ms`` (warm-up and probe
    iterations excluded; recomputed the same way from metrics.jsonl when a run has no summary); several runs
    of one (task, mode) give the median of their medians.

Benchmark JSON (a dedicated timing measurement; the format this module reads)::

    {"date": "...", "command": "...", "device": "cuda", "gpu": "NVIDIA H100 ...", "versions": {"torch": ...},
     "results": [{"task": "ant", "mode": "full", "bwd_ms": 123.4,
                  "num_envs": 64, "horizon": 32, "image_size": 84}, ...]}

A bare list of result objects is accepted too; ``median_bwd_ms`` is accepted for ``bwd_ms``. Results whose
``status`` is not ``ok`` (``benchmarks/iteration.py`` records oom and error points) are left out. The same files'
``iter_ms`` give the seed statistics' equal-wall-clock view, as do ``benchmarks/population.py`` files (a "rows"
list), which hold no Table 1 rows.
The figures are (re)drawn into ``<report folder>/figures/`` so the report folder is self-contained. Every path
the report names (inputs, figures, the floors file) is relative to the report's folder, and recorded commands show
their program by name: a report holds no absolute path of the machine that wrote it.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import shlex
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from statistics import median

import tyro

from ablations.memory import plot_sweep, read_csv
from ablations.reports.paper_numbers import load_paper_numbers
from ablations.reports.parts import (
    NOT_RUN,
    figure_lines,
    is_population_member,
    markdown_table,
    ms_text,
    read_benchmark_json,
    report_path,
    run_device,
    run_median_ms,
)
from ablations.reports.plot import FIGURES, make_plots
from ablations.reports.seeds import PROBE_FIGURES, SEED_FIGURES, arm_label, probe_section, seed_section
from ablations.reports.stats import check_at_iteration
from ablations.reports.style import Floors, PlotResult, group_runs, load_floors
from ablations.run_folder import Run, RunFolder, find_runs, say_metrics_notes
from gradlab.files import atomic_write_text
from vocabulary import PRESET_RASTER_MODEL

__all__ = ["ReportConfig", "build_report", "PAPER_TABLE1_MS", "PAPER_DEVICE", "TABLE1_TASKS", "run_bwd_ms",
           "load_benchmark", "collect_bwd", "Cell", "table1_section", "curves_section", "floors_section",
           "memory_section", "provenance_section", "load_memory_sweeps", "runs_table", "command_text"]

_PAPER = load_paper_numbers()
#: The paper's Table 1: backward time per iteration, converted from seconds to ms: task -> (D.Va = decoupled,
#: SHAC with rendering = full); from ablations/reports/paper_numbers.json, which cites it.
PAPER_TABLE1_MS = _PAPER.table1_ms()
#: The tasks of the paper's Table 1, in its order: Table 1 here has a row for each (and for any other task measured).
TABLE1_TASKS = tuple(PAPER_TABLE1_MS)
PAPER_DEVICE = _PAPER.table1_device()
#: The decoupled arm's image model (D.Va's preset): the decoupled row a benchmark's full row is set beside.
_DVA_RASTER = PRESET_RASTER_MODEL["dva"]


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
    floors: Path | None = None
    """task-floors JSON with the zero- and random-action return floors; None: docs/floors.json of this checkout."""
    title: str = "Policy gradients through pixels: full vs decoupled"
    """Title of the report."""
    reps: int = 2000
    """Bootstrap resamples per confidence interval of the seed statistics (ablations.reports.stats.DEFAULT_REPS)."""
    at_iteration: int | None = None
    """Read the seed statistics (section 3) as if every run had stopped at this iteration, e.g. to set longer
    runs beside shorter ones; None: at the fewest iterations any run of the task reached."""
    registration: Path | None = None
    """A confirmatory registration (preregistration.json, ablations/registration.py): the report opens with the
    registered family analysed at the latest complete look, and section 3 shows everything else without Holm's
    correction and without verdicts. Registered runs whose tree hash or registered fields differ are refused by
    name. None: no registration (section 3 corrects and reads what it shows)."""


# ---------------------------------------------------------------------------------------------- inputs
def run_bwd_ms(run: Run) -> float | None:
    """A run's median backward ms per iteration (:func:`run_median_ms`)."""
    return run_median_ms(run, "bwd_ms")


def load_benchmark(path: str | os.PathLike) -> tuple[dict, list[dict]]:
    """(metadata, results) of a benchmark JSON; ValueError naming the problem for anything else."""
    path = Path(path)
    data = read_benchmark_json(path)
    meta, results = ({}, data) if isinstance(data, list) else (data, data.get("results") if isinstance(data, dict)
                                                               else None)
    if isinstance(data, dict) and results is None and isinstance(data.get("rows"), list):
        # benchmarks/population.py: iteration times of populations (ablations.reports.arms reads them); no Table 1 rows
        return {k: v for k, v in meta.items() if k != "rows"}, []
    if not isinstance(results, list):
        raise ValueError(f"--benchmark {path}: expected a 'results' list of {{task, mode, bwd_ms}} objects")
    out = []
    for i, r in enumerate(results):
        if isinstance(r, dict) and r.get("status", "ok") != "ok":
            continue  # a point the benchmark could not measure (oom, error): nothing to report
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


@dataclass
class Cell:
    """Our backward time for one (task, label) and where it came from; ``mode`` is the label's mode.
    ``decoupled``: for a full cell of a benchmark file, (label, cell) of the decoupled time that file measured
    with it (D.Va's own image model where it timed several), the partner of a full / decoupled ratio."""

    ms: float
    n: int
    source: str
    setting: str
    device: str
    mode: str = ""
    decoupled: tuple[str, Cell] | None = None


def collect_bwd(runs: list[Run], benchmarks: list[tuple[Path, dict, list[dict]]], *, label=None
                ) -> dict[tuple[str, str], Cell]:
    """Our backward-time cells keyed by (task, label): benchmarks first (label = mode), then runs grouped by
    :func:`ablations.reports.style.group_runs` with ``label`` (see the module docstring), population members left out
    (:func:`is_population_member`)."""
    cells: dict[tuple[str, str], Cell] = {}
    for path, meta, results in benchmarks:
        # Rows of one mode that differ in raster model or renderer (benchmarks/iteration.py records both) are
        # told apart as runs are: "full (hard)" beside "full (alpha)".
        varying = {m: [k for k in ("raster_model", "renderer")
                       if len({json.dumps(r.get(k)) for r in results if r["mode"] == m}) > 1]
                   for m in {r["mode"] for r in results}}
        by_key: dict[tuple[str, str], list[dict]] = {}
        for r in results:
            keys = varying[r["mode"]]
            lab = f"{r['mode']} ({', '.join(str(r.get(k)) for k in keys)})" if keys else r["mode"]
            by_key.setdefault((r["task"], lab), []).append(r)
        here = {}
        for key, rs in by_key.items():
            settings = sorted({_setting(r) for r in rs})
            here[key] = Cell(ms=median([r["bwd_ms"] for r in rs]), n=len(rs), source=f"benchmark {path.name}",
                             setting=" / ".join(settings), device=str(meta.get("gpu") or meta.get("device") or "?"),
                             mode=rs[0]["mode"])
        for (task, _), cell in here.items():
            if cell.mode != "full":
                continue
            # the decoupled arm's own rows first: D.Va's image model, rasterized (not ray-traced), then by label
            decs = sorted((key for key in by_key if key[0] == task and here[key].mode == "decoupled"),
                          key=lambda key: (by_key[key][0].get("raster_model") not in (None, _DVA_RASTER),
                                           by_key[key][0].get("renderer") not in (None, "soft"), key[1]))
            if decs:
                cell.decoupled = (decs[0][1], here[decs[0]])
        for key, cell in here.items():
            cells.setdefault(key, cell)  # the first benchmark given wins
    for (task, lab), rs in group_runs(runs, label=label).items():
        if (task, lab) in cells:
            continue
        vals = [(v, r) for r in rs if not is_population_member(r) and (v := run_bwd_ms(r)) is not None]
        if not vals:
            continue
        settings = sorted({_setting(r.config) for _, r in vals})
        devices = sorted({run_device(r) for _, r in vals})
        cells[(task, lab)] = Cell(ms=median([v for v, _ in vals]), n=len(vals), source="runs",
                                  setting=" / ".join(settings), device=" / ".join(devices), mode=rs[0].mode)
    return cells


# ---------------------------------------------------------------------------------------------- formatting
def _mtime(p: Path) -> str:
    try:
        return _dt.datetime.fromtimestamp(p.stat().st_mtime).astimezone().isoformat(timespec="seconds")
    except OSError:
        return "?"


def _started(run: Run) -> str:
    """config.json's started_utc, else the file's modification time, marked as such."""
    if run.started_utc:
        return run.started_utc
    return f"{_mtime(RunFolder(run.path).config_path)} (file time)"


def _ended(run: Run) -> str:
    """summary.json's ended_utc, else its modification time, marked as such; '-' without a summary."""
    ended = (run.summary or {}).get("ended_utc")
    if isinstance(ended, str) and ended:
        return ended
    path = RunFolder(run.path).summary_path
    return f"{_mtime(path)} (file time)" if path.exists() else "-"


def _program(path: str) -> str:
    """A command's program by its name, not the path it had on the machine that ran it: ``ablate``, or
    ``python -m ablations`` for a package's ``__main__.py``."""
    p = Path(path)
    return f"python -m {p.parent.name}" if p.name == "__main__.py" else p.name


def command_text(cmd) -> str:
    """A recorded command line (argument list, or text as recorded) as the report shows it."""
    if isinstance(cmd, (list, tuple)) and cmd:
        return " ".join([_program(str(cmd[0])), *(shlex.quote(str(c)) for c in cmd[1:])])
    return str(cmd) if cmd else "(not recorded)"


def _commit(run: Run) -> str:
    try:
        first = (run.path / "git.txt").read_text().splitlines()[0]
    except (OSError, IndexError):
        return "?"
    return first.split()[1][:12] if first.startswith("commit ") and len(first.split()) > 1 else first[:40]


# ---------------------------------------------------------------------------------------------- sections
def table1_section(cells: dict[tuple[str, str], Cell], *, heading: str = "## 1. Backward time per iteration (Table 1)",
                   members_left_out: int = 0) -> list[str]:
    """Table 1: our decoupled and full backward ms per task beside the paper's; one row per full variant.
    ``members_left_out``: how many runs :func:`collect_bwd` left out as population members (said below it)."""
    cite = _PAPER.cite(_PAPER.backward_s[0]["source"]) if _PAPER.backward_s else "?"
    out = [heading, "",
           "Median backward time of one SHAC iteration (one window of `horizon` steps for `num_envs` "
           "environments), in ms. **Ours** is measured by this toolkit (CUDA-synchronised timers, warm-up "
           f"excluded); **paper** is {cite}, converted from seconds, quoted for comparison and not measured "
           "here. The reference implementation's timers do not synchronise CUDA, so its times may not include "
           "all asynchronous GPU work. Absolute times depend on the device and the sizes; compare the ratios.", ""]
    header = ["task", "ours: decoupled (D.Va) [ms]", "ours: full [ms]", "ours: full / decoupled",
              "ours: setting (envs x steps, image), device, source",
              f"paper ({PAPER_DEVICE}): D.Va [ms]", f"paper ({PAPER_DEVICE}): SHAC with rendering [ms]",
              "paper: ratio"]
    rows = []
    extra = sorted({t for t, _ in cells if t not in TABLE1_TASKS})

    def of_mode(task: str, mode: str) -> list[tuple[str, Cell]]:
        found = [(lab, c) for (t, lab), c in cells.items() if t == task and (c.mode or lab) == mode]
        # The plain mode first (a benchmark's, or runs without variants), then the variants by label.
        return sorted(found, key=lambda lc: (lc[0] != mode, lc[0]))

    for task in (*TABLE1_TASKS, *extra):
        decs = of_mode(task, "decoupled")
        paper = PAPER_TABLE1_MS.get(task)
        for full_label, full in of_mode(task, "full") or [("full", None)]:
            # the decoupled time its benchmark file measured with it, where there is one: a ratio needs both
            dec_label, dec = (full.decoupled if full and full.decoupled else None) or (
                decs[0] if decs else ("decoupled", None))
            if dec and full:
                # A ratio of two times means something only when one process kind on one device measured both
                # (a benchmark alone on its GPU; runs that shared theirs are slowed by their neighbours).
                if dec.setting != full.setting:
                    ratio = "n/a (settings differ)"
                elif (dec.source, dec.device) != (full.source, full.device):
                    ratio = "n/a (measured apart)"
                else:
                    ratio = f"{full.ms / dec.ms:.2f}x" if dec.ms > 0 else NOT_RUN
            else:
                ratio = NOT_RUN
            info = []
            for name, c in ((dec_label, dec), (full_label, full)):
                if c:
                    info.append(f"{name}: {c.setting}, {c.device}, {c.source} (n={c.n})")
            rows.append([task, ms_text(dec.ms if dec else None), ms_text(full.ms if full else None), ratio,
                         "; ".join(info) or NOT_RUN,
                         ms_text(paper[0]) if paper else "-", ms_text(paper[1]) if paper else "-",
                         f"{paper[1] / paper[0]:.2f}x" if paper else "-"])
    out += markdown_table(header, rows)
    state = sorted((t, lab) for (t, lab), c in cells.items() if (c.mode or lab) in ("state", "blind"))
    if state:
        out += ["", "Runs that render nothing during training (state, blind) have backward times too: "
                + ", ".join(f"{t} {lab} {ms_text(cells[(t, lab)].ms)} ms" for t, lab in state) + "."]
    if members_left_out:
        out += ["", f"{members_left_out} run(s) trained as population members are left out: a member's times are "
                "its whole population's (give --benchmark files for their arms' times alone)."]
    return [*out, ""]


def floors_section(runs: list[Run], floors: Floors, *, base: Path) -> list[str]:
    """The zero- and random-action return floors of the runs' tasks, their source (relative to ``base``, the
    report's folder), and the tasks without one."""
    tasks = list(dict.fromkeys(t for t, _ in group_runs(runs)))
    out = ["### Return floors", ""]
    if floors.source is not None:
        floors = replace(floors, source=Path(report_path(floors.source, base)))
    if floors.source is None:
        out += ["No floors file (docs/floors.json of this checkout is missing; give --floors FILE written by "
                "`task-floors`): the return curves have no floor lines.", ""]
        return out
    out += [f"Undiscounted episode return of zero action and of uniform random actions in [-1, 1] "
            f"(mean +- std over episodes), from `{floors.source}` (written by `task-floors`); drawn as "
            "horizontal lines beside every return curve. A learning curve means little below them.", ""]
    rows = []
    for task in tasks:
        f = floors.of(task)
        if f is None:
            rows.append([task, "no entry", "no entry", "-"])
            continue
        cells = [f"{f[k]['mean']:.4g} +- {f[k].get('std', float('nan')):.3g}" if k in f else "-"
                 for k in ("zero", "random")]
        eps = {f[k].get("episodes") for k in f if f[k].get("episodes") is not None}
        rows.append([task, *cells, " / ".join(str(e) for e in sorted(eps)) or "?"])
    out += markdown_table(["task", "zero action", "random action", "episodes"], rows)
    missing = [t for t in tasks if floors.of(t) is None]
    if missing:
        out += ["", "**Warning:** " + "; ".join(floors.missing_message(t) for t in missing) + "."]
    return [*out, ""]


def runs_table(runs: list[Run], *, label=None) -> list[str]:
    """One row per run: its group, status, size, training return at its end (the exploring policy's last 100
    episodes: not the deterministic evaluation return the seed statistics read), medians of time and memory."""
    rows = []
    for (_task, lab), rs in group_runs(runs, label=label).items():
        for r in rs:
            s = r.summary or {}
            last = r.metrics[-1] if r.metrics else {}
            peak = s.get("peak_alloc_mb")
            rows.append([r.path.name, r.task, lab, r.seed, s.get("status", "no summary"),
                         s.get("iterations", last.get("iter")), s.get("env_steps", last.get("env_steps")),
                         s.get("final_return", last.get("return_mean")), s.get("median_fwd_ms"), run_bwd_ms(r),
                         peak if peak is not None else s.get("median_saved_mb"),
                         "alloc" if peak is not None else "saved" if s.get("median_saved_mb") is not None else ""])
    out = markdown_table(["run", "task", "mode", "seed", "status", "iterations", "env steps",
                          "training return (last 100 episodes, at the run's end)",
                          "median fwd [ms]", "median bwd [ms]", "memory [MB]", "memory kind"], rows)
    out += ["", "memory kind: alloc = CUDA peak allocated; saved = median bytes saved for backward (CPU runs)."]
    members = sum(map(is_population_member, runs))
    if members:
        out.append(f"{members} run(s) trained as population members: their times and memory are their whole "
                   "population's.")
    return [*out, ""]


def curves_section(runs: list[Run], fig_dir: Path, base: Path, *, floors: Floors,
                   heading: str = "## 2. Training curves", plots: PlotResult | None = None, label=None,
                   leave_out: tuple[str, ...] = ()) -> list[str]:
    """The ablate-plot figures (drawn into ``fig_dir`` unless ``plots`` holds them already; linked relative to
    ``base``) but those named in ``leave_out`` (shown by another section), the floors and a runs table;
    ``label``: a run's group (:func:`ablations.reports.style.group_runs`)."""
    out = [heading, ""]
    if not runs:
        return [*out, "No training runs were given.", ""]
    res = plots if plots is not None else make_plots(runs, fig_dir, floors=floors, label=label)
    out += ["Per task and group, mean +- one standard deviation across seeds (n in the legends; where fewer runs "
            "cover an iteration the line goes on dotted, with n at each change).", ""]
    out += [f"**{line}.**" for line in res.left_out if line.startswith("left out of every figure")]
    out += [""] if out[-1] != "" else []
    out += figure_lines(res, [f for f in FIGURES if f not in leave_out], base)
    out += floors_section(runs, floors, base=base)
    return [*out, "### Runs", "", *runs_table(runs, label=label)]


def memory_section(sweeps: list[Path], fig_dir: Path, base: Path, *, heading: str = "## 3. Memory sweep"
                   ) -> list[str]:
    """The ablate-memory table(s) and figures of each sweep folder (figures into ``fig_dir``)."""

    out = [heading, ""]
    if not sweeps:
        return [*out, "No memory sweep was given (`ablate-memory`).", ""]
    for i, folder in enumerate(sweeps):
        rows = read_csv(folder / "memory.csv")
        task = rows[0]["task"] if rows else "?"
        out += [f"### {task} ({report_path(folder, base)})", ""]
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
        out += markdown_table(["mode", "meshes", "verts/mesh", "faces", "vertices", "fwd [ms]", "bwd [ms]",
                       "peak alloc [MB]", "peak reserved [MB]", "saved [MB]", "status"], table)
        out.append("")
        sub = fig_dir / f"memory_{i}_{task}"
        for f in plot_sweep(rows, sub):
            out += [f"![{f.stem} ({task})]({report_path(f, base)})", ""]
    return out


def provenance_section(runs: list[Run], sweeps: list[Path], benchmarks: list[tuple[Path, dict, list[dict]]], *,
                       base: Path, heading: str = "## 4. Provenance") -> list[str]:
    """Device, versions, commit, start and end, and command of every input (paths relative to ``base``, the
    report's folder), and this report's command."""
    out = [heading, "", f"Report written {_dt.datetime.now().astimezone().isoformat(timespec='seconds')} "
           f"by `{command_text(sys.argv)}`.", ""]
    if runs:
        out += ["### Runs", ""]
        rows = []
        for r in sorted(runs, key=lambda r: str(r.path)):
            env = r.environment
            versions = ", ".join(f"{k} {env[k]}" for k in ("python", "torch", "cuda", "mujoco",
                                                             "pytorch_kinematics") if env.get(k))
            rows.append([report_path(r.path, base), run_device(r), versions, _commit(r), _started(r), _ended(r),
                         f"`{command_text(r.command)}`"])
        out += markdown_table(["run", "device", "versions", "commit", "started (config.json started_utc)",
                               "ended (summary.json ended_utc)", "command"], rows)
        out.append("")
    for folder in sweeps:
        try:
            meta = json.loads((folder / "memory.json").read_text())
        except (OSError, json.JSONDecodeError):
            meta = {}
        env = meta.get("environment") or {}
        out += [f"### Memory sweep {report_path(folder, base)}", "",
                f"- dates: started {meta.get('started', '?')}, last point {meta.get('updated', '?')}",
                f"- device: {env.get('gpu') or env.get('device') or '?'}; versions: "
                + (", ".join(f"{k} {env[k]}" for k in ("python", "torch", "cuda", "mujoco") if env.get(k)) or "?")]
        for c in meta.get("commands", []):
            out.append(f"- command ({c.get('started', '?')}): `{command_text(c.get('argv'))}`")
        out.append("")
    for path, meta, _ in benchmarks:
        out += [f"### Benchmark {report_path(path, base)}", "",
                f"- date: {meta.get('date', _mtime(path) + ' (file time)')}",
                f"- device: {meta.get('gpu') or meta.get('device') or '?'}; versions: "
                f"{meta.get('versions') or '?'}",
                f"- command: `{command_text(meta.get('command'))}`", ""]
    return out


# ---------------------------------------------------------------------------------------------- the report
def load_memory_sweeps(folders) -> list[Path]:
    """The ablate-memory folders, each checked for its memory.csv (ValueError naming the folder)."""
    sweeps = []
    for m in folders:
        m = Path(m)
        if not (m / "memory.csv").exists():
            raise ValueError(f"--memory {m}: no memory.csv there (not an ablate-memory output folder)")
        sweeps.append(m)
    return sweeps


def build_report(cfg: ReportConfig) -> Path:
    """Write the report (and its figures) and return its path; ValueError on bad or missing input."""
    if not cfg.runs and not cfg.memory and not cfg.benchmark:
        raise ValueError("nothing to report: give run folders, --memory SWEEP_DIR and/or --benchmark FILE.json")
    if cfg.reps < 1:
        raise ValueError(f"--reps must be a positive number of bootstrap resamples, got {cfg.reps}")
    try:
        check_at_iteration(cfg.at_iteration)
    except ValueError as e:
        raise ValueError(f"--at-iteration: {e}") from None
    runs = find_runs(list(cfg.runs)) if cfg.runs else []
    say_metrics_notes(runs)  # damaged lines skipped, iterations twice or out of order
    sweeps = load_memory_sweeps(cfg.memory)
    benchmarks = [(Path(b), *load_benchmark(b)) for b in cfg.benchmark]
    floors = load_floors(cfg.floors)

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
    if cfg.registration is not None:
        from ablations.registration import load_registration
        from ablations.reports.confirmatory import registered_section

        lines += registered_section(load_registration(cfg.registration), runs)
    label = arm_label(runs) if runs else None
    plots = make_plots(runs, fig_dir, floors=floors, label=label) if runs else None
    lines += table1_section(collect_bwd(runs, benchmarks),
                            members_left_out=sum(map(is_population_member, runs)))
    lines += curves_section(runs, fig_dir, base, floors=floors, plots=plots, label=label,
                            leave_out=(*SEED_FIGURES, *PROBE_FIGURES))
    lines += seed_section(runs, fig_dir, base, label=label, benchmarks=cfg.benchmark, floors=floors, plots=plots,
                          reps=cfg.reps, at_iteration=cfg.at_iteration, exploratory=cfg.registration is not None)
    lines += probe_section(runs, base, label=label, plots=plots)
    lines += memory_section(sweeps, fig_dir, base, heading="## 5. Memory sweep")
    lines += provenance_section(runs, sweeps, benchmarks, base=base, heading="## 6. Provenance")

    atomic_write_text(out, "\n".join(lines).rstrip() + "\n")
    return out
