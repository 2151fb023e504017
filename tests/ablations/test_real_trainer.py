"""ablate-memory end to end: the real SHAC trainer, simulator and renderer, one process per point, tiny sizes.

Skipped only while the stack it measures cannot be imported (tasks.make, diffrender.render, the
TaskRenderer that gradlab.shac renders with); any other failure is a failure. Marked slow: one point of the
real trainer takes 10-40 s on 2 CPU cores (imports, model build, the first iteration), and it needs four.
Run it with ``pytest -m slow tests/ablations``.
"""

from __future__ import annotations

import importlib

import pytest

from ablations.memory import MemoryConfig, sweep


def _missing() -> str | None:
    for module, name in (("tasks", "make"), ("diffrender", "render"), ("tasks.vision", "TaskRenderer"),
                         ("gradlab.shac", "SHAC")):
        try:
            getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError) as e:
            return f"{module}.{name} is not available yet ({type(e).__name__}: {e})"
    return None


@pytest.mark.slow
@pytest.mark.skipif(_missing() is not None, reason=str(_missing()))
def test_real_sweep_tiny(tmp_path):
    import diffrender
    import tasks

    out = tmp_path / "sweep"
    cfg = MemoryConfig(task="cartpole", modes=("decoupled", "full"), meshes=(0, 2), verts=(14,), num_envs=2,
                       horizon=2, image_size=16, warmup_iters=1, iters=1, device="cpu", out=out, timeout_s=300.0,
                       progress=False)
    rows = sweep(cfg)
    pts = {(r["mode"], r["meshes"]): r for r in rows}
    assert len(pts) == 4
    for key, r in pts.items():
        log = (out / r["log"]).read_text()[-3000:]
        assert r["status"] == "ok", f"{key}: {r['error']}\n{log}"
        assert r["fwd_ms"] > 0 and r["bwd_ms"] > 0 and r["iter_ms"] > 0 and r["max_rss_mb"] > 0
        assert r["peak_alloc_mb"] is None  # CPU: no CUDA peaks, and none invented

    # The scene size is the mesh the renderer rasterizes: the robot (+ 2 extra spheres of ~14 vertices).
    robot = diffrender.RobotModel.from_mjcf(tasks.make("cartpole", 1, device="cpu", seed=0).mjcf_path, detail=1)
    for meshes, model in ((0, robot), (2, robot.with_extra_meshes(2, 14, seed=0))):
        for mode in ("full", "decoupled"):
            assert (pts[(mode, meshes)]["scene_faces"], pts[(mode, meshes)]["scene_verts"]) == \
                (model.num_faces, model.num_vertices)
    assert pts[("full", 2)]["scene_faces"] > pts[("full", 0)]["scene_faces"]

    # Full mode keeps the renders in the graph; decoupled does not, so its saved bytes ignore the scene.
    assert pts[("full", 0)]["saved_mb"] > pts[("decoupled", 0)]["saved_mb"]
    assert pts[("full", 2)]["saved_mb"] > pts[("full", 0)]["saved_mb"]
    assert pts[("decoupled", 2)]["saved_mb"] == pytest.approx(pts[("decoupled", 0)]["saved_mb"], abs=1e-6)
    assert (out / "memory_peak.png").exists() and (out / "memory_bwd.png").exists()
