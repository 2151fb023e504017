"""The Warp simulator (tasks/warp_sim.py) against the PyTorch reference (tasks/dynamics.py) and MuJoCo.

For every task a short rollout starts from a state with contact points below the ground and limited joints past
both ends of their range, so that the contact (normal, damping, friction and its Coulomb cap) and joint-limit
branches act from the first substep. The Warp float32 states after the horizon must lie within a small multiple
of the torch simulator's own float32-against-float64 spread, measured in the same test; the gradients of the
summed reward into the actions and the initial state must match the float64 reference as closely as the torch
float32 gradients do (cosine >= 1 - 1e-6, relative error <= max(1e-4, 4 x torch float32's)).

Measured on the CPU at these horizons (HORIZONS; 2 environments), largest state error against float64, torch
float32 / Warp float32: cartpole 4.6e-6 / 4.6e-6, hopper 1.1e-5 / 1.3e-5, ant 6.7e-6 / 6.5e-6, humanoid
6.7e-5 / 8.3e-5. Gradients into actions, qpos and qvel: 1 - cosine <= 3e-12 and relative error <= 3.4e-6 for
both backends on every task. At longer horizons (8 hopper, 16 ant, 8 humanoid steps from resets) the gradients'
relative errors stay at 3e-7 .. 2.5e-5 for both.

Tests that stay torch-only (the Warp backend has no counterpart of what they check): test_dynamics.py's
contact-force hand computation and zero-tangential-velocity gradient (internal functions of the torch simulator),
the spd_inverse/linalg tests and the inertia-product identity (torch internals), and every compile/CUDA-graph
test (the Warp step is kept out of torch.compile, and CUDA graphs need a GPU).
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch

import tasks
from tasks import load_model
from tasks.task import ASSETS

from .helpers import directional_fd_check
from .mujoco_checks import assert_float64_matches_mujoco, mujoco_reference, random_states

pytest.importorskip("warp")

# robot -> control steps of the comparison horizon (short: the torch reference is the slow side on the CPU)
HORIZONS = {"cartpole": 8, "cartpole-swingup": 4, "hopper": 3, "ant": 2, "humanoid": 1}


def _sims(robot: str, dtype: torch.dtype):
    from tasks.warp_sim import WarpSimulator

    path = str(ASSETS / f"{robot}.xml")
    model = load_model(path)
    return mujoco.MjModel.from_xml_path(path), model, WarpSimulator(model, dtype=dtype)


@pytest.mark.parametrize("robot", ("cartpole", "hopper", "ant", "humanoid"))
def test_kinematics_inertia_and_qacc_match_mujoco_float32(robot):
    """frames, mass_matrix and forward_dynamics (contacts and limits off) equal MuJoCo's to float32 rounding."""
    m, model, sim = _sims(robot, torch.float32)
    qs, vs, ts = random_states(m, model, 8, seed=1)
    ref = mujoco_reference(m, qs, vs, ts)
    q, v, t = (torch.tensor(x, dtype=torch.float32) for x in (qs, vs, ts))
    fr = sim.frames(q)
    assert (fr.pos.double() - ref["xpos"]).abs().max() < 2e-5
    assert (fr.rot.double() - ref["xmat"]).abs().max() < 2e-5
    M = sim.mass_matrix(q).double()
    assert ((M - ref["M"]).abs().max() / ref["M"].abs().max()) < 2e-5
    qacc = sim.forward_dynamics(q, v, t).double()
    rel = ((qacc - ref["qacc"]).norm(dim=-1) / ref["qacc"].norm(dim=-1)).max().item()
    assert rel < 1e-3, f"{robot}: qacc relative error {rel:.3e}"  # the torch float32 simulator's bound


@pytest.mark.slow
@pytest.mark.parametrize("robot", ("cartpole", "cartpole-swingup", "hopper", "ant", "humanoid"))
def test_kinematics_inertia_and_qacc_match_mujoco_float64(robot):
    """As test_dynamics.test_forward_dynamics_matches_mujoco, with the float64 Warp kernels (slow: their module's
    first compile)."""
    m, model, sim = _sims(robot, torch.float64)
    assert_float64_matches_mujoco(sim, m, model)


