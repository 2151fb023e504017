"""``ablate-paper``: the D.Va paper's experiment set as one ``ablate-sweep``, and one report of it.

Per task (default cartpole-swingup, hopper and ant) and seed, every arm of ``--arms`` (:data:`vocabulary.ARMS`)
runs under a wall-clock budget (``--time-limit-min``); an arm is a named set of ``ablate`` flags. The runs that
can share a process train as populations (``--pack auto``: up to 12 per GPU process, one run per process on the
CPU; ablate-sweep --pack).

The report is :func:`ablations.reports.paper.build_paper_report`'s.
"""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass
from pathlib import Path

from ablations.command import command_errors
from ablations.reports import load_floors
from ablations.reports.paper import build_paper_report
from ablations.reports.report import (
    load_benchmark,
    load_memory_sweeps,
)
from gradlab.presets import preset_values
from vocabulary import ARMS, DEFAULT_ARMS

__all__ = ["PaperConfig", "sweep_config", "phases", "gpus_per_run", "main"]

#: The tasks run unless --tasks names others. D.Va's cartpole stays available; its report marks it as not ranking
#: arms (its zero action scores above the paper's final return, docs/floors.json).
DEFAULT_TASKS = ("cartpole-swingup", "hopper", "ant")
#: Flags ablate-paper sets itself (through its own options).
_OWN_FLAGS = {"iters": "--iters", "time_limit_min": "--time-limit-min"}


@dataclass
class PaperConfig:
    """Run the D.Va paper's experiment set (arms x tasks x seeds on ablate-sweep, a wall-clock budget per run) and
    write one report; --report-only DIR redraws the report of an existing sweep folder."""

    out: Path = Path("paper")
    """The sweep folder (sweep.json, runs/, logs/; rerun to resume); the report goes to <out>/report/."""
    tasks: tuple[str, ...] = DEFAULT_TASKS
    """Tasks. D.Va's cartpole can be added, but its zero action scores above the paper's final return
    (docs/floors.json): the report marks it as not ranking arms."""
    arms: tuple[str, ...] = DEFAULT_ARMS
    """Arms to run: decoupled (D.Va), full-hard (--mode full --preset shac-diffrender: the paper's baseline),
    full-hard-dva (--mode full --raster-model hard: the baseline's estimator on D.Va's schedule), full-soft (--mode
    full: the default soft raster model, softmax), full-alpha (--mode full --raster-model alpha; not in the default
    set), state, blind."""
    seeds: tuple[int, ...] = (0, 1, 2)
    """Seeds per task and arm."""
    time_limit_min: float | None = 60.0
    """Wall-clock budget of every run in minutes (ablate --time-limit-min); None: run --iters iterations."""
    iters: int = 100_000
    """Iteration cap of every run (the budget usually ends a run first; the presets' learning-rate decay
    lengths do not depend on it)."""
    set: tuple[str, ...] = ()
    """More ablate flags for every run, as FLAG=VALUE (e.g. compile=true cosine-every=10 device=cuda)."""
    pack: str = "auto"
    """Runs that can share a process (every arm but state, per task) train as populations of at most N members
    (ablate-sweep --pack): auto: 12 on GPU runs (what the population benchmark measured at that size: BENCHMARKS.md
    section 7), 1 on the CPU; 1: one run
    per process. A member's iteration time is its population's: the report sets each arm's time alone beside
    it (--benchmark)."""
    gpus_per_run: float | None = None
    """GPUs Ray reserves per process, a run or a population (0.25: four share a GPU; 0: CPU runs). None: 1 on a
    machine with a CUDA GPU or with --address, else 0 (CPU runs, said before they start)."""
    cpus_per_run: float = 1.0
    """CPUs Ray reserves per process (a run or a population)."""
    address: str | None = None
    """Ray cluster to join (see ablate-sweep --address); None: a local cluster."""
    max_retries: int = 3
    """Retries of a run whose worker died (each resumes from its last checkpoint)."""
    progress: bool = True
    """Live table of the runs."""
    dry_run: bool = False
    """List the runs (ablate command of each) and exit; starts nothing."""
    report_only: Path | None = None
    """Write the report of this existing sweep folder and exit; runs nothing."""
    report: Path | None = None
    """The report's markdown file; None: <sweep folder>/report/report.md."""
    benchmark: tuple[Path, ...] = ()
    """benchmarks/iteration.py JSONs for Table 1 (backward time per iteration; the first file that has a task and
    mode wins; without them the runs' own, which a GPU shared by several runs slows) and for each arm's iteration
    time alone; benchmarks/population.py JSONs for the latter too (a population of one is a decoupled run alone)
    and their populations against separate processes."""
    memory: tuple[Path, ...] = ()
    """ablate-memory folders for the memory sweep (Fig. 10)."""
    floors: Path | None = None
    """task-floors JSON of the zero- and random-action return floors; None: docs/floors.json of this checkout."""


def _arm_table(names: tuple[str, ...]) -> dict[str, dict]:
    unknown = [n for n in names if n not in ARMS]
    if unknown or not names:
        raise ValueError(f"--arms {' '.join(unknown) or '(none)'}: choose from {', '.join(ARMS)}")
    if len(set(names)) != len(names):
        raise ValueError(f"--arms lists an arm twice: {list(names)}")
    return {n: {"mode": ARMS[n].mode, "flags": dict(ARMS[n].flags), "about": ARMS[n].about} for n in names}


