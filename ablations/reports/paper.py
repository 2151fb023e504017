"""The report of an ``ablate-paper`` sweep folder: :func:`build_paper_report` (``ablations.paper`` is the command).

The report (``<out>/report/report.md``, figures beside it; ``--report-only DIR`` redraws it from an existing sweep
folder) has:

    1. the arms and how many of their runs finished;
    2. return against wall-clock time and against environment steps, mean +- one standard deviation across
       seeds, with the zero- and random-action floors (``docs/floors.json`` or ``--floors``);
    3. the paper's Fig. 3: the full and the decoupled gradient norms and their cosine over training, from the
       probe iterations (both gradients of the same rollout), with the render term by parameter group and the
       per-frame image sensitivity, and a table of their medians;
    4. our numbers beside the paper's (ablations/reports/paper_numbers.json, each with its citation; "~" marks values
       read off a plot): final return, return at the paper's comparison time, wall-clock time to the paper's
       return at that time, backward time per iteration;
    5. Table 1 (backward time per iteration) from a ``benchmarks/iteration.py`` JSON (``--benchmark``), else
       from the runs; 6. each arm's iteration time alone (from a benchmarks/iteration.py or
       benchmarks/population.py JSON) beside its runs' (a population member's is its population's:
       ``ablations.reports.arms.iteration_times``); 7. the memory sweep (Fig. 10) of ``ablate-memory`` folders
       (``--memory``); 8. the runs; 9. provenance.

A task whose zero action scores at least the paper's final return there (D.Va's cartpole: the pole starts upright
and stays so) is marked as not ranking arms. Nothing is estimated: a comparison without our measurement says
"not run" or "not reached".
"""


from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path

import numpy as np

from ablations.reports import iteration_times, load_floors, make_plots
from ablations.reports.paper_numbers import PaperNumbers, format_value, load_paper_numbers
from ablations.reports.parts import (
    NOT_RUN,
    figure_lines,
    is_population_member,
    markdown_table,
    read_benchmark_json,
    report_path,
    run_median_ms,
)
from ablations.reports.report import (
    collect_bwd,
    command_text,
    floors_section,
    load_benchmark,
    load_memory_sweeps,
    memory_section,
    provenance_section,
    runs_table,
    table1_section,
)
from ablations.reports.seeds import NOT_RANKING, not_ranking_reason
from ablations.run_folder import Run, RunFolder, is_number, load_run
from gradlab.files import atomic_write_text
from vocabulary import ARMS

__all__ = ["build_paper_report"]

_RETURN_FIGURES = ("return_vs_wall_clock.png", "return_vs_env_steps.png", "return_vs_iter.png")
_FIG3_FIGURES = ("probe_grad_norms.png", "cosine_vs_iter.png", "cosine_hist.png", "render_term_groups.png",
                 "image_sensitivity.png")
_COST_FIGURES = ("timing.png", "memory.png", "grad_norm.png")



def _sweep_runs(folder: Path) -> tuple[dict, list[Run], dict[str, str], list[str]]:
    """(manifest, runs with a run folder, run folder name -> arm, ids of runs without a folder)."""
    from ablations.sweep import load_manifest

    if not folder.is_dir():
        raise ValueError(f"--report-only {folder}: no such folder")
    manifest = load_manifest(folder)
    if manifest is None:
        raise ValueError(f"--report-only {folder}: no sweep.json there (not an ablate-paper or ablate-sweep folder)")
    runs, arm_of, missing = [], {}, []
    for run_id, rec in manifest.get("runs", {}).items():
        path = folder / rec.get("folder", f"runs/{run_id}")
        if not RunFolder(path).config_path.exists():
            missing.append(run_id)
            continue
        run = load_run(path)
        runs.append(run)
        arm_of[path.name] = rec.get("arm") or rec.get("mode") or run.mode
    return manifest, runs, arm_of, missing


def _mean_std(vals: list[float]) -> str:
    if not vals:
        return NOT_RUN
    std = f" +- {np.std(vals, ddof=1):.4g}" if len(vals) > 1 else ""
    return f"{np.mean(vals):.4g}{std} (n={len(vals)})"


def _final_return(run: Run) -> float | None:
    s = run.summary or {}
    if isinstance(s.get("final_return"), (int, float)):
        return float(s["final_return"])
    vals = run.series("iter", "return_mean")[1]
    return float(vals[-1]) if len(vals) else None


