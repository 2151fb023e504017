"""Command-line entry points: ``ablate``, ``ablate-memory``, ``ablate-plot``, ``ablate-report``, and :func:`parse`,
which every ``ablations`` command's options go through.

Each command takes a dataclass whose field docstrings are its ``--help`` (tyro). Bad input (unknown task or mode,
non-positive sizes, an unwritable output folder) is reported in one line naming its flag before any work starts.
"""

from __future__ import annotations

import dataclasses
import inspect
import os
import sys
from collections.abc import Sequence
from typing import Annotated, Any, NoReturn, TypeVar

from ablations.command import command_errors
from tasks.command_line import check_argv, tyro_one_line

__all__ = ["ablate_main", "memory_main", "plot_main", "report_main", "plan_main", "parse", "ABLATE_GROUPS"]

T = TypeVar("T")

#: ``ablate --help`` in panels, essentials first: panel -> the RunConfig fields it shows, in order. A field no
#: panel names is shown in the last panel ("more").
ABLATE_GROUPS: dict[str, tuple[str, ...]] = {
    "essentials": ("task", "mode", "seed", "iters", "num_envs", "device", "threads", "compile", "out", "name",
                   "resume", "restart", "time_limit_min", "progress", "member"),
    "evaluation-and-probes": ("eval_every", "eval_envs", "video_every", "video_steps", "cosine_every",
                              "eval_final_every", "eval_final_from"),
    "training": ("preset", "horizon", "gamma", "lam", "actor_lr", "critic_lr", "lr_decay_iters", "lr_warmup_iters",
                 "encoder_lr_scale", "betas", "grad_clip", "abort_grad_norm", "critic_iterations", "critic_batches",
                 "target_alpha", "obs_clip", "bootstrap_last_step", "episode_length"),
    "networks": ("trunk_dim", "actor_hidden", "critic_hidden", "actor_init"),
    "images": ("image_size", "frames", "renderer", "raster_model", "sigma", "render_gamma", "render_detail",
               "extra_meshes", "extra_mesh_verts"),
    "run-folder": ("checkpoint_every", "keep_checkpoints", "warmup_iters", "tensorboard"),
    "compiling": ("overlap_critic", "compile_cache", "compile_helper"),
    "distillation": ("expert", "distill_buffer", "distill_starts", "distill_updates", "distill_batch",
                     "distill_loss_threshold"),
}


def _fail(msg: str) -> NoReturn:
    print(f"error: {msg}", file=sys.stderr)
    raise SystemExit(2)


def _one_paragraph(helptext: Any) -> str | None:
    """A field's help as one paragraph (blank lines kept): tyro breaks the help wherever a field docstring's
    source line ends (a continuation line starts with indentation), and each piece then wraps on its own."""
    text = helptext() if callable(helptext) else helptext
    if not text:
        return text
    paragraphs = [" ".join(line.strip() for line in p.splitlines() if line.strip()) for p in text.split("\n\n")]
    return "\n\n".join(p for p in paragraphs if p)


def parse(cls: type[T], argv: Sequence[str] | None, *, groups: dict[str, tuple[str, ...]] | None = None,
          prog: str | None = None, default: T | None = None) -> T:
    """``tyro.cli(cls)`` with readable ``--help``: each field's docstring is one paragraph, and with ``groups``
    ({panel: field names}) the flags appear in panels in that order (the flags keep their names; fields that no
    panel names go to a last panel, "more"). ``default``: an instance whose values are the defaults. Every refusal
    is one ``error:`` line naming its flag (``tasks.command_line``), exit status 2."""
    import tyro
    from tyro.constructors import MISSING_NONPROP, ConstructorRegistry, StructConstructorSpec, StructFieldSpec

    registry = ConstructorRegistry()
    panels: dict[type, list[StructFieldSpec]] = {}
    inside: list[bool] = []

    @registry.struct_rule
    def readable(info):
        if info.type in panels:  # one panel: its fields, gathered as keyword arguments of cls
            return StructConstructorSpec(instantiate=dict, fields=tuple(panels[info.type]))
        if info.type is not cls or inside:
            return None
        inside.append(True)
        try:  # tyro's own reading of the dataclass: types, defaults, docstrings
            spec = ConstructorRegistry.get_struct_spec(info)
        finally:
            inside.pop()
        fields = [StructFieldSpec(name=f.name, type=f.type, default=f.default, helptext=_one_paragraph(f.helptext))
                  for f in spec.fields]
        if not groups:
            return StructConstructorSpec(instantiate=spec.instantiate, fields=tuple(fields))
        by_name = {f.name: f for f in fields}
        placed = {n for names in groups.values() for n in names}
        members = {**{g: [by_name[n] for n in names if n in by_name] for g, names in groups.items()},
                   "more": [f for f in fields if f.name not in placed]}
        panel_fields = []
        for name, field_specs in members.items():
            if field_specs:
                panel = type(name, (), {})
                panels[panel] = field_specs
                panel_fields.append(StructFieldSpec(name=name, type=Annotated[panel, tyro.conf.OmitArgPrefixes],
                                                    default=MISSING_NONPROP))

        def instantiate(**by_panel: dict) -> T:
            return spec.instantiate(**{k: v for values in by_panel.values() for k, v in values.items()})

        return StructConstructorSpec(instantiate=instantiate, fields=tuple(panel_fields))

    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        check_argv(cls, argv, prog)
    except ValueError as e:
        _fail(str(e))
    return tyro_one_line(lambda: tyro.cli(cls, args=argv, prog=prog, default=default,
                                          description=inspect.cleandoc(cls.__doc__ or ""), registry=registry), prog)


