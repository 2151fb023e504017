"""The public task API: construction, layouts, determinism, resets, state round trips and bad inputs."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

import tasks

DIMS = {"cartpole": (5, 1), "cartpole-swingup": (5, 1), "hopper": (11, 3), "ant": (37, 8), "humanoid": (76, 21),
        "cheetah": (17, 6)}


def test_registry_lists_the_paper_tasks_and_the_swingup_variant():
    assert set(tasks.TASKS) == set(DIMS)


def test_unknown_task_lists_known_names():
    with pytest.raises(ValueError, match=r"known tasks: .*cartpole"):
        tasks.make("walker", 2)


def test_unknown_override_lists_valid_fields():
    with pytest.raises(ValueError, match=r"unknown override.*'episode_lenght'.*valid:.*episode_length"):
        tasks.make("cartpole", 2, episode_lenght=5)


def test_bad_override_values():
    with pytest.raises(ValueError, match=r"substeps"):
        tasks.make("cartpole", 2, substeps=0)
    with pytest.raises(ValueError, match=r"limit_damping"):
        tasks.make("cartpole", 2, limit_damping="sometimes")
    with pytest.raises(ValueError, match=r"num_envs"):
        tasks.make("cartpole", 0)


@pytest.mark.parametrize("name", tasks.TASKS)
def test_dims_and_attributes(name):
    env = tasks.make(name, 3)
    n_obs, n_act = DIMS[name]
    assert (env.num_obs, env.num_act) == (n_obs, n_act)
    assert env.reset().shape == (3, n_obs)
    assert env.state_obs().shape == (3, n_obs)
    obs, r, done, info = env.step(torch.zeros(3, n_act))
    assert obs.shape == (3, n_obs) and r.shape == (3,) and done.shape == (3,) and done.dtype == torch.bool
    assert info["obs_before_reset"].shape == (3, n_obs)
    assert info["qpos_before_reset"].shape == env.qpos.shape and info["qvel_before_reset"].shape == env.qvel.shape
    assert info["terminated"].dtype == torch.bool and info["truncated"].dtype == torch.bool
    assert env.dt == pytest.approx(1 / 60)
    assert Path(env.mjcf_path).is_file() and env.mjcf_path.endswith(f"{name}.xml")
    assert env.progress.dtype == torch.long and env.prev_actions.shape == (3, n_act)
    assert env.camera.height == 84 and env.camera.width == 84


def test_cameras():
    cams = {n: tasks.make(n, 1).camera for n in tasks.TASKS}
    expected = {
        "cartpole": ((0, -2.8, 1.2), (0, 0, 1.2), 90, "none"),
        "cartpole-swingup": ((0, -2.8, 1.2), (0, 0, 1.2), 90, "none"),
        "hopper": ((0, -2.8, 0.1), (0, 0, 0), 45, "xz"),  # offsets from the torso (1.25 m at the start)
        "ant": ((0.5, -2, 1), (0, 0, 1), 90, "xyz"),
        "humanoid": ((-3, 0, 1), (0, 0, 0), 45, "xyz"),
        "cheetah": ((0, -3, -0.4), (0, 0, -0.4), 45, "xz"),  # offsets from the torso (0.8 m at the start)
    }
    for n, cam in cams.items():
        eye, target, fov, track = expected[n]
        assert cam.eye == pytest.approx(eye) and cam.target == pytest.approx(target)
        assert cam.fov_deg == fov and cam.track == track
        with pytest.raises(AttributeError):
            cam.fov_deg = 10  # frozen


def test_hopper_camera_sees_dvas_view_at_the_start():
    # D.Va: eye (0,-2.8,1.35) -> (0,0,1.25) in world coordinates at the start pose.
    from tasks.vision import TaskRenderer

    env = tasks.make("hopper", 1, dtype=torch.float64)
    cam = TaskRenderer(env).camera(env.qpos)
    assert cam.eye[0].tolist() == pytest.approx([0.0, -2.8, 1.35])


def test_cheetah_camera_keeps_dvas_height_above_the_floor():
    """D.Va viewer/torch3d_robo cheetah_renderer.py: eye (0, -3, 0.25) + (q_x, 0, q_z) looking at (0, 0, 0.25)
    + (q_x, 0, q_z), fov 45, over a floor drawn at z = -0.35: the eye is 0.6 + q_z above that floor. Ours is
    drawn at the physics ground (z = 0), and the eye is 0.6 + q_z above it too (0.4 m at the start, q_z =
    -0.2), looking horizontally, tracking x and z."""
    from tasks.vision import TaskRenderer

    env = tasks.make("cheetah", 2, dtype=torch.float64)
    q = env.qpos.clone()
    q[1, 0], q[1, 1] = 2.0, -0.45
    cam = TaskRenderer(env).camera(q)
    torch.testing.assert_close(cam.eye, torch.tensor([[0.0, -3.0, 0.4], [2.0, -3.0, 0.15]], dtype=torch.float64))
    assert (cam.eye[:, 2] - env.model.ground_height).tolist() == pytest.approx((0.6 + q[:, 1]).tolist())



def _count_fk(monkeypatch) -> dict:
    """Count calls of pytorch-kinematics' chain FK and of RobotModel's FK entry point."""
    import pytorch_kinematics as pk

    import diffrender

    calls = {"chain": 0, "model": 0}
    chain_fk, model_fk = pk.Chain.forward_kinematics_tensor, diffrender.RobotModel.frame_poses

    def counted_chain(self, *args, **kwargs):
        calls["chain"] += 1
        return chain_fk(self, *args, **kwargs)

    def counted_model(self, *args, **kwargs):
        calls["model"] += 1
        return model_fk(self, *args, **kwargs)

    monkeypatch.setattr(pk.Chain, "forward_kinematics_tensor", counted_chain)
    monkeypatch.setattr(diffrender.RobotModel, "frame_poses", counted_model)
    return calls


def _two_pass_image(renderer, qpos):
    """The image as composed with one FK pass for the meshes and another for the camera anchor."""
    import diffrender

    robot, spec = renderer.robot, renderer.spec
    verts, normals = robot.world_vertices_and_normals(qpos)
    root = robot.link_poses(qpos)[:, renderer.root_index, :3, 3]
    cam = diffrender.tracking_camera(root, eye_offset=spec.eye, target_offset=spec.target, track=spec.track,
                                     fov_deg=spec.fov_deg, height=renderer.height, width=renderer.width)
    return diffrender.render(verts, robot.faces, robot.colors, cam, renderer.settings, normals=normals)


@pytest.mark.parametrize("name", ["hopper", "ant"])
def test_task_renderer_runs_forward_kinematics_once_per_frame(name, monkeypatch):
    from tasks.vision import TaskRenderer

    env = tasks.make(name, 2, dtype=torch.float64)
    env.reset()
    renderer = TaskRenderer(env, height=24, width=24)
    g = torch.Generator().manual_seed(0)
    q = (env.qpos + 0.05 * torch.randn(env.qpos.shape, dtype=torch.float64, generator=g)).requires_grad_()
    weights = torch.rand(2, 3, 24, 24, dtype=torch.float64, generator=g)

    reference = _two_pass_image(renderer, q)
    (grad_reference,) = torch.autograd.grad((reference * weights).sum(), q)

    calls = _count_fk(monkeypatch)
    image = renderer(q)
    assert calls == {"chain": 1, "model": 1}
    (grad,) = torch.autograd.grad((image * weights).sum(), q)
    assert calls == {"chain": 1, "model": 1}  # the backward does not run FK again either
    assert torch.equal(image, reference)
    # the camera's and the meshes' gradients now meet at the frames instead of at qpos: same sum, other order
    torch.testing.assert_close(grad, grad_reference, rtol=1e-12, atol=1e-12)
    assert grad[:, :2].abs().sum() > 0  # the root position reaches the image (camera and meshes)

    capacity = renderer.freeze_capacity(q.detach())
    assert calls == {"chain": 2, "model": 2}
    assert renderer.settings.bin_capacity == capacity and capacity > 64


def test_task_renderer_rejects_bad_qpos_before_rendering():
    from tasks.vision import TaskRenderer

    env = tasks.make("hopper", 1, dtype=torch.float64)
    renderer = TaskRenderer(env, height=16, width=16)
    with pytest.raises(ValueError, match=r"qpos has dtype torch.float32"):
        renderer(env.qpos.float())
    with pytest.raises(ValueError, match=r"qpos must have shape \(B, 6\)"):
        renderer.freeze_capacity(env.qpos[:, :3])

def test_cartpole_reward_and_obs_on_hand_made_states():
    env = tasks.make("cartpole", 3, dtype=torch.float64)
    qpos = torch.tensor([[0.0, 0.0], [1.0, 0.5], [-2.0, 2 * math.pi - 0.5]], dtype=torch.float64)
    qvel = torch.tensor([[0.0, 0.0], [2.0, -3.0], [0.5, 1.0]], dtype=torch.float64)
    a = torch.zeros(3, 1, dtype=torch.float64)
    r = env.compute_reward(qpos, qvel, a)
    expected = [10.0, 10 - 0.25 - 0.1 * 9 - 0.05 * 1 - 0.1 * 4, 10 - 0.25 - 0.1 - 0.05 * 4 - 0.1 * 0.25]
    assert torch.allclose(r, torch.tensor(expected, dtype=torch.float64))
    obs = env.observe(qpos, qvel, a)
    assert torch.allclose(obs[1], torch.tensor([1.0, 2.0, math.sin(0.5), math.cos(0.5), -3.0], dtype=torch.float64))
    term = env.compute_terminated(torch.tensor([[2.4, 0.0], [-2.6, 0.0], [2.6, 0.0]]), qvel.float())
    assert term.tolist() == [False, True, True]


def test_cartpole_reset_distribution():
    env = tasks.make("cartpole", 4096, seed=3)
    env.reset()
    x, th = env.qpos[:, 0], env.qpos[:, 1]
    assert x.abs().max() <= math.pi / 12 and (th + math.pi).abs().max() <= math.pi / 12
    assert env.qvel.abs().max() <= 0.05
    assert x.std() > 0.1 and env.qvel.std() > 0.02  # spread over the whole interval, not a constant
    assert abs(x.mean().item()) < 0.01


@pytest.mark.parametrize("name", tasks.TASKS)
def test_seeded_determinism(name):
    def run(seed):
        env = tasks.make(name, 4, seed=seed)
        out = [env.reset()]
        gen = torch.Generator().manual_seed(0)
        for _ in range(5):
            out.append(env.step(torch.rand(4, env.num_act, generator=gen) * 2 - 1)[0])
        return torch.stack(out)

    a, b, c = run(7), run(7), run(8)
    assert torch.equal(a, b)
    assert not torch.equal(a[0], c[0])


def test_reset_by_where_and_gradient_cut():
    """A terminating env is reset (progress 0, prev_actions 0, fresh start state, no gradient to the old
    trajectory); the others continue untouched."""
    env = tasks.make("cartpole", 3, dtype=torch.float64, seed=5)
    env.reset()
    q = env.qpos.detach().clone()
    q[0, 0] = 2.6  # beyond |x| = 2.5: terminates on this step
    q = q.requires_grad_(True)
    env.qpos = q
    env.progress = torch.tensor([10, 10, 10])
    a = torch.full((3, 1), 0.5, dtype=torch.float64, requires_grad=True)
    obs, _r, done, info = env.step(a)
    assert done.tolist() == [True, False, False] and info["terminated"].tolist() == [True, False, False]
    assert env.progress.tolist() == [0, 11, 11]
    assert env.prev_actions[0].abs().sum() == 0 and torch.equal(env.prev_actions[1:], a[1:].detach())
    assert abs(env.qpos[0, 1].item() + math.pi) <= math.pi / 12 + 1e-12  # hanging again
    assert torch.equal(env.qpos[1:], info["qpos_before_reset"][1:])
    assert torch.equal(obs[1:], info["obs_before_reset"][1:])
    assert torch.equal(obs[0], env.observe(env.qpos, env.qvel, env.prev_actions)[0])
    # the reset env's new state carries no gradient; the old trajectory (obs_before_reset) still does
    g_q, g_a = torch.autograd.grad(env.qpos[0].sum() + env.qvel[0].sum(), (q, a), allow_unused=True, retain_graph=True)
    assert (g_q is None or g_q.abs().sum() == 0) and (g_a is None or g_a.abs().sum() == 0)
    g_before = torch.autograd.grad(info["obs_before_reset"][0].sum(), a, retain_graph=True)[0]
    assert g_before[0].abs().sum() > 0
    g_cont = torch.autograd.grad(env.qvel[1].sum(), a)[0]
    assert g_cont[1].abs().sum() > 0 and g_cont[0].abs().sum() == 0


def test_truncation_at_episode_length():
    env = tasks.make("cartpole", 2, episode_length=3)
    env.reset()
    dones = [env.step(torch.zeros(2, 1))[2] for _ in range(4)]
    assert [d.tolist() for d in dones] == [[False, False], [False, False], [True, True], [False, False]]


def test_early_termination_off():
    env = tasks.make("cartpole", 1, early_termination=False)
    env.reset()
    env.qpos = torch.tensor([[3.0, 0.0]])
    _, _, done, info = env.step(torch.zeros(1, 1))
    assert not done.item() and not info["terminated"].item()


def test_invalid_state_always_terminates():
    env = tasks.make("cartpole", 2, early_termination=False)
    env.reset()
    env.qvel = torch.tensor([[float("nan"), 0.0], [0.0, 0.0]])
    _, _, done, _info = env.step(torch.zeros(2, 1))
    assert done.tolist() == [True, False] and torch.isfinite(env.qpos).all() and torch.isfinite(env.qvel).all()


@pytest.mark.parametrize("name", tasks.TASKS)
def test_get_set_state_resumes_bit_identically(name):
    env = tasks.make(name, 4, seed=11, episode_length=7)  # short episodes: resets (and RNG draws) happen
    env.reset()
    gen = torch.Generator().manual_seed(1)
    acts = torch.rand(20, 4, env.num_act, generator=gen) * 2 - 1
    for a in acts[:5]:
        env.step(a)
    snap = env.get_state()
    first = [env.step(a)[0] for a in acts[5:]]
    env.set_state(snap)
    second = [env.step(a)[0] for a in acts[5:]]
    assert all(torch.equal(x, y) for x, y in zip(first, second))


def test_the_state_tensors_are_named_once():
    """get_state, set_state and state_tensors all follow Task.STATE_TENSORS."""
    env = tasks.make("hopper", 3)
    assert list(env.state_tensors()) == list(tasks.Task.STATE_TENSORS)
    assert all(env.state_tensors()[k] is getattr(env, k) for k in env.STATE_TENSORS)
    assert list(env.get_state()) == [*env.STATE_TENSORS, "rng"]
    fresh = {k: v.clone() + 1 for k, v in env.state_tensors().items()}
    env.use_state_tensors(fresh)
    assert all(getattr(env, k) is fresh[k] for k in env.STATE_TENSORS)
    with pytest.raises(ValueError, match="qvel has shape"):
        env.set_state({**env.get_state(), "qvel": torch.zeros(2, 2)})


def test_detach_cuts_the_graph():
    env = tasks.make("cartpole", 2)
    env.reset()
    a = torch.zeros(2, 1, requires_grad=True)
    env.step(a)
    assert env.qpos.requires_grad
    env.detach()
    assert not env.qpos.requires_grad and not env.qvel.requires_grad and not env.prev_actions.requires_grad


def test_detach_with_requires_grad_starts_a_leaf_that_leaves_parameter_gradients_alone():
    env = tasks.make("cartpole", 2)
    env.reset()
    env.step(torch.zeros(2, 1, requires_grad=True))
    env.detach(requires_grad=True)
    assert env.qpos.is_leaf and env.qpos.requires_grad and env.qvel.is_leaf and env.qvel.requires_grad
    assert env.qpos.grad_fn is None and not env.prev_actions.requires_grad  # the cut holds

    grads = []
    for leaf in (False, True):  # the same window from the same state: the action parameter's gradient
        env = tasks.make("cartpole", 2, seed=1, dtype=torch.float64)
        env.reset()
        env.detach(requires_grad=leaf)
        w = torch.tensor([[0.3]], dtype=torch.float64, requires_grad=True)
        loss = sum(env.step(torch.tanh(w * (t + 1)).expand(2, 1))[1].sum() for t in range(3))
        grads.append(torch.autograd.grad(loss, w)[0])
    assert torch.equal(grads[0], grads[1])


def test_a_window_started_from_a_leaf_compiles_each_step_once():
    """Task.compile's graphs guard on which inputs require grad. A window from a plainly detached state calls the
    substep with three grad patterns (the start state without grad; the first step's later substeps; the later
    steps, whose cached mass matrix requires grad) and the factorisation with two; from a leaf that requires
    grad (SHAC under --compile) each once. Counted as the graphs dynamo makes (eager backend: no code generation);
    the per-step reward and reset is one graph either way."""
    import torch._dynamo
    from torch._dynamo.utils import counters

    def graphs(leaf: bool) -> int:
        torch._dynamo.reset()
        counters.clear()
        env = tasks.make("cartpole", 2, seed=0).compile(backend="eager")
        env.reset()
        w = torch.tensor([[0.3]], requires_grad=True)
        for _ in range(2):  # two windows
            env.detach(requires_grad=leaf)
            sum(env.step(torch.tanh(w).expand(2, 1))[1].sum() for _ in range(3)).backward()
        return counters["stats"]["unique_graphs"]

    try:
        assert graphs(leaf=False) == 3 + 2 + 1
        assert graphs(leaf=True) == 1 + 1 + 1
    finally:
        torch._dynamo.reset()


def test_compile_parts_compiles_only_those_and_running_eagerly_steps_without_them():
    """Task.compile(parts=...) compiles only the named physics parts (what one compile helper process compiles);
    running_eagerly runs compiled parts eagerly for a while (a process compiling ahead only its own share), with
    the same numbers, and restores them. Graphs are counted per compiled function (eager backend)."""
    import torch._dynamo
    from torch._dynamo.utils import counters

    start = tasks.make("cartpole", 2, seed=0)
    start.reset()
    start = start.get_state()

    def step_twice(env) -> torch.Tensor:
        env.set_state(start)
        return torch.stack([env.step(torch.full((2, 1), 0.5, dtype=env.dtype))[1] for _ in range(2)])

    try:
        torch._dynamo.reset()
        counters.clear()
        env = tasks.make("cartpole", 2, seed=0).compile(backend="eager", parts=("factorize", "finish"))
        expected = step_twice(tasks.make("cartpole", 2, seed=0))
        assert torch.equal(step_twice(env), expected)
        assert counters["stats"]["unique_graphs"] == 2  # the factorisation and the reward/reset; no substep
        with env.running_eagerly(["finish"]):
            counters.clear()
            assert torch.equal(step_twice(env), expected)
            assert counters["stats"]["unique_graphs"] == 0  # the factorisation's graph again, no new one
            assert env._finish == env._finish_impl
        assert env._finish != env._finish_impl  # compiled again after the block
        with pytest.raises(ValueError, match="physics parts are some of"):
            env.compile(parts=("substep", "renderer"))
        with pytest.raises(ValueError, match="physics parts are some of"):
            env.compile(parts="substep")  # a string is not a collection of parts
    finally:
        torch._dynamo.reset()


def test_bad_actions_raise_clear_errors():
    env = tasks.make("cartpole", 2)
    env.reset()
    with pytest.raises(ValueError, match=r"shape \(2,\).*\(2, 1\)"):
        env.step(torch.zeros(2))
    with pytest.raises(TypeError, match=r"float64.*float32"):
        env.step(torch.zeros(2, 1, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"meta.*cpu"):
        env.step(torch.zeros(2, 1, device="meta"))
    with pytest.raises(TypeError, match=r"torch.Tensor"):
        env.step([[0.0], [0.0]])
    nan = torch.tensor([[0.0], [float("nan")]])
    env.step(nan)  # validation off: no host sync, no error
    checked = tasks.make("cartpole", 2, validate=True)
    checked.reset()
    with pytest.raises(ValueError, match=r"NaN/inf in environments \[1\]"):
        checked.step(nan)


def test_validate_from_environment(monkeypatch):
    monkeypatch.setenv("TASKS_VALIDATE", "1")
    assert tasks.make("cartpole", 1).config.validate
    monkeypatch.setenv("TASKS_VALIDATE", "0")
    assert not tasks.make("cartpole", 1).config.validate


def test_actions_are_clipped():
    env = tasks.make("cartpole", 1, dtype=torch.float64)
    env.reset()
    s = env.get_state()
    big = env.step(torch.tensor([[5.0]], dtype=torch.float64))[0]
    env.set_state(s)
    one = env.step(torch.tensor([[1.0]], dtype=torch.float64))[0]
    assert torch.equal(big, one)


def test_float64_task_runs_in_float64():
    env = tasks.make("cartpole", 2, dtype=torch.float64)
    obs = env.reset()
    assert obs.dtype == torch.float64 and env.qpos.dtype == torch.float64
    assert env.step(torch.zeros(2, 1, dtype=torch.float64))[1].dtype == torch.float64


def test_hopper_reward_obs_termination_on_hand_made_states():
    env = tasks.make("hopper", 3, dtype=torch.float64)
    qpos = torch.tensor(
        [[0.0, 1.25, 0.1, 0.0, 0.0, 0.0], [1.0, 0.75, -0.2, -0.5, -0.5, 0.1], [2.0, 0.70, 0.0, 0.0, 0.0, 0.0]],
        dtype=torch.float64,
    )
    qvel = torch.arange(18, dtype=torch.float64).reshape(3, 6) / 10
    a = torch.tensor([[0.5, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], dtype=torch.float64)
    r = env.compute_reward(qpos, qvel, a)
    ang = (math.pi / 6) ** 2
    expected = [
        0.0 + 0.3 + (1 - 0.01 / ang) - 0.1 * 0.25,  # at the start height: height term clipped to 0.3
        0.6 + (-200 * 0.2**2) + (1 - 0.04 / ang),  # 0.5 m below: h = -0.2
        1.2 + (-200 * 0.25**2) + 1 - 0.1 * 3,  # 0.55 m below: h = -0.25
    ]
    assert torch.allclose(r, torch.tensor(expected, dtype=torch.float64))
    assert env.compute_terminated(qpos, qvel).tolist() == [False, True, True]
    assert torch.equal(env.observe(qpos, qvel, a), torch.cat((qpos[:, 1:], qvel), dim=1))


def test_cheetah_reward_obs_and_no_termination_on_hand_made_states():
    """D.Va envs/cheetah.py: reward ``obs[:, 8] - 0.1 |a|^2`` with obs ``[joint_q[1:], joint_qd]``, so entry 8 is
    the rootx velocity; no termination, however low or upside down the torso."""
    env = tasks.make("cheetah", 3, dtype=torch.float64)
    qpos = torch.zeros(3, 9, dtype=torch.float64)
    qpos[:, 1] = torch.tensor([-0.2, -0.9, 0.5])  # torso 0.8 m up, 0.1 m up, 1.5 m up
    qpos[2, 2] = math.pi  # upside down
    qvel = torch.arange(27, dtype=torch.float64).reshape(3, 9) / 10 - 1.0
    a = torch.tensor([[0.0] * 6, [0.5] * 6, [1.0, -1.0, 0.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    r = env.compute_reward(qpos, qvel, a)
    assert torch.allclose(r, torch.tensor([-1.0, -0.1 - 0.1 * 1.5, 0.8 - 0.1 * 2], dtype=torch.float64))
    obs = env.observe(qpos, qvel, a)
    assert torch.equal(obs, torch.cat((qpos[:, 1:], qvel), dim=1)) and torch.equal(obs[:, 8], qvel[:, 0])
    assert env.compute_terminated(qpos, qvel).tolist() == [False, False, False]


def test_cheetah_reset_distribution():
    """D.Va envs/cheetah.py stochastic init: rootx 0 and rootz -0.2 plus ``0.1 * (rand - 0.5) * 2``, rooty
    ``(rand - 0.5) * 0.2``, joints ``0.1 * (rand - 0.5) * 2`` around 0, every rate ``0.5 * (rand - 0.5)``."""
    env = tasks.make("cheetah", 4096, seed=4, dtype=torch.float64)
    env.reset()
    dev = env.qpos - torch.tensor([0.0, -0.2] + [0.0] * 7, dtype=torch.float64)
    assert (dev.abs() <= 0.1).all() and (dev.abs().amax(0) > 0.099).all()
    assert (env.qvel.abs() <= 0.25).all() and (env.qvel.abs().amax(0) > 0.249).all()
    assert (dev.mean(0).abs() < 0.01).all() and (env.qvel.mean(0).abs() < 0.02).all()


def _quat(axis, angle):
    axis = torch.tensor(axis, dtype=torch.float64)
    return torch.cat(
        (torch.tensor([math.cos(angle / 2)], dtype=torch.float64), math.sin(angle / 2) * axis / axis.norm())
    )


def test_ant_reward_and_obs_on_hand_made_states():
    env = tasks.make("ant", 3, dtype=torch.float64)
    qpos = torch.zeros(3, 15, dtype=torch.float64)
    qpos[:, 2] = torch.tensor([0.5, 0.6, 0.3])
    qpos[0, 3:7] = _quat([1, 0, 0], 0.0)
    qpos[1, 3:7] = _quat([0, 0, 1], math.pi / 2)  # facing +y: heading 0
    qpos[2, 3:7] = _quat([0, 1, 0], math.pi / 2)  # pitched 90 deg: up 0, heading 0
    qpos[:, 7:] = torch.arange(8, dtype=torch.float64) / 10
    qvel = torch.zeros(3, 14, dtype=torch.float64)
    qvel[:, 0] = torch.tensor([1.5, -1.0, 0.0])
    qvel[1, 3:6] = torch.tensor([1.0, 0.0, 0.0])  # body-frame roll rate of a torso yawed by 90 deg
    qvel[:, 6:] = 1.0
    a = torch.full((3, 8), 0.5, dtype=torch.float64)
    r = env.compute_reward(qpos, qvel, a)
    expected = [1.5 + 0.1 + 1 + 0.23, -1.0 + 0.1 + 0 + 0.33, 0 + 0 + 0 + 0.03]
    assert torch.allclose(r, torch.tensor(expected, dtype=torch.float64), atol=1e-12)
    obs = env.observe(qpos, qvel, a)
    assert obs.shape == (3, 37)
    assert torch.allclose(obs[1, 0:1], qpos[1, 2:3]) and torch.allclose(obs[1, 1:5], qpos[1, 3:7])
    assert torch.allclose(obs[1, 5:8], qvel[1, 0:3])
    assert torch.allclose(obs[1, 8:11], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), atol=1e-12)  # world
    assert torch.allclose(obs[1, 11:19], qpos[1, 7:]) and torch.allclose(obs[1, 19:27], 0.1 * qvel[1, 6:])
    assert torch.allclose(obs[:, 27], torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64), atol=1e-12)  # up
    assert torch.allclose(obs[:, 28], torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), atol=1e-12)  # heading
    assert torch.equal(obs[:, 29:], a)
    assert env.compute_terminated(qpos, qvel).tolist() == [False, False, False]
    qpos[0, 2] = 0.26
    assert env.compute_terminated(qpos, qvel).tolist() == [True, False, False]


def test_humanoid_reward_on_hand_made_states():
    env = tasks.make("humanoid", 3, dtype=torch.float64)
    qpos = torch.zeros(3, 28, dtype=torch.float64)
    qpos[:, 3] = 1.0
    qpos[:, 2] = torch.tensor([1.0, 0.8, 0.5])
    qvel = torch.zeros(3, 27, dtype=torch.float64)
    qvel[:, 0] = 2.0
    a = torch.zeros(3, 21, dtype=torch.float64)
    a[2] = 1.0
    r = env.compute_reward(qpos, qvel, a)
    expected = [2 + 0.1 + 1 + 10 * 0.1, 2 + 0.1 + 1 - 200 * 0.04**2, 2 + 0.1 + 1 - 200 * 0.34**2 - 0.002 * 21]
    assert torch.allclose(r, torch.tensor(expected, dtype=torch.float64))
    assert env.compute_terminated(qpos, qvel).tolist() == [False, False, True]
    assert env.observe(qpos, qvel, a).shape == (3, 76)


@pytest.mark.parametrize("name", ["ant", "humanoid"])
def test_floating_base_reset_distribution(name):
    env = tasks.make(name, 2048, seed=4)
    env.reset()
    start = 0.75 if name == "ant" else 1.35
    pos, quat = env.qpos[:, :3], env.qpos[:, 3:7]
    assert (pos[:, :2].abs() <= 0.1).all() and ((pos[:, 2] - start).abs() <= 0.1).all()
    assert torch.allclose(quat.norm(dim=1), torch.ones(2048), atol=1e-6)
    angle = 2 * torch.acos(quat[:, 0].clamp(max=1.0))
    assert angle.max() <= math.pi / 24 + 1e-5 and angle.max() > 0.9 * math.pi / 24
    joints0 = tasks.make(name, 1, reset_noise=False).qpos[0, 7:]
    assert ((env.qpos[:, 7:] - joints0).abs() <= 0.2 + 1e-6).all()
    assert (env.qvel.abs() <= 0.25).all() and env.qvel.std() > 0.1
    # the rotation axis is spread over all directions
    axes = quat[:, 1:] / quat[:, 1:].norm(dim=1, keepdim=True)
    assert (axes.mean(0).abs() < 0.1).all()


def test_mass_matrix_caching_is_a_small_approximation():
    """dflex's mass-matrix caching (default: once per control step) changes a step slightly, not grossly;
    mass_matrix_every=1 recomputes it every substep."""
    outs = []
    for every in (None, 1, 4):
        env = tasks.make("humanoid", 2, seed=0, dtype=torch.float64, mass_matrix_every=every)
        env.reset()
        for _ in range(3):
            env.step(torch.full((2, 21), 0.5, dtype=torch.float64))
        outs.append(env.qvel)
    cached, fresh, every4 = outs
    assert not torch.equal(cached, fresh)
    err_cached, err_every4 = (cached - fresh).abs().max(), (every4 - fresh).abs().max()
    assert err_cached < 0.15 * fresh.abs().max()  # 3 steps of strong actions while falling: ~7% here
    assert err_every4 < err_cached  # refreshing more often approaches the exact path
    with pytest.raises(ValueError, match="mass_matrix_every"):
        tasks.make("humanoid", 1, mass_matrix_every=0)


def test_contact_override_turns_the_ground_off():
    env = tasks.make("ant", 1, contact=False, early_termination=False, reset_noise=False)
    assert env.sim.contact is None
    env.reset()
    with torch.no_grad():
        for _ in range(40):
            env.step(torch.zeros(1, 8))
    assert env.qpos[0, 2] < 0.0  # fell through where the floor would be


def test_counter_rng_is_uniform_reproducible_and_advances_in_place():
    from tasks.rng import CounterRNG

    rng = CounterRNG(1000, 7, seed=123, device="cpu")
    state = rng.state
    a = rng.uniform(torch.float64)
    assert rng.state is state and int(state[1]) == 1  # advanced in place (CUDA-graph replays advance it)
    b = rng.uniform(torch.float64)
    assert a.shape == (1000, 7) and (a >= 0).all() and (a < 1).all()
    assert abs(a.mean().item() - 0.5) < 0.01 and abs(a.var().item() - 1 / 12) < 0.005
    assert not torch.equal(a, b)
    assert abs(torch.corrcoef(torch.stack((a.flatten(), b.flatten())))[0, 1].item()) < 0.03
    assert abs(torch.corrcoef(torch.stack((a[:, 0], a[:, 1])))[0, 1].item()) < 0.1  # columns independent
    rng.set_state(torch.tensor([123, 0]))
    assert torch.equal(rng.uniform(torch.float64), a)
    other = CounterRNG(1000, 7, seed=124, device="cpu").uniform(torch.float64)
    assert not torch.equal(other, a)


def test_renderer_compile_keeps_the_cpu_scene_and_the_tiled_kernels_eager():
    """TaskRenderer.compile on the CPU compiles nothing. The scene stays eager: inductor's C++ code for the backward
    of pytorch-kinematics' forward kinematics corrupted the heap (torch 2.13; the process aborted). The tiled
    backend's own kernels stay eager wherever it renders (tests/test_cuda.py pins it on a GPU): their compiled
    backward gave NaN image gradients in full mode on an H200."""
    from tasks.vision import TaskRenderer

    renderer = TaskRenderer(tasks.make("cartpole", 2), height=16, width=16)
    scene = renderer._scene
    assert renderer.compile() is renderer
    assert renderer._scene == scene and not renderer.settings.compile


def test_compile_settings_combo_kernels_unless_a_mode_is_given(monkeypatch):
    """Task.compile's defaults (static shapes, inductor combo kernels, small reductions unrolled, programmatic
    dependent launch made race-free) reach torch.compile; a user's mode replaces the options (torch.compile
    refuses both), a user's options are merged over the default."""
    calls = []
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: calls.append(kw) or fn)
    task = tasks.make("cartpole", 2)
    task.compile()
    opts = dict(calls[-1]["options"])
    marker = opts.pop("post_grad_custom_post_pass")  # puts the PDL wait placement into inductor's cache key
    assert calls[-1]["dynamic"] is False and marker.uuid() == "pixelgrad-pdl-wait-first-v1"
    assert opts == {"combo_kernels": True, "unroll_reductions_threshold": 32, "triton.enable_pdl": True}
    task.compile(options={"max_autotune": True, "unroll_reductions_threshold": 8})
    opts = {k: v for k, v in calls[-1]["options"].items() if k != "post_grad_custom_post_pass"}
    assert opts == {"combo_kernels": True, "unroll_reductions_threshold": 8, "triton.enable_pdl": True,
                    "max_autotune": True}
    task.compile(options={"triton.enable_pdl": False})
    assert calls[-1]["options"]["triton.enable_pdl"] is False
    assert "post_grad_custom_post_pass" not in calls[-1]["options"]
    task.compile(mode="max-autotune-no-cudagraphs")
    assert calls[-1] == {"dynamic": False, "mode": "max-autotune-no-cudagraphs"}
    import torch._dynamo.config as dynamo_config

    assert dynamo_config.recompile_limit >= 64


