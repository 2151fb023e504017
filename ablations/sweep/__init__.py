"""``ablate-sweep``: a grid of ``ablate`` runs (tasks x modes x seeds x any ``ablate`` flag) on Ray core.

Each run is one Ray task that starts ``python -m ablations ablate`` as a child process in a scratch folder on
whichever node Ray picked, so a crash, an out-of-memory kill or a bad configuration stays inside that run.
The node needs no filesystem shared with the driver: a small actor pinned to the driver's node (``RunStore``)
receives the run folder packed as a tar archive every time a new checkpoint appears and once at the end, and
writes it under ``<sweep>/runs/<run_id>/``. A retried task (its worker died, or its child was killed by a
signal) asks the store for the latest checkpoint it holds and continues with ``ablate --resume``. The driver
keeps at most (CPUs / ``--cpus-per-run``) runs in flight per node (:func:`run_slots`).

The sweep folder::

    sweep.json                    the manifest (written atomically): grid, the command that made it, and per run
                                  its status (queued / running / done / failed / interrupted), error, folder,
                                  iteration, checkpoint (the newest iteration the folder holds one of), latest
                                  return
    runs/<run_id>/                each run folder as ``ablate`` writes it (config.json, metrics.jsonl,
                                  summary.json, videos/, the two newest checkpoints)
    runs/<population>/<member>/   with --pack: a population folder (population.json) and its members' run folders
    logs/<job>.attempt<N>.log     the child's output of each attempt that ended (a killed worker leaves none);
                                  <job> is the run's id, or its population's
    discarded/                    folders of earlier attempts that stopped before any checkpoint (a fresh
                                  start needs an empty folder; nothing is deleted)

A rerun with the same folder skips runs whose summary says they finished, resumes the others from their last
checkpoint and starts the rest from scratch. Ctrl-C stops in two stages: the driver raises the store's stop
request, each worker sends its ablate a SIGINT (a second one after ``worker.STOP_GRACE_S``), ships the folder and
returns its runs "interrupted" (not retried); the driver waits for them (``driver.STOP_WAIT_S`` at most) and prints
the iteration each kept. Library use (the ``ablate-paper`` layer): build a
:class:`SweepConfig` (or :func:`parse_args`), then :func:`run_sweep` returns the manifest; :func:`plan` lists
the runs without starting anything. Both take ``arms``: named sets of ablate flags, each with its own mode,
that replace the modes axis (tasks x arms x seeds x --vary), for comparisons whose sides differ in more than
the mode (the paper's full arm with its own preset beside the soft-rasterizer one).

``--pack N`` trains the runs that can share a process (the same task and every setting but a member's own: mode,
seed, raster model, preset, the learning-rate schedule...) as populations of at most N members (``auto``: 12 on
GPU runs, 1 on the CPU), each one ``ablate --member ...`` process and one Ray task with one run's resources
(:mod:`~ablations.sweep.packing`). A population's folder is ``runs/<task>_population<k>/``: population.json and
its members' run folders; each run's record in sweep.json names its folder and its job. Everything above holds
for a population as for a run: its checkpoints travel once every member has one of that iteration, a killed
worker's retry resumes it with ``ablate --resume <population folder>``, and a rerun keeps every run that has a
folder in the job it has (whatever --pack says then), so nothing trained is lost or trained twice.

Each run folder keeps its ``KEPT_CHECKPOINTS`` newest checkpoints, so a resume survives a damaged newest one
(``ablate --resume`` falls back to the next).

Modules, by role:
    config    :class:`SweepConfig` (the flags), the TOML file, ``--set``/``--vary`` as ablate arguments
    grid      :func:`plan` (every run, checked by ablate's parser) and :func:`attempt_command` (the one place
              that turns a run into the command line its process runs)
    packing   :class:`Job` (one Ray task: a run, or a population of runs) and :func:`pack_runs`
    transfer  :func:`pack_run` / :func:`unpack_run`: run folders as tar archives between nodes
    store     :class:`RunStore` (the driver-side actor) and what the sweep decides from a run folder
    worker    the Ray task: one attempt of one job; ``child.py`` ties its process to the worker
    manifest  sweep.json
    table     the live table
    driver    :func:`run_sweep`, :func:`dry_run` and :func:`main` (the ``ablate-sweep`` command)

Test seam (not a user option): ``run_sweep(..., program=[...])`` runs that program with ablate's arguments
instead of ``python -m ablations ablate`` (tests/ablations/fake_ablate.py: a worker killed mid-run, a run that
records when it trained).
"""

from ablations.sweep.config import SweepConfig, parse_args
from ablations.sweep.driver import dry_run, main, run_slots, run_sweep
from ablations.sweep.grid import RunSpec, attempt_command, plan
from ablations.sweep.manifest import load_manifest
from ablations.sweep.packing import Job, pack_runs
from ablations.sweep.store import RunStore
from ablations.sweep.transfer import KEPT_CHECKPOINTS, pack_run, unpack_run
from ablations.sweep.worker import RunProcessDied

__all__ = ["SweepConfig", "RunSpec", "RunStore", "RunProcessDied", "parse_args", "plan", "run_sweep", "dry_run",
           "load_manifest", "pack_run", "unpack_run", "main", "KEPT_CHECKPOINTS", "run_slots", "attempt_command", "Job",
           "pack_runs"]
