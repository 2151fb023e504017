"""Stand-ins for ``ablations.memory.measure.measure_point`` (the sweep's test seam), run inside the worker processes.

Behaviour per point comes from the environment, so one sweep can mix successes and failures:
    FAKE_BEHAVIOUR  JSON {"<mode>_m<meshes>_v<verts>": behaviour}; default "ok". Behaviours:
                    ok, oom (torch.OutOfMemoryError), cpu_oom (the CPU allocator's RuntimeError), error
                    (ValueError), kill (SIGKILL to itself, as the kernel's OOM killer does), exit (exit code 3
                    after a message), exit_oom_log (exit 1 after CUDA's out-of-memory message), hang (sleep).
    FAKE_LOG        file to which every call appends one JSON line {point, pid, csv_rows}
    FAKE_OUT        the sweep's folder: every call first parses memory.csv as it is at that moment
"""

from __future__ import annotations

import csv
import json
import os
import signal
import sys
import time


def scene(point: dict) -> tuple[int, int]:
    """A made-up scene size: 100 robot faces plus 2 faces per extra vertex."""
    extra = point["meshes"] * point["verts_per_mesh"]
    return 100 + 2 * extra, 60 + extra


def _csv_rows(out: str) -> int | None:
    """Rows of memory.csv right now; raises if it is torn (a row with missing cells or an unfinished line)."""
    path = os.path.join(out, "memory.csv")
    if not os.path.exists(path):
        return None
    text = open(path).read()
    assert text.endswith("\n"), "memory.csv ends mid-line"
    rows = list(csv.reader(text.splitlines()))
    width = len(rows[0])
    assert all(len(r) == width for r in rows), "memory.csv has a row with missing cells"
    return len(rows) - 1


def fake(point: dict, progress) -> dict:
    pid = f"{point['mode']}_m{point['meshes']}_v{point['verts_per_mesh']}"
    behaviour = json.loads(os.environ.get("FAKE_BEHAVIOUR", "{}")).get(pid, "ok")
    log = os.environ.get("FAKE_LOG")
    out = os.environ.get("FAKE_OUT")
    rows = _csv_rows(out) if out else None
    if log:
        with open(log, "a") as f:
            f.write(json.dumps({"point": pid, "pid": os.getpid(), "csv_rows": rows}) + "\n")
    faces, verts = scene(point)
    progress({"scene_faces": faces, "scene_verts": verts})
    if behaviour == "oom":
        import torch

        raise torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 20.00 GiB")
    if behaviour == "cpu_oom":
        raise RuntimeError("[enforce fail at alloc_cpu.cpp:117] DefaultCPUAllocator: can't allocate memory")
    if behaviour == "error":
        raise ValueError("boom: the renderer disliked this point")
    if behaviour == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    if behaviour == "exit":
        print("segfault-ish failure in a native library", file=sys.stderr, flush=True)
        os._exit(3)
    if behaviour == "exit_oom_log":
        print("RuntimeError: CUDA error: out of memory", file=sys.stderr, flush=True)
        os._exit(1)
    if behaviour == "hang":
        time.sleep(600)
    full = point["mode"] == "full"
    return {
        "scene_faces": faces,
        "scene_verts": verts,
        "fwd_ms": 1.0 + faces * 0.01,
        "bwd_ms": (3.0 if full else 1.0) * (1.0 + faces * 0.01),
        "critic_ms": 0.5,
        "iter_ms": 10.0,
        "peak_alloc_mb": None,
        "peak_reserved_mb": None,
        "saved_mb": (faces * 0.1 if full else 1.0) * point["horizon"],
        "max_rss_mb": 300.0,
    }
