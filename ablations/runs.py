"""The training loop of ``ablate`` (:func:`run`): one run or a population's members in one process, each in a run
folder of its own, and the summary each folder ends with.

A run trains in a run folder (``ablations.run_folder``: config.json, git.txt, metrics.jsonl, summary.json,
checkpoints/, videos/) that a researcher can trust, resume and plot. Its settings are ``ablations.run_config``'s;
its members (a ``gradlab.roster.Roster``) and folders are made or found by ``ablations.population.prepare`` before
any expensive work. The loop (:func:`_train`) tells ``ablations.run_log.RunLog`` what to record and
``ablations.stopping.Keeper`` what to checkpoint, and a stop or an error keeps its last finished iteration
resumable through the keeper's one rescue (docs/design.md, "Run folders and resume"). A run alone is a
population of one; only its folder's layout, its progress label and its closing lines tell them apart.
"""

from __future__ import annotations

import os
import time
import warnings
from collections.abc import Collection, Sequence
from pathlib import Path

import torch

from ablations.population import Prepared, prepare
from ablations.run_config import RunConfig
from ablations.run_folder import RunFolder
from ablations.run_log import RunLog
from ablations.startup import Startup
from ablations.stopping import Keeper, RunFailed, StopOnSignal, plain_warnings
from diffrender import BinCapacityWarning
from gradlab import precision
from gradlab.distill import Distill
from gradlab.shac import SHAC

__all__ = ["PROBE_KEYS", "REQUIRED_KEYS", "TIMING_KEYS", "run", "use_threads"]

#: Keys every metrics line has.
REQUIRED_KEYS = ("iter", "env_steps", "wall_s", "return_mean", "actor_loss", "critic_loss", "grad_norm",
                 "grad_norm_clipped", "fwd_ms", "bwd_ms", "peak_alloc_mb", "peak_reserved_mb")
#: Keys added on probed iterations.
PROBE_KEYS = ("cos_full_decoupled", "grad_norm_full", "grad_norm_decoupled", "grad_norm_render_term")
#: Keys that depend on the clock, not on the computation (excluded when comparing runs for determinism).
TIMING_KEYS = ("wall_s", "fwd_ms", "bwd_ms", "critic_ms", "iter_ms", "eval_s", "peak_alloc_mb", "peak_reserved_mb")


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
            startup.open(prepared.cfgs, prepared.roster.cfgs, prepared.device, prepared.home,
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


def _train(prepared: Prepared, startup: Startup, stop: StopOnSignal, *, started: float,
           cache_opened: float) -> Path:
    """The rest of :func:`run` once its folders and start-up are settled: build the trainer, record the runs,
    train, write the summaries (``RunLog``), the checkpoints and what every way out keeps (``Keeper``)."""
    cfg, device = prepared.cfgs[0], prepared.device  # the settings members share
    trainer_built = time.time()
    # --mode distill's students train in a trainer of their own with SHAC's interface (gradlab/distill.py)
    trainer = (Distill if cfg.mode == "distill" else SHAC)(prepared.roster, device=device)
    startup.trainer_built(trainer)
    trainer_done = time.time()
    resuming = prepared.states is not None
    if resuming:
        trainer.load_state_dict(prepared.states)
        prepared.states = None  # not kept alive for the whole run (optimizer states can be large)
    log = RunLog(prepared, trainer, started=started, cache_opened=cache_opened, trainer_built=trainer_built,
                 trainer_done=trainer_done)
    keeper = Keeper(trainer, prepared.folders, keep=cfg.keep_checkpoints, device=device)
    try:
        with stop.held():  # every member's record or none: a population stopped half-way would not resume
            log.record_runs(trainer.iteration, resuming=resuming)
        log.open(startup)
        # The budget is the trainer's own wall-clock, which a checkpoint carries: a run killed and resumed gets
        # the same training time as one that ran through, so that return-against-time curves stay comparable.
        budget_s = None if cfg.time_limit_min is None else 60.0 * cfg.time_limit_min
        ended = budget_s is not None and trainer.wall_s >= budget_s  # a resumed run whose budget is used up
        stop.defer_to_iteration_end()  # from here a first signal lets the iteration finish
        while not ended and trainer.iteration < cfg.iters and not stop.requested:
            keeper.begin()
            rows = trainer.train_iteration()
            log.trained(rows)
            startup.after_iteration()
            it = trainer.iteration
            ended = it == cfg.iters or (budget_s is not None and trainer.wall_s >= budget_s)
            video = bool(cfg.video_every) and (it % cfg.video_every == 0 or ended)
            if video or cfg.evaluates_at(it, ended):
                log.evaluation(rows, it, startup, video=video)
            log.iteration(rows)
            keeper.finished(it, save=it % cfg.checkpoint_every == 0 or ended or stop.requested)
            log.progress(rows, it)
        if stop.requested and not ended:
            keeper.save()
            log.end("interrupted", f"{stop.requested} after iteration {trainer.iteration}")
        else:
            log.end("finished" if trainer.iteration >= cfg.iters else "time_limit", None)
    except BaseException as e:  # every way out: the last finished iteration kept where it can be, and recorded
        stop.finishing()
        status, line = keeper.rescue(e, ran=log.first_iter_s is not None, home=prepared.home)
        log.end(status, line)
        if isinstance(e, Exception):
            raise RunFailed(status, line) from e
        if not isinstance(e, KeyboardInterrupt):  # a second signal (or one before the loop) stopped it at once
            raise
    finally:
        stop.finishing()
        startup.close()
        log.close(compiled=startup.record(), resumes_from=keeper.checkpointed or None, lost=keeper.lost)
    return prepared.home
