"""The measurement of one sweep point with the real SHAC trainer (run inside a worker process)."""

from __future__ import annotations

import math
from collections.abc import Callable

__all__ = ["measure_point", "scene_size"]


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

    from ablations.run_records import environment_info
    from gradlab.config import SHACConfig
    from gradlab.shac import SHAC
    from gradlab.timing import median

    device = torch.device(point["device"])
    warmup, iters = int(point["warmup_iters"]), int(point["iters"])
    meshes, verts = int(point["meshes"]), int(point["verts_per_mesh"])
    cfg = SHACConfig(
        task=point["task"], mode=point["mode"], renderer=point.get("renderer", "soft"), iters=warmup + iters,
        num_envs=int(point["num_envs"]), horizon=int(point["horizon"]), seed=int(point["seed"]),
        image_size=int(point["image_size"]),
        extra_meshes=meshes, extra_mesh_verts=verts if meshes else SHACConfig.extra_mesh_verts,
        # No probe iterations: they differentiate twice and would measure neither mode. The cost of a random
        # policy is what is measured here, so the learning-stability abort is off (the NaN guard stays on).
        cosine_every=0, abort_grad_norm=math.inf)
    trainer = SHAC([cfg], device=device)
    faces, nverts = scene_size(trainer)
    env = environment_info(device)
    progress({"scene_faces": faces, "scene_verts": nverts, "gpu": env.get("gpu")})

    measured = []
    for i in range(warmup + iters):
        (m,) = trainer.train_iteration()
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
