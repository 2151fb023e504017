"""One training run: ``ablate``'s settings (:class:`RunConfig`) and its loop (:func:`run`).

A run trains in a run folder (``ablations.run_folder``: config.json, git.txt, metrics.jsonl, summary.json,
checkpoints/, videos/) that a researcher can trust, resume and plot. Bad input is a ValueError naming its flag
before the folder exists. SIGINT or SIGTERM lets the running iteration finish, checkpoints it and marks the
summary ``interrupted``; a second signal stops at once and checkpoints the last finished iteration, which the loop
holds a copy of when it is not on disk already. An error (out of memory on either device included) does the same
before it is reported, so every way a run stops leaves its last finished iteration resumable, or says in the
summary and the last line it prints which iterations are lost and why. ``ablate --resume`` then repeats nothing
(docs/design.md, "Run folders and resume").
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import datetime
import math
import os
import re
import signal
import sys
import threading
import time
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from ablations.run_folder import RunFolder, environment_info, evaluation_of
from ablations.startup import Startup
from gradlab import precision
from gradlab.checkpoint import LoadedCheckpoint
from gradlab.config import SHACConfig
from gradlab.config_checks import check_integers, check_number
from gradlab.presets import PRESET_FIELDS, PRESETS, preset_record
from gradlab.probes import NonFiniteError
from gradlab.seeding import resolve_device
from gradlab.timing import median

__all__ = ["RunConfig", "run", "prepare", "closing_lines", "default_threads", "use_threads", "shac_part",
           "describe_error", "RunFailed", "NothingToDo", "REQUIRED_KEYS", "PROBE_KEYS", "TIMING_KEYS", "RESUMABLE"]

#: Keys every metrics line has.
REQUIRED_KEYS = ("iter", "env_steps", "wall_s", "return_mean", "actor_loss", "critic_loss", "grad_norm",
                 "grad_norm_clipped", "fwd_ms", "bwd_ms", "peak_alloc_mb", "peak_reserved_mb")
#: Keys added on probed iterations.
PROBE_KEYS = ("cos_full_decoupled", "grad_norm_full", "grad_norm_decoupled", "grad_norm_render_term")
#: Keys that depend on the clock, not on the computation (excluded when comparing runs for determinism).
TIMING_KEYS = ("wall_s", "fwd_ms", "bwd_ms", "critic_ms", "iter_ms", "eval_s", "peak_alloc_mb", "peak_reserved_mb")
#: Settings a resume may change (where it runs, how long it goes on); config.json wins for every other one.
RESUMABLE = ("device", "iters", "time_limit_min", "compile_cache", "threads")
#: Most CPU threads a run takes by default: the simulator's and networks' tensors are small, so more threads add
#: synchronisation more than speed.
MAX_DEFAULT_THREADS = 8
_IMPORTED = time.time()  # when no better process start time is known (_process_started)


@dataclass
class RunConfig(SHACConfig):
    """Train SHAC on a task with full, decoupled (D.Va) or state policy gradients, and measure them."""

    device: str = "auto"
    """auto (CUDA when present, else CPU), cpu, or cuda[:N]."""
    threads: int | None = None
    """CPU threads of torch in this process (and OMP_NUM_THREADS / MKL_NUM_THREADS of the processes it starts);
    recorded in config.json. None: $OMP_NUM_THREADS where set, else half the cores this process may use, at least
    1 and at most 8, so that a run leaves room on a shared machine (two runs each taking every core are many
    times slower than both with half). On the CPU the thread count changes the metrics' last bits."""
    out: Path = Path("runs")
    """Parent folder of the run folder."""
    name: str | None = None
    """Run folder name; None: <task>_<mode>_seed<seed>_<date>-<time>."""
    resume: Path | None = None
    """Continue the run in this folder from its newest readable checkpoint. Its config.json wins over other flags
    except --device, --iters, --time-limit-min, --compile-cache and --threads, which a resume may change (e.g. to
    train the same run longer). metrics.jsonl keeps every readable line up to the checkpoint's iteration; lines
    after it (iterations the resume trains again) and damaged lines are moved to metrics.jsonl.redone-<time> and
    metrics.jsonl.damaged-<time> beside it, each named in one line (a last line cut off mid-write is dropped).
    A folder without a checkpoint is refused unless --restart is given."""
    restart: bool = False
    """With --resume of a folder that holds no checkpoint (the run stopped before its first one): train it again
    from iteration 1 in that folder, its old metrics.jsonl, summary.json and videos/ kept beside under the suffix
    .before-restart-<time>. A folder with a checkpoint resumes from it either way."""
    checkpoint_every: int = 50
    """Iterations between checkpoints (and always at the end, and when a signal or an error stops the run: the
    last finished iteration is checkpointed then, from a copy the run holds in memory)."""
    keep_checkpoints: int = 2
    """Checkpoints kept on disk (oldest deleted); more than one lets a resume survive a damaged newest one."""
    video_every: int = 100
    """Iterations between evaluation videos (MP4 of the deterministic policy; also at the end); 0 disables."""
    video_steps: int | None = 300
    """Steps per evaluation video (at most one episode; 300 steps = 5 s at 60 fps); None: one episode."""
    time_limit_min: float | None = None
    """Stop cleanly (final checkpoint, video and summary) once the run's training wall-clock (the sum of its
    iterations' times, compilation included, carried across --resume) reaches this many minutes; None: run all
    iterations."""
    warmup_iters: int = 2
    """Iterations excluded from the timing medians in summary.json (allocator and kernel warm-up)."""
    tensorboard: bool = False
    """Also log the metrics to TensorBoard (needs the tensorboard package) in <run>/tb."""
    progress: bool = True
    """Show a progress bar: ret= the training return (mean of the last 100 finished training episodes of the
    exploring policy; - before the first ends), eval= the last deterministic evaluation return, ms= the
    iteration's wall-clock milliseconds, gn= the actor's gradient norm before clipping."""
    compile_cache: str | None = None
    """With --compile: the root folder of torch.compile's caches (a subfolder per torch/Triton/device version;
    delete it to start cold); None: $PIXELGRAD_COMPILE_CACHE, else ~/.cache/pixelgrad/compile; 'off': torch's
    own cache locations and no artifact file."""
    compile_helper: bool = True
    """With --compile on a GPU and nothing compiled for these settings yet: helper processes compile the rest of
    the physics, the renderer and the networks while this one compiles the physics substep, into the same cache
    (ablations/startup/helpers.py); --no-compile-helper compiles everything in this process."""

    def validate(self) -> None:
        """SHACConfig's checks plus the run options'; every error names its flag."""
        super().validate()
        check_integers(self, ("checkpoint_every", "keep_checkpoints"), minimum=1)
        check_integers(self, ("threads", "video_steps"), minimum=1, optional=True)
        check_integers(self, ("video_every", "warmup_iters"), minimum=0)
        if self.time_limit_min is not None:
            check_number("time_limit_min", self.time_limit_min, "(0, inf)")
        if self.compile_cache is not None and not self.compile_cache.strip():
            raise ValueError("--compile-cache is empty: give a folder, or 'off' for torch's own cache locations")


