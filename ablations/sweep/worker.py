"""The Ray task: one attempt of one job (a run, or a population of runs in one process) on whichever node Ray
picked.

The attempt runs :func:`~ablations.sweep.grid.attempt_command` as a child process (through ``child.py``, which
ties it to this worker) in a scratch folder of the node, watches the folder it writes (a run folder, or a
population folder and its members' run folders), and sends every new checkpoint (of every member, once all have
it, with the metrics and videos so far) to the driver's :class:`~ablations.sweep.store.RunStore`, and the whole
folder and its log at the end.
"""

from __future__ import annotations

import os
import platform
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ablations.run_config import SWEEP_WIDE
from ablations.run_folder import POPULATION_RECORD, RESUME_FILES, MetricsTail, RunFolder
from ablations.sweep.grid import attempt_command
from ablations.sweep.store import FINISHED, common_checkpoint
from ablations.sweep.transfer import archive_names, pack_run, unpack_run
from gradlab.checkpoint import checkpoint_path

__all__ = ["run_attempt", "RunProcessDied", "WORKER_POLL_S", "STOP_GRACE_S"]

#: Seconds between the worker's looks at its run folder.
WORKER_POLL_S = 0.5
#: Seconds a stopping attempt's ablate gets to finish its iteration after the first SIGINT, before the second
#: (which stops it at once, keeping the last finished iteration). ``opts["stop_grace_s"]`` overrides it.
STOP_GRACE_S = 30.0
_CHILD = Path(__file__).with_name("child.py")


class RunProcessDied(RuntimeError):
    """The ``ablate`` child was killed by a signal (the kernel's OOM killer, a node going away): Ray retries."""


def _tail(path: Path, n: int = 30) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


def _error_of(log: Path, returncode: int) -> str:
    """The line ablate's CLI prints for a failure ("error: ..."), else the last lines of the log."""
    lines = _tail(log, 200).splitlines()
    errors = [ln for ln in lines if ln.startswith("error: ")]
    if errors:
        return errors[-1][len("error: "):]
    exc = [ln for ln in lines if re.match(r"^[A-Za-z_][\w.]*(Error|Exception|Exit|Interrupt)\b", ln)]
    return (exc[-1] if exc else " | ".join(lines[-3:]) or "no output") + f" (exit code {returncode})"


