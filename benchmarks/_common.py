"""What the benchmark scripts share: the commit a result measured, how a call is timed, the scene they render.

The scripts import it as a sibling module (``python benchmarks/X.py`` puts this folder first on ``sys.path``).

- :func:`commit`: the source tree a results file measured.
- :func:`time_ms`, :func:`median_ms`: a call's time [ms] after warm-up, through ``gradlab.timing.RegionTimer``
  (CUDA events read after a synchronisation on a CUDA device, ``perf_counter`` elsewhere); :func:`sync`.
- :func:`graphed`: a call captured once in a CUDA graph and replayed, as the trainer runs under ``--compile``.
- :class:`Scene`: the ant at random poses, with extra sphere meshes up to a face count, under its task's camera.
- :func:`write_json`: a results file, written atomically (a crash keeps the previous complete file).
- :func:`apply_fused_variant`: the fused rasterizer's tuning constants for one timed variant (``--variants``).
"""

from __future__ import annotations

import json
import math
import os
import statistics
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import torch

import diffrender as dr
from diffrender.raster.fused import tuning
from gradlab.timing import RegionTimer

ROOT = Path(__file__).resolve().parents[1]
ASSETS = ROOT / "tasks" / "assets"


def commit() -> str:
    """``$PIXELGRAD_COMMIT`` when set, else the short HEAD with ``+dirty`` when tracked files differ from it.

    The variable exists for copies of the tree whose ``.git`` lags behind their files (a GPU machine that is
    sent the working tree with the repository it was started from): the caller names the commit it sent."""
    named = os.environ.get("PIXELGRAD_COMMIT")
    if named:
        return named

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, timeout=30,
                              check=True).stdout.strip()

    try:
        head = git("rev-parse", "--short", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def sync(device: torch.device | str) -> None:
    """Wait for the device's queued work (nothing to wait for on the CPU)."""
    device = torch.device(device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_ms(fn: Callable[[], Any], device: torch.device | str, *, warmup: int = 0,
            repeats: int) -> tuple[list[float], Any]:
    """Each of ``repeats`` calls of ``fn``'s time [ms], after ``warmup`` untimed calls, and the last call's result."""
    for _ in range(warmup):
        fn()
    timer = RegionTimer(torch.device(device))
    times, out = [], None
    for _ in range(repeats):
        timer.reset()
        with timer("call"):
            out = fn()
        times.append(timer.ms["call"])
    return times, out


def median_ms(fn: Callable[[], Any], device: torch.device | str, *, warmup: int = 0, repeats: int) -> float:
    """The median of :func:`time_ms`'s times [ms]."""
    return statistics.median(time_ms(fn, device, warmup=warmup, repeats=repeats)[0])


def graphed(fn: Callable[[], Any], device: torch.device | str, *, warmup: int = 2) -> Callable[[], None]:
    """``fn`` captured in a CUDA graph (after ``warmup`` calls on a side stream); returns its replay.
    This is how the trainer runs the renderer under ``--compile``: kernel-launch overhead disappears."""
    side = torch.cuda.Stream(device)
    side.wait_stream(torch.cuda.current_stream(device))
    with torch.cuda.stream(side):
        for _ in range(warmup):
            fn()
    torch.cuda.current_stream(device).wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        fn()
    return graph.replay


class Scene:
    """The ant at random poses: ``faces`` 0 is the plain ant (detail 1, 1,856 faces), fewer than that its
    detail-0 model (944), more adds extra sphere meshes (480 or 960 faces each) up to about ``faces``."""

    _cache: ClassVar[dict] = {}

    def __init__(self, faces: int, batch: int, res: int, device, dtype, seed: int = 0):
        key = (faces, device, dtype)
        if key not in Scene._cache:
            robot = dr.RobotModel.from_mjcf(ASSETS / "ant.xml", detail=1, dtype=dtype, device=device)
            if faces > robot.num_faces:
                per_mesh_verts = 242 if faces <= 20_000 else 482  # 480 / 960 faces per sphere
                per_mesh_faces = 2 * per_mesh_verts - 4
                n = math.ceil((faces - robot.num_faces) / per_mesh_faces)
                robot = robot.with_extra_meshes(n, per_mesh_verts, seed=seed)
            elif 0 < faces < robot.num_faces:
                robot = dr.RobotModel.from_mjcf(ASSETS / "ant.xml", detail=0, dtype=dtype, device=device)
            Scene._cache[key] = robot
        self.robot = robot = Scene._cache[key]
        g = torch.Generator().manual_seed(seed)
        q = torch.zeros(batch, robot.nq, dtype=torch.float64)
        q[:, :2] = torch.randn(batch, 2, generator=g)
        q[:, 2] = 0.75
        q[:, 3] = 1.0
        q[:, 7:] = torch.tensor([0, 1, 0, -1, 0, -1, 0, 1.0]) + 0.3 * torch.randn(batch, 8, generator=g)
        self.qpos = q.to(device=device, dtype=dtype)
        with torch.no_grad():
            self.verts = robot.world_vertices(self.qpos)
        self.res = res

    def camera(self, qpos: torch.Tensor) -> dr.Camera:
        # the ant task's camera: eye (0.5, -2, 1) -> (0, 0, 1) from the torso, fov 90
        return dr.tracking_camera(qpos[:, :3], eye_offset=(0.5, -2.0, 1.0), target_offset=(0.0, 0.0, 1.0),
                                  track="xyz", fov_deg=90.0, height=self.res, width=self.res)


def write_json(path: Path, doc: Any, *, indent: int = 1) -> None:
    """``doc`` as JSON at ``path`` (its folder made if missing), through a temporary file renamed over it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(doc, indent=indent) + "\n")
    os.replace(tmp, path)


#: The fused rasterizer's tuning constants a benchmark's ``--variants`` may set, with their defaults.
FUSED_DEFAULTS = {name: getattr(tuning, name) for name in (
    "COEF_ELEMS", "SUPER_BLOCK", "TILE", "FACE_BLOCK", "BWD_TILE", "BWD_TILE_DENSE", "DENSE_FACES_PER_PIXEL",
    "BWD_SUB_BLOCK", "BWD_MAX_SPLITS", "BWD_SPLIT_SUPER_BLOCKS", "FWD_MAX_SPLITS", "FWD_SPLIT_SUPER_BLOCKS",
    "FWD_SUB_BLOCK", "FWD_WARPS", "FWD_COMPACT", "FWD_DEFER_SHADING", "BWD_COMPACT", "FWD_MAXNREG", "BWD_MAXNREG",
    "BWD_MAXNREG_HARD", "FWD_BIN", "BIN_CAPACITY")}


def apply_fused_variant(variant: str) -> dict:
    """Set the fused backend's tuning constants named in ``variant`` ("default" or "NAME=VALUE,NAME=VALUE"),
    after restoring the defaults; returns the values in force. The kernels read them when they launch (a new
    value compiles a new specialisation), so a variant applies to everything rendered after the call."""
    for name, value in FUSED_DEFAULTS.items():
        setattr(tuning, name, value)
    if variant != "default":
        for item in variant.split(","):
            name, _, value = item.partition("=")
            if name not in FUSED_DEFAULTS or not value:
                raise ValueError(f"--variants: {item!r} is not NAME=VALUE with NAME one of {', '.join(FUSED_DEFAULTS)}")
            setattr(tuning, name, type(FUSED_DEFAULTS[name] or 0)(float(value)))
    return {name: getattr(tuning, name) for name in FUSED_DEFAULTS}