def _return_at(run: Run, seconds: float) -> float | None:
    """Return at a wall-clock time (linear between logged iterations); None if the run stopped before it."""
    x, y = run.series("wall_s", "return_mean")
    if not len(x) or x[-1] < seconds or x[0] > seconds:
        return None
    return float(np.interp(seconds, x, y))


def _time_to(run: Run, threshold: float) -> float | None:
    """Wall-clock seconds at the first logged iteration whose return reaches the threshold; None if never."""
    x, y = run.series("wall_s", "return_mean")
    hit = np.nonzero(y >= threshold)[0]
    return float(x[hit[0]]) if len(hit) else None


def _not_ranking(task: str, floors, paper: PaperNumbers) -> str:
    """Why a task of ``ablations.reports.seeds.NOT_RANKING`` ranks no arms, with its zero-action floor and the paper's
    final return there, where known."""
    finals = [format_value(e) for e in paper.final_return if e["task"] == task]
    return not_ranking_reason(task, floors, facts=[f"the paper's final return {', '.join(finals)}"] if finals else [])


def _packing_lines(manifest: dict) -> list[str]:
    """How the runs were packed into processes (sweep.json's jobs), when any population trained."""
    jobs = manifest.get("jobs") or {}
    sizes = sorted((len(j.get("runs", [])) for j in jobs.values()), reverse=True)
    if not any(n > 1 for n in sizes):
        return []
    populations = [n for n in sizes if n > 1]
    return ["", f"The runs trained in {len(sizes)} processes: {len(populations)} populations (of "
                f"{', '.join(map(str, populations))} members) and {len(sizes) - len(populations)} runs alone "
                f"(--pack {manifest.get('sweep', {}).get('pack', '?')}). A member's wall-clock and iteration time "
                "are its population's (section 6)."]


def _comparison(runs: list[Run], arm_of: dict[str, str], arms: list[str], tasks: list[str], paper: PaperNumbers,
                cells, not_ranking: dict[str, str]) -> list[str]:
    out = ["## 4. Our numbers beside the paper's", "",
           "Ours: mean +- sample standard deviation across seeds (n = seeds with the measurement). Paper: as "
           "published, with its source; `~` marks a value read off a plot. D.Va is our `decoupled` arm, SHAC with "
           "a differentiable renderer our `full-hard` arm (the hard rasterizer and the baseline's decay length); "
           "other arms have no counterpart in the paper. Our final return here is the training return (the "
           "exploring policy's last 100 episodes at the run's end), not the deterministic evaluation return of the "
           "seed statistics. Wall-clock times depend on the device: the paper's "
           "are on its device, ours on the device of each run (provenance below).", ""]
    if any(is_population_member(r) for r in runs):
        out += ["Packed runs' wall-clock times are their populations' (section 2 says why).", ""]
    if not_ranking:
        out += [f"Tasks marked `(does not rank arms)`: {', '.join(not_ranking)} (see the top of this report).", ""]
    method_of = {a: ARMS[a].paper for a in arms}
    by = {(t, a): [r for r in runs if r.task == t and arm_of.get(r.path.name) == a] for t in tasks for a in arms}
    rows = []
    for task in tasks:
        shown = f"{task} (does not rank arms)" if task in not_ranking else task
        for arm in arms:
            rs, method = by[(task, arm)], method_of[arm]
            finals = [v for r in rs if (v := _final_return(r)) is not None]
            minutes = [r.series("wall_s", "return_mean")[0][-1] / 60 for r in rs
                       if len(r.series("wall_s", "return_mean")[0])]
            ours = _mean_std(finals) + (f", after {np.mean(minutes):.0f} min" if minutes else "")
            entries = [e for e in paper.final_return if e["task"] == task and e["method"] == method]
            for e in entries or [None]:
                rows.append([shown, "final return (ours: training return)", arm, ours,
                             format_value(e) + (f" ({e['note']})" if e.get("note") else "") if e else "-",
                             paper.cite(e["source"]) if e else "-"])
        for e in (x for x in paper.return_at_time if x["task"] == task):
            for arm in arms:
                method = method_of[arm]
                rs = by[(task, arm)]
                at = [v for r in rs if (v := _return_at(r, 60 * e["minutes"])) is not None]
                ours = _mean_std(at) if at else (NOT_RUN if not rs else f"not reached ({len(rs)} runs stopped "
                                                                        f"before {e['minutes']:g} min)")
                paper_value = format_value(e, method) if method in e else "-"
                rows.append([shown, f"return at {e['minutes']:g} min", arm, ours, paper_value,
                             paper.cite(e["source"]) if method in e else "-"])
                if method in e:
                    threshold = e[method]
                    times = [t / 60 for r in rs if (t := _time_to(r, threshold)) is not None]
                    reached = f"{_mean_std(times)} min" if times else "not reached"
                    rows.append([shown, f"minutes to return {threshold:g}", arm,
                                 f"{reached}; {len(times)}/{len(rs)} seeds reached it" if rs else NOT_RUN,
                                 f"{'~' if e['approx'] else ''}<= {e['minutes']:g}", paper.cite(e["source"])])
        for e in (x for x in paper.backward_s if x["task"] == task):
            for arm in arms:
                method = method_of[arm]
                if method not in e:
                    continue
                cell = cells.get((task, arm))
                ours = f"{cell.ms:.4g} ms ({cell.source}, {cell.device})" if cell else NOT_RUN
                rows.append([shown, "backward per iteration", arm, ours, f"{1000 * e[method]:.4g} ms",
                             paper.cite(e["source"])])
    out += markdown_table(["task", "quantity", "arm", "ours", "paper", "paper's source"], rows)
    return [*out, ""]


