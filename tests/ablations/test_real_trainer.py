"""ablate-memory end to end: the real SHAC trainer, simulator and renderer, one process per point, tiny sizes.

Skipped only while the stack it measures cannot be imported (tasks.make, diffrender.render, the
TaskRenderer that gradlab.shac renders with); any other failure is a failure.
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


@pytest.mark.skipif(_missing() is not None, reason=str(_missing()))
def test_real_sweep_tiny(tmp_path):
    out = tmp_path / "sweep"
    cfg = MemoryConfig(task="cartpole", modes=("decoupled", "full"), meshes=(0, 2), verts=(8,), num_envs=2,
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
        assert r["scene_faces"] > 0 and r["scene_verts"] > 0
    for mode in ("full", "decoupled"):
        # Two extra meshes of 8 vertices each: exactly 16 more vertices, and more faces, in the scene.
        assert pts[(mode, 2)]["scene_verts"] - pts[(mode, 0)]["scene_verts"] == 16
        assert pts[(mode, 2)]["scene_faces"] > pts[(mode, 0)]["scene_faces"]
    # Full mode keeps the renders in the graph; decoupled does not, so its saved bytes ignore the scene.
    assert pts[("full", 0)]["saved_mb"] > pts[("decoupled", 0)]["saved_mb"]
    assert pts[("full", 2)]["saved_mb"] > pts[("full", 0)]["saved_mb"]
    assert pts[("decoupled", 2)]["saved_mb"] == pytest.approx(pts[("decoupled", 0)]["saved_mb"], abs=1e-6)
    assert (out / "memory_peak.png").exists() and (out / "memory_bwd.png").exists()