def ablate_main(argv: list[str] | None = None) -> None:
    """``ablate --mode full|decoupled|state --task ant ...``: train and measure one run."""
    args = sys.argv[1:] if argv is None else argv
    where = "the run folder is as it was" if "--resume" in args else "nothing was written"
    with _SignalsWhileImporting() as importing:
        from ablations.startup import Startup

        startup = Startup.before_torch(args)  # first: torch is not imported yet
        import ablations.runs  # noqa: F401  (torch, the simulator, the renderer)
    if importing.signal is not None:
        startup.close()
        print(f"{importing.signal}: stopped while starting, before training; {where}", file=sys.stderr)
        raise SystemExit(130)
    try:
        try:
            _ablate(argv, startup)
        finally:
            startup.close()
    except KeyboardInterrupt as e:  # a signal while preparing (settings, folders): nothing trained yet
        print(f"{str(e) or 'SIGINT'}: stopped while starting, before training; {where}", file=sys.stderr)
        raise SystemExit(130) from None


class _SignalsWhileImporting:
    """SIGINT and SIGTERM while ablate imports torch and its own packages: noted, and acted on once the imports are
    done. A KeyboardInterrupt raised inside the import of a compiled extension (torch's) cannot be caught: the
    process aborts. A second signal ends the process at once (nothing has been written yet)."""

    def __init__(self) -> None:
        self.signal: str | None = None
        self._previous: dict = {}

    def __enter__(self) -> _SignalsWhileImporting:
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in (signal.SIGINT, signal.SIGTERM)}
        return self

    def __exit__(self, *exc) -> None:
        import signal

        for s, handler in self._previous.items():
            signal.signal(s, handler)

    def _handle(self, signum: int, frame) -> None:
        import os
        import signal

        name = signal.Signals(signum).name
        if self.signal is not None:
            print(f"{name}: stopped while starting, before training; nothing was written", file=sys.stderr)
            os._exit(130)
        self.signal = name


def _ablate(argv: list[str] | None, startup) -> None:
    # not at the top: these import torch, and ablate starts before torch is imported (ablate_main imports them
    # once Startup.before_torch has run)
    from ablations.population import AblateConfig, NothingToDo, closing_lines, home_of
    from ablations.runs import run
    from ablations.stopping import RunFailed, describe_error

    argv = list(sys.argv[1:] if argv is None else argv)
    cfg = parse(AblateConfig, argv, groups=ABLATE_GROUPS, prog="ablate")
    try:
        members, resume_flags = _checked_members(cfg, argv)
        home = run(members, startup=startup, resume_flags=resume_flags)
    except ValueError as e:
        _fail(str(e))
    except NothingToDo as e:
        print(e)
        return
    except RunFailed as e:  # recorded in summary.json, the last finished iteration checkpointed where it could be
        if e.status == "failed":  # not a known way to fail: where it happened matters
            import traceback

            traceback.print_exception(e.__cause__, file=sys.stderr)
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2 if e.status == "nonfinite" else 1) from None
    except Exception as e:  # before training started (building the trainer): no iteration to lose
        status, text = describe_error(e, where="while building the trainer")
        if status == "failed":
            raise
        # a resume may have renamed damaged checkpoints aside already (each said in a warning above)
        where = "nothing was trained or recorded" if cfg.resume is not None else "nothing was written"
        print(f"error: {text}; {where}", file=sys.stderr)
        raise SystemExit(1) from None
    try:
        print("\n".join(closing_lines(home)))
        statuses = {(f.read_summary() or {}).get("status") for f in home_of(home)[0]}
    except KeyboardInterrupt as e:  # the run has ended and is recorded; only this summing up is cut short
        print(f"{str(e) or 'SIGINT'}: the run has ended; see {home}", file=sys.stderr)
        raise SystemExit(130) from None
    if "interrupted" in statuses:
        raise SystemExit(130)


def _field(key: str, fields) -> str:
    """The field a flag sets: ``num-envs`` -> ``num_envs``, ``no-progress`` -> ``progress``."""
    name = key.replace("-", "_")
    return name[3:] if name.startswith("no_") and name[3:] in fields else name


