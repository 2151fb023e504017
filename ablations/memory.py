"""Mesh-complexity sweep: what full (through-pixels) and decoupled (D.Va) gradients cost as the scene grows.

The scene grows by extra meshes attached to robot links (``SHACConfig.extra_meshes`` x ``extra_mesh_verts``),
so their vertices depend on ``qpos`` and, in full mode, every render of a 32-step window stays in the graph.
Each point of (mode x meshes x vertices per mesh) runs in ONE FRESH PROCESS::

    python -m ablations.memory --point '<json>' --result PATH

so its peak memory is its own (the CUDA caching allocator never shrinks, and fragmentation from one point must
not inflate the next) and an out-of-memory crash or a kill by the kernel takes down that point only.

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
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime as _dt
import importlib
import io
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

__all__ = ["MemoryConfig", "COLUMNS", "sweep", "measure_point", "run_point", "read_csv", "plot_sweep",
           "scene_size", "DEFAULT_MEASURE"]

#: The per-point measurement run inside the worker process (the real trainer).
DEFAULT_MEASURE = "ablations.memory:measure_point"

#: Columns of memory.csv, in order. Units: ms (medians over the measured iterations), MB = 2**20 bytes.
COLUMNS = (
    "task", "mode", "meshes", "verts_per_mesh", "status",
    "scene_faces", "scene_verts",
    "fwd_ms", "bwd_ms", "critic_ms", "iter_ms",
    "peak_alloc_mb", "peak_reserved_mb", "saved_mb", "max_rss_mb",
    "point_s", "num_envs", "horizon", "image_size", "warmup_iters", "iters", "device", "seed", "gpu",
    "started", "error", "log",
)
_INT_COLUMNS = {"meshes", "verts_per_mesh", "scene_faces", "scene_verts", "num_envs", "horizon", "image_size",
                "warmup_iters", "iters", "seed"}
_FLOAT_COLUMNS = {"fwd_ms", "bwd_ms", "critic_ms", "iter_ms", "peak_alloc_mb", "peak_reserved_mb", "saved_mb",
                  "max_rss_mb", "point_s"}
#: Settings every row of one memory.csv must share (otherwise its rows are not comparable).
FIXED = ("task", "num_envs", "horizon", "image_size", "warmup_iters", "iters", "device", "seed")
#: Statuses that are results: a restarted sweep never re-runs them.
FINAL_STATUSES = ("ok", "oom")
SWEPT_MODES = ("full", "decoupled")
_TASKS = ("cartpole", "hopper", "ant", "humanoid")


@dataclass
class MemoryConfig:
    """Sweep scene complexity (extra meshes x vertices per mesh) x gradient mode and measure time and memory.

    Each point runs the real SHAC trainer in a fresh process: warm-up iterations, then measured iterations whose
    medians (times) and maxima (peak memory) are reported. Out-of-memory points are rows with status "oom".
    """

    task: str = "cartpole"
    """Task: cartpole, hopper, ant or humanoid."""
    modes: tuple[Literal["full", "decoupled"], ...] = ("decoupled", "full")
    """Gradient modes to sweep (full: through the rendered images; decoupled: D.Va)."""
    meshes: tuple[int, ...] = (0, 4, 16, 64)
    """Numbers of extra meshes attached to robot links (0: the robot alone, measured once per mode)."""
    verts: tuple[int, ...] = (64, 256, 1024)
    """Vertices per extra mesh (each >= 6). The renderer builds the latitude-longitude sphere closest to it
    (V = 2r(r-1)+2: 6, 14, 26, 42, ...); the CSV's scene_verts and scene_faces are the exact counts."""
    num_envs: int = 64
    """Parallel environments per point."""
    horizon: int = 32
    """SHAC window length in steps (renders kept alive for backward in full mode)."""
    image_size: int = 84
    """Rendered image height and width [pixels]."""
    warmup_iters: int = 2
    """Training iterations run first and not measured (allocator, kernels, caches warm up)."""
    iters: int = 5
    """Measured training iterations per point (times are their medians, peak memory their maximum)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """auto (CUDA when present, else CPU), cpu or cuda."""
    seed: int = 0
    """Seed of every point (networks, resets, noise)."""
    out: Path = Path("runs/memory")
    """Output folder (memory.csv, memory.json, PNGs, logs/). An existing sweep there is continued."""
    timeout_s: float = 1800.0
    """Wall-clock limit per point [s]; a point past it is killed and recorded with status "timeout"."""
    retry_failed: bool = False
    """Re-run points whose existing row has status error or timeout (ok and oom rows are always kept)."""
    progress: bool = True
    """Show a progress bar over the points."""

    def validate(self) -> None:
        """Clear errors for bad values, before any work."""
        if self.task not in _TASKS:
            raise ValueError(f"unknown task {self.task!r}; valid tasks: {', '.join(_TASKS)}")
        if not self.modes:
            raise ValueError("--modes is empty: give full and/or decoupled")
        for m in self.modes:
            if m not in SWEPT_MODES:
                raise ValueError(f"mode {m!r} cannot be swept (no rendering cost); use full and/or decoupled")
        if not self.meshes or any(not isinstance(m, int) or m < 0 for m in self.meshes):
            raise ValueError(f"--meshes must be non-negative integers, got {self.meshes!r}")
        # diffrender's sweep spheres (latlong_sphere_mesh) need 6 vertices at least: refuse here, not per point.
        if not self.verts or any(not isinstance(v, int) or v < 6 for v in self.verts):
            raise ValueError(f"--verts must be integers >= 6 (the smallest sweep sphere), got {self.verts!r}")
        for name in ("num_envs", "horizon", "iters"):
            v = getattr(self, name)
            if not isinstance(v, int) or v <= 0:
                raise ValueError(f"--{name.replace('_', '-')} must be a positive integer, got {v!r}")
        if not isinstance(self.warmup_iters, int) or self.warmup_iters < 0:
            raise ValueError(f"--warmup-iters must be a non-negative integer, got {self.warmup_iters!r}")
        if not isinstance(self.image_size, int) or self.image_size < 16:
            raise ValueError(f"--image-size must be an integer >= 16 pixels, got {self.image_size!r}")
        if not self.timeout_s > 0:
            raise ValueError(f"--timeout-s must be positive, got {self.timeout_s}")

    def points(self, device: str) -> list[dict]:
        """The sweep's points, in run order (cheap first, so a sweep that dies late has the small ones).

        ``meshes == 0`` has no extra mesh, so it is one point per mode with ``verts_per_mesh = 0``.
        """
        sizes = sorted({(0, 0) if m == 0 else (m, v) for m in self.meshes for v in self.verts},
                       key=lambda mv: (mv[0] * mv[1], mv))
        fixed = dict(task=self.task, num_envs=self.num_envs, horizon=self.horizon, image_size=self.image_size,
                     warmup_iters=self.warmup_iters, iters=self.iters, device=device, seed=self.seed)
        return [dict(fixed, mode=mode, meshes=m, verts_per_mesh=v) for m, v in sizes
                for mode in sorted(set(self.modes), key=SWEPT_MODES.index)]


def _key(row: dict) -> tuple:
    return (row["mode"], int(row["meshes"]), int(row["verts_per_mesh"]))


def point_id(point: dict) -> str:
    """File-name-safe name of a point, e.g. ``ant_full_m16_v256``."""
    return f"{point['task']}_{point['mode']}_m{point['meshes']}_v{point['verts_per_mesh']}"


def _now() -> str:
    return _dt.datetime.now().astimezone().isoformat(timespec="seconds")


# ---------------------------------------------------------------------------------------------- the measurement
def scene_size(trainer) -> tuple[int | None, int | None]:
    """(faces, vertices) of the rendered scene of a trainer (robot + extra meshes), or None when unknown.

    Read from the mesh the renderer rasterizes: a ``diffrender.RobotModel`` (``num_faces``, ``num_vertices``)
    that is the trainer's renderer or one of its attributes; else a ``faces`` (F, 3) / ``colors`` (V, 3) pair.
    The analytic floor has no faces and is not counted.
    """
    renderer = getattr(trainer, "renderer", None)
    if renderer is None:
        return None, None
    candidates = [renderer, *(v for v in getattr(renderer, "__dict__", {}).values() if not isinstance(v, type))]
    for obj in candidates:
        nf, nv = getattr(obj, "num_faces", None), getattr(obj, "num_vertices", None)
        if isinstance(nf, int) and isinstance(nv, int):
            return nf, nv
    for obj in candidates:
        faces, colors = getattr(obj, "faces", None), getattr(obj, "colors", None)
        if hasattr(faces, "shape") and hasattr(colors, "shape"):
            return int(faces.shape[-2]), int(colors.shape[-2])
    return None, None


def measure_point(point: dict, progress: Callable[[dict], None]) -> dict:
    """Run the real trainer for one point; returns the measured ``COLUMNS`` values.

    ``progress(dict)`` records what is known so far (the scene size, before training), so a point that is
    later killed still has its x coordinate. Times are medians over the measured iterations [ms]; peak memory
    is the maximum over them [MB]; ``saved_mb`` is what autograd saved for backward in one window [MB].
    """
    import resource

    import torch

    from ablations.runs import environment_info
    from gradlab.config import SHACConfig
    from gradlab.shac import SHAC
    from gradlab.timing import median

    device = torch.device(point["device"])
    warmup, iters = int(point["warmup_iters"]), int(point["iters"])
    meshes, verts = int(point["meshes"]), int(point["verts_per_mesh"])
    cfg = SHACConfig(
        task=point["task"], mode=point["mode"], iters=warmup + iters, num_envs=int(point["num_envs"]),
        horizon=int(point["horizon"]), seed=int(point["seed"]), image_size=int(point["image_size"]),
        extra_meshes=meshes, extra_mesh_verts=verts if meshes else SHACConfig.extra_mesh_verts,
        # No probe iterations: they differentiate twice and would measure neither mode. The cost of a random
        # policy is what is measured here, so the learning-stability abort is off (the NaN guard stays on).
        cosine_every=0, abort_grad_norm=math.inf)
    trainer = SHAC(cfg, device=device)
    faces, nverts = scene_size(trainer)
    env = environment_info(device)
    progress({"scene_faces": faces, "scene_verts": nverts, "gpu": env.get("gpu")})

    measured = []
    for i in range(warmup + iters):
        m = trainer.train_iteration()
        if i >= warmup:
            measured.append(m)

    def med(key: str) -> float | None:
        vals = [m[key] for m in measured if m.get(key) is not None]
        return median(vals) if vals else None

    def peak(key: str) -> float | None:
        vals = [m[key] for m in measured if m.get(key) is not None]
        return max(vals) if vals else None

    return {
        "status": "ok",
        "scene_faces": faces,
        "scene_verts": nverts,
        "fwd_ms": med("fwd_ms"),
        "bwd_ms": med("bwd_ms"),
        "critic_ms": med("critic_ms"),
        "iter_ms": med("iter_ms"),
        "peak_alloc_mb": peak("peak_alloc_mb"),
        "peak_reserved_mb": peak("peak_reserved_mb"),
        "saved_mb": med("saved_mb"),
        # Linux reports ru_maxrss in KiB: the process's high-water resident memory (CPU peak, incl. libraries).
        "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "gpu": env.get("gpu"),
        "environment": env,
    }


# ---------------------------------------------------------------------------------------------- the worker
_OOM_PATTERNS = ("out of memory", "outofmemoryerror", "memoryerror", "can't allocate memory",
                 "cannot allocate memory", "cuda_error_out_of_memory")


def _is_oom(exc: BaseException) -> bool:
    if isinstance(exc, MemoryError):
        return True
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(exc, getattr(torch, "OutOfMemoryError", ())):
        return True
    # The CPU allocator raises a plain RuntimeError ("DefaultCPUAllocator: can't allocate memory").
    return isinstance(exc, RuntimeError) and any(p in str(exc).lower() for p in _OOM_PATTERNS)


def _write_handoff(path: Path, obj: dict) -> None:
    """The worker's result file (temp + fsync + rename, as gradlab.checkpoint does). Written without importing
    torch: a point's process imports only what its measurement needs, and ``--help`` stays instant."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(obj, f, default=str)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


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
    import threading

    parent = os.getppid()

    def watch() -> None:
        while True:
            time.sleep(period_s)
            if os.getppid() != parent:
                os.killpg(os.getpgrp(), signal.SIGKILL)

    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()


