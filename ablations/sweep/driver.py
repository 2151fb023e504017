"""The driver: runs (or resumes) the grid on Ray, keeps sweep.json current, and the ``ablate-sweep`` command."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ablations.command import command_errors
from ablations.folder_lock import FolderLock
from ablations.run_folder import RunFolder, check_writable
from ablations.sweep.config import SweepConfig, parse_args, parse_set, parse_vary
from ablations.sweep.grid import plan
from ablations.sweep.manifest import MANIFEST, load_manifest, plan_jobs, prepare_manifest, write_manifest
from ablations.sweep.store import RunStore, job_state, run_path
from ablations.sweep.table import LiveTable
from ablations.sweep.worker import RunProcessDied, run_attempt

__all__ = ["run_sweep", "dry_run", "main", "run_slots", "quiet_token_notice", "DRIVER_POLL_S"]

#: Seconds between the driver's looks at the runs (and table updates).
DRIVER_POLL_S = 1.0
#: Seconds a stopping sweep (Ctrl-C) waits for its workers to checkpoint and send their folders, on top of the
#: workers' grace before their second SIGINT (``STOP_GRACE_S``); runs still out then go back to queued.
STOP_WAIT_S = 120.0
#: The workers' grace between their two SIGINTs (None: ``ablations.sweep.worker.STOP_GRACE_S``).
STOP_GRACE_S: float | None = None
#: Where a job trained, as its worker reports it and the manifest keeps it beside each run.
PLACEMENT = ("node", "host", "gpus")
#: The start of the line Ray logs whenever it starts a local cluster with token authentication, its default.
_TOKEN_NOTICE = "Token authentication is enabled for this Ray cluster"


class _DropTokenNotice(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith(_TOKEN_NOTICE)


def quiet_token_notice() -> None:
    """Leave out Ray's notice that it enabled token authentication: printed on every sweep, it asks nothing of the
    user. Its warning that authentication is disabled (RAY_AUTH_MODE=disabled) is still printed."""
    logger = logging.getLogger("ray._private.authentication.authentication_token_setup")
    if not any(isinstance(f, _DropTokenNotice) for f in logger.filters):
        logger.addFilter(_DropTokenNotice())


def _ray_init(cfg: SweepConfig) -> bool:
    """Connect to (or start) the cluster unless this process already is; True when this call did it."""
    import ray

    if ray.is_initialized():
        return False
    kwargs: dict[str, Any] = dict(address=cfg.address, include_dashboard=False, logging_level=logging.WARNING,
                                  log_to_driver=False)
    if cfg.num_cpus is not None:
        kwargs["num_cpus"] = cfg.num_cpus
    if cfg.num_gpus is not None:
        kwargs["num_gpus"] = cfg.num_gpus
    quiet_token_notice()
    try:
        ray.init(**kwargs)
    except ConnectionError as e:
        raise ValueError(f"--address {cfg.address}: cannot join the Ray cluster: {e}") from None
    return True


def _check_resources(cfg: SweepConfig) -> None:
    """Refuse a sweep that no node could ever schedule (Ray would wait for ever)."""
    import ray

    nodes = [n for n in ray.nodes() if n.get("Alive")]
    cpus = max((n["Resources"].get("CPU", 0) for n in nodes), default=0)
    gpus = max((n["Resources"].get("GPU", 0) for n in nodes), default=0)
    if cfg.cpus_per_run > cpus:
        raise ValueError(f"--cpus-per-run {cfg.cpus_per_run}: no node of the cluster has that many (largest: {cpus})")
    if cfg.gpus_per_run > gpus:
        raise ValueError(f"--gpus-per-run {cfg.gpus_per_run}: no node of the cluster has that many GPUs "
                         f"(largest: {gpus}); --gpus-per-run 0 trains on the CPU")


def run_slots(cfg: SweepConfig) -> int:
    """How many runs (or populations: a process each) the cluster trains at once: per live node, its CPUs /
    --cpus-per-run (and GPUs / --gpus-per-run), rounded down, summed; at least 1.

    The driver keeps no more processes than this in flight. Ray's reservations alone do not hold the line: a task
    blocked in ``ray.get`` (a worker waiting for the run store) hands its CPU back, and Ray starts another run on it.
    """
    import ray

    total = 0
    for node in ray.nodes():
        if not node.get("Alive"):
            continue
        res = node["Resources"]
        fit = math.floor(res.get("CPU", 0) / cfg.cpus_per_run + 1e-9)
        if cfg.gpus_per_run:
            fit = min(fit, math.floor(res.get("GPU", 0) / cfg.gpus_per_run + 1e-9))
        total += fit
    return max(1, total)


def _describe_failure(exc: BaseException) -> str:
    cause = getattr(exc, "cause", None)
    if isinstance(cause, BaseException):
        exc = cause
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".strip()[:2000]


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S")


def run_sweep(cfg: SweepConfig, set_table: dict | None = None, vary_table: dict | None = None, *,
              command: Sequence[str] | None = None, arms: dict | None = None,
              program: Sequence[str] | None = None) -> dict:
    """Run (or resume) the sweep; returns the final manifest. Bad input raises ValueError before any run.

    ``arms``: see :func:`~ablations.sweep.plan`. ``command``: the command line sweep.json records (None:
    ``ablate-sweep`` and this process's arguments). Uses the Ray connection of this process when there is one
    (it is left open), else joins or starts the cluster that ``cfg.address`` names and shuts the connection down
    at the end. ``program`` is a test seam, not a user option: a stand-in for ``python -m ablations ablate``
    (see :func:`~ablations.sweep.grid.attempt_command`).
    """
    specs = plan(cfg, set_table, vary_table, arms=arms)
    set_table = parse_set(cfg.set) if set_table is None else set_table
    vary_table = parse_vary(cfg.vary) if vary_table is None else vary_table
    out = Path(cfg.out).resolve()
    created = not out.exists()
    check_writable(out)
    lock = FolderLock(out).acquire("sweep folder")  # one driver an --out: two would train each run twice
    try:
        return _run_locked(cfg, specs, set_table, vary_table, out, created, lock, command=command, arms=arms,
                           program=program)
    finally:
        lock.release()


def _run_locked(cfg: SweepConfig, specs: list, set_table: dict, vary_table: dict, out: Path, created: bool,
                lock: FolderLock, *, command: Sequence[str] | None, arms: dict | None,
                program: Sequence[str] | None) -> dict:
    """:func:`run_sweep` once it holds the lock of ``out`` (``created``: made for this sweep)."""
    manifest, todo = prepare_manifest(cfg, specs, set_table, vary_table, None if command is None else list(command),
                                      arms)
    if not todo:
        write_manifest(out, manifest)
        return manifest

    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    started_here = _ray_init(cfg)
    table = store = None
    pending: dict = {}
    stopping: list = []  # the jobs out when Ctrl-C came
    accepted = False  # sweep.json is written once the cluster can run the sweep: a refused start leaves none
    try:
        try:
            _check_resources(cfg)
        except ValueError:
            if created:
                lock.release()  # first: the folder holds nothing else
                with contextlib.suppress(OSError):
                    out.rmdir()  # made for this sweep, still empty
            raise
        accepted = True
        write_manifest(out, manifest)
        runs = manifest["runs"]
        store = ray.remote(RunStore).options(
            num_cpus=0, max_concurrency=1,
            scheduling_strategy=NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False),
        ).remote(str(out), {job.job_id: max(runs[r].get("attempts", 0) for r in job.run_ids) for job in todo})
        # A population is one Ray task with the resources of one run.
        task = ray.remote(run_attempt).options(num_cpus=cfg.cpus_per_run, num_gpus=cfg.gpus_per_run,
                                               max_retries=cfg.max_retries, retry_exceptions=[RunProcessDied])
        opts = {"sweep_id": manifest["id"], "gpus_per_run": cfg.gpus_per_run, "cpus_per_run": cfg.cpus_per_run,
                "keep_checkpoints": cfg.keep_checkpoints, "program": None if program is None else list(program),
                "stop_grace_s": STOP_GRACE_S}
        queue = list(todo)
        jobs = {job.job_id: job for job in todo}
        table = LiveTable(manifest, todo, enabled=cfg.progress)
        last_write = time.monotonic()
        def finish(ref) -> None:
            """Record the result of a job's task."""
            job = pending.pop(ref)
            try:
                result = ray.get(ref)
            except ray.exceptions.RayError as e:
                # Retries are spent (a worker death, a killed ablate) or the task itself broke.
                tries = max(max(runs[r].get("attempts") or 0 for r in job.run_ids), 1)
                error = f"{_describe_failure(e)} (attempt {tries}, --max-retries {cfg.max_retries})"
                result = {"runs": {r: {"status": "failed", "error": error} for r in job.run_ids}}
            where = {k: result[k] for k in PLACEMENT if k in result}
            for run_id, outcome in result["runs"].items():
                rec = runs[run_id]
                rec.update({k: v for k, v in {**outcome, **where}.items()
                            if k in ("status", "error", "iteration", "latest_return", "checkpoint", *PLACEMENT,
                                     "summary_status")}, updated=_now())
                rec["attempts"] = max(rec.get("attempts", 0), result.get("attempt", 0))
            if not cfg.keep_checkpoints and all(runs[r]["status"] == "done" for r in job.run_ids):
                for r in job.run_ids:
                    RunFolder(out / runs[r]["folder"]).drop_checkpoints()
                    runs[r]["checkpoint"] = None

        while queue or pending:
            if queue:
                free = max(0, run_slots(cfg) - len(pending))
                for job in queue[:free]:
                    pending[task.remote(dataclasses.asdict(job), store, opts)] = job
                del queue[:free]
            ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=DRIVER_POLL_S)
            changed = False
            for job_id, info in ray.get(store.snapshot.remote()).items():
                for run_id in jobs[job_id].run_ids:
                    rec = runs[run_id]
                    if rec["status"] in ("done", "failed") and info.get("attempts", 0) <= rec.get("attempts", 0):
                        continue
                    new = {k: info[k] for k in (*PLACEMENT, "attempts", "resumed", "checkpoint") if k in info}
                    new.update({k: v for k, v in (info.get("runs") or {}).get(run_id, {}).items()
                                if k in ("iteration", "latest_return", "wall_s")})
                    if info.get("status") == "running" and rec["status"] == "queued":
                        new["status"] = "running"
                    if any(rec.get(k) != v for k, v in new.items()):
                        rec.update(new, updated=_now())
                        changed = changed or "status" in new
            for ref in ready:
                finish(ref)
                changed = True
            if changed or time.monotonic() - last_write > 10 * DRIVER_POLL_S:
                write_manifest(out, manifest)
                last_write = time.monotonic()
            table.update()
        snap = ray.get(store.snapshot.remote())
        for job_id, info in snap.items():
            for run_id in jobs[job_id].run_ids:
                runs[run_id]["attempts"] = max(runs[run_id].get("attempts", 0), info.get("attempts", 0))
    except KeyboardInterrupt:
        stopping[:] = pending.values()
        if store is not None and pending:
            _stop_workers(store, pending, finish)
        # Runs still out go back to queued: a rerun resumes them from the checkpoints the folder holds.
        for job in pending.values():
            for run_id in job.run_ids:
                manifest["runs"][run_id]["status"] = "queued"
        if table is not None:
            table.update()
        _print_kept(manifest, [r for job in stopping for r in job.run_ids])
        raise
    finally:
        if table is not None:
            table.close()
        if accepted:
            write_manifest(out, manifest)
        if started_here:
            ray.shutdown()
    return manifest