def _checked_members(cfg, argv: list[str]) -> tuple[list, frozenset[str] | None]:
    """The runs ``ablate``'s options stand for (one: a single run), each validated as given (before a preset fills
    in), after the checks that need the whole command line, and for ``--resume`` the settings its flags change
    (those given, a default's value included; else None); ValueError naming the flag (``--member`` and its entry
    for a listed member's own settings), before anything is created."""
    # not at the top: these import torch (see _ablate)
    from ablations.run_config import RESUMABLE, check_given_flags
    from ablations.run_config import SWEEP_WIDE as RUN_SWEEP_WIDE
    from tasks.command_line import scan, usable_cores

    fields = {f.name for f in dataclasses.fields(cfg)}
    given = scan(argv)
    if cfg.resume is not None:
        # config.json wins over every other setting, so any other flag would be dropped without a word
        # --restart says what the resume of a folder without a checkpoint does (a sweep's retry passes it)
        takes = {*RESUMABLE, "resume", "restart", "progress"}
        ignored = list(dict.fromkeys(g.spelling for g in given if _field(g.key, fields) not in takes))
        if ignored:
            raise ValueError(f"--resume continues {cfg.resume} with the settings its config.json records, so "
                             f"{', '.join(ignored)} would be ignored: drop {'it' if len(ignored) == 1 else 'them'} "
                             f"(a resume takes {', '.join('--' + k.replace('_', '-') for k in RESUMABLE)})")
    if cfg.name is not None and (cfg.name in ("", ".", "..") or "/" in cfg.name
                                 or any(sep and sep in cfg.name for sep in (os.sep, os.altsep))):
        raise ValueError(f"--name {cfg.name!r}: the run folder's name inside --out, not a path (no '/', not '.' "
                         f"or '..'); give the parent folder with --out")
    if cfg.threads is not None and cfg.threads > usable_cores():
        cores = usable_cores()
        raise ValueError(f"--threads {cfg.threads} is more than the {cores} cores this process may use (its CPU "
                         f"affinity): more threads than cores make every iteration wait; give at most {cores}")
    # a resume's settings are its folders' (checked as they are read)
    if cfg.resume is not None:
        return cfg.members(), frozenset(_field(g.key, fields) for g in given) & frozenset(RESUMABLE)
    members = cfg.checked_members()
    if not os.environ.get(RUN_SWEEP_WIDE):  # a sweep's --set is given for every run of its grid
        check_given_flags(members, {_field(g.key, fields) for g in given})
    return members, None


def memory_main(argv: list[str] | None = None) -> None:
    """``ablate-memory --task ant --meshes 0 4 16 --verts 64 256 ...``: the mesh-complexity sweep."""
    from ablations.memory import MemoryConfig, sweep

    cfg = parse(MemoryConfig, argv, prog="ablate-memory")
    # interrupted: the sweep has stopped its workers; what they measured is in memory.csv
    with command_errors(lambda: f"interrupted: the points measured so far are kept in {cfg.out}; the same command "
                                f"continues the sweep"):
        rows = sweep(cfg)
    counts: dict[str, int] = {}
    for r in rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    print(f"{cfg.out / 'memory.csv'}: {len(rows)} points (" + ", ".join(f"{n} {s}" for s, n in counts.items()) + ")")


def plot_main(argv: list[str] | None = None) -> None:
    """``ablate-plot RUN_DIR... --out DIR``: training curves, mean +- std across seeds, as PNG files."""
    from ablations.reports import PlotConfig, plot_runs

    cfg = parse(PlotConfig, argv, prog="ablate-plot")
    try:
        res = plot_runs(cfg)
    except ValueError as e:
        _fail(str(e))
    for path in res.files.values():
        print(path)
    for name, why in res.skipped.items():
        print(f"skipped {name}: {why}", file=sys.stderr)
    for line in res.left_out:
        print(line, file=sys.stderr)


def report_main(argv: list[str] | None = None) -> None:
    """``ablate-report RUN_DIR... [--memory DIR...] [--benchmark FILE...] --out report.md``."""
    from ablations.reports import ReportConfig, build_report

    cfg = parse(ReportConfig, argv, prog="ablate-report")
    try:
        print(build_report(cfg))
    except ValueError as e:
        _fail(str(e))


def plan_main(argv: list[str] | None = None) -> None:
    """``ablate-plan RUN_DIR... --registration FILE`` (the power of a registered design from pilot runs), or
    ``ablate-plan --pin --registration FILE`` (pin the training tree hash)."""
    from ablations.reports.confirmatory import PlanConfig, plan

    cfg = parse(PlanConfig, argv, prog="ablate-plan")
    try:
        print(plan(cfg))
    except ValueError as e:
        _fail(str(e))