def _worker_main(argv: list[str] | None = None) -> int:
    """The per-point process: measure, classify failures, write the result file. Internal; see the module doc."""
    parser = argparse.ArgumentParser(prog="python -m ablations.memory",
                                     description="One point of the ablate-memory sweep (internal).")
    parser.add_argument("--point", required=True, help="the point as JSON")
    parser.add_argument("--result", required=True, type=Path, help="where to write the result JSON")
    parser.add_argument("--measure", default=DEFAULT_MEASURE, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    point = json.loads(args.point)
    known: dict = {"status": "running"}
    if argv is None:  # a real worker process (not a test calling this function in-process)
        _die_with_parent()

    def progress(update: dict) -> None:
        # Written at once, so a process the kernel kills later still leaves its scene size behind.
        known.update({k: v for k, v in update.items() if v is not None})
        _write_handoff(args.result, known)

    try:
        result = {**known, **_resolve(args.measure)(point, progress)}
        result.setdefault("status", "ok")
        if result["status"] == "running":
            result["status"] = "ok"
    except Exception as e:
        traceback.print_exc()
        first = (str(e).strip().splitlines() or [""])[0]
        status = "oom" if _is_oom(e) else "error"
        result = {**known, "status": status, "error": f"{type(e).__name__}: {first}"[:500]}
    _write_handoff(args.result, result)
    return 0


# ---------------------------------------------------------------------------------------------- one point
def _tail(path: Path, n: int = 40) -> list[str]:
    try:
        return [ln for ln in path.read_text(errors="replace").splitlines() if ln.strip()][-n:]
    except OSError:
        return []


def run_point(point: dict, *, out: Path, timeout_s: float, measure: str = DEFAULT_MEASURE) -> dict:
    """Run one point in a fresh process and return its CSV row (never raises for a failed point).

    Classification: ``ok``; ``oom`` for torch.OutOfMemoryError / MemoryError / an allocator failure in the
    worker, a worker killed by SIGKILL (exit -9 or 137: the kernel's out-of-memory killer), or a non-zero exit
    whose log reports running out of memory; ``timeout`` past ``timeout_s``; ``error`` (with the message)
    otherwise. The worker's stdout and stderr go to ``out/logs/<point>.log``.
    """
    pid = point_id(point)
    log_path = out / "logs" / f"{pid}.log"
    result_path = out / ".points" / f"{pid}.json"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    result_path.parent.mkdir(parents=True, exist_ok=True)
    result_path.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "ablations.memory", "--point", json.dumps(point), "--result", str(result_path)]
    if measure != DEFAULT_MEASURE:
        cmd += ["--measure", measure]
    started, t0 = _now(), time.perf_counter()
    status = error = None
    with open(log_path, "w") as log:
        log.write(f"# {started} {' '.join(cmd)}\n")
        log.flush()
        # A new session (process group): a timeout or Ctrl-C kills the worker AND anything it spawned
        # (compile workers), and the terminal's SIGINT reaches only the sweep, which then cleans up.
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True)
        try:
            rc = proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            _kill_group(proc)
            rc, status, error = proc.returncode, "timeout", f"no result after {timeout_s:g} s; killed"
        except BaseException:
            _kill_group(proc)
            raise
    point_s = time.perf_counter() - t0
    result: dict = {}
    if result_path.exists():
        try:
            result = json.loads(result_path.read_text())
        except (OSError, json.JSONDecodeError):
            result = {}
        result_path.unlink(missing_ok=True)
    rel_log = str(log_path.relative_to(out))
    if status is None:
        if result.get("status") in ("ok", "oom", "error") and rc == 0:
            status, error = result["status"], result.get("error")
        elif rc in (-signal.SIGKILL, 128 + signal.SIGKILL):
            status = "oom"
            error = f"worker killed by SIGKILL (most likely the kernel's out-of-memory killer); see {rel_log}"
        else:
            tail = _tail(log_path)
            if rc is not None and rc < 0:
                name = signal.Signals(-rc).name if -rc in signal.valid_signals() else str(-rc)
                why = f"worker died from signal {name}"
            elif rc == 0:
                why = "worker exited without a result"
            else:
                why = f"worker exited with code {rc}"
            if any(p in ln.lower() for ln in tail for p in _OOM_PATTERNS):
                status = "oom"
            else:
                status = "error"
            last = next((ln for ln in reversed(tail) if not ln.startswith("#")), "")
            error = f"{why}: {last}"[:500] if last else why
    row = {k: point.get(k) for k in COLUMNS}
    row.update({k: v for k, v in result.items() if k in COLUMNS and k not in FIXED and k not in ("mode",)})
    for k in ("meshes", "verts_per_mesh"):
        row[k] = point[k]
    row.update(status=status, error=error, started=started, point_s=point_s, log=rel_log)
    if status != "ok":
        # Times of a failed point are not measurements.
        for k in ("fwd_ms", "bwd_ms", "critic_ms", "iter_ms", "peak_alloc_mb", "peak_reserved_mb", "saved_mb"):
            row[k] = None
    row["_environment"] = result.get("environment")
    return row