def _packed_wall_clock_note(runs: list[Run]) -> list[str]:
    """A paragraph for wall-clock results when some runs trained as population members (none otherwise)."""
    if not any(is_population_member(r) for r in runs):
        return []
    return ["**Packed runs:** a population member's wall-clock is its population's (one iteration trains every "
            "member together), so for packed runs return against wall-clock time compares populations, not arms; "
            "section 6 sets each arm's iteration time alone beside its population's.", ""]


def _population_comparison(paths) -> list[list]:
    """Rows of benchmarks/population.py files: task, N, one iteration of an N-member population, of each of N
    single runs sharing the GPU at once, and the throughput ratio (the first file that has a (task, N) wins)."""
    rows, seen = [], set()
    for path in map(Path, paths):
        data = read_benchmark_json(path)
        found = data.get("rows") if isinstance(data, dict) else None
        ok = [r for r in found or [] if isinstance(r, dict) and r.get("status", "ok") == "ok"
              and is_number(r.get("iter_ms"))]
        device = data.get("gpu") or data.get("device") or "?"
        for task, n in sorted({(r.get("task"), r.get("members")) for r in ok if r.get("kind") == "population"
                               and isinstance(r.get("members"), int) and r["members"] > 1} - seen):
            seen.add((task, n))
            together = [r["iter_ms"] for r in ok if r.get("kind") == "population" and r.get("task") == task
                        and r.get("members") == n]
            apart = [r["iter_ms"] for r in ok if r.get("kind") == "separate" and r.get("task") == task
                     and r.get("processes") == n]
            pop, sep = float(np.median(together)), float(np.median(apart)) if apart else None
            rows.append([task, n, f"{pop:.4g}", f"{pop / n:.4g}", f"{sep:.4g}" if sep else "-",
                         f"{sep / pop:.2f}x" if sep else "-", f"benchmark {path.name}, {device}"])
    return rows


