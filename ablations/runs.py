"""The training loop of ``ablate`` (:func:`run`): one run or a population's members in one process, each in a run
folder of its own, and the summary each folder ends with.

A run trains in a run folder (``ablations.run_folder``: config.json, git.txt, metrics.jsonl, summary.json,
checkpoints/, videos/) that a researcher can trust, resume and plot. Its settings are ``ablations.run_config``'s;
its folders are made or found by ``ablations.population.prepare`` before any expensive work, and a stop or an error
keeps its last finished iteration resumable through ``ablations.stopping`` (docs/design.md, "Run folders and
resume"). A single run is a population of one; only the trainer's API (``SHAC(cfg)``) and the folder's layout
tell them apart.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import os
import sys
import time
import warnings
from collections.abc import Collection, Sequence
from pathlib import Path

import torch
from tqdm.auto import tqdm

from ablations.population import NothingToDo, Prepared, closing_lines, prepare
from ablations.run_config import RESUMABLE, RunConfig, default_threads, shac_part
from ablations.run_folder import RunFolder, environment_info, evaluation_of
from ablations.startup import Startup
from ablations.stopping import (
    RunFailed,
    StopOnSignal,
    checkpoint,
    copy_state,
    describe_error,
    plain_warnings,
    rescue,
)
from ablations.tree_hash import tree_hash
from diffrender import BinCapacityWarning
from gradlab import precision
from gradlab.config import SHACConfig
from gradlab.distill import Distill
from gradlab.presets import preset_record
from gradlab.shac import SHAC
from gradlab.timing import median

__all__ = ["RunConfig", "run", "prepare", "closing_lines", "default_threads", "use_threads", "shac_part",
           "describe_error", "RunFailed", "NothingToDo", "StopOnSignal", "plain_warnings", "REQUIRED_KEYS",
           "PROBE_KEYS", "TIMING_KEYS", "RESUMABLE"]

#: Keys every metrics line has.
REQUIRED_KEYS = ("iter", "env_steps", "wall_s", "return_mean", "actor_loss", "critic_loss", "grad_norm",
                 "grad_norm_clipped", "fwd_ms", "bwd_ms", "peak_alloc_mb", "peak_reserved_mb")
#: Keys added on probed iterations.
PROBE_KEYS = ("cos_full_decoupled", "grad_norm_full", "grad_norm_decoupled", "grad_norm_render_term")
#: Keys that depend on the clock, not on the computation (excluded when comparing runs for determinism).
TIMING_KEYS = ("wall_s", "fwd_ms", "bwd_ms", "critic_ms", "iter_ms", "eval_s", "peak_alloc_mb", "peak_reserved_mb")
_IMPORTED = time.time()  # when no better process start time is known (_process_started)


# ---------------------------------------------------------------------------------------------- CPU threads
def use_threads(n: int) -> None:
    """torch's intra-op threads of this process, and OMP_NUM_THREADS / MKL_NUM_THREADS of the processes it starts
    (compile helpers and workers)."""
    torch.set_num_threads(n)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(n)


# ---------------------------------------------------------------------------------------------- running
def run(runs: RunConfig | Sequence[RunConfig], *, startup: Startup | None = None,
        resume_flags: Collection[str] | None = None) -> Path:
    """Train (or resume) runs in this process: one (a single run) or several (a population's members, one batched
    simulation); ``runs`` as :func:`ablations.population.prepare` takes them. Returns the folder ``ablate`` names
    (a run alone's run folder, or the population folder that holds the members' run folders), whose summary.json
    (each member's) says how it ended (``interrupted``: by a signal, after checkpointing its last finished
    iteration). Raises ValueError on bad input before any work, NothingToDo for a resume of a finished run,
    RunFailed for an error once training started (recorded, the last finished iteration checkpointed where it
    could be), and KeyboardInterrupt for a signal that came before the run recorded its settings (its folder is
    then removed; a resumed one is left as it was). ``startup``: this process's start-up
    (``Startup.before_torch``: the bytecode folder, compile helpers on standby); None: one that started nothing
    before torch was imported. ``resume_flags``: as :func:`ablations.population.prepare` takes them."""
    started = time.time()
    startup = startup or Startup()
    folders: list[RunFolder] = []
    prepared = None
    with StopOnSignal() as stop, plain_warnings():
        # the renderer grows its automatic bin capacity as the robot moves and still renders every frame
        # completely (diffrender.BinCapacityWarning): nothing a run's user has to act on
        warnings.filterwarnings("ignore", category=BinCapacityWarning)
        try:
            prepared = prepare(runs, resume_flags=resume_flags)
            folders, cfg = prepared.folders, prepared.cfgs[0]
            use_threads(cfg.threads)
            # process-wide (TF32 switches, the encoders' precision): before the trainer is built; config.json's
            # environment then records the switches the run trained with
            precision.use(cfg.precision, prepared.device)
            cache_opened = time.time()
            startup.open(cfg, [shac_part(c) for c in prepared.cfgs], prepared.device, prepared.home,
                         resuming=prepared.states is not None)
            return _train(prepared, startup, stop, started=started, cache_opened=cache_opened)
        except BaseException:
            if prepared is not None:
                prepared.release()  # first: a folder holding only its lock file is empty
            for folder in folders:
                folder.remove_if_empty()  # stopped before it wrote its first record
            if prepared is not None and prepared.population is not None:
                prepared.population.remove_if_unused()  # and so did every member of a new population
            raise
        finally:
            if prepared is not None:
                prepared.release()  # after the last summary (_train's own finally wrote it)
            startup.close()  # on every way out, an error before the training loop included


def _record_runs(prepared: Prepared, members: list, iteration: int, *, resuming: bool, started: float) -> None:
    """Each run's records: config.json (every setting, resolved, with what the preset supplied) and git.txt of a
    new run, or of a restarted one once its earlier records are set aside beside them (each named); a resumed
    run keeps its own, its metrics lines after the checkpoint of ``iteration`` set aside to be trained again
    (damaged ones named), except a member that stopped before it (its lines end where it stopped). Every start
    appends its code's provenance (provenance.jsonl). ``members``: the trainer's, in the folders' order."""
    cfgs, folders = prepared.cfgs, prepared.folders
    tree = tree_hash()  # the code that trains, hashed where a device copy has no repository to name it
    for i, (member_cfg, folder) in enumerate(zip(cfgs, folders)):
        if folder.config_path.exists():
            if resuming:
                for note in [] if members[i].failed is not None else folder.settle_metrics(iteration):
                    print(note, file=sys.stderr)
                folder.append_provenance("resume", iteration)  # the code of this resume, beside the first's
                continue
            notes = folder.set_aside_for_restart()
            if member_cfg.restart:  # a resume of a folder that trained nothing sets aside its records unasked
                for note in notes:
                    print(note, file=sys.stderr)
            restarted = True
        else:
            restarted = False
        shac_fields = dataclasses.fields(SHACConfig)
        resolved = dataclasses.replace(member_cfg, **{f.name: getattr(members[i].cfg, f.name) for f in shac_fields})
        config = dataclasses.asdict(resolved)
        del config["restart"]  # what this start did, not a setting of the run (arms compare the settings)
        record = {
            "config": config,
            # which values the preset supplied and which flags overrode it (flag and preset value side by side)
            "preset": preset_record(shac_part(member_cfg), members[i].cfg),
            "started_utc": _utc(started),
            "environment": environment_info(prepared.device),
            "command": sys.argv,
            "tree_hash": tree.value,
            "tree_hash_source": tree.source,
        }
        if getattr(members[i], "expert", None) is not None:  # a distill student's expert and what it cost
            record["expert"] = {"source": members[i].expert.source, "wall_s": members[i].expert.wall_s,
                                "env_steps": members[i].expert.env_steps, "iterations": members[i].expert.iterations}
        if prepared.population is not None:  # the process it trained in: one of these members, in this folder
            record["population"] = {"folder": prepared.population.path.name,
                                    "members": [f.path.name for f in folders], "index": i}
        folder.write_config(record)
        folder.write_git()
        folder.append_provenance("restart" if restarted else "start", 0)


