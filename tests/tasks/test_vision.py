"""TaskRenderer's image sources: the soft rasterizer and the forward-only Warp ray tracer."""

import pytest
import torch

import tasks
from tasks.vision import TaskRenderer


@pytest.fixture(scope="module")
def ant():
    task = tasks.make("ant", 2, seed=3)
    task.reset()
    return task


def test_warp_renderer_matches_the_rasterizers_sharp_limit(ant):
    sharp = dict(sigma=1e-3, gamma=1e-5)
    traced = TaskRenderer(ant, renderer="warp", **sharp)(ant.qpos)
    soft = TaskRenderer(ant, **sharp)(ant.qpos)
    assert traced.shape == soft.shape == (2, 3, 84, 84)
    # Only pixels on silhouette and depth edges may differ (the per-robot IoU and colour bounds are pinned in
    # tests/diffrender/test_raytrace.py); here: the two task-level paths render the same scene.
    differ = (traced - soft).abs().amax(1) > 2 / 255
    assert differ.float().mean() < 0.01


def test_warp_renderer_refuses_a_gradient_and_soft_keeps_one(ant):
    renderer = TaskRenderer(ant, renderer="warp")
    qpos = ant.qpos.clone().requires_grad_(True)
    with pytest.raises(RuntimeError, match="without gradient"):
        renderer(qpos)
    with torch.no_grad():
        assert torch.isfinite(renderer(qpos)).all()
    image = renderer.soft(qpos)  # the rasterizer, for probes and full mode
    image.sum().backward()
    assert qpos.grad is not None and qpos.grad.abs().sum() > 0


def test_unknown_renderer_is_named(ant):
    with pytest.raises(ValueError, match=r"unknown renderer 'raytrace'.*soft, warp"):
        TaskRenderer(ant, renderer="raytrace")


def test_a_render_without_grad_hands_the_scene_a_state_without_grad(ant):
    """Compiled, the scene guards on requires_grad even under no_grad; a state that requires grad (a SHAC window
    starts from such a leaf) is detached there, so that no-grad renders share one graph; with grad it is not."""
    renderer = TaskRenderer(ant, height=16, width=16)
    seen, scene = [], renderer._scene
    renderer._scene = lambda q: seen.append(q.requires_grad) or scene(q)
    qpos = ant.qpos.clone().requires_grad_()
    with torch.no_grad():
        plain = renderer(qpos)
    assert seen == [False] and not plain.requires_grad
    image = renderer(qpos)
    assert seen == [False, True] and image.requires_grad
    torch.testing.assert_close(image.detach(), plain, rtol=0, atol=0)