def cuda_gpus() -> int:
    """CUDA GPUs this process can see."""
    import torch

    return torch.cuda.device_count()


def gpus_per_run(cfg: PaperConfig) -> tuple[float, str | None]:
    """(--gpus-per-run to use, a line saying why when it was not given and the runs go to the CPU)."""
    if cfg.gpus_per_run is not None:
        return float(cfg.gpus_per_run), None
    if cfg.address is not None or cuda_gpus() > 0:
        return 1.0, None
    return 0.0, ("no CUDA GPU on this machine: the runs train on the CPU (--gpus-per-run 0); on a GPU machine "
                 "each run gets one (--gpus-per-run 1)")


def sweep_config(cfg: PaperConfig):
    """(SweepConfig, arms) of the experiment set; ValueError naming a bad option."""
    from ablations.sweep import SweepConfig

    arms = _arm_table(cfg.arms)
    for item in cfg.set:
        key = item.split("=", 1)[0].strip().lstrip("-").replace("-", "_")
        if key in _OWN_FLAGS:
            raise ValueError(f"--set {item}: ablate-paper sets it; use {_OWN_FLAGS[key]}")
    if cfg.iters <= 0:
        raise ValueError(f"--iters must be positive, got {cfg.iters}")
    if cfg.time_limit_min is not None and cfg.time_limit_min <= 0:
        raise ValueError(f"--time-limit-min must be positive, got {cfg.time_limit_min}")
    own = [f"iters={cfg.iters}"] + ([f"time-limit-min={cfg.time_limit_min:g}"] if cfg.time_limit_min else [])
    modes = tuple(dict.fromkeys(a["mode"] for a in arms.values()))
    sweep = SweepConfig(out=cfg.out, tasks=cfg.tasks, modes=modes, seeds=cfg.seeds, set=(*own, *cfg.set),
                        gpus_per_run=gpus_per_run(cfg)[0], cpus_per_run=cfg.cpus_per_run, address=cfg.address,
                        max_retries=cfg.max_retries, progress=cfg.progress, pack=cfg.pack)
    return sweep, arms


#: Where the distill arm's experts train, inside --out: one sweep folder per task.
EXPERTS = "experts"


def phases(cfg: PaperConfig) -> list[tuple]:
    """The sweeps to run, in order, each (SweepConfig, arms): the experiment set's (:func:`sweep_config`), preceded,
    where --arms names distill, by one sweep per task of its state experts (the expert arm, one per seed, each in
    a process of its own, for the teacher's ``max_epochs`` iterations under the same budget), in
    ``<out>/experts/<task>``; each distill run's ``--expert`` is the folder of its task's and seed's expert."""
    sweep, arms = sweep_config(cfg)
    if "distill" not in arms:
        return [(sweep, arms)]
    experts = []
    for task in cfg.tasks:
        iters = preset_values("teacher", task, "state")["lr_decay_iters"]  # the teacher's max_epochs
        expert_cfg = dataclasses.replace(cfg, out=cfg.out / EXPERTS / task, tasks=(task,), arms=("expert",),
                                         iters=iters, pack="1")
        experts.append(sweep_config(expert_cfg))
    where = cfg.out / EXPERTS / "{task}" / "runs" / "{task}_expert_seed{seed}"
    arms["distill"]["flags"]["expert"] = str(where)
    return [*experts, (sweep, arms)]


def main(argv: list[str] | None = None) -> None:
    """``ablate-paper [--tasks hopper ant] [--seeds 0 1 2] [--time-limit-min 60] ...``; see --help."""
    from ablations.cli import parse

    cfg = parse(PaperConfig, argv, prog="ablate-paper")
    with command_errors(lambda: f"interrupted; rerun the same command to resume ({cfg.out})"):
        if cfg.report_only is not None:
            print(build_paper_report(cfg.report_only, out=cfg.report, benchmark=cfg.benchmark, memory=cfg.memory,
                                     floors=cfg.floors))
            return
        from ablations.sweep import dry_run, run_sweep

        planned = phases(cfg)
        cpu_note = gpus_per_run(cfg)[1]
        if cfg.dry_run:
            for sweep, arms in planned:
                dry_run(sweep, arms=arms, local_gpus=cuda_gpus())
            if cpu_note:
                print(cpu_note)
            return
        if cpu_note:
            print(cpu_note, file=sys.stderr)
        # Inputs of the report are checked before hours of training, not after.
        for b in cfg.benchmark:
            load_benchmark(b)
        load_memory_sweeps(cfg.memory)
        load_floors(cfg.floors)
        command = ["ablate-paper", *(sys.argv[1:] if argv is None else argv)]
        for sweep, arms in planned[:-1]:  # the distill arm's experts first; a failed one stops before its students
            experts = run_sweep(sweep, arms=arms, command=command)
            failed = [k for k, r in experts["runs"].items() if r["status"] == "failed"]
            if failed:
                raise ValueError(f"the distill arm's experts {', '.join(failed)} failed ({sweep.out}); rerun to "
                                 "resume them")
        sweep, arms = planned[-1]
        manifest = run_sweep(sweep, arms=arms, command=command)
        print(build_paper_report(cfg.out, out=cfg.report, benchmark=cfg.benchmark, memory=cfg.memory,
                                 floors=cfg.floors))
    failed = [k for k, r in manifest["runs"].items() if r["status"] == "failed"]
    for run_id in failed:
        print(f"failed {run_id}: {manifest['runs'][run_id]['error']}", file=sys.stderr)
    if failed:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
