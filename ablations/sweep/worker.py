"""The Ray task: one attempt of one run on whichever node Ray picked.

The attempt runs :func:`~ablations.sweep.grid.attempt_command` as a child process (through ``child.py``, which
ties it to this worker) in a scratch folder of the node, watches the run folder it writes, and sends every new
checkpoint (with the metrics and videos so far) to the driver's :class:`~ablations.sweep.store.RunStore`, and
the whole folder and its log at the end.
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

from ablations.run_folder import RESUME_FILES, MetricsTail, RunFolder
from ablations.sweep.grid import attempt_command
from ablations.sweep.store import FINISHED
from ablations.sweep.transfer import archive_names, pack_run, unpack_run

__all__ = ["run_attempt", "RunProcessDied", "WORKER_POLL_S"]

#: Seconds between the worker's looks at its run folder.
WORKER_POLL_S = 0.5
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


def run_attempt(spec: dict, store, opts: dict) -> dict:
    """Body of the Ray task: one attempt of one run (fresh or resumed); returns its result for the manifest.

    ``spec``: a :class:`~ablations.sweep.grid.RunSpec` as a dict; ``store``: the RunStore actor; ``opts``:
    sweep_id, cpus_per_run, gpus_per_run, keep_checkpoints and program (None: ablate).
    """
    import ray

    run_id = spec["run_id"]
    attempt, pack = ray.get(store.begin.remote(run_id))
    base = Path(tempfile.gettempdir()) / "ablate-sweep" / opts["sweep_id"]
    for stale in base.glob(f"{run_id}.attempt*"):  # left by an earlier attempt on this node that was killed
        shutil.rmtree(stale, ignore_errors=True)
    scratch = base / f"{run_id}.attempt{attempt}"
    run_dir = scratch / run_id
    scratch.mkdir(parents=True)
    if pack is not None:
        unpack_run(pack, run_dir)
    # the run's torch threads are the CPUs Ray reserved for it (at least one)
    command = attempt_command(spec["args"], run_id, resume=pack is not None, program=opts.get("program"),
                              threads=max(1, int(opts["cpus_per_run"])))
    folder = RunFolder(run_dir)
    # What the store already holds needs no second trip.
    shipped = folder.newest_checkpoint()
    sent_videos: set[str] = set()
    env = dict(os.environ)
    if not opts["gpus_per_run"]:
        env["CUDA_VISIBLE_DEVICES"] = ""
    log = scratch / "ablate.log"
    node = ray.get_runtime_context().get_node_id()
    try:
        with open(log, "wb") as log_f:
            proc = subprocess.Popen([sys.executable, str(_CHILD), str(os.getpid()), *command], cwd=scratch,
                                    stdout=log_f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        store.report.remote(run_id, attempt, {"status": "running", "node": node, "host": platform.node(),
                                              "resumed": pack is not None})
        metrics = MetricsTail(folder.metrics_path)
        reported = None
        while True:
            returncode = proc.poll()
            last = metrics.poll()
            if last is not None and last.get("iter") != reported:
                reported = last.get("iter")
                store.report.remote(run_id, attempt, {"iteration": reported,
                                                      "latest_return": last.get("return_mean")})
            ckpt = folder.newest_checkpoint()
            if returncode is None and ckpt is not None and ckpt != shipped:
                # metrics.jsonl gets an iteration's line before its checkpoint: read after seeing the checkpoint,
                # it covers every iteration the checkpoint does.
                videos = [n for n in (str(v.relative_to(run_dir)) for v in folder.videos()) if n not in sent_videos]
                data = pack_run(run_dir, only=[*RESUME_FILES, *videos, str(ckpt.relative_to(run_dir))])
                if f"checkpoints/{ckpt.name}" in archive_names(data):
                    ray.get(store.save.remote(run_id, attempt, data))
                    shipped = ckpt
                    sent_videos.update(videos)
            if returncode is not None:
                break
            time.sleep(WORKER_POLL_S)
        ray.get(store.save_log.remote(run_id, attempt, log.read_text(errors="replace")))
        if returncode < 0:
            try:
                name = signal.Signals(-returncode).name
            except ValueError:
                name = str(-returncode)
            raise RunProcessDied(f"ablate was killed by signal {name} on {platform.node()} "
                                 f"(attempt {attempt}); last output: {_tail(log, 3)}")
        summary = folder.read_summary() or {}
        done = returncode == 0 and summary.get("status") in FINISHED
        rest = [str(p.relative_to(run_dir)) for p in run_dir.rglob("*") if p.is_file()]
        # An unfinished run keeps its checkpoint whatever --keep-checkpoints says: a rerun resumes from it.
        data = pack_run(run_dir, only=[n for n in rest if n not in sent_videos],
                        checkpoints=1 if opts["keep_checkpoints"] or not done else 0)
        ray.get(store.save.remote(run_id, attempt, data))
        if summary.get("status") == "interrupted":
            # ablate stopped on SIGINT/SIGTERM (a node being drained, a job scheduler) after checkpointing: like a
            # killed run, it is retried from that checkpoint
            raise RunProcessDied(f"ablate stopped on a signal on {platform.node()} (attempt {attempt}): "
                                 f"{summary.get('error')}")
        last = metrics.poll() or {}
        return {"status": "done" if done else "failed",
                "error": None if done else _error_of(log, returncode),
                "summary_status": summary.get("status"),
                "iteration": summary.get("iterations", last.get("iter")),
                "latest_return": summary.get("final_return", last.get("return_mean")),
                "attempt": attempt, "node": node, "host": platform.node()}
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
