"""The simulator against MuJoCo: kinematics, inertia and contact-free accelerations on random states."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch

import tasks
from tasks import UnsupportedModelError, load_model
from tasks.dynamics import ContactParams, Simulator
from tasks.task import ASSETS

from .mujoco_checks import assert_float64_matches_mujoco, random_states

ROBOTS = ("cartpole", "cartpole-swingup", "hopper", "ant", "humanoid", "cheetah")


@pytest.mark.parametrize("robot", ROBOTS)
def test_forward_dynamics_matches_mujoco(robot):
    """qacc, M, xpos, xmat equal MuJoCo's to 1e-8 relative in float64 (damping, springs, armature included)."""
    path = str(ASSETS / f"{robot}.xml")
    m = mujoco.MjModel.from_xml_path(path)
    model = load_model(path)
    assert_float64_matches_mujoco(Simulator(model, dtype=torch.float64), m, model)
    # the physics must not depend on the robot's distance from the world origin
    assert model.nv > 0


def test_forward_dynamics_float32_close_to_float64():
    path = str(ASSETS / "humanoid.xml")
    m = mujoco.MjModel.from_xml_path(path)
    model = load_model(path)
    qs, vs, ts = random_states(m, model, 8, seed=2)
    acc64 = Simulator(model, dtype=torch.float64).forward_dynamics(*(torch.tensor(x) for x in (qs, vs, ts)))
    acc32 = Simulator(model, dtype=torch.float32).forward_dynamics(
        *(torch.tensor(x, dtype=torch.float32) for x in (qs, vs, ts))
    )
    rel = ((acc32.double() - acc64).norm(dim=-1) / acc64.norm(dim=-1)).max().item()
    assert rel < 1e-3, rel


def test_far_from_origin_keeps_float32_accuracy():
    """Spatial quantities use the floating base as reference point: an ant 1 km from the world origin gets
    the same float32 accelerations as one at the origin (world-origin coordinates would lose ~1e-4)."""
    model = load_model(ASSETS / "ant.xml")
    sim = Simulator(model, dtype=torch.float32)
    m = mujoco.MjModel.from_xml_path(str(ASSETS / "ant.xml"))
    qs, vs, ts = random_states(m, model, 8, seed=3)
    q, v, t = (torch.tensor(x, dtype=torch.float32) for x in (qs, vs, ts))
    far = q.clone()
    far[:, 0:2] += 1000.0
    near_acc, far_acc = sim.forward_dynamics(q, v, t), sim.forward_dynamics(far, v, t)
    rel = ((far_acc - near_acc).norm(dim=-1) / near_acc.norm(dim=-1)).max().item()
    assert rel < 1e-5, rel


def test_free_joint_integration_matches_mujoco_convention():
    """Free joint: world-frame linear velocity, body-frame angular velocity, as mj_integratePos integrates."""
    path = str(ASSETS / "ant.xml")
    m = mujoco.MjModel.from_xml_path(path)
    sim = Simulator(load_model(path), dtype=torch.float64)
    rng = np.random.default_rng(4)
    q = m.qpos0 + rng.uniform(-0.3, 0.3, m.nq)
    q[3:7] /= np.linalg.norm(q[3:7])
    v = rng.uniform(-2, 2, m.nv)
    dt = 1e-4
    ref = q.copy()
    mujoco.mj_integratePos(m, ref, v, dt)
    ours = sim.integrate(torch.tensor(q)[None], torch.tensor(v)[None], dt)[0].numpy()
    # first-order quaternion update vs MuJoCo's exact rotation: equal to O(dt^2)
    np.testing.assert_allclose(ours, ref, atol=1e-7)


def test_contact_force_hand_computed():
    """One sphere (ant torso) pushed 1 cm into the ground while sliding: normal, damping and capped friction."""
    model = load_model(ASSETS / "ant.xml")
    cp = ContactParams(ke=4e4, kd=1e4, kf=3e3, mu=0.75)
    sim = Simulator(model, dtype=torch.float64, contact=cp)
    qpos = torch.tensor(model.qpos0)[None].clone()
    qpos[0, 2] = 0.25 - 0.01  # torso sphere r = 0.25: 1 cm deep; legs lifted far above the ground
    qpos[0, 7:] = torch.tensor([0.0, -1.0, 0.0, 1.0, 0.0, 1.0, 0.0, -1.0])  # ankles up
    qvel = torch.zeros(1, model.nv, dtype=torch.float64)
    qvel[0, 0] = 2.0  # sliding along +x
    qvel[0, 2] = -0.5  # moving down
    fr = sim.frames(qpos)
    vb = torch.einsum("bn,xnk->xbk", sim._body_dof_anc, fr.S * qvel[..., None])
    f = sim._contact_forces(fr, vb)[0, 0]  # torso
    normal = 4e4 * 0.01 + 1e4 * 0.5 * 0.01
    friction = -min(3e3 * 2.0, 0.75 * 4e4 * 0.01)
    p = torch.tensor([0.0, 0.0, -0.25], dtype=torch.float64)  # contact point relative to the torso origin
    force = torch.tensor([friction, 0.0, normal], dtype=torch.float64)
    assert torch.allclose(f[3:], force)
    assert torch.allclose(f[:3], torch.linalg.cross(p, force))
    # every other body is out of contact
    assert sim._contact_forces(fr, vb)[0, 1:].abs().max() == 0