def _start(robot: str, num_envs: int = 2, **overrides):
    """A float64 start state (qpos, qvel) with contact points 2 cm below the ground and the first limited joint past
    its upper limit in env 0 and its lower limit in env 1; plus large random actions (T, B, A) in [-1.5, 1.5]."""
    task = tasks.make(robot, num_envs, dtype=torch.float64, seed=3, early_termination=False, **overrides)
    task.reset()
    qpos, qvel = task.qpos.clone(), task.qvel.clone()
    model, sim = task.model, task.sim
    limited = np.flatnonzero(model.hs_limited)
    h = int(limited[0])
    lo, hi = model.hs_range[h]
    qpos[0, model.hs_qadr[h]] = hi + 0.1
    qpos[1, model.hs_qadr[h]] = lo - 0.1
    if sim.contact is not None:
        fr = sim.frames(qpos)
        pts = (fr.rot[:, model.contact_body] @ torch.tensor(model.contact_pos)[..., None])[..., 0]
        z = pts[..., 2] + fr.pos[:, model.contact_body, 2] - torch.tensor(model.contact_dist)
        lift = z.min(dim=1).values - (model.ground_height or 0.0) + 0.02  # (B,)
        if model.nf:
            qpos[:, model.free_qadr[0] + 2] -= lift
        else:
            qpos[:, model.hs_qadr[list(model.hs_names).index("rootz")]] -= lift
    gen = torch.Generator().manual_seed(1)
    actions = 1.5 * torch.randn(HORIZONS[robot], num_envs, task.num_act, generator=gen, dtype=torch.float64)
    return qpos, qvel, actions


def _rollout(robot, backend, dtype, qpos, qvel, actions, **overrides):
    """Final state and the gradients of the summed reward into (actions, qpos, qvel), all in float64."""
    task = tasks.make(robot, qpos.shape[0], dtype=dtype, seed=3, early_termination=False, sim_backend=backend,
                      **overrides)
    q, v, a = (x.to(dtype).requires_grad_(True) for x in (qpos, qvel, actions))
    task.qpos, task.qvel = q, v
    total = q.new_zeros(())
    for step in a:
        _, r, _, info = task.step(step)
        total = total + r.sum()
    grads = torch.autograd.grad(total, (a, q, v))
    state = torch.cat((info["qpos_before_reset"], info["qvel_before_reset"]), dim=1)
    return state.detach().double(), [g.double() for g in grads]


def _cos_rel(x: torch.Tensor, ref: torch.Tensor) -> tuple[float, float]:
    cos = torch.nn.functional.cosine_similarity(x.flatten(), ref.flatten(), dim=0).item()
    return cos, ((x - ref).norm() / ref.norm()).item()


@pytest.mark.parametrize("robot, overrides", [
    ("cartpole", {}), ("cartpole-swingup", {}), ("hopper", {}), ("hopper", {"limit_damping": "violated"}),
    ("hopper", {"mass_matrix_every": 5}), ("ant", {}), ("humanoid", {})])
def test_horizon_states_and_gradients_match_torch(robot, overrides):
    qpos, qvel, actions = _start(robot, **overrides)
    ref_state, ref_grads = _rollout(robot, "torch", torch.float64, qpos, qvel, actions, **overrides)
    t32_state, t32_grads = _rollout(robot, "torch", torch.float32, qpos, qvel, actions, **overrides)
    w32_state, w32_grads = _rollout(robot, "warp", torch.float32, qpos, qvel, actions, **overrides)
    spread = (t32_state - ref_state).abs().max().item()  # the torch simulator's own float32 error
    err = (w32_state - ref_state).abs().max().item()
    assert err <= 4 * spread + 1e-6, f"{robot}: Warp state error {err:.3e}, torch float32 spread {spread:.3e}"
    for name, g, g32, gref in zip(("actions", "qpos", "qvel"), w32_grads, t32_grads, ref_grads):
        cos, rel = _cos_rel(g, gref)
        cos32, rel32 = _cos_rel(g32, gref)
        assert cos >= 1 - 1e-6 and rel <= max(1e-4, 4 * rel32), (
            f"{robot}: gradient into {name}: cosine {cos:.9f}, relative error {rel:.2e} "
            f"(torch float32: {cos32:.9f}, {rel32:.2e})")


