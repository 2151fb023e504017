"""The ``ablate-memory`` flags and the points of a sweep."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from vocabulary import RENDERERS, TASKS

__all__ = ["MemoryConfig", "SWEPT_MODES", "point_id"]

#: Gradient modes a sweep can compare (state mode renders nothing, so it has no rendering cost to sweep).
SWEPT_MODES = ("full", "decoupled")


@dataclass
class MemoryConfig:
    """Sweep scene complexity (extra meshes x vertices per mesh) x gradient mode and measure time and memory.

    Each point runs the real SHAC trainer in a fresh process: warm-up iterations, then measured iterations whose
    medians (times) and maxima (peak memory) are reported. Out-of-memory points are rows with status "oom".
    One renderer per sweep folder: sweep the other into another --out. For each --verts value the renderer
    builds the latitude-longitude sphere closest to it (V = 2r(r-1)+2: 6, 14, 26, 42, ...); the CSV's
    scene_verts and scene_faces are the exact counts. With --jobs above 1 the peak memory stays exact (each
    process's own), but times and out-of-memory share the device: keep 1 for times of record and retry an "oom"
    point alone.
    """

    # Each field's docstring (its --help) is one source line: tyro breaks the help text where a line ends.

    # The tasks and renderers are vocabulary's (torch-free), checked in validate().
    task: str = "cartpole"
    """Task, as ablate's --task: cartpole, cartpole-swingup, hopper, ant, humanoid or cheetah."""
    modes: tuple[Literal["full", "decoupled"], ...] = ("decoupled", "full")
    """Gradient modes to sweep (full: through the rendered images; decoupled: D.Va)."""
    renderer: str = "soft"
    """Image source: soft (the differentiable rasterizer) or warp (forward-only ray tracer; decoupled only)."""
    meshes: tuple[int, ...] = (0, 4, 16, 64)
    """Numbers of extra meshes attached to robot links (0: the robot alone, measured once per mode)."""
    verts: tuple[int, ...] = (64, 256, 1024)
    """Vertices per extra mesh, each >= 6 (the closest sphere is built; the CSV has the exact counts)."""
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
    jobs: int = 1
    """Points run at once, each in its own process (keep 1 for times of record: they share the device)."""

    def validate(self) -> None:
        """Clear errors for bad values, each naming its flag, before any work."""
        if self.task not in TASKS:
            raise ValueError(f"--task: unknown task {self.task!r}; valid tasks: {', '.join(TASKS)}")
        if not self.modes:
            raise ValueError("--modes is empty: give full and/or decoupled")
        for m in self.modes:
            if m not in SWEPT_MODES:
                raise ValueError(f"--modes: mode {m!r} cannot be swept (no rendering cost); use full and/or "
                                 f"decoupled")
        if self.renderer not in RENDERERS:
            raise ValueError(f"--renderer: unknown renderer {self.renderer!r}; valid renderers: "
                             f"{', '.join(RENDERERS)}")
        if self.renderer == "warp" and "full" in self.modes:
            raise ValueError("--renderer warp renders without gradient, so --modes full (gradients through the "
                             "images) needs --renderer soft; sweep --modes decoupled with warp")
        if not self.meshes or any(not isinstance(m, int) or m < 0 for m in self.meshes):
            raise ValueError(f"--meshes must be non-negative integers, got {self.meshes!r}")
        # diffrender's sweep spheres (latlong_sphere_mesh) need 6 vertices at least: refuse here, not per point.
        if not self.verts or any(not isinstance(v, int) or v < 6 for v in self.verts):
            raise ValueError(f"--verts must be integers >= 6 (the smallest sweep sphere), got {self.verts!r}")
        for name in ("num_envs", "horizon", "iters", "jobs"):
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
        fixed = dict(task=self.task, renderer=self.renderer, num_envs=self.num_envs, horizon=self.horizon,
                     image_size=self.image_size, warmup_iters=self.warmup_iters, iters=self.iters, device=device,
                     seed=self.seed)
        return [dict(fixed, mode=mode, meshes=m, verts_per_mesh=v) for m, v in sizes
                for mode in sorted(set(self.modes), key=SWEPT_MODES.index)]


def point_id(point: dict) -> str:
    """File-name-safe name of a point, e.g. ``ant_full_m16_v256`` (``ant_decoupled_warp_m16_v256`` with the
    ray tracer)."""
    renderer = "" if point.get("renderer", "soft") == "soft" else f"_{point['renderer']}"
    return f"{point['task']}_{point['mode']}{renderer}_m{point['meshes']}_v{point['verts_per_mesh']}"