def shac_part(cfg: RunConfig) -> SHACConfig:
    """The SHACConfig fields of a RunConfig."""
    names = {f.name for f in dataclasses.fields(SHACConfig)}
    return SHACConfig(**{k: v for k, v in dataclasses.asdict(cfg).items() if k in names})


# ---------------------------------------------------------------------------------------------- CPU threads
def default_threads() -> int:
    """$OMP_NUM_THREADS where it is a positive integer, else half the cores this process may use (its CPU
    affinity), at least 1 and at most ``MAX_DEFAULT_THREADS``."""
    env = os.environ.get("OMP_NUM_THREADS", "")
    if env.isdigit() and int(env) > 0:
        return int(env)
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity outside Linux
        cores = os.cpu_count() or 1
    return max(1, min(MAX_DEFAULT_THREADS, cores // 2))


def use_threads(n: int) -> None:
    """torch's intra-op threads of this process, and OMP_NUM_THREADS / MKL_NUM_THREADS of the processes it starts
    (compile helpers and workers)."""
    torch.set_num_threads(n)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(n)


# ---------------------------------------------------------------------------------------------- preparing
def _stored_config(folder: RunFolder, overrides: RunConfig) -> RunConfig:
    """The RunConfig of a run folder's config.json with what a resume may change taken from ``overrides``; a
    damaged or foreign file is named in a ValueError."""
    try:
        stored = folder.read_record()["config"]
    except ValueError as e:
        raise ValueError(f"--resume {folder.path}: {e}; it is the record of the run's settings, restore it (e.g. "
                         f"from a copy) to resume") from None
    fields = {f.name for f in dataclasses.fields(RunConfig)}
    stored = {k: v for k, v in stored.items() if k in fields}
    for k in ("actor_hidden", "critic_hidden", "betas"):
        if stored.get(k) is not None:
            stored[k] = tuple(stored[k])
    if stored.get("preset") not in PRESETS and all(stored.get(k) is not None for k in PRESET_FIELDS):
        # config.json holds every value a preset supplied, so a run whose preset has no table here (an older
        # folder's) resumes with exactly its values, under the default preset's name
        print(f"note: --resume {folder.path}: preset {stored.get('preset')!r} has no table here; the run resumes "
              f"with the values its config.json records (as --preset {RunConfig.preset} with them set)",
              file=sys.stderr)
        stored["preset"] = RunConfig.preset
    stored["out"] = Path(stored.get("out", folder.path.parent))
    stored.update(resume=folder.path, progress=overrides.progress, restart=overrides.restart)
    defaults = RunConfig()
    for k in RESUMABLE:
        if getattr(overrides, k) != getattr(defaults, k):
            stored[k] = getattr(overrides, k)
    try:
        cfg = RunConfig(**stored)
        cfg.validate()
    except (TypeError, ValueError) as e:
        raise ValueError(f"--resume {folder.path}: {folder.config_path}: {e}") from None
    return cfg


def prepare(cfg: RunConfig) -> tuple[RunConfig, RunFolder, torch.device, LoadedCheckpoint | None]:
    """Validate everything, then create the run folder (or find the one to resume), before any expensive work.

    Returns the config (a resume's as its folder records it; ``threads`` resolved), the run folder, the device
    and, on ``--resume``, the checkpoint to start from (None: the folder has none, the run starts over in it).
    """
    if cfg.resume is not None:
        try:
            folder = RunFolder.existing(cfg.resume)
        except ValueError as e:
            raise ValueError(f"--resume {cfg.resume}: {e}") from None
        cfg = _stored_config(folder, cfg)
        device = resolve_device(cfg.device)
        try:
            resume_from = folder.load_checkpoint(device)
        except ValueError as e:
            raise ValueError(f"--resume {folder.path}: {e}") from None
        check_resume([folder], cfg, None if resume_from is None else resume_from.state)
    else:
        if cfg.restart:
            raise ValueError("--restart goes with --resume RUN_FOLDER (a folder that holds no checkpoint)")
        cfg.validate()
        device = resolve_device(cfg.device)
        precision.check(cfg.precision, device)  # a refusal before the folder is made
        name = cfg.name or f"{cfg.task}_{cfg.mode}_seed{cfg.seed}_{time.strftime('%Y%m%d-%H%M%S')}"
        folder, resume_from = RunFolder.create(cfg.out, name), None
    if cfg.threads is None:
        cfg = dataclasses.replace(cfg, threads=default_threads())
    return cfg, folder, device, resume_from


class NothingToDo(Exception):
    """A resume of a run that has nothing left to train (its message: one line saying so and how to extend it)."""


def check_resume(folders: list[RunFolder], cfg: RunConfig, state: dict | None) -> None:
    """What a resume of ``folders`` (a run's, or a population's members') from the checkpoint ``state`` (one
    member's; None: none of them has one) would do, decided before any work: NothingToDo when the run is finished
    (its iterations done or its time budget spent); ValueError when there is no checkpoint but there are
    iterations a start from iteration 1 would train again, unless --restart asks for it."""
    where = folders[0].path if len(folders) == 1 else folders[0].path.parent
    if state is not None:
        it = state["iteration"]
        if it >= cfg.iters:
            raise NothingToDo(f"{where} is finished at iteration {it} (--iters {cfg.iters}): nothing to do; to train "
                              f"it longer: ablate --resume {where} --iters M  (M > {it})")
        if cfg.time_limit_min is not None and state["wall_s"] >= 60.0 * cfg.time_limit_min:
            raise NothingToDo(f"{where} has used its --time-limit-min {cfg.time_limit_min:g} at iteration {it} "
                              f"({state['wall_s'] / 60:.2f} min of training): nothing to do; to train it longer: "
                              f"ablate --resume {where} --time-limit-min M  (M > {state['wall_s'] / 60:.2f})")
        return
    trained = max((max([r["iter"] for r in f.read_metrics()] or [0]) for f in folders), default=0)
    summaries = [f.read_summary() or {} for f in folders]
    trained = max([trained] + [s.get("iterations") or 0 for s in summaries if isinstance(s.get("iterations"), int)])
    if trained == 0 or cfg.restart:
        return
    if all(s.get("status") in ("finished", "time_limit") for s in summaries):
        raise NothingToDo(f"{where} is finished at iteration {trained} and keeps no checkpoint (deleted since): "
                          f"nothing to resume from; --restart trains it again from iteration 1")
    raise ValueError(f"--resume {where}: no checkpoint to resume from, but {trained} iteration(s) trained (it "
                     f"stopped before its first checkpoint, --checkpoint-every {cfg.checkpoint_every}); add --restart "
                     f"to train it again from iteration 1 in this folder (the old metrics.jsonl, summary.json and "
                     f"videos are kept beside it as *.before-restart-<time>)")


# ---------------------------------------------------------------------------------------------- running
def run(cfg: RunConfig | Sequence[RunConfig], *, startup: Startup | None = None) -> Path:
    """Train (or resume) a run, or a population (several configs: the members, trained in one process); returns
    its folder (a population's: the folder that holds its members' run folders), whose summary.json (each
    member's) says how it ended (``interrupted``: by a signal, after checkpointing its last finished iteration).
    Raises ValueError on bad input before any work, NothingToDo for a resume of a finished run, RunFailed for an
    error once training started (recorded, the last finished iteration checkpointed where it could be), and
    KeyboardInterrupt for a signal that came before the run recorded its settings (its folder is then removed;
    a resumed one is left as it was). ``startup``: this process's start-up
    (``Startup.before_torch``: the bytecode folder, compile helpers on standby); None: one that started nothing
    before torch was imported."""
    from ablations import population

    started = time.time()
    startup = startup or Startup()
    folders: list[RunFolder] = []
    with StopOnSignal() as stop, plain_warnings():
        from diffrender import BinCapacityWarning

        # the renderer grows its automatic bin capacity as the robot moves and still renders every frame
        # completely (diffrender.BinCapacityWarning): nothing a run's user has to act on
        warnings.filterwarnings("ignore", category=BinCapacityWarning)
        try:
            single = isinstance(cfg, RunConfig) and not (cfg.resume is not None and population.is_member(cfg.resume))
            if single:
                one, folder, device, resume_from = prepare(cfg)
                cfgs, folders, states, home = [one], [folder], resume_from and resume_from.state, None
            else:
                cfgs, folders, device, states, home = population.prepare(cfg)
            use_threads(cfgs[0].threads)
            # process-wide (TF32 switches, the encoders' precision): before the trainer is built; config.json's
            # environment then records the switches the run trained with
            precision.use(cfgs[0].precision, device)
            cache_opened = time.time()
            startup.open(cfgs[0], shac_part(cfgs[0]) if single else [shac_part(c) for c in cfgs], device,
                         folders[0].path if single else home.path, resuming=states is not None)
            return _train(cfgs, folders, device, states, startup, stop, started=started, cache_opened=cache_opened,
                          population=home)
        except BaseException:
            for folder in folders:
                folder.remove_if_empty()  # stopped before it wrote its first record
            raise
        finally:
            startup.close()  # on every way out, an error before the training loop included


def _train(cfgs: list[RunConfig], folders: list[RunFolder], device: torch.device, states, startup: Startup,
           stop: StopOnSignal, *, started: float, cache_opened: float, population=None) -> Path:
    """The rest of :func:`run` once its folders and start-up are settled: build the trainer, record the runs,
    train, write the summaries. ``cfgs`` and ``folders``: one per member in the trainer's member order (a single
    run: one); ``states``: the checkpoint state(s) to resume from (None: a fresh start); ``population``: the
    population's folder (None: a single run)."""
    from tqdm.auto import tqdm

    from gradlab.shac import SHAC

    single = population is None
    cfg = cfgs[0]  # the settings members share
    trainer_built = time.time()
    trainer = SHAC(shac_part(cfg) if single else [shac_part(c) for c in cfgs], device=device)
    startup.trainer_built(trainer)
    trainer_done = time.time()
    # where the seconds before the first iteration go (summary.json "startup_s"; benchmarks/startup.py): parts
    # that together make up first_iter_s; "run_folder" is the bookkeeping around the trainer (checking the
    # config, the run folder, a checkpoint to resume, git and environment records, the progress bar)
    startup_s = {"imports": started - _process_started(), "compile_cache": trainer_built - cache_opened,
                 "trainer": trainer_done - trainer_built}
    if states is not None:
        trainer.load_state_dict(states)
        del states  # not kept alive for the whole run (optimizer states can be large)
        resuming = True
    else:
        resuming = False
    if cfg.tensorboard:  # bad input: said before the run records anything
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError as e:
            raise ValueError("--tensorboard needs the tensorboard package: pip install tensorboard") from e
    members = [trainer.members[i] for i in range(len(cfgs))]
    statuses: list[tuple[str, str | None]] = [("running", None)] * len(cfgs)
    stopped = [m.failed is not None for m in members]  # a resumed population's failed members stay stopped
    # The loop's bookkeeping of what a stop would keep: ``done`` is the newest iteration whose metrics every
    # member's folder holds, ``checkpointed`` the newest one on disk, ``held`` (iteration, state) a copy of the
    # newest finished iteration that is not on disk yet, and ``between`` whether the live trainer is at a finished
    # iteration (not inside one), so that its own state is that iteration's.
    done = checkpointed = trainer.iteration
    held: tuple[int, object] | None = None
    between = True
    lost: str | None = None
    first_iter_s = None
    bar = writer = None
    try:
        for i, (member_cfg, folder) in enumerate(zip(cfgs, folders)):
            if folder.config_path.exists():
                # a resume: the metrics lines after the checkpoint are trained again, damaged ones set aside (each
                # named); a restart (no checkpoint) keeps the old records beside the new
                notes = folder.settle_metrics(trainer.iteration) if resuming else folder.set_aside_for_restart()
                for note in notes:
                    print(note, file=sys.stderr)
                continue
            shac_fields = dataclasses.fields(SHACConfig)
            resolved = dataclasses.replace(member_cfg, **{f.name: getattr(members[i].cfg, f.name)
                                                          for f in shac_fields})
            config = dataclasses.asdict(resolved)
            del config["restart"]  # what this start did, not a setting of the run (arms compare the settings)
            record = {
                "config": config,
                # which values the preset supplied and which flags overrode it (flag and preset value side by side)
                "preset": preset_record(shac_part(member_cfg), members[i].cfg),
                "started_utc": _utc(started),
                "environment": environment_info(device),
                "command": sys.argv,
            }
            if not single:  # the process it trained in: one of these members, in this folder
                record["population"] = {"folder": population.path.name, "members": [f.path.name for f in folders],
                                        "index": i}
            folder.write_config(record)
            folder.write_git()

        if cfg.tensorboard:
            writer = SummaryWriter(str(folders[0].path / "tb"))

        base = f"{cfg.task}/{cfg.mode}" if single else f"{cfg.task}/{len(cfgs)} members"
        bar = tqdm(total=cfg.iters, initial=trainer.iteration, disable=not cfg.progress, desc=base, unit="it",
                   dynamic_ncols=True)
        eval_text = "-"
        startup_s["run_folder"] = (cache_opened - started) + (time.time() - trainer_done)
        # The first iterations wait for the compiler: the bar says which part it compiles or captures, then its name.
        ahead_s = startup.before_first_iteration(
            lambda text: bar.set_description(base if text is None else f"{base}: {text}"))
        if ahead_s is not None:
            startup_s["compile_ahead"] = ahead_s
            # compiling counts in the training wall-clock (--time-limit-min, the wall_s curves) wherever it happens:
            # runs with and without helpers spend their budgets alike
            trainer.wall_s += ahead_s
        # The budget is the trainer's own wall-clock, which a checkpoint carries: a run killed and resumed gets
        # the same training time as one that ran through, so that return-against-time curves stay comparable.
        budget_s = None if cfg.time_limit_min is None else 60.0 * cfg.time_limit_min
        spent = budget_s is not None and trainer.wall_s >= budget_s  # a resumed run whose budget is used up
        ended = spent
        stop.defer_to_iteration_end()  # from here a first signal lets the iteration finish
        while not ended and trainer.iteration < cfg.iters and not stop.requested:
            between = False
            out = trainer.train_iteration()
            rows = [out] if single else out
            live = [r for r in rows if r is not None]
            if first_iter_s is None:
                first_iter_s = time.time() - _process_started()
                # a resumed run starts from its checkpoint's state and frames: no reset and render
                startup_s.update(first_reset_render=trainer.start_s or 0.0, first_iteration=live[0]["iter_ms"] / 1e3)
            startup.after_iteration()
            it = trainer.iteration
            ended = it == cfg.iters or (budget_s is not None and trainer.wall_s >= budget_s)
            video = bool(cfg.video_every) and (it % cfg.video_every == 0 or ended)
            if video or (cfg.eval_every and (it % cfg.eval_every == 0 or ended)):
                # the deterministic policy from the fixed evaluation seed (SHAC.evaluate), filmed on video iterations
                t_eval = time.perf_counter()
                with startup.evaluating():
                    evaluated = trainer.evaluate(video_steps=(cfg.video_steps or trainer.task.episode_length)
                                                 if video else 0)
                eval_s = time.perf_counter() - t_eval  # what the evaluation cost beside the iteration (iter_ms)
                for row, folder, ev in zip(rows, folders, [evaluated] if single else evaluated):
                    if row is not None:
                        frames = ev.pop("frames")
                        row.update(ev, eval_s=eval_s)
                        folder.write_video(it, frames)
            for i, (row, folder) in enumerate(zip(rows, folders)):
                if row is not None:
                    folder.append_metrics(row)
                elif not stopped[i]:  # a member that stopped this iteration: its record says why, the others go on
                    stopped[i] = True
                    statuses[i] = ("nonfinite", members[i].failed)
                    folder.write_summary(_summary(folder.read_metrics(), cfgs[i], *statuses[i], started))
            done, between = it, True
            if writer is not None:
                for k, v in live[0].items():
                    if isinstance(v, (int, float)) and not isinstance(v, bool):
                        writer.add_scalar(k, v, it)
            if it % cfg.checkpoint_every == 0 or ended or stop.requested:
                _checkpoint(trainer.state_dict(), folders, it, cfg.keep_checkpoints)
                checkpointed, held = it, None
            else:
                held = None  # the older copy first: two at once would double what it holds
                held = (it, _copy_state(trainer.state_dict()))
                if device.type == "cuda":  # waited for here, outside the next iteration's measured time
                    torch.cuda.synchronize(device)
            evals = [ev for r in live if (ev := evaluation_of(r)) is not None]
            if evals:
                eval_text = f"{sum(e[0] for e in evals) / len(evals):.1f}"
            returns = [r["return_mean"] for r in live if r["return_mean"] is not None]
            bar.set_postfix({"ret": f"{sum(returns) / len(returns):.1f}" if returns else "-", "eval": eval_text,
                             "ms": f"{live[0]['iter_ms']:.0f}", "gn": f"{max(r['grad_norm'] for r in live):.2g}"})
            bar.update(1)
        if stop.requested and not ended:
            if checkpointed != trainer.iteration:
                _checkpoint(trainer.state_dict(), folders, trainer.iteration, cfg.keep_checkpoints)
                checkpointed = trainer.iteration
            status, error = "interrupted", f"{stop.requested} after iteration {trainer.iteration}"
        else:
            status, error = ("finished" if trainer.iteration >= cfg.iters else "time_limit"), None
        statuses = [s if stopped[i] else (status, error) for i, s in enumerate(statuses)]
    except KeyboardInterrupt as e:  # a second signal (or one before the loop): stopped at once
        stop.finishing()
        name = str(e) or "SIGINT"  # Python's own handler raises it without one
        kept, lost = _rescue(trainer, folders, between, held, done, checkpointed, cfg.keep_checkpoints)
        checkpointed = kept
        if not between:
            why = f"{name} during iteration {done + 1}: stopped at once, iteration {done + 1} is lost"
        elif first_iter_s is None:  # building, recording, compiling ahead: no iteration had started
            why = f"{name} before iteration {done + 1}: stopped at once"
        else:
            why = f"{name} after iteration {done}: stopped at once"
        why += f"; {lost}" if lost else (f"; resumes from iteration {kept}" if kept else "")
        statuses = [s if stopped[i] else ("interrupted", why) for i, s in enumerate(statuses)]
    except Exception as e:  # every error: recorded, the last finished iteration kept, then raised
        stop.finishing()
        where = (f"during iteration {done + 1}" if not between else f"before iteration {done + 1}"
                 if first_iter_s is None else f"after iteration {done}")
        status, text = describe_error(e, device, where)  # a NonFiniteError names its iteration itself
        kept, lost = _rescue(trainer, folders, between, held, done, checkpointed, cfg.keep_checkpoints)
        checkpointed = kept
        home = folders[0].path if single else population.path
        line = text + (f"; {lost}" if lost else f"; the run resumes from iteration {kept}: ablate --resume {home}"
                       if kept else "; no iteration finished, nothing to resume")
        statuses = [s if stopped[i] else (status, line) for i, s in enumerate(statuses)]
        raise RunFailed(status, line) from e
    except BaseException as e:  # SystemExit and its like: the summary says so rather than "running"
        stop.finishing()
        kept, lost = _rescue(trainer, folders, between, held, done, checkpointed, cfg.keep_checkpoints)
        checkpointed = kept
        statuses = [s if stopped[i] else ("failed", f"{type(e).__name__} after iteration {done}")
                    for i, s in enumerate(statuses)]
        raise
    finally:
        stop.finishing()
        startup.close()
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.close()
        for i, folder in enumerate(folders):
            if folder.config_path.exists() and not (stopped[i] and folder.summary_path.exists()):
                folder.write_summary(_summary(folder.read_metrics(), cfgs[i], *statuses[i], started,
                                              first_iter_s=first_iter_s, compiled=startup.record(),
                                              startup_s=startup_s, resumes_from=checkpointed or None, lost=lost))
    return folders[0].path if single else population.path


class RunFailed(RuntimeError):
    """A run stopped on an error, after recording it in its summary.json (``status``: nonfinite, oom or failed)
    and checkpointing its last finished iteration where it could; the message is one line: what went wrong, and
    what the run folder keeps or which iterations are lost."""

    def __init__(self, status: str, line: str):
        super().__init__(line)
        self.status = status


def describe_error(e: BaseException, device=None, where: str = "") -> tuple[str, str]:
    """(summary status, one line) of an error that stopped a run ``where`` (e.g. "during iteration 3"): ``oom``
    for running out of memory on either device (torch's OutOfMemoryError, MemoryError, or the CPU allocator's
    RuntimeError), ``nonfinite`` for a NonFiniteError, ``failed`` for any other."""
    from ablations.memory.worker import is_oom

    first = (str(e).strip().splitlines() or [""])[0]
    at = f" {where}" if where else ""
    if isinstance(e, NonFiniteError):
        return "nonfinite", first
    if is_oom(e):
        on = "GPU" if "cuda" in first.lower() or getattr(device, "type", device) == "cuda" else "CPU"
        size = re.search(r"tried to allocate ([0-9.]+) ?(bytes|[KMGT]i?B)", first, re.IGNORECASE)
        if size and size.group(2) == "bytes":
            what = f"an allocation of {int(size.group(1)) / 2**30:.3g} GiB failed"
        elif size:
            what = f"an allocation of {size.group(1)} {size.group(2)} failed"
        else:
            what = first[:200] or type(e).__name__
        return "oom", f"out of memory on the {on}{at} ({what}; fewer --num-envs or a smaller --image-size need less)"
    return "failed", f"{type(e).__name__}{at}: {first}"[:500]


def _copy_state(state):
    """A copy of a trainer's state_dict() that the next iteration does not change (its tensors are the live
    ones): CUDA tensors copied to (pinned) host memory without waiting for them, the rest cloned or deep-copied.
    Host memory, not the device's: the copy must not change a run's measured peak memory. Its cost is mostly the
    encoder's first linear layer and its two Adam moments (hopper, 64 environments: 74 MB a run, about 10 ms on
    the CPU; a few ms over PCIe), paid between iterations."""
    if isinstance(state, torch.Tensor):
        return state.detach().to("cpu", non_blocking=True) if state.is_cuda else state.detach().clone()
    if isinstance(state, dict):
        return {k: _copy_state(v) for k, v in state.items()}
    if type(state) in (list, tuple):
        return type(state)(_copy_state(v) for v in state)
    return copy.deepcopy(state)


def _rescue(trainer, folders: list[RunFolder], between: bool, held, done: int, checkpointed: int,
            keep: int) -> tuple[int, str | None]:
    """After a stop mid-run: checkpoint the last finished iteration (``done``) when it is not on disk, from the
    live trainer when it stopped between iterations, else from the copy ``held``. Returns (the iteration the run
    folder now resumes from, 0 for none; None, or what is lost and why when that is not ``done``)."""
    if done <= checkpointed:
        return checkpointed, None
    try:
        if between:
            states = trainer.state_dict()
        elif held is not None and held[0] == done:
            states = held[1]
            if torch.cuda.is_available() and torch.cuda.is_initialized():
                torch.cuda.synchronize()  # the copies to host memory were not waited for
        else:
            raise RuntimeError("no copy of it was held")
        _checkpoint(states, folders, done, keep)
        return done, None
    except BaseException as e:  # a third signal, a full disk, a device that failed: say what is lost
        why = describe_error(e)[1] if not isinstance(e, KeyboardInterrupt) else f"{str(e) or 'SIGINT'} again"
        since = f"since the checkpoint of iteration {checkpointed}" if checkpointed else "(no checkpoint yet)"
        span = f"iteration {done}" if done == checkpointed + 1 else f"iterations {checkpointed + 1}..{done}"
        return checkpointed, f"lost {span} {since}: checkpointing iteration {done} failed ({why})"


def _checkpoint(states, folders: list[RunFolder], iteration: int, keep: int) -> None:
    """Every member's checkpoint of ``iteration`` (``states``: the trainer's state_dict()) into its folder (a
    stopped member's too, recording why it stopped: a population resumes from an iteration every member has)."""
    for folder, state in zip(folders, [states] if len(folders) == 1 and isinstance(states, dict) else states):
        folder.save_checkpoint(iteration, state, keep=keep)


class StopOnSignal:
    """SIGINT and SIGTERM as a request to stop, inside ``with``.

    Before :meth:`defer_to_iteration_end` (building the trainer, compiling ahead) a signal raises
    KeyboardInterrupt at once; after it the first signal only sets :attr:`requested` (its name), so that the
    training loop finishes the iteration it is in, checkpoints it and stops; a second one raises
    KeyboardInterrupt. After :meth:`finishing` (the run is writing its last checkpoint and summary) a signal is
    only answered: those writes are what keeps the run resumable. Outside the main thread (where Python delivers
    signals) it does nothing.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested: str | None = None
        self._deferring = False
        self._finishing = False
        self._previous: dict = {}

    def __enter__(self) -> StopOnSignal:
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in self.SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)

    def defer_to_iteration_end(self) -> None:
        self._deferring = True

    def finishing(self) -> None:
        self._finishing = True

    def _handle(self, signum: int, frame) -> None:
        name = signal.Signals(signum).name
        from tqdm import tqdm

        if self._finishing:
            tqdm.write(f"{name}: already stopping; writing the last checkpoint and summary.json first (SIGKILL stops "
                       f"at once, without them)", file=sys.stderr)
            return
        if not self._deferring or self.requested is not None:
            raise KeyboardInterrupt(name)
        self.requested = name
        tqdm.write(f"{name}: stopping once this iteration has finished and is checkpointed (send it again to stop "
                   f"at once: this iteration is then lost, the one before it checkpointed)", file=sys.stderr)


@contextlib.contextmanager
def plain_warnings() -> Iterator[None]:
    """Inside: every warning is one line ``warning: <message>`` on stderr, each message once, written through
    tqdm so that it does not tear the progress bar (Python's own form adds the source line and repeats per place
    it is raised). The warning filters stay as they are."""
    from tqdm import tqdm

    shown: set[tuple[type, str]] = set()

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        key = (category, str(message))
        if key not in shown:
            shown.add(key)
            tqdm.write(f"warning: {message}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.showwarning = show
        yield


# ---------------------------------------------------------------------------------------------- the summary
def _utc(t: float) -> str:
    """Seconds since the epoch as an ISO-8601 UTC timestamp (what the report prints as started/ended)."""
    return datetime.datetime.fromtimestamp(t, datetime.timezone.utc).isoformat(timespec="seconds")


def _process_started() -> float:
    """When this process started, in seconds since the epoch: from /proc on Linux (interpreter start and imports
    included), else when this module was imported."""
    try:
        # /proc/self/stat field 22 is the start time in clock ticks after boot; the 20th field after the
        # parenthesised command name (which may itself hold spaces)
        ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        boot = next(int(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines()
                    if line.startswith("btime "))
        started = boot + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return _IMPORTED
    # a clock that disagrees with the import time (containers that fake /proc) is not trusted
    return started if 0.0 <= _IMPORTED - started < 3600.0 else _IMPORTED


def _summary(rows: list[dict], cfg: RunConfig, status: str, error: str | None, started: float, *,
             first_iter_s: float | None = None, compiled: dict | None = None,
             startup_s: dict | None = None, resumes_from: int | None = None, lost: str | None = None) -> dict:
    timed = [r for r in rows if r["iter"] > cfg.warmup_iters]
    plain = [r for r in timed if not r.get("probed")]
    probed = [r for r in timed if r.get("probed")]

    def med(key: str, rs: list[dict]) -> float | None:
        vals = [r[key] for r in rs if r.get(key) is not None]
        return median(vals) if vals else None

    def peak(key: str) -> float | None:
        vals = [r[key] for r in rows if r.get(key) is not None]
        return max(vals) if vals else None

    returns = [r["return_mean"] for r in rows if r.get("return_mean") is not None]
    evals = [(r["iter"], *ev) for r in rows if (ev := evaluation_of(r)) is not None]
    cos = [r["cos_full_decoupled"] for r in rows if r.get("cos_full_decoupled") is not None]
    return {
        "status": status,
        "error": error,
        "ended_utc": _utc(time.time()),
        "task": cfg.task,
        "mode": cfg.mode,
        "seed": cfg.seed,
        "iterations": rows[-1]["iter"] if rows else 0,
        "env_steps": rows[-1]["env_steps"] if rows else 0,
        "wall_s": rows[-1]["wall_s"] if rows else 0.0,
        # the iteration of the newest checkpoint, where ablate --resume starts (None: none); what a stop lost
        "resumes_from": resumes_from,
        "lost": lost,
        "final_return": returns[-1] if returns else None,
        "best_return": max(returns) if returns else None,
        # the deterministic policy's return (metrics eval_return_mean, or eval_return on video iterations): the
        # last evaluation's mean, its std over episodes (None where not logged) and iteration, and the best mean
        "final_eval_return": evals[-1][1] if evals else None,
        "final_eval_std": evals[-1][2] if evals and not math.isnan(evals[-1][2]) else None,
        "final_eval_iter": evals[-1][0] if evals else None,
        "best_eval_return": max(e[1] for e in evals) if evals else None,
        "threads": cfg.threads,
        "median_fwd_ms": med("fwd_ms", plain),
        "median_bwd_ms": med("bwd_ms", plain),
        "median_critic_ms": med("critic_ms", plain),
        # the critic fit ran alongside the backward (CUDA graphs, overlap_critic): its ms are not in iter_ms
        "critic_overlapped": any(r.get("critic_overlapped", False) for r in plain),
        "median_iter_ms": med("iter_ms", plain),
        "median_iter_ms_probed": med("iter_ms", probed),
        "median_grad_norm": med("grad_norm", rows),
        "median_cos_full_decoupled": median(cos) if cos else None,
        "peak_alloc_mb": peak("peak_alloc_mb"),
        "peak_reserved_mb": peak("peak_reserved_mb"),
        "median_saved_mb": med("saved_mb", plain),
        "warmup_iters_excluded": cfg.warmup_iters,
        "session_seconds": time.time() - started,
        # from this process's start to the end of its first training iteration (imports, setup, compilation)
        "first_iter_s": first_iter_s,
        # seconds of each part of that: imports (process start to ablate's own code), opening the compile cache,
        # building the trainer, its first reset and render, the first iteration (a resumed run: the ones it ran)
        "startup_s": startup_s,
        "compile": compiled,
    }


def closing_lines(run_dir: str | os.PathLike, *, floors=None) -> list[str]:
    """What ``ablate`` prints when a run ends: how it ended, its final training return and last deterministic
    evaluation return beside the task's zero- and random-action floors (``floors``: an ``ablations.reports.Floors``;
    default docs/floors.json of this checkout), the absolute run folder and the command that resumes it."""
    from ablations.reports import load_floors

    folder = RunFolder(Path(run_dir).resolve())
    s = folder.read_summary() or {}
    task = s.get("task", "?")
    status = s.get("status", "no summary")
    lines = [f"{task}/{s.get('mode', '?')} seed {s.get('seed', '?')}: {status} after {s.get('iterations', 0)} "
             f"iterations ({s.get('env_steps', 0)} environment steps, {s.get('wall_s', 0.0):.0f} s of training)"
             + (f"; {s['error']}" if s.get("error") else "")]

    def value(v) -> str:
        return "-" if v is None else f"{v:.1f}"

    lines.append(f"  training return    {value(s.get('final_return')):>9}  (mean of the last 100 finished training "
                 f"episodes, exploring policy)")
    ev, std = s.get("final_eval_return"), s.get("final_eval_std")
    if ev is None:
        lines.append("  evaluation return          -  (none yet: --eval-every or --video-every sets how often)")
    else:
        spread = f" +- {std:.1f}" if std is not None else ""
        lines.append(f"  evaluation return  {value(ev):>9}{spread}  (deterministic policy, at iteration "
                     f"{s.get('final_eval_iter')})")
    floors = floors or load_floors()
    known = floors.of(task) or {}
    if known:
        parts = [f"{policy} action {known[policy]['mean']:.1f}" for policy in ("zero", "random") if policy in known]
        lines.append(f"  floors             {', '.join(parts)}  ({floors.source})")
        if ev is not None:
            sides = [f"{'above' if ev > stats['mean'] else 'below'} the {policy}-action floor"
                     for policy, stats in known.items()]
            lines.append(f"  the evaluation return is {' and '.join(sides)}")
    else:
        lines.append(f"  floors             none for {task} ({floors.source or 'no floors file'}; "
                     f"task-floors --tasks {task} measures them)")
    lines.append(f"  run folder         {folder.path}")
    more = "" if status == "interrupted" else " --iters N  (to train longer)"
    lines.append(f"  resume             ablate --resume {folder.path}{more}")
    if s.get("lost"):  # last, where it is seen: what the resume will train again, and why
        lines.append(f"  lost               {s['lost']}")
    return lines
