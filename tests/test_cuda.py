"""GPU correctness of every layer (skipped where there is no CUDA device; run on the GPU machine).

CPU tests prove the maths; these prove the same code gives the same numbers on CUDA: the simulator's
forward dynamics against MuJoCo, a rollout's return and gradient against the CPU, the renderer against the
CPU, and one SHAC iteration per mode with the GPU's peak-memory probes filled in.
"""

from __future__ import annotations

import contextlib
import types

import mujoco
import numpy as np
import pytest
import torch

import tasks
from gradlab import SHAC, SHACConfig, graphs
from gradlab.graphs import GraphedCriticPhase
from gradlab.timing import RegionTimer
from tasks.vision import TaskRenderer

pytestmark = [pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]


@pytest.mark.parametrize("name", list(tasks.TASKS))
def test_forward_dynamics_matches_mujoco_on_cuda(name):
    task = tasks.make(name, 5, device="cuda", dtype=torch.float64, seed=1)
    task.reset()
    m = mujoco.MjModel.from_xml_path(task.mjcf_path)
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    d = mujoco.MjData(m)
    gen = torch.Generator().manual_seed(0)
    qvel = torch.randn(5, m.nv, generator=gen, dtype=torch.float64)
    tau = 10 * torch.randn(5, m.nv, generator=gen, dtype=torch.float64)
    qacc = task.sim.forward_dynamics(task.qpos, qvel.cuda(), tau.cuda()).cpu().numpy()
    for b in range(5):
        d.qpos[:] = task.qpos[b].cpu().numpy()
        d.qvel[:] = qvel[b].numpy()
        d.qfrc_applied[:] = tau[b].numpy()
        mujoco.mj_forward(m, d)
        np.testing.assert_allclose(qacc[b], d.qacc, rtol=1e-8, atol=1e-8 * max(1.0, np.abs(d.qacc).max()))