def run_attempt(job: dict, store, opts: dict) -> dict:
    """Body of the Ray task: one attempt of one job (a run, or a population of runs; fresh or resumed); returns
    each run's result for the manifest: {"runs": {run_id: {status, error, ...}}, "attempt", "node", "host",
    "gpus"}.

    ``job``: a :class:`~ablations.sweep.packing.Job` as a dict; ``store``: the RunStore actor; ``opts``: sweep_id,
    cpus_per_run, gpus_per_run, keep_checkpoints, program (None: ablate) and stop_grace_s (None:
    :data:`STOP_GRACE_S`).

    Once the store's stop request is up (the driver's Ctrl-C), the attempt's ablate gets a SIGINT, and a second
    one after ``stop_grace_s`` (or at once on a request of level 2); the folder is then sent to the store as at the
    end of a run, and its unfinished runs come back "interrupted" with the iteration of their newest checkpoint
    (``checkpoint``), not raised for a retry. An attempt that begins under a stop request starts nothing.
    """
    import ray

    job_id, run_ids = job["job_id"], list(job["run_ids"])
    if ray.get(store.stopping.remote()):
        return {"runs": {r: {"status": "interrupted"} for r in run_ids}, "attempt": 0}
    attempt, pack = ray.get(store.begin.remote(job_id, list(job["members"])))
    base = Path(tempfile.gettempdir()) / "ablate-sweep" / opts["sweep_id"]
    for stale in base.glob(f"{job_id}.attempt*"):  # left by an earlier attempt on this node that was killed
        shutil.rmtree(stale, ignore_errors=True)
    scratch = base / f"{job_id}.attempt{attempt}"
    job_dir = scratch / job_id
    scratch.mkdir(parents=True)
    if pack is not None:
        unpack_run(pack, job_dir)
    # the run's torch threads are the CPUs Ray reserved for it (at least one)
    command = attempt_command(job["args"], job_id, resume=pack is not None, program=opts.get("program"),
                              threads=max(1, int(opts["cpus_per_run"])))
    folders = [RunFolder(job_dir / m) for m in job["members"]]
    # What the store already holds needs no second trip.
    shipped = common_checkpoint(folders)
    sent_videos: set[str] = set()
    env = dict(os.environ)
    if not opts["gpus_per_run"]:
        env["CUDA_VISIBLE_DEVICES"] = ""
    env[SWEEP_WIDE] = "1"  # its flags are the grid's, given for every run (ablate exempts them)
    log = scratch / "ablate.log"
    node = ray.get_runtime_context().get_node_id()
    # where the job trains: Ray's GPU ids for this worker (its CUDA_VISIBLE_DEVICES), [] on the CPU
    gpus = [str(g) for g in ray.get_gpu_ids()]
    try:
        with open(log, "wb") as log_f:
            proc = subprocess.Popen([sys.executable, str(_CHILD), str(os.getpid()), *command], cwd=scratch,
                                    stdout=log_f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        store.report.remote(job_id, attempt, {"status": "running", "node": node, "host": platform.node(),
                                              "gpus": gpus, "resumed": pack is not None})
        tails = [MetricsTail(f.metrics_path) for f in folders]
        reported: dict[str, object] = {}
        grace = opts.get("stop_grace_s")
        grace = STOP_GRACE_S if grace is None else float(grace)
        sigints, first_sigint = 0, 0.0
        while True:
            returncode = proc.poll()
            level = ray.get(store.stopping.remote()) if returncode is None else 0
            if level and sigints < 2:
                # ablate's first SIGINT checkpoints the iteration it is in once that ends; its second stops at
                # once and checkpoints the held copy of the last finished one
                if sigints == 0 or level >= 2 or time.monotonic() - first_sigint > grace:
                    proc.send_signal(signal.SIGINT)
                    sigints += 1
                    first_sigint = first_sigint or time.monotonic()
            rows = {}
            for run_id, tail in zip(run_ids, tails):
                last = tail.poll()
                if last is not None and last.get("iter") != reported.get(run_id):
                    reported[run_id] = last.get("iter")
                    rows[run_id] = {"iteration": last.get("iter"), "latest_return": last.get("return_mean"),
                                    "wall_s": last.get("wall_s")}  # what a time-limited run's progress shows
            if rows:
                store.report.remote(job_id, attempt, {"runs": rows})
            common = common_checkpoint(folders)
            if returncode is None and common is not None and common != shipped:
                # metrics.jsonl gets an iteration's line before its checkpoint (every member's, in a population):
                # read after seeing the checkpoint, it covers every iteration the checkpoint does.
                data, videos = _checkpoint_archive(job_dir, folders, common, sent_videos)
                if data is not None:
                    ray.get(store.save.remote(job_id, attempt, data))
                    shipped = common
                    sent_videos.update(videos)
                    store.report.remote(job_id, attempt, {"checkpoint": shipped})
            if returncode is not None:
                break
            time.sleep(WORKER_POLL_S)
        ray.get(store.save_log.remote(job_id, attempt, log.read_text(errors="replace")))
        if returncode < 0 and not sigints:
            try:
                name = signal.Signals(-returncode).name
            except ValueError:
                name = str(-returncode)
            raise RunProcessDied(f"ablate was killed by signal {name} on {platform.node()} "
                                 f"(attempt {attempt}); last output: {_tail(log, 3)}")
        summaries = [f.read_summary() or {} for f in folders]
        done = [returncode == 0 and s.get("status") in FINISHED for s in summaries]
        rest = [str(p.relative_to(job_dir)) for p in job_dir.rglob("*") if p.is_file()]
        # An unfinished job keeps its checkpoints whatever --keep-checkpoints says: a rerun resumes from them (a
        # population from an iteration every member has, a finished member's included).
        data = pack_run(job_dir, only=[n for n in rest if n not in sent_videos],
                        checkpoints=1 if opts["keep_checkpoints"] or not all(done) else 0)
        ray.get(store.save.remote(job_id, attempt, data))
        kept = common_checkpoint(folders)
        stopped = [s for s in summaries if s.get("status") == "interrupted"]
        if stopped and not sigints:
            # ablate stopped on SIGINT/SIGTERM (a node being drained, a job scheduler) after checkpointing: like a
            # killed run, it is retried from that checkpoint
            raise RunProcessDied(f"ablate stopped on a signal on {platform.node()} (attempt {attempt}): "
                                 f"{stopped[0].get('error')}")
        results = {}
        for run_id, folder, summary, ok, tail in zip(run_ids, folders, summaries, done, tails):
            last = tail.poll() or {}
            if sigints and not ok:  # stopped by the driver: the rerun resumes it from the checkpoint it kept
                results[run_id] = {"status": "interrupted", "error": None, "checkpoint": kept,
                                   "summary_status": summary.get("status"),
                                   "iteration": summary.get("iterations", last.get("iter")),
                                   "latest_return": summary.get("final_return", last.get("return_mean"))}
                continue
            results[run_id] = {"status": "done" if ok else "failed",
                               "error": None if ok else _run_error(log, returncode, folder, summary),
                               "summary_status": summary.get("status"),
                               "iteration": summary.get("iterations", last.get("iter")),
                               "latest_return": summary.get("final_return", last.get("return_mean"))}
        return {"runs": results, "attempt": attempt, "node": node, "host": platform.node(), "gpus": gpus}
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _checkpoint_archive(job_dir: Path, folders: list[RunFolder], iteration: int,
                        sent_videos: set[str]) -> tuple[bytes | None, list[str]]:
    """(archive of what a resume from ``iteration`` needs: every run folder's records, metrics and checkpoint of
    that iteration, the population's record and the videos not sent yet; the new videos). The archive is None
    when a checkpoint was rotated away before it was read (the next look sends a newer one)."""
    videos = [n for f in folders for n in (str(v.relative_to(job_dir)) for v in f.videos()) if n not in sent_videos]
    checkpoints = [str(checkpoint_path(f.checkpoint_dir, iteration).relative_to(job_dir)) for f in folders]
    records = [str((f.path / name).relative_to(job_dir)) for f in folders for name in RESUME_FILES]
    population = [POPULATION_RECORD] if (job_dir / POPULATION_RECORD).is_file() else []
    data = pack_run(job_dir, only=[*population, *records, *videos, *checkpoints])
    names = set(archive_names(data))
    return (data if all(Path(c).as_posix() in names for c in checkpoints) else None), videos


def _run_error(log: Path, returncode: int, folder: RunFolder, summary: dict) -> str:
    """Why a run did not finish: the process's error, or (a population member that stopped alone while the
    others went on) its summary's status and error."""
    if returncode != 0 or not summary:
        return _error_of(log, returncode) if returncode != 0 else f"no summary.json in {folder.path.name}"
    return f"{summary.get('status')}: {summary.get('error')}"