def test_start_states_exercise_contact_and_limits():
    """The comparison's start states have contact points below the ground and joints past both limits."""
    for robot in ("hopper", "ant", "humanoid"):
        qpos, _, _ = _start(robot)
        task = tasks.make(robot, 2, dtype=torch.float64)
        model = task.model
        fr = task.sim.frames(qpos)
        pts = (fr.rot[:, model.contact_body] @ torch.tensor(model.contact_pos)[..., None])[..., 0]
        z = pts[..., 2] + fr.pos[:, model.contact_body, 2] - torch.tensor(model.contact_dist)
        assert (z < (model.ground_height or 0.0)).any(dim=1).all(), robot
        q = qpos[:, torch.as_tensor(model.hs_qadr)]
        lo, hi = torch.tensor(model.hs_range).T
        limited = torch.as_tensor(model.hs_limited)
        assert ((q > hi) & limited)[0].any() and ((q < lo) & limited)[1].any(), robot


def test_repeated_backward_gives_the_same_gradient():
    """Probe iterations backpropagate one rollout up to three times: every pass the same gradient."""
    qpos, qvel, actions = _start("hopper")
    task = tasks.make("hopper", 2, seed=3, early_termination=False, sim_backend="warp")
    a = actions.float().requires_grad_(True)
    task.qpos, task.qvel = qpos.float(), qvel.float()
    total = sum(task.step(x)[1].sum() for x in a)
    grads = [torch.autograd.grad(total, a, retain_graph=True)[0] for _ in range(3)]
    assert torch.isfinite(grads[0]).all() and grads[0].abs().sum() > 0
    assert torch.equal(grads[0], grads[1]) and torch.equal(grads[0], grads[2])


def test_step_checks_its_inputs():
    from tasks.warp_sim import WarpSimulator

    sim = WarpSimulator(load_model(str(ASSETS / "hopper.xml")))
    q, v = torch.zeros(2, sim.nq), torch.zeros(2, sim.nv)
    with pytest.raises(ValueError, match="tau must have shape"):
        sim.step(q, v, torch.zeros(2, sim.nv + 1), 0.001, 2, 2)
    with pytest.raises(ValueError, match="float64"):
        sim.step(q.double(), v, v, 0.001, 2, 2)
    with pytest.raises(ValueError, match="mass_matrix_every"):
        sim.step(q, v, v, 0.001, 2, 0)
    with pytest.raises(ValueError, match="sim_backend"):
        tasks.make("hopper", 1, sim_backend="jax")


@pytest.mark.slow
def test_float64_gradient_matches_finite_differences():
    """Central differences of a float64 two-step hopper rollout (contacts and limits active) into the actions and
    the initial state (slow: the float64 module's first compile)."""
    qpos, qvel, actions = _start("hopper", num_envs=2)
    task = tasks.make("hopper", 2, dtype=torch.float64, seed=3, early_termination=False, sim_backend="warp",
                      substeps=4)

    def f(a, q, v):
        task.qpos, task.qvel = q, v
        return sum(task.step(x)[1].sum() for x in a)

    directional_fd_check(f, [actions[:2], qpos, qvel], n_dirs=3, eps=1e-6, rtol=1e-5)


def test_the_setting_reaches_the_task_and_is_no_arm_setting():
    """``--sim-backend`` (SHACConfig.sim_backend) builds the population's task on that backend; config.json records
    it (a SHACConfig field), and runs differing only in it are one arm."""
    import dataclasses

    from gradlab import members
    from gradlab.config import SHACConfig
    from vocabulary import NOT_ARM_SETTINGS, SIM_BACKENDS

    assert SIM_BACKENDS == ("torch", "warp") and "sim_backend" in NOT_ARM_SETTINGS
    assert SHACConfig().sim_backend == "torch" and tasks.make("hopper", 1).warp_sim is None  # the default
    cfg = SHACConfig(task="hopper", sim_backend="warp")
    assert dataclasses.asdict(cfg)["sim_backend"] == "warp"
    task = members.make_task(cfg, [0], 2, torch.device("cpu"))
    assert task.config.sim_backend == "warp" and task.warp_sim is not None