def _iteration_time_section(runs: list[Run], label, manifest: dict, folder: Path, benchmarks) -> list[str]:
    """Section 6: per task and arm, its iteration time alone (a benchmark: ``ablations.reports.arms.iteration_times``)
    beside its runs' median and how they trained (alone, or in populations of N); the benchmark's populations
    against separate processes; and, for packed arms without a time alone, that their wall-clock is not theirs."""
    out = ["## 6. Iteration time: each arm alone, and as its runs trained here", "",
           "*Alone*: one run of the arm timed by itself (a benchmarks/iteration.py or benchmarks/population.py JSON "
           "given with --benchmark). *Here*: the median over the arm's runs of their median iteration time "
           "(warm-up and probe iterations left out) as they trained in this sweep. A population member's "
           "iteration is its population's, every member's step together: for a packed arm *here* is the "
           "population's time, not the arm's.", ""]
    jobs = manifest.get("jobs") or {}
    sizes_of = {(folder / rec.get("folder", f"runs/{run_id}")).resolve(): len(jobs.get(rec.get("job"), {}).get(
        "runs", [])) or 1 for run_id, rec in manifest.get("runs", {}).items()}

    def size(run: Run) -> int:
        """Runs in its process, as sweep.json's jobs record them."""
        return sizes_of.get(run.path.resolve(), 1)

    times = iteration_times(runs, label, benchmarks)
    groups: dict[tuple[str, str], list[Run]] = {}
    for r in runs:
        groups.setdefault((r.task, label(r)), []).append(r)
    rows, unknown = [], []
    for (task, arm), rs in groups.items():
        found = times[task].found.get(arm) if task in times else None
        alone = found if found is not None and found.source != "runs" else None
        here = [v for r in rs if (v := run_median_ms(r, "iter_ms")) is not None]
        sizes = sorted({size(r) for r in rs})
        how = "alone in its process" if sizes == [1] else "in populations of " + ", ".join(map(str, sizes))
        rows.append([task, arm, f"{alone.ms:.4g}" if alone else "not measured",
                     f"{alone.source}, {alone.device} (n={alone.n})" if alone else "-",
                     f"{np.median(here):.4g}" if here else "-", how])
        if alone is None and sizes != [1]:
            unknown.append(f"{task} {arm}")
    out += [*markdown_table(["task", "arm", "alone [ms]", "alone: source", "here [ms]", "how its runs trained"],
                            rows), ""]
    gpus = manifest.get("sweep", {}).get("gpus_per_run")
    if is_number(gpus) and 0 < gpus < 1:
        out += [f"Processes shared GPUs here (--gpus-per-run {gpus:g}): *here* includes waiting for the other "
                "processes on the same GPU.", ""]
    if unknown:
        out += [f"No benchmark gives the iteration time alone of {', '.join(unknown)}: wall-clock comparisons of "
                "packed members are not an arm's own time. Compare them at equal iterations or environment steps, "
                "or time the arms alone (benchmarks/iteration.py) and pass the JSON with --benchmark.", ""]
    comparison = _population_comparison(benchmarks)
    if comparison:
        out += ["A population against separate processes (benchmarks/population.py): one iteration of an N-member "
                "population, and that of each of N single runs sharing the GPU at once; the population's "
                "throughput is the ratio of the two.", "",
                *markdown_table(["task", "members", "population [ms]", "per member [ms]", "N separate, each [ms]",
                                 "population's throughput", "source"], comparison), ""]
    return out


def _probe_table(runs: list[Run], arm_of: dict[str, str]) -> list[str]:
    keys = ("grad_norm_full", "grad_norm_decoupled", "cos_full_decoupled", "grad_norm_render_term")
    rows = []
    groups: dict[tuple[str, str], list[Run]] = {}
    for r in runs:
        groups.setdefault((r.task, arm_of.get(r.path.name, r.mode)), []).append(r)
    for (task, arm), rs in sorted(groups.items()):
        vals = {k: [v for r in rs for v in r.series("iter", k)[1]] for k in keys}
        if not vals["cos_full_decoupled"]:
            continue
        rows.append([task, arm, len(vals["cos_full_decoupled"]),
                     *(f"{np.median(vals[k]):.4g}" if vals[k] else "-" for k in keys)])
    if not rows:
        return ["No run has probe iterations (full and decoupled runs with --cosine-every > 0 have).", ""]
    return [*markdown_table(["task", "arm", "probes", "median norm of full", "median norm of decoupled",
                             "median cos(full, decoupled)", "median norm of render term"], rows), ""]


