"""Mesh-complexity sweep: what full (through-pixels) and decoupled (D.Va) gradients cost as the scene grows.

The scene grows by extra meshes attached to robot links (``SHACConfig.extra_meshes`` x ``extra_mesh_verts``),
so their vertices depend on ``qpos`` and, in full mode, every render of a 32-step window stays in the graph.
Each point of (mode x meshes x vertices per mesh) runs in ONE FRESH PROCESS::

    python -m ablations.memory --point '<json>' --result PATH

so its peak memory is its own (the CUDA caching allocator never shrinks, and fragmentation from one point must
not inflate the next) and an out-of-memory crash or a kill by the kernel takes down that point only.

Modules, by role:
    config    :class:`MemoryConfig` (the ``ablate-memory`` flags) and the sweep's points
    measure   :func:`measure_point`: the real trainer on one point (runs inside the worker process)
    worker    the worker process: runs a measurement, classifies its exceptions, hands back the result
    sweep     :func:`sweep` and :func:`run_point`: one worker per point, timeouts, OOM classification, resume
    table     memory.csv / memory.json rows (``COLUMNS``), read and written atomically
    plots     :func:`plot_sweep`: the PNGs (:func:`sweep_figures`: their matplotlib Figures)

Outputs in ``--out``:
    memory.csv          one row per point (``COLUMNS``), rewritten atomically (temp + rename) after every point
    memory.json         the sweep's settings, the commands that ran it, environment, dates and the same rows
    memory_peak.png     peak memory (CUDA: allocated; always: saved for backward; CPU: also peak RSS) vs faces
    memory_bwd.png      backward time vs scene faces
    logs/<point>.log    stdout + stderr of each point's process

A restarted sweep (same ``--out``) skips the points that already have a row; ``--retry-failed`` re-runs rows
whose status is ``error`` or ``timeout`` (``ok`` and ``oom`` are results, not failures).

Test seam (not a user option): ``sweep(cfg, measure="module:function")`` runs that function in the worker
process instead of :func:`measure_point`; it is called as ``fn(point, progress)`` and returns a dict of
``COLUMNS`` values. Exceptions it raises are classified exactly as the real trainer's are.

Every module here imports only the standard library at import time (torch, matplotlib and tqdm where they are
used), so a worker process starts with nothing but what its measurement needs.
"""

from ablations.memory.config import MemoryConfig, point_id
from ablations.memory.measure import measure_point, scene_size
from ablations.memory.plots import plot_sweep, sweep_figures
from ablations.memory.sweep import run_point, sweep
from ablations.memory.table import COLUMNS, csv_text, read_csv
from ablations.memory.worker import DEFAULT_MEASURE

__all__ = ["MemoryConfig", "COLUMNS", "sweep", "measure_point", "run_point", "read_csv", "csv_text", "plot_sweep",
           "sweep_figures", "scene_size", "point_id", "DEFAULT_MEASURE"]
