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


def _plain_compile_cache_warnings() -> None:
    """A compile cache warning as one ``warning: ...`` line, like the run's other warnings, not Python's
    file:line format."""
    import warnings

    from gradlab.compiling import CompileCacheWarning

    show = warnings.showwarning

    def show_plainly(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, CompileCacheWarning):
            print(f"warning: {message}", file=sys.stderr)
        else:
            show(message, category, filename, lineno, file, line)

    warnings.showwarning = show_plainly


def ablate_main(argv: list[str] | None = None) -> None:
    """``ablate --mode full|decoupled|state --task ant ...``: train and measure one run."""
    from ablations.bytecode import keep_bytecode, resolve_bytecode_folder
    from ablations.compile_helper import CompileHelpers

    # Before torch is imported: where the environment keeps Python's bytecode out of the install, every start
    # would compile torch's Python again (ablations/bytecode.py); and a cold --compile start on a GPU shares its
    # compiling with helper processes, whose imports then overlap this one's (ablations/compile_helper.py).
    keep_bytecode(resolve_bytecode_folder())
    standby = CompileHelpers.standby_for(sys.argv[1:] if argv is None else argv)
    try:
        _ablate(argv, standby)
    finally:
        if standby is not None:
            standby.stop()  # nothing left to do once the run gave them their shares or let them go


def _ablate(argv: list[str] | None, standby) -> None:
    import tyro

    from ablations.runs import RunConfig, run
    from gradlab.probes import NonFiniteError

    cfg = tyro.cli(RunConfig, args=argv, description=RunConfig.__doc__)
    _plain_compile_cache_warnings()
    try:
        run_dir = run(cfg, standby=standby)
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
