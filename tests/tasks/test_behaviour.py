"""Physical behaviour: what the robots do unactuated (and the ant with its legs pushed down), and the
contact-free integrator against MuJoCo's semi-implicit Euler."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest
import torch

import tasks
from tasks.dynamics import Simulator
from tasks.task import ASSETS


def heights(env, action, steps):
    """Torso heights (steps, B) and whether each env terminated, under a constant action."""
    out, term = [], torch.zeros(env.num_envs, dtype=torch.bool)
    with torch.no_grad():
        for _ in range(steps):
            _, _, _, info = env.step(action)
            term |= info["terminated"]
            out.append(info["qpos_before_reset"][:, 2 if env.name != "hopper" else 1].clone())
    return torch.stack(out), term


@pytest.mark.slow
def test_ant_lands_on_its_legs_then_sinks_onto_its_torso():
    """What is true of SHAC's 182 kg ant with dflex contact and limit penalties: dropped from 0.75 m it lands
    on its feet (torso ~0.5 m), but its ankles give way against the soft limit penalty (ke 1e3) and it sinks
    until the torso sphere (r = 0.25) rests on the ground - never through it - so unactuated it terminates."""
    env = tasks.make("ant", 2, reset_noise=False, early_termination=False)
    env.reset()
    h, _ = heights(env, torch.zeros(2, 8), 200)
    assert (h[:40] > 0.45).all()  # standing on its legs for the first 0.67 s
    assert (h > 0.2).all()  # never through the floor
    assert ((h[-20:] > 0.22) & (h[-20:] < 0.27)).all()  # torso on the ground, below the termination height
    env = tasks.make("ant", 2, reset_noise=False)
    env.reset()
    _, term = heights(env, torch.zeros(2, 8), 200)
    assert term.all()


def test_ant_stands_when_its_ankles_push():
    """Ankle torque (half strength, in the direction of the start pose's ankle angles) holds the torso up."""
    env = tasks.make("ant", 2, seed=1)
    env.reset()
    push = torch.tensor([[0.0, 0.5, 0.0, -0.5, 0.0, -0.5, 0.0, 0.5]]).repeat(2, 1)
    h, term = heights(env, push, 150)
    assert not term.any()
    assert (h[30:] > 0.5).all() and (h < 0.8).all()


@pytest.mark.slow
def test_humanoid_stands_briefly_then_falls():
    env = tasks.make("humanoid", 2, reset_noise=False, early_termination=False)
    env.reset()
    h, _ = heights(env, torch.zeros(2, 21), 120)
    assert (h[:20] > 1.2).all()  # upright for the first third of a second
    assert (h[-10:] < 0.5).all()  # lying on the ground at the end
    assert (h > 0.05).all()  # never through the floor
    env = tasks.make("humanoid", 4, seed=2)
    env.reset()
    _, term = heights(env, torch.zeros(4, 21), 120)
    assert term.all()  # termination (torso below 0.74 m) fires within 2 s


def test_hopper_lands_and_keeps_its_foot_on_the_ground():
    """Hopper upright with its foot 4 cm above the ground: it lands, does not sink through (torso stays
    within a few cm of 1.2 m for a second) and the height term of the reward stays at its cap."""
    env = tasks.make("hopper", 2, reset_noise=False, early_termination=False)
    env.reset()
    h, _ = heights(env, torch.zeros(2, 3), 60)
    assert (h > 1.15).all() and (h < 1.26).all()
    assert h[-1].max() < 1.24  # it did land


def test_cheetah_lands_on_its_feet_and_ffoot_returns_to_its_range():
    """The cheetah dropped from its start (torso 0.8 m up, feet 0.3-0.4 m above the floor) lands on its feet:
    the torso stays above 0.45 m, never on the ground, and ffoot, started 0.3 rad past its upper limit
    (-0.3 rad), is pushed back to that limit within four control steps."""
    env = tasks.make("cheetah", 1, reset_noise=False)
    env.reset()
    z, ffoot = [], []
    with torch.no_grad():
        for _ in range(30):
            env.step(torch.zeros(1, 6))
            z.append(1.0 + env.qpos[0, 1].item())
            ffoot.append(env.qpos[0, 8].item())
    assert min(z) > 0.5 and z[-1] < 0.6  # it fell about 0.25 m onto its feet
    assert max(ffoot[3:]) < -0.25  # back at the limit, within its soft penalty's give


def test_contact_free_trajectory_matches_mujoco_euler():
    """200 substeps of hopper dynamics with contacts, limits and passive forces off equal MuJoCo's Euler
    integrator (semi-implicit: velocities first, then positions with the new velocities)."""
    m = mujoco.MjModel.from_xml_path(str(ASSETS / "hopper.xml"))
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONSTRAINT | mujoco.mjtDisableBit.mjDSBL_SPRING
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_DAMPER  # MuJoCo's Euler treats damping implicitly
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    d.qpos[:] = m.qpos0 + rng.uniform(-0.3, 0.3, m.nq)
    d.qvel[:] = rng.uniform(-1, 1, m.nv)
    tau = rng.uniform(-20, 20, m.nv)
    d.qfrc_applied[:] = tau
    model = tasks.make("hopper", 1).model
    model = dataclasses.replace(model, dof_damping=np.zeros(model.nv))
    sim = Simulator(model, dtype=torch.float64)
    q, v = torch.tensor(d.qpos.copy())[None], torch.tensor(d.qvel.copy())[None]
    t = torch.tensor(tau)[None]
    for _ in range(200):
        mujoco.mj_step(m, d)
        q, v = sim.substep(q, v, t, m.opt.timestep)
    np.testing.assert_allclose(q[0].numpy(), d.qpos, atol=1e-9)
    np.testing.assert_allclose(v[0].numpy(), d.qvel, atol=1e-8)