@pytest.mark.parametrize("name", ["cartpole", "ant"])
def test_rollout_return_and_gradient_match_cpu(name):
    results = []
    for device in ("cpu", "cuda"):
        task = tasks.make(name, 4, device=device, dtype=torch.float64, seed=2)
        task.reset()
        theta = torch.linspace(-0.8, 0.8, 6 * 4 * task.num_act, dtype=torch.float64)
        theta = theta.reshape(6, 4, task.num_act).to(device).requires_grad_(True)
        ret = sum(task.step(torch.tanh(theta[t]))[1].sum() for t in range(6))
        (g,) = torch.autograd.grad(ret, theta)
        results.append((ret.detach().cpu(), g.cpu()))
    torch.testing.assert_close(results[1][0], results[0][0], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(results[1][1], results[0][1], rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("name", ["hopper", "humanoid"])
def test_task_images_and_gradients_match_cpu(name):
    out = []
    for device in ("cpu", "cuda"):
        task = tasks.make(name, 3, device=device, dtype=torch.float64, seed=4)
        task.reset()
        qpos = task.qpos.clone().requires_grad_(True)
        img = TaskRenderer(task, height=48, width=48)(qpos)
        w = torch.linspace(0, 1, img.numel(), dtype=img.dtype, device=device).reshape(img.shape)
        (g,) = torch.autograd.grad((img * w).sum(), qpos)
        out.append((img.detach().cpu(), g.cpu()))
    torch.testing.assert_close(out[1][0], out[0][0], rtol=1e-7, atol=1e-7)
    torch.testing.assert_close(out[1][1], out[0][1], rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("name", ["ant", "hopper"])
def test_compiled_task_renderer_matches_eager(name):
    """TaskRenderer.compile (FK, camera and the fused rasterizer's per-face setup through torch.compile):
    the eager images and qpos gradients, float64, with and without grad (separately compiled graphs)."""
    task = tasks.make(name, 3, device="cuda", dtype=torch.float64, seed=2)
    task.reset()
    eager = TaskRenderer(task, height=32, width=32)
    compiled = TaskRenderer(task, height=32, width=32).compile()
    assert compiled.settings.compile and not eager.settings.compile
    # the tiled backend's own kernels stay eager (tests/tasks/test_tasks.py says why); its scene is compiled
    tiled = TaskRenderer(task, height=32, width=32, backend="tiled").compile()
    assert not tiled.settings.compile and tiled._scene != tiled.scene
    out = []
    for r in (eager, compiled):
        with torch.no_grad():
            plain = r(task.qpos)
        qpos = task.qpos.clone().requires_grad_(True)
        img = r(qpos)
        w = torch.linspace(-1, 1, img.numel(), dtype=img.dtype, device="cuda").reshape(img.shape)
        (g,) = torch.autograd.grad((img * w).sum(), qpos)
        out.append((plain, img.detach(), g))
    for a, b in zip(*out):
        assert a.abs().max() > 0
        torch.testing.assert_close(b, a, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("mode", ["full", "decoupled", "state", "blind"])
def test_shac_iteration_on_cuda(mode):
    cfg = SHACConfig(task="ant", mode=mode, num_envs=8, horizon=4, iters=10, cosine_every=1, critic_iterations=2)
    (m,) = SHAC([cfg], device="cuda").train_iteration()
    assert m["peak_alloc_mb"] > 0 and m["peak_reserved_mb"] >= m["peak_alloc_mb"]
    assert np.isfinite(m["grad_norm"]) and m["fwd_ms"] > 0 and m["bwd_ms"] > 0
    if mode in ("full", "decoupled"):
        assert -1 <= m["cos_full_decoupled"] <= 1
        assert all(np.isfinite(m[f"image_sensitivity_f{i}"]) for i in range(3))
        assert np.isfinite(m["grad_norm_render_term_encoder"])


@pytest.mark.parametrize("members", [1, 2])
def test_a_checkpoint_loaded_onto_the_gpu_resumes_as_if_uninterrupted(tmp_path, members):
    """``ablate --resume`` on a GPU loads checkpoints with map_location="cuda", which moves the generators' host
    ByteTensor states to the GPU too; the trainer must restore them there as well as on the CPU."""
    from gradlab.checkpoint import load_checkpoint

    cfgs = [SHACConfig(task="cartpole", mode="decoupled", num_envs=4, horizon=4, iters=4, critic_iterations=2,
                       image_size=32, seed=s) for s in range(members)]
    straight = SHAC(cfgs, device="cuda")
    straight.train_iteration()
    state = straight.state_dict()
    path = tmp_path / "ckpt.pt"
    torch.save(state, path)
    after = straight.train_iteration()
    resumed = SHAC(cfgs, device="cuda")
    resumed.load_state_dict(load_checkpoint(path, map_location="cuda"))
    again = resumed.train_iteration()
    for a, b in zip(after, again, strict=True):
        assert b["grad_norm"] == pytest.approx(a["grad_norm"], rel=1e-4)


def test_ray_tracer_on_cuda_matches_cpu_and_replays_in_a_graph():
    """The Warp tracer on PyTorch's stream: the CUDA image is the rasterizer's sharp limit, and a captured
    frame, replayed after the state changed in place, equals an eager frame of the new state (refit inside the
    graph)."""
    task = tasks.make("ant", 8, device="cuda", seed=2)
    task.reset()
    sharp = dict(sigma=1e-3, gamma=1e-5)
    traced = TaskRenderer(task, renderer="warp", **sharp)(task.qpos)
    soft = TaskRenderer(task, **sharp)(task.qpos)  # the rasterizer's sharp limit, on the GPU too
    differ = (traced - soft).abs().amax(1) > 2 / 255
    assert differ.float().mean() < 0.01  # only silhouette and depth-edge pixels

    task = tasks.make("ant", 8, device="cuda", seed=2)
    task.reset()
    renderer = TaskRenderer(task, renderer="warp")
    qpos = task.qpos.clone()
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side), torch.no_grad():
        renderer(qpos)  # builds the BVH and loads the kernel before the capture
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph), torch.no_grad():
        out = renderer(qpos)
    qpos[:, 7:] += 0.3  # bend every joint
    graph.replay()
    torch.cuda.synchronize()
    with torch.no_grad():
        expected = renderer(qpos)
    torch.testing.assert_close(out, expected, atol=1e-5, rtol=0)


@pytest.mark.parametrize(("task", "mode", "renderer"), [("cartpole", "decoupled", "soft"), ("ant", "full", "soft"),
                                                       ("ant", "decoupled", "warp"), ("hopper", "blind", "soft")])
def test_captured_iterations_match_eager(task, mode, renderer):
    """--compile on CUDA: two eager warm-up iterations, then captured forward/backward/critic graphs replayed,
    with an eager probe iteration in between; the numbers follow the eager run's within float tolerance."""
    def run(compile_: bool):
        cfg = SHACConfig(task=task, mode=mode, num_envs=8, horizon=4, iters=100, cosine_every=3, critic_iterations=2,
                         image_size=48, seed=5, compile=compile_, renderer=renderer)
        trainer = SHAC([cfg], device="cuda")
        return [trainer.train_iteration()[0] for _ in range(6)]

    eager, graphed = run(False), run(True)
    # Iterations 0 and 1 run eagerly (warm-up); 2 captures the plain window, 3 (a probe) the probe window.
    assert [m["graph"] for m in graphed] == [False, False, True, True, True, True]
    probes = mode != "blind"
    assert [m["probed"] for m in graphed] == [probes, False, False, probes, False, False]
    assert not any(m["graph"] for m in eager)
    for i, (a, b) in enumerate(zip(eager, graphed)):
        # compiled kernels round differently and Adam carries the differences forward; through the renderer
        # (full) a first step already moves the gradient norm by up to 0.3 % (H100)
        tol = 3e-3 * (1 + i)
        for k in ("actor_loss", "grad_norm", "critic_loss"):
            assert b[k] == pytest.approx(a[k], rel=tol, abs=1e-5), (i, k, a[k], b[k])


class _UnsyncedTimer(RegionTimer):
    """The trainer's timer without its synchronisations (which would order the streams themselves): every
    region reads 0 ms, so only the code's own stream waits order the work."""

    @contextlib.contextmanager
    def __call__(self, name):
        self.ms[name] = 0.0
        yield

    @contextlib.contextmanager
    def concurrent(self, name, stream):
        self.ms[name] = 0.0
        yield


class _NoMemoryProbe:
    def __init__(self, device):
        self.peak_alloc_mb = self.peak_reserved_mb = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None


def test_critic_fit_beside_the_backward_gives_the_numbers_of_the_fit_after_it(monkeypatch):
    """overlap_critic: a replayed window fits the critic on its own stream while the backward replays. The fit
    must start after the forward wrote this window's buffers, and the main stream must wait for it before the
    target update and the next forward. Timers that synchronise would order the streams by themselves, so they
    are replaced; the forward's replay and the fit each start late (GPU sleeps, the forward's longer), so that a
    missing wait reads stale buffers or an unfitted critic. The critic, the target critic and the actor after
    seven iterations equal those of fitting after the backward, and the two kinds of graph are captured on
    different streams (cuBLAS workspaces)."""
    sleep = int(2e7)  # GPU clock cycles: ~10 ms
    fit = GraphedCriticPhase.__call__

    def late_fit(self, buffers):
        torch.cuda._sleep(sleep)
        return fit(self, buffers)

    def run(overlap: bool):
        cfg = SHACConfig(task="cartpole", mode="decoupled", num_envs=8, horizon=4, iters=100, cosine_every=0,
                         critic_iterations=2, image_size=48, seed=3, compile=True, overlap_critic=overlap)
        trainer = SHAC([cfg], device="cuda")
        metrics = [trainer.train_iteration()[0] for _ in range(3)]  # the third captures and replays the window
        if overlap:
            assert trainer.window.capture_stream != trainer.critic_fit.stream
        window = trainer.window.captured[False]
        forward = window.fwd
        window.fwd = types.SimpleNamespace(replay=lambda: (torch.cuda._sleep(3 * sleep), forward.replay()))
        with monkeypatch.context() as m:
            m.setattr(GraphedCriticPhase, "__call__", late_fit)
            m.setattr(graphs, "MemoryProbe", _NoMemoryProbe)
            trainer.timer.__class__ = _UnsyncedTimer
            metrics += [trainer.train_iteration()[0] for _ in range(4)]
        torch.cuda.synchronize()
        return trainer, metrics

    (after, m_after), (beside, m_beside) = run(False), run(True)
    assert [m["critic_overlapped"] for m in m_beside] == [False, False, True, True, True, True, True]
    assert not any(m["critic_overlapped"] for m in m_after)
    for name in ("critic", "target_critic", "actor"):
        a, b = getattr(after.members[0], name).state_dict(), getattr(beside.members[0], name).state_dict()
        for k in a:
            torch.testing.assert_close(b[k], a[k], rtol=1e-5, atol=1e-6, msg=lambda m, k=k, n=name: f"{n}.{k}: {m}")
    assert [m["critic_loss"] for m in m_beside] == pytest.approx([m["critic_loss"] for m in m_after], rel=1e-5)


def test_critic_fit_beside_the_backward_is_timed_on_its_stream():
    """With the trainer's own timers the overlapped fit reports its own (non-zero) milliseconds."""
    cfg = SHACConfig(task="cartpole", mode="decoupled", num_envs=8, horizon=4, iters=100, cosine_every=0,
                     critic_iterations=2, image_size=48, seed=3, compile=True)
    trainer = SHAC([cfg], device="cuda")
    metrics = [trainer.train_iteration()[0] for _ in range(4)]
    assert [m["critic_overlapped"] for m in metrics] == [False, False, True, True]
    assert all(m["critic_ms"] > 0 and m["bwd_ms"] > 0 for m in metrics)


def test_probe_window_runs_eagerly_once_before_its_capture():
    """Probes switched on after the plain window is captured (as benchmarks/iteration.py does): the first
    probe iteration runs eagerly (compiling the grad-mode render), the next is captured and replayed."""
    cfg = SHACConfig(task="cartpole", mode="decoupled", num_envs=8, horizon=4, iters=100, cosine_every=0,
                     critic_iterations=2, image_size=48, seed=1, compile=True)
    trainer = SHAC([cfg], device="cuda")
    plain = [trainer.train_iteration()[0] for _ in range(3)]
    trainer.cfg.cosine_every = 1
    probed = [trainer.train_iteration()[0] for _ in range(3)]
    assert [m["graph"] for m in plain + probed] == [False, False, True, False, True, True]
    assert all(m["probed"] for m in probed)
    assert all(np.isfinite(m["cos_full_decoupled"]) and np.isfinite(m["grad_norm"]) for m in probed)


def test_warp_simulator_on_cuda_matches_cpu_and_replays_in_a_graph():
    """The Warp simulator on PyTorch's stream: a CUDA horizon (forward and backward) equals the CPU one, and a
    captured horizon, replayed after the start state changed in place, equals an eager horizon of the new state."""
    pytest.importorskip("warp")

    def horizon(task, q0, v0, theta):
        task.qpos, task.qvel = q0, v0
        total = theta.new_zeros(())
        for a in torch.tanh(theta):
            total = total + task.step(a)[1].sum()
        (grad,) = torch.autograd.grad(total, theta)
        return total.detach(), grad

    results = []
    for device in ("cpu", "cuda"):
        task = tasks.make("ant", 8, device=device, seed=2, sim_backend="warp", early_termination=False)
        task.reset()
        theta = 0.5 * torch.randn(4, 8, task.num_act, generator=torch.Generator().manual_seed(0))
        results.append(horizon(task, task.qpos, task.qvel, theta.to(device).requires_grad_(True)))
    torch.testing.assert_close(results[1][0].cpu(), results[0][0], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(results[1][1].cpu(), results[0][1], rtol=1e-3, atol=1e-5)

    task = tasks.make("ant", 8, device="cuda", seed=2, sim_backend="warp", early_termination=False)
    task.reset()
    q0, v0 = task.qpos.clone(), task.qvel.clone()
    theta = (0.5 * torch.randn(4, 8, task.num_act, generator=torch.Generator().manual_seed(0))).cuda()
    theta.requires_grad_(True)
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        horizon(task, q0, v0, theta)  # loads the kernels before the capture
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out = horizon(task, q0, v0, theta)
    q0[:, 7:] += 0.1  # bend every joint
    graph.replay()
    torch.cuda.synchronize()
    expected = horizon(task, q0, v0, theta)
    torch.testing.assert_close(out[0], expected[0], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out[1], expected[1], rtol=1e-4, atol=1e-6)