def _kill_group(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


# ---------------------------------------------------------------------------------------------- results on disk
def _parse(key: str, value: str):
    if value == "":
        return None
    if key in _INT_COLUMNS:
        return int(float(value))
    if key in _FLOAT_COLUMNS:
        return float(value)
    return value


def read_csv(path: str | os.PathLike) -> list[dict]:
    """Rows of a memory.csv with numbers parsed (empty cells are None)."""
    path = Path(path)
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in ("task", "mode", "meshes", "verts_per_mesh", "status") if c not in
                   (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path} is not an ablate-memory CSV: columns {missing} missing")
        return [{k: _parse(k, v if v is not None else "") for k, v in r.items() if k in COLUMNS} for r in reader]


def _csv_text(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: "" if r.get(k) is None else (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k])
                    for k in COLUMNS})
    return buf.getvalue()


def _sort_rows(rows: list[dict]) -> list[dict]:
    return sorted(rows, key=lambda r: (SWEPT_MODES.index(r["mode"]) if r["mode"] in SWEPT_MODES else 9,
                                       r["meshes"], r["verts_per_mesh"]))


def _write(out: Path, rows: list[dict], meta: dict) -> None:
    """memory.csv and memory.json, each replaced atomically: a reader (or a killed sweep) never sees half."""
    from gradlab.checkpoint import atomic_write_json, atomic_write_text

    rows = _sort_rows(rows)
    atomic_write_text(out / "memory.csv", _csv_text(rows))
    meta["updated"] = _now()
    atomic_write_json(out / "memory.json", {**meta, "rows": [{k: r.get(k) for k in COLUMNS} for r in rows]})