def build_paper_report(folder: str | Path, *, out: str | Path | None = None, benchmark=(),
                       memory: tuple = (), floors: str | Path | None = None) -> Path:
    """Write the report of an ablate-paper sweep folder (figures beside it); returns its path.

    ValueError naming the input when the folder is not a sweep, or a --benchmark/--memory/--floors input is bad.
    """
    folder = Path(folder)
    manifest, runs, arm_of, missing = _sweep_runs(folder)
    out = Path(out) if out is not None else folder / "report" / "report.md"
    if out.suffix.lower() != ".md":
        raise ValueError(f"--report {out}: the report is a markdown file; give a path ending in .md")
    benchmark = (benchmark,) if isinstance(benchmark, (str, os.PathLike)) else tuple(benchmark or ())
    benchmarks = [(Path(b), *load_benchmark(b)) for b in benchmark]
    sweeps = load_memory_sweeps(memory)
    floor_data = load_floors(floors)
    paper = load_paper_numbers()
    base = out.parent
    fig_dir = base / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)

    sweep = manifest.get("sweep", {})
    arm_specs = sweep.get("arms") or {m: {"mode": m, "flags": {}} for m in sweep.get("modes", [])}
    arms = list(arm_specs)
    tasks = list(sweep.get("tasks") or dict.fromkeys(r.task for r in runs))
    label = (lambda r: arm_of.get(r.path.name, r.mode))  # noqa: E731 - the group label of a run is its arm

    lines = [f"# D.Va paper experiments: {', '.join(tasks)}", "",
             f"Sweep folder `{report_path(folder, base)}`; {len(runs)} of {len(manifest.get('runs', {}))} runs "
             "have a run folder. Nothing here is estimated: a number without a measurement says so.", ""]
    not_ranking = {t: _not_ranking(t, floor_data, paper) for t in tasks if t in NOT_RANKING}
    for task, why in not_ranking.items():
        lines += [f"**{task}:** {why}. Its results are reported, not compared.", ""]
    lines += ["## 1. Arms", ""]
    counts = {a: {} for a in arms}
    for rec in manifest.get("runs", {}).values():
        a = rec.get("arm") or rec.get("mode")
        if a in counts:
            counts[a][rec.get("status")] = counts[a].get(rec.get("status"), 0) + 1
    rows = [[a, spec.get("mode"), " ".join(f"--{k.replace('_', '-')} {v}" for k, v in spec.get("flags", {}).items())
             or "-", spec.get("about") or (ARMS[a].about if a in ARMS else ""),
             ", ".join(f"{n} {s}" for s, n in sorted(counts[a].items())) or "-"] for a, spec in arm_specs.items()]
    lines += markdown_table(["arm", "mode", "extra ablate flags", "what it is", "runs"], rows)
    shared = sweep.get("set") or {}
    lines += ["", "Every run: " + (" ".join(f"--{k.replace('_', '-')} {v}" for k, v in shared.items()) or
                                   "ablate's defaults") + f"; seeds {sweep.get('seeds', '?')}."]
    lines += _packing_lines(manifest)
    if missing:
        lines += ["", f"Runs without a run folder yet (queued or failed before starting): {', '.join(missing)}."]
    lines.append("")

    res = make_plots(runs, fig_dir, floors=floor_data, label=label) if runs else None
    lines += ["## 2. Return against wall-clock time and environment steps", ""]
    if res is None:
        lines += ["No run has a run folder yet.", ""]
    else:
        lines += ["Mean +- one sample standard deviation across seeds (n in the legends), with the zero- and "
                  "random-action floors as horizontal lines.", ""]
        lines += figure_lines(res, _RETURN_FIGURES, base)
        lines += _packed_wall_clock_note(runs)
        lines += floors_section(runs, floor_data, base=base)
    lines += ["## 3. Full and decoupled gradients of the same rollout (the paper's Fig. 3)", ""]
    if res is not None:
        lines += ["On probe iterations the trainer computes both gradients of one rollout: the full one "
                  "(through the renderer) and the decoupled one (the image input detached), whatever mode it "
                  "trains with; the render term is their difference.", ""]
        lines += figure_lines(res, _FIG3_FIGURES, base)
        lines += _probe_table(runs, arm_of)
    cells = collect_bwd(runs, benchmarks, label=label)
    lines += _comparison(runs, arm_of, arms, tasks, paper, cells, not_ranking)
    lines += table1_section(cells, heading="## 5. Backward time per iteration (Table 1)",
                            members_left_out=sum(map(is_population_member, runs)))
    if res is not None:
        lines += ["### Cost over training", "", *figure_lines(res, _COST_FIGURES, base)]
    lines += _iteration_time_section(runs, label, manifest, folder, benchmark)
    lines += memory_section(sweeps, fig_dir, base, heading="## 7. Memory against scene complexity (Fig. 10)")
    lines += ["## 8. Runs", "", *(runs_table(runs, label=label) if runs else ["No run folders.", ""])]
    lines += provenance_section(runs, sweeps, benchmarks, base=base, heading="## 9. Provenance")
    lines += [f"Sweep command: `{command_text(manifest.get('command'))}`; sweep created "
              f"{manifest.get('created', '?')}, updated {manifest.get('updated', '?')}; report "
              f"{_dt.datetime.now().astimezone().isoformat(timespec='seconds')}."]

    atomic_write_text(out, "\n".join(lines).rstrip() + "\n")
    return out
