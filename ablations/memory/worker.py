"""The per-point worker process: run a measurement, classify its failure, hand the result back to the sweep.

Started by :func:`ablations.memory.sweep.run_point` as ``python -m ablations.memory --point JSON --result PATH``.
The result file is JSON lines: every line updates the ones before it. The worker appends one line as soon as
the measurement reports progress (the scene size) and one with the outcome, so a worker the kernel kills
mid-point still leaves what it knew; a line torn by the kill is ignored by :func:`read_result`. Appending needs
no temp-and-rename, so the worker imports no torch-dependent helper and starts in a fraction of a second.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path

__all__ = ["DEFAULT_MEASURE", "OOM_PATTERNS", "is_oom", "read_result", "main"]

#: The per-point measurement run inside the worker process (the real trainer).
DEFAULT_MEASURE = "ablations.memory.measure:measure_point"

#: Lower-case fragments of the messages with which PyTorch, CUDA and the C allocator report running out of memory.
OOM_PATTERNS = ("out of memory", "outofmemoryerror", "memoryerror", "can't allocate memory",
                "cannot allocate memory", "cuda_error_out_of_memory")


def is_oom(exc: BaseException) -> bool:
    """Whether an exception means the point ran out of memory (a result of the sweep, not a failure)."""
    if isinstance(exc, MemoryError):
        return True
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(exc, getattr(torch, "OutOfMemoryError", ())):
        return True
    # The CPU allocator raises a plain RuntimeError ("DefaultCPUAllocator: can't allocate memory").
    return isinstance(exc, RuntimeError) and any(p in str(exc).lower() for p in OOM_PATTERNS)


def _append_result(path: Path, obj: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        f.write(json.dumps(obj, default=str) + "\n")
        f.flush()
        os.fsync(f.fileno())


def read_result(path: str | os.PathLike) -> dict:
    """The worker's result so far: its JSON lines merged in order ({} for a missing file; a torn line ends it)."""
    result: dict = {}
    try:
        text = Path(path).read_text()
    except OSError:
        return result
    for line in text.splitlines():
        try:
            update = json.loads(line)
        except json.JSONDecodeError:
            break
        if isinstance(update, dict):
            result.update(update)
    return result


def _resolve(spec: str) -> Callable:
    module, _, name = spec.partition(":")
    if not module or not name:
        raise ValueError(f"measure function must be 'module:function', got {spec!r}")
    return getattr(importlib.import_module(module), name)


def _die_with_parent(period_s: float = 1.0) -> None:
    """End this worker (and its process group) when the sweep that started it is gone.

    The worker runs in its own session, so a sweep killed with SIGKILL cannot take it down; without this it
    would go on holding the GPU. Polling the parent id is portable, where prctl(PR_SET_PDEATHSIG) is not.
    """
    parent = os.getppid()

    def watch() -> None:
        while True:
            time.sleep(period_s)
            if os.getppid() != parent:
                os.killpg(os.getpgrp(), signal.SIGKILL)

    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()


def main(argv: list[str] | None = None) -> int:
    """Measure one point, classify failures, write the result file; always returns 0 once the file is written.

    ``argv`` given (a test calling this in-process): the parent watch is not started.
    """
    parser = argparse.ArgumentParser(prog="python -m ablations.memory",
                                     description="One point of the ablate-memory sweep (internal).")
    parser.add_argument("--point", required=True, help="the point as JSON")
    parser.add_argument("--result", required=True, type=Path, help="where to write the result (JSON lines)")
    parser.add_argument("--measure", default=DEFAULT_MEASURE, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    point = json.loads(args.point)
    known: dict = {"status": "running"}
    if argv is None:
        _die_with_parent()

    def progress(update: dict) -> None:
        # Written at once, so a process the kernel kills later still leaves its scene size behind.
        update = {k: v for k, v in update.items() if v is not None}
        known.update(update)
        _append_result(args.result, {"status": "running", **update})

    try:
        result = {**known, **_resolve(args.measure)(point, progress)}
        result.setdefault("status", "ok")
        if result["status"] == "running":
            result["status"] = "ok"
    except Exception as e:
        traceback.print_exc()
        first = (str(e).strip().splitlines() or [""])[0]
        status = "oom" if is_oom(e) else "error"
        result = {**known, "status": status, "error": f"{type(e).__name__}: {first}"[:500]}
    _append_result(args.result, result)
    return 0