def _stop_workers(store, pending: dict, finish) -> None:
    """The second stage of a Ctrl-C: raise the store's stop request, so that each worker sends its ablate SIGINT
    (a second one after its grace), sends the folder and returns; record each job's result as it comes, for
    :data:`STOP_WAIT_S` (and the workers' grace) at most. A second Ctrl-C asks for the second SIGINT at once; a
    third stops waiting."""
    import ray

    from ablations.sweep.worker import STOP_GRACE_S as WORKER_GRACE

    print(f"stopping: each running ablate checkpoints its last finished iteration and sends its folder (Ctrl-C "
          f"again: at once; a third time: stop waiting) ({len(pending)} job(s))", file=sys.stderr, flush=True)
    ray.get(store.stop.remote(1))
    grace = WORKER_GRACE if STOP_GRACE_S is None else STOP_GRACE_S
    deadline = time.monotonic() + grace + STOP_WAIT_S
    presses = 1
    while pending and time.monotonic() < deadline:
        try:
            ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=DRIVER_POLL_S)
            for ref in ready:
                finish(ref)
        except KeyboardInterrupt:
            presses += 1
            if presses >= 3:
                break
            ray.get(store.stop.remote(2))


def _print_kept(manifest: dict, run_ids: list[str]) -> None:
    """A line per run that was out when the sweep stopped: the iteration it kept, or that it left nothing."""
    for run_id in run_ids:
        rec = manifest["runs"][run_id]
        ckpt = rec.get("checkpoint")
        if rec["status"] == "done":
            continue
        kept = f"kept iteration {ckpt} of {rec.get('iters')}" if ckpt else "no checkpoint kept: starts afresh"
        print(f"{rec['status']} {run_id}: {kept} ({rec.get('folder')})", file=sys.stderr, flush=True)