def _train(prepared: Prepared, startup: Startup, stop: StopOnSignal, *, started: float,
           cache_opened: float) -> Path:
    """The rest of :func:`run` once its folders and start-up are settled: build the trainer, record the runs,
    train, write the summaries. Every list here has one entry per member, in the trainer's member order (a single
    run: one)."""
    cfgs, folders, device, states = prepared.cfgs, prepared.folders, prepared.device, prepared.states
    cfg = cfgs[0]  # the settings members share
    trainer_built = time.time()
    parts = [shac_part(c) for c in cfgs]
    # the trainer's edge: a run alone is built as one (its failure raises NonFiniteError, its values come unwrapped);
    # --mode distill's students train in a trainer of their own with SHAC's interface (gradlab/distill.py)
    trainer_class = Distill if cfg.mode == "distill" else SHAC
    trainer = trainer_class(parts[0] if len(parts) == 1 else parts, device=device)

    def per_member(value) -> list:
        return [value] if trainer.single else value

    def states_now() -> list:
        return per_member(trainer.state_dict())

    startup.trainer_built(trainer)
    trainer_done = time.time()
    # where the seconds before the first iteration go (summary.json "startup_s"; benchmarks/startup.py): parts
    # that together make up first_iter_s; "run_folder" is the bookkeeping around the trainer (checking the
    # config, the run folder, a checkpoint to resume, git and environment records, the progress bar)
    startup_s = {"imports": started - _process_started(), "compile_cache": trainer_built - cache_opened,
                 "trainer": trainer_done - trainer_built}
    if states is not None:
        trainer.load_state_dict(states[0] if trainer.single else states)
        prepared.states = states = None  # not kept alive for the whole run (optimizer states can be large)
        resuming = True
    else:
        resuming = False
    if cfg.tensorboard:  # bad input: said before the run records anything
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError as e:
            raise ValueError("--tensorboard needs the tensorboard package: pip install tensorboard") from e
    members = [trainer.members[i] for i in range(len(cfgs))]
    stopped = [m.failed is not None for m in members]  # a resumed population's failed members stay stopped
    statuses: list[tuple[str, str | None]] = [("nonfinite", m.failed) if m.failed is not None else ("running", None)
                                              for m in members]
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
        with stop.held():  # every member's record or none: a population stopped half-way would not resume
            _record_runs(prepared, members, trainer.iteration, resuming=resuming, started=started)

        if cfg.tensorboard:
            writer = SummaryWriter(str(folders[0].path / "tb"))

        base = f"{cfg.task}/{cfg.mode}" if len(cfgs) == 1 else f"{cfg.task}/{len(cfgs)} members"
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
            rows = per_member(trainer.train_iteration())
            live = [r for r in rows if r is not None]
            if first_iter_s is None:
                first_iter_s = time.time() - _process_started()
                # a resumed run starts from its checkpoint's state and frames: no reset and render
                startup_s.update(first_reset_render=trainer.start_s or 0.0, first_iteration=live[0]["iter_ms"] / 1e3)
            startup.after_iteration()
            it = trainer.iteration
            ended = it == cfg.iters or (budget_s is not None and trainer.wall_s >= budget_s)
            video = bool(cfg.video_every) and (it % cfg.video_every == 0 or ended)
            if video or cfg.evaluates_at(it, ended):
                # the deterministic policy from the fixed evaluation seed (SHAC.evaluate), filmed on video iterations
                t_eval = time.perf_counter()
                with startup.evaluating():
                    evaluated = trainer.evaluate(video_steps=(cfg.video_steps or trainer.task.episode_length)
                                                 if video else 0)
                eval_s = time.perf_counter() - t_eval  # what the evaluation cost beside the iteration (iter_ms)
                for row, folder, ev in zip(rows, folders, per_member(evaluated)):
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
                checkpoint(states_now(), folders, it, cfg.keep_checkpoints)
                checkpointed, held = it, None
            else:
                held = None  # the older copy first: two at once would double what it holds
                held = (it, copy_state(states_now()))
                if device.type == "cuda":  # waited for here, outside the next iteration's measured time
                    torch.cuda.synchronize(device)
            evals = [ev for r in live if (ev := evaluation_of(r)) is not None]
            if evals:
                eval_text = f"{sum(e[0] for e in evals) / len(evals):.1f}"
            returns = [r["return_mean"] for r in live if r["return_mean"] is not None]
            norms = [r["grad_norm"] for r in live if r["grad_norm"] is not None]  # None: no update (distill)
            bar.set_postfix({"ret": f"{sum(returns) / len(returns):.1f}" if returns else "-", "eval": eval_text,
                             "ms": f"{live[0]['iter_ms']:.0f}", "gn": f"{max(norms):.2g}" if norms else "-"})
            bar.update(1)
        if stop.requested and not ended:
            if checkpointed != trainer.iteration:
                checkpoint(states_now(), folders, trainer.iteration, cfg.keep_checkpoints)
                checkpointed = trainer.iteration
            status, error = "interrupted", f"{stop.requested} after iteration {trainer.iteration}"
        else:
            status, error = ("finished" if trainer.iteration >= cfg.iters else "time_limit"), None
        statuses = [s if stopped[i] else (status, error) for i, s in enumerate(statuses)]
    except KeyboardInterrupt as e:  # a second signal (or one before the loop): stopped at once
        stop.finishing()
        name = str(e) or "SIGINT"  # Python's own handler raises it without one
        kept, lost = rescue(states_now, folders, between, held, done, checkpointed, cfg.keep_checkpoints)
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
        kept, lost = rescue(states_now, folders, between, held, done, checkpointed, cfg.keep_checkpoints)
        checkpointed = kept
        line = text + (f"; {lost}" if lost else f"; the run resumes from iteration {kept}: ablate --resume "
                                                f"{prepared.home}"
                       if kept else "; no iteration finished, nothing to resume")
        statuses = [s if stopped[i] else (status, line) for i, s in enumerate(statuses)]
        raise RunFailed(status, line) from e
    except BaseException as e:  # SystemExit and its like: the summary says so rather than "running"
        stop.finishing()
        kept, lost = rescue(states_now, folders, between, held, done, checkpointed, cfg.keep_checkpoints)
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
    return prepared.home


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