def test_pdl_kernels_wait_before_their_first_access():
    """tasks._pdl replaces inductor's PDL wait placement (a wait only before reading what the previous kernel
    wrote) with a wait before any access: a kernel touching none of its predecessor's buffers, here a store to
    "buf7", still waits; a kernel without PDL gets nothing; inside a looped reduction the wait goes before the
    loop."""
    from torch._inductor.codegen.triton import TritonKernel

    from tasks import _pdl

    assert _pdl.install() and _pdl.install()  # idempotent

    class Buffer:
        def __init__(self):
            self.lines = []

        def writeline(self, line):
            self.lines.append(line)

    class Tree:
        is_loop = True

    class Kernel:  # the attributes the code generator's method reads
        GDC_WAIT = TritonKernel.GDC_WAIT

        def __init__(self, pdl, looped=False):
            self.pdl, self.inside_reduction, self.range_trees, self.body = pdl, looped, [Tree()], Buffer()

        def _enable_pdl_codegen(self):
            return self.pdl

    for kernel, where in ((Kernel(True), "buffer"), (Kernel(True, looped=True), "body")):
        buf = Buffer()
        TritonKernel._handle_pdl_before_access(kernel, buf, "buf7", consider_reads=True)
        target = buf if where == "buffer" else kernel.body
        assert target.lines == [TritonKernel.GDC_WAIT]
    off, buf = Kernel(False), Buffer()
    TritonKernel._handle_pdl_before_access(off, buf, "buf7")
    assert buf.lines == [] and off.body.lines == []


def test_one_device_resolver_for_every_command():
    """tasks.resolve_device turns a --device flag into a torch.device (gradlab re-exports the same function): auto
    is CUDA where present, a missing GPU or an unknown name is an error naming the flag's value, never the CPU."""
    import gradlab

    assert gradlab.resolve_device is tasks.resolve_device
    cuda = torch.cuda.is_available()
    assert tasks.resolve_device("auto") == torch.device("cuda" if cuda else "cpu")
    assert tasks.resolve_device(torch.device("cpu")) == torch.device("cpu")
    with pytest.raises(ValueError, match="unknown device 'tpu': use auto, cpu or cuda"):
        tasks.resolve_device("tpu")
    if not cuda:
        with pytest.raises(ValueError, match="--device cuda:1 asked for, but torch sees no CUDA device"):
            tasks.resolve_device("cuda:1")
