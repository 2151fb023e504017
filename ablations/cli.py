"""Command-line entry points: ``ablate``, ``ablate-memory``, ``ablate-plot``, ``ablate-report``.

Each takes a dataclass whose field docstrings are its ``--help`` (tyro). Bad input (unknown task or mode,
non-positive sizes, an unwritable output folder) is reported in one line before any work starts.
"""

from __future__ import annotations

import sys

__all__ = ["ablate_main", "memory_main", "plot_main", "report_main"]


def _fail(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr)
    raise SystemExit(2)


def ablate_main(argv: list[str] | None = None) -> None:
    """``ablate --mode full|decoupled|state --task ant ...``: train and measure one run."""
    from ablations.startup import Startup

    startup = Startup.before_torch(sys.argv[1:] if argv is None else argv)  # first: torch is not imported yet
    try:
        _ablate(argv, startup)
    finally:
        startup.close()


def _ablate(argv: list[str] | None, startup) -> None:
    import tyro

    from ablations.runs import RunConfig, run
    from gradlab.probes import NonFiniteError

    cfg = tyro.cli(RunConfig, args=argv, description=RunConfig.__doc__)
    try:
        run_dir = run(cfg, startup=startup)
    except ValueError as e:
        _fail(str(e))
    except NonFiniteError as e:
        _fail(f"{e} (the last good checkpoint is kept; see summary.json)")
    print(run_dir)


def memory_main(argv: list[str] | None = None) -> None:
    """``ablate-memory --task ant --meshes 0 4 16 --verts 64 256 ...``: the mesh-complexity sweep."""
    import tyro

    from ablations.memory import MemoryConfig, sweep

    cfg = tyro.cli(MemoryConfig, args=argv)
    try:
        rows = sweep(cfg)
    except ValueError as e:
        _fail(str(e))
    counts: dict[str, int] = {}
    for r in rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    print(f"{cfg.out / 'memory.csv'}: {len(rows)} points (" + ", ".join(f"{n} {s}" for s, n in counts.items()) + ")")


def plot_main(argv: list[str] | None = None) -> None:
    """``ablate-plot RUN_DIR... --out DIR``: training curves, mean +- std across seeds, as PNG files."""
    import tyro

    from ablations.plot import PlotConfig, plot_runs

    cfg = tyro.cli(PlotConfig, args=argv)
    try:
        res = plot_runs(cfg)
    except ValueError as e:
        _fail(str(e))
    for path in res.files.values():
        print(path)
    for name, why in res.skipped.items():
        print(f"skipped {name}: {why}", file=sys.stderr)


def report_main(argv: list[str] | None = None) -> None:
    """``ablate-report RUN_DIR... [--memory DIR...] [--benchmark FILE...] --out report.md``."""
    import tyro

    from ablations.report import ReportConfig, build_report

    cfg = tyro.cli(ReportConfig, args=argv)
    try:
        print(build_report(cfg))
    except ValueError as e:
        _fail(str(e))