def test_unsupported_joint_is_named(tmp_path):
    xml = """<mujoco><worldbody><body name="b"><joint name="shoulder" type="ball"/>
             <geom type="sphere" size="0.1"/></body></worldbody></mujoco>"""
    p = tmp_path / "ball.xml"
    p.write_text(xml)
    with pytest.raises(UnsupportedModelError, match=r"shoulder.*ball"):
        load_model(p)


def test_contact_gradient_finite_at_zero_tangential_velocity():
    """Friction uses v_t/|v_t|; at v_t = 0 (a point pressing straight down, or resting) values and gradients
    must stay finite: the viscous branch is taken and the division is never evaluated."""
    model = load_model(ASSETS / "ant.xml")
    sim = Simulator(model, dtype=torch.float64, contact=ContactParams(ke=4e4, kd=1e4, kf=3e3, mu=0.75))
    qpos = torch.tensor(model.qpos0)[None].clone()
    qpos[0, 2] = 0.24  # torso sphere 1 cm into the ground
    qpos[0, 7:] = torch.tensor([0.0, -1.0, 0.0, 1.0, 0.0, 1.0, 0.0, -1.0])
    for vz in (-0.3, 0.0):  # pressing down / resting
        qvel = torch.zeros(1, model.nv, dtype=torch.float64)
        qvel[0, 2] = vz
        q, v = qpos.clone().requires_grad_(True), qvel.requires_grad_(True)
        qacc = sim.acceleration(q, v, torch.zeros(1, model.nv, dtype=torch.float64))
        gq, gv = torch.autograd.grad(qacc.square().sum(), (q, v))
        assert torch.isfinite(qacc).all() and torch.isfinite(gq).all() and torch.isfinite(gv).all()
        assert gv[0, 0].abs() > 0  # the viscous friction still responds to sliding


def test_spd_inverse_library_and_torch_agree():
    """The mass-matrix inverse by LAPACK/cuSOLVER and by the plain-tensor Cholesky (linalg="torch") agree,
    and a float32 solve through the inverse is as accurate as a direct solve (humanoid: cond(M) ~ 5e3)."""
    from tasks.dynamics import spd_inverse

    model = load_model(ASSETS / "humanoid.xml")
    m = mujoco.MjModel.from_xml_path(str(ASSETS / "humanoid.xml"))
    qs, _, _ = random_states(m, model, 16, seed=5)
    M = Simulator(model, dtype=torch.float64).mass_matrix(torch.tensor(qs))
    a, b = spd_inverse(M, method="library"), spd_inverse(M, method="torch")
    assert torch.allclose(a, b, rtol=1e-10, atol=1e-12 * a.abs().max())
    assert torch.allclose(a @ M, torch.eye(model.nv, dtype=torch.float64).expand_as(M), atol=1e-9)
    r = torch.randn(16, model.nv, dtype=torch.float64)
    x = torch.linalg.solve(M, r)
    x_inv = (spd_inverse(M.float()) @ r.float()[..., None]).squeeze(-1).double()
    x_solve = torch.linalg.solve(M.float(), r.float()).double()
    err_inv = ((x_inv - x).norm(dim=-1) / x.norm(dim=-1)).max()
    err_solve = ((x_solve - x).norm(dim=-1) / x.norm(dim=-1)).max()
    assert err_inv < 1e-4 and err_inv < 5 * err_solve


def test_linalg_torch_task_matches_library():
    env_a = tasks.make("ant", 2, seed=1, dtype=torch.float64)
    env_b = tasks.make("ant", 2, seed=1, dtype=torch.float64, linalg="torch")
    outs = []
    for env in (env_a, env_b):
        env.reset()
        for _ in range(3):
            obs = env.step(torch.full((2, 8), 0.3, dtype=torch.float64))[0]
        outs.append(obs)
    assert torch.allclose(outs[0], outs[1], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("robot", ["ant", "humanoid"])
def test_inertia_times_equals_the_spatial_inertia_product(robot):
    """The bias forces multiply by the spatial inertia without forming it: ``I6 v`` from (I_c, c, m) equals the
    6x6 product, values and gradients w.r.t. the frames and the motion (float64)."""
    sim = Simulator(load_model(str(ASSETS / f"{robot}.xml")), dtype=torch.float64)
    gen = torch.Generator().manual_seed(1)
    qpos = torch.randn(3, sim.nq, dtype=torch.float64, generator=gen)
    X = sim.frames(qpos).X.detach().requires_grad_(True)
    v = torch.randn(3, sim.nb, 6, dtype=torch.float64, generator=gen, requires_grad=True)
    parts = sim._inertia_parts(X)
    fast = sim._inertia_times(*parts, v)
    ref = (sim._spatial_inertia(*parts) @ v.unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(fast, ref, rtol=1e-12, atol=1e-12)
    w = torch.randn(fast.shape, dtype=torch.float64, generator=gen)
    g_fast = torch.autograd.grad((fast * w).sum(), (X, v), retain_graph=True)  # parts are shared
    g_ref = torch.autograd.grad((ref * w).sum(), (X, v))
    for a, b in zip(g_fast, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    assert g_fast[0].abs().sum() > 0