def _check_compatible(rows: list[dict], points: list[dict], csv_path: Path) -> None:
    if not rows or not points:
        return
    want = {k: points[0][k] for k in FIXED}
    for r in rows:
        diff = {k: (r.get(k), want[k]) for k in FIXED if r.get(k) != want[k]}
        if diff:
            text = ", ".join(f"{k}: {a!r} there vs {b!r} now" for k, (a, b) in diff.items())
            raise ValueError(f"{csv_path} holds a sweep with other settings ({text}); its rows would not be "
                             f"comparable: use another --out")


# ---------------------------------------------------------------------------------------------- the sweep
def sweep(cfg: MemoryConfig, *, measure: str = DEFAULT_MEASURE) -> list[dict]:
    """Run (or continue) the sweep; returns all rows of memory.csv. Raises ValueError on bad input."""
    from tqdm.auto import tqdm

    from gradlab.seeding import resolve_device

    cfg.validate()
    device = str(resolve_device(cfg.device))
    out = Path(cfg.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_text("ok")
        probe.unlink()
    except OSError as e:
        raise ValueError(f"output folder {out} is not writable: {e}") from None

    points = cfg.points(device)
    csv_path, json_path = out / "memory.csv", out / "memory.json"
    rows = read_csv(csv_path) if csv_path.exists() else []
    _check_compatible(rows, points, csv_path)
    meta: dict = {}
    if json_path.exists():
        try:
            meta = {k: v for k, v in json.loads(json_path.read_text()).items() if k != "rows"}
        except (OSError, json.JSONDecodeError):
            meta = {}
    meta.setdefault("started", _now())
    meta["config"] = {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(cfg).items()}
    meta.setdefault("commands", []).append({"argv": sys.argv, "cwd": os.getcwd(), "started": _now()})

    keep = set(FINAL_STATUSES) if cfg.retry_failed else None
    done = {_key(r) for r in rows if keep is None or r["status"] in keep}
    todo = [p for p in points if _key(p) not in done]
    bar = tqdm(total=len(points), initial=len(points) - len(todo), disable=not cfg.progress, unit="point",
               desc=f"memory {cfg.task}", dynamic_ncols=True)
    try:
        _write(out, rows, meta)
        for p in todo:
            bar.set_description(point_id(p))
            row = run_point(p, out=out, timeout_s=cfg.timeout_s, measure=measure)
            env = row.pop("_environment", None)
            if env and "environment" not in meta:
                meta["environment"] = env
            rows = [r for r in rows if _key(r) != _key(p)] + [row]
            _write(out, rows, meta)
            bwd = row.get("bwd_ms")
            bar.set_postfix(status=row["status"], bwd_ms="-" if bwd is None else f"{bwd:.0f}")
            bar.update(1)
    finally:
        bar.close()
    rows = read_csv(csv_path)  # exactly what is on disk (numbers as the CSV stores them)
    plot_sweep(rows, out)
    return rows


# ---------------------------------------------------------------------------------------------- plots
def _x_of(rows: list[dict]) -> tuple[str, Callable[[dict], float | None], bool]:
    """x axis: total scene faces when every measured row knows them, else extra vertices (meshes x verts)."""
    if all(r.get("scene_faces") for r in rows if r["status"] == "ok"):
        return "scene faces (robot + extra meshes)", lambda r: r.get("scene_faces"), True
    return "extra mesh vertices (meshes x vertices per mesh)", lambda r: r["meshes"] * r["verts_per_mesh"], False


def _spans_decade(values) -> bool:
    """True when the positive values cover a factor of 10 or more (a log axis is then worth it)."""
    v = [x for x in values if isinstance(x, (int, float)) and x > 0]
    return bool(v) and max(v) >= 10 * min(v)


def plot_sweep(rows: list[dict], out: str | os.PathLike) -> list[Path]:
    """memory_peak.png and memory_bwd.png from sweep rows; returns the files written (none without ok rows).

    One line per (mode, vertices per mesh); the robot-only point (0 meshes) starts every line of its mode.
    Out-of-memory points are crosses at the top edge (their x known when the worker counted the scene first).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.transforms import blended_transform_factory

    from gradlab.checkpoint import atomic_write_bytes

    out = Path(out)
    ok = [r for r in rows if r["status"] == "ok"]
    if not ok:
        return []
    xlabel, xf, logx = _x_of(rows)
    cuda = any(r.get("peak_alloc_mb") is not None for r in ok)
    panels = [("peak_alloc_mb", "peak allocated [MB] (CUDA)")] if cuda else []
    panels.append(("saved_mb", "saved for backward per window [MB]"))
    if not cuda:
        panels.append(("max_rss_mb", "peak process RSS [MB] (CPU)"))
    panels = [(k, label) for k, label in panels if any(r.get(k) is not None for r in ok)]
    verts = sorted({r["verts_per_mesh"] for r in rows if r["meshes"] > 0})
    modes = [m for m in SWEPT_MODES if any(r["mode"] == m for r in rows)]
    # Colour = mode (as in ablate-plot: full red, decoupled blue), darker = more vertices per mesh.
    ramps = {"full": plt.get_cmap("Reds"), "decoupled": plt.get_cmap("Blues")}

    def color(mode: str, v: int):
        i = verts.index(v) if v in verts else len(verts) - 1
        return ramps.get(mode, plt.get_cmap("Greys"))(0.45 + 0.5 * i / max(len(verts) - 1, 1))

    styles = {"full": ("-", "o"), "decoupled": ("--", "s")}
    task = rows[0]["task"]
    written = []

    def lines(ax, key: str) -> None:
        drawn = False
        for mode in modes:
            base = [r for r in ok if r["mode"] == mode and r["meshes"] == 0 and r.get(key) is not None]
            for v in verts or [0]:
                pts = base + [r for r in ok if r["mode"] == mode and r["meshes"] > 0 and r["verts_per_mesh"] == v
                              and r.get(key) is not None]
                pts = sorted((xf(r), r[key]) for r in pts if xf(r) is not None)
                if not pts:
                    continue
                ls, mk = styles.get(mode, ("-", "o"))
                label = f"{mode}, {v} verts/mesh" if verts else mode
                ax.plot([p[0] for p in pts], [p[1] for p in pts], ls, marker=mk, color=color(mode, v),
                        label=label, ms=4)
                drawn = True
        trans = blended_transform_factory(ax.transData, ax.transAxes)
        failed = [r for r in rows if r["status"] in ("oom", "timeout")]
        unknown, labelled = [], set()
        for r in failed:
            x = xf(r)
            if x is None:
                unknown.append(f"{r['mode']} m{r['meshes']} v{r['verts_per_mesh']}")
                continue
            ax.plot([x], [0.97], "x", color=color(r["mode"], r["verts_per_mesh"]), transform=trans, ms=8, mew=2,
                    label=None if r["status"] in labelled else r["status"], clip_on=False)
            labelled.add(r["status"])
        if unknown:
            ax.text(0.01, 0.01, "oom/timeout, size unknown: " + ", ".join(unknown), transform=ax.transAxes,
                    fontsize=7, va="bottom")
        # Log axes where the data span a decade or more (scene sizes usually do); on a narrow span a log axis
        # only makes the tick labels unreadable.
        if logx and _spans_decade([xf(r) for r in ok]):
            ax.set_xscale("log")
        elif not logx:
            ax.set_xscale("symlog")
        if drawn and _spans_decade([r.get(key) for r in ok]):
            ax.set_yscale("log")  # only with data on it: an empty log axis cannot place its ticks
        ax.set_xlabel(xlabel)
        ax.grid(True, which="both", alpha=0.3)

    def save(fig, name: str) -> None:
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=120, bbox_inches="tight")
        plt.close(fig)
        atomic_write_bytes(out / name, buf.getvalue())
        written.append(out / name)

    setting = (f"{task}, {ok[0]['num_envs']} envs x {ok[0]['horizon']} steps, {ok[0]['image_size']} px, "
               f"{ok[0]['device']}" + (f" ({ok[0]['gpu']})" if ok[0].get("gpu") else ""))
    if panels:
        fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.2), squeeze=False,
                                 layout="constrained")
        for ax, (key, label) in zip(axes[0], panels):
            lines(ax, key)
            ax.set_ylabel(label)
        axes[0][0].legend(fontsize=7)
        fig.suptitle(f"Memory vs scene size: {setting}", fontsize=10)
        save(fig, "memory_peak.png")

    fig, ax = plt.subplots(figsize=(5.5, 4.2), layout="constrained")
    lines(ax, "bwd_ms")
    ax.set_ylabel("backward per iteration [ms] (median)")
    ax.legend(fontsize=7)
    ax.set_title(f"Backward time vs scene size: {setting}", fontsize=9)
    save(fig, "memory_bwd.png")
    return written


if __name__ == "__main__":
    sys.exit(_worker_main())
