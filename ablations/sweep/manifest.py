"""sweep.json: the grid, the command that made it, per run its status, error, folder, job and progress, and the
jobs (``jobs``: each Ray task's runs, their folders in its folder, and the ablate arguments it starts with)."""

from __future__ import annotations

import json
import os
import sys
import time
import uuid
from pathlib import Path

from ablations.sweep.config import SweepConfig
from ablations.sweep.grid import RunSpec
from ablations.sweep.packing import Job, assign_jobs
from ablations.sweep.store import resumable, run_path, run_state
from gradlab.files import atomic_write_json

__all__ = ["MANIFEST", "STATUSES", "load_manifest", "prepare_manifest", "plan_jobs", "write_manifest",
           "status_counts"]

MANIFEST = "sweep.json"
#: A run's status; ``interrupted``: stopped by a Ctrl-C of the driver, its ``checkpoint`` kept (a rerun resumes it).
STATUSES = ("queued", "running", "done", "failed", "interrupted")


def load_manifest(out: str | os.PathLike) -> dict | None:
    """The sweep folder's sweep.json, or None when there is none yet."""
    path = Path(out) / MANIFEST
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not valid JSON ({e}); written atomically, it was edited by hand") from None


def _new_record(spec: RunSpec) -> dict:
    return {"task": spec.task, "mode": spec.mode, "arm": spec.arm, "seed": spec.seed, "flags": spec.flags,
            "args": list(spec.args), "iters": spec.iters, "folder": run_path(".", spec.run_id).as_posix(),
            "status": "queued", "error": None, "iteration": None, "checkpoint": None, "latest_return": None,
            "attempts": 0,
            "resumed": False, "node": None, "host": None, "gpus": None, "updated": None}


def plan_jobs(cfg: SweepConfig, specs: list[RunSpec], manifest: dict | None) -> list[Job]:
    """The jobs of the grid in the sweep folder as it is (:func:`~ablations.sweep.packing.assign_jobs`)."""
    return assign_jobs(specs, cfg.pack_size(), manifest or {}, cfg.out)


def prepare_manifest(cfg: SweepConfig, specs: list[RunSpec], set_table: dict, vary_table: dict,
                     command: list[str] | None, arms: dict | None = None) -> tuple[dict, list[Job]]:
    """The manifest to start from (existing runs checked against the grid) and the jobs to launch.

    ``command``: the command line to record (None: ``ablate-sweep`` and this process's arguments).
    """
    out = Path(cfg.out)
    manifest = load_manifest(out) or {"version": 1, "id": uuid.uuid4().hex[:12],
                                      "created": time.strftime("%Y-%m-%dT%H:%M:%S"), "runs": {}}
    runs = manifest["runs"]
    for spec in specs:
        old = runs.get(spec.run_id)
        if old is not None and old.get("args") != list(spec.args):
            raise ValueError(f"{out / MANIFEST}: run {spec.run_id} was made with the flags {' '.join(old['args'])}, "
                             f"this sweep gives it {' '.join(spec.args)}; use another --out for a different sweep")
    jobs = plan_jobs(cfg, specs, manifest)
    for spec in specs:
        runs.setdefault(spec.run_id, _new_record(spec))
    old = manifest.get("jobs") or {}
    table = manifest["jobs"] = {job.job_id: job.record() for job in jobs}
    todo = []
    for job in jobs:
        open_runs = []
        for i, run_id in enumerate(job.run_ids):
            rec = runs[run_id]
            rec.update(job=job.job_id, folder=job.folder(i))
            if run_state(out / job.folder(i), job.iters) == "done":
                rec.update(status="done", error=None)
            else:
                open_runs.append(rec)
        if not open_runs or (not cfg.rerun_failed and all(r["status"] == "failed" for r in open_runs)):
            continue
        resumed = resumable(run_path(out, job.job_id), job.members)  # some run is open, so not 'done'
        for rec in open_runs:
            rec.update(status="queued", resumed=resumed)
        todo.append(job)
    for job_id, rec in old.items():  # jobs of runs that this grid leaves out stay on record
        if job_id not in table and any(runs.get(r, {}).get("job") == job_id for r in rec.get("runs", [])):
            table[job_id] = rec
    manifest["sweep"] = {"tasks": list(cfg.tasks), "modes": list(cfg.modes), "seeds": list(cfg.seeds),
                         "set": {k: v for k, v in set_table.items()}, "vary": {k: v for k, v in vary_table.items()},
                         "cpus_per_run": cfg.cpus_per_run, "gpus_per_run": cfg.gpus_per_run,
                         "max_retries": cfg.max_retries, "pack": str(cfg.pack), "pack_size": cfg.pack_size()}
    if arms is not None:
        manifest["sweep"]["arms"] = arms
    manifest["command"] = list(command) if command is not None else ["ablate-sweep", *sys.argv[1:]]
    return manifest, todo


def status_counts(manifest: dict) -> dict[str, int]:
    """Runs per status, every status listed."""
    counts = {s: 0 for s in STATUSES}
    for rec in manifest["runs"].values():
        counts[rec["status"]] = counts.get(rec["status"], 0) + 1
    return counts


def write_manifest(out: Path, manifest: dict) -> None:
    """Write sweep.json atomically, with the counts and the time of this write."""
    manifest["counts"] = status_counts(manifest)
    manifest["updated"] = time.strftime("%Y-%m-%dT%H:%M:%S")
    atomic_write_json(out / MANIFEST, manifest)