def dry_run(cfg: SweepConfig, set_table: dict | None = None, vary_table: dict | None = None, *,
            arms: dict | None = None, local_gpus: int | None = None) -> list[str]:
    """Print (and return) one line per job (a run, or a population followed by a line per member), with what a
    (re)run would do with it; starts nothing. ValueError for what the real run would refuse before it starts
    (a changed grid; more GPUs a run than this machine has, ``local_gpus`` of them, None: as torch sees them)."""
    specs = plan(cfg, set_table, vary_table, arms=arms)
    out = Path(cfg.out)
    # what the real run refuses before it starts anything, refused here too: a grid changed under a sweep.json,
    # and (on this machine's own cluster) more GPUs a run than the machine has
    prepare_manifest(cfg, specs, parse_set(cfg.set) if set_table is None else set_table,
                     parse_vary(cfg.vary) if vary_table is None else vary_table, None, arms)
    if cfg.gpus_per_run and cfg.address is None:
        if cfg.num_gpus is not None or local_gpus is not None:
            gpus = cfg.num_gpus if cfg.num_gpus is not None else local_gpus
        else:
            import torch

            gpus = torch.cuda.device_count()
        if cfg.gpus_per_run > gpus:
            raise ValueError(f"--gpus-per-run {cfg.gpus_per_run}: this machine has {gpus} GPU(s); --gpus-per-run 0 "
                             f"trains on the CPU")
    manifest = load_manifest(out) or {"runs": {}}
    jobs = plan_jobs(cfg, specs, manifest)
    lines = []
    for job in jobs:
        state = job_state(run_path(out, job.job_id), job.members, job.iters)
        if state != "done" and not cfg.rerun_failed and all(
                manifest["runs"].get(r, {}).get("status") == "failed" for r in job.run_ids):
            state = "failed (left)"
        lines.append(f"{state:8s} {job.job_id}: ablate {' '.join(job.args)}")
        if job.population:
            lines += [f"{'':8s}   {run_id} in {job.folder(i)}" for i, run_id in enumerate(job.run_ids)]
    populations = sum(job.population for job in jobs)
    if populations:
        lines.append(f"{len(specs)} runs in {len(jobs)} processes ({populations} populations of at most "
                     f"{cfg.pack_size()}, --pack {cfg.pack}); {cfg.cpus_per_run} CPU and {cfg.gpus_per_run} GPU "
                     f"each process")
    else:
        lines.append(f"{len(specs)} runs; {cfg.cpus_per_run} CPU and {cfg.gpus_per_run} GPU each")
    for line in lines:
        print(line)
    return lines


def main(argv: list[str] | None = None, *, program: Sequence[str] | None = None) -> None:
    """``ablate-sweep --tasks cartpole hopper --modes full decoupled --seeds 0 1 2 --vary image-size=64,84``.

    ``program``: the test seam of :func:`run_sweep`.
    """
    with command_errors(lambda: f"interrupted; rerun the same command to resume ({Path(cfg.out) / MANIFEST})"):
        cfg, set_table, vary_table = parse_args(argv)
        if cfg.dry_run:
            dry_run(cfg, set_table, vary_table)
            return
        command = None if argv is None else ["ablate-sweep", *argv]
        manifest = run_sweep(cfg, set_table, vary_table, command=command, program=program)
    counts = manifest["counts"]
    print(f"{Path(cfg.out) / MANIFEST}: " + ", ".join(f"{n} {s}" for s, n in counts.items()))
    for run_id, rec in manifest["runs"].items():
        if rec["status"] == "failed":
            print(f"failed {run_id}: {rec['error']}", file=sys.stderr)
    if counts.get("failed"):
        raise SystemExit(1)
