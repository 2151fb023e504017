"""Every task constant pinned to the reference code it comes from (docs/tasks.md lists them in one table).

References: HaoxiangYou/D.VA at 01b2be4 (D.Va, "D.Va" below) and NVlabs/DiffRL at a4c0dd1 (SHAC, "DiffRL").
Both build their robots with dflex: ``utils/load_utils.py`` (``urdf_load`` for the cartpole, ``parse_mjcf``
for the rest) turns the asset into dflex links, ``dflex/dflex/model.py`` gives shapes their mass at density
1000 and ``dflex/dflex/sim.py`` (``jcalc_tau``) applies the joint forces. Each test's docstring names the
file and value it pins.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import torch

import tasks
from tasks.floors import action_floors, rollout_returns
from tasks.task import ASSETS

DEG = math.pi / 180


def _model(name: str):
    return tasks.make(name, 1).model


def _by_name(model, values) -> dict[str, float]:
    """Per hinge/slide joint values keyed by joint name (values indexed by dof)."""
    return {n: float(values[d]) for n, d in zip(model.hs_names, model.hs_dof)}


def _dflex_shape_mass(m: mujoco.MjModel, g: int, density: float = 1000.0) -> float:
    """Mass dflex gives geom ``g`` (model.py ``compute_sphere_inertia``, ``compute_capsule_inertia``,
    ``compute_box_inertia``): sphere 4/3 pi r^3, capsule a cylinder plus one whole sphere, box its volume."""
    size = m.geom_size[g]
    t = m.geom_type[g]
    if t == mujoco.mjtGeom.mjGEOM_SPHERE:
        return density * 4 / 3 * math.pi * size[0] ** 3
    if t == mujoco.mjtGeom.mjGEOM_CAPSULE:
        r, half = size[0], size[1]
        return density * (4 / 3 * math.pi * r**3 + math.pi * r * r * 2 * half)
    if t == mujoco.mjtGeom.mjGEOM_BOX:
        return density * 8 * size[0] * size[1] * size[2]
    raise AssertionError(f"unexpected geom type {t}")


# ---------------------------------------------------------------------------------------------------------------
# cartpole (D.Va) and cartpole-swingup (SHAC)
def test_cartpole_joint_springs_are_dvas_urdf_load_defaults():
    """D.Va utils/load_utils.py ``urdf_load`` defaults: ``damping=10.0, stiffness=100.0, armature=0.0``, passed
    to every joint (envs/cartpole.py overrides none of them); dflex's joint target is 0, so the springs pull
    the pole upright (th = 0) and the cart to x = 0."""
    m = _model("cartpole")
    assert m.hs_names == ("slider", "hinge")
    assert m.hs_stiffness.tolist() == [100.0, 100.0]
    assert m.hs_springref.tolist() == [0.0, 0.0]
    assert m.dof_damping.tolist() == [10.0, 10.0]
    assert m.dof_armature.tolist() == [0.0, 0.0]


def test_cartpole_swingup_has_shacs_joints():
    """DiffRL utils/load_utils.py ``urdf_load`` passes neither stiffness nor its own ``armature`` argument to
    dflex model.py ``add_link``, whose defaults are ``armature=0.01, stiffness=0.0, damping=0.0``; the URDF
    has no <dynamics>, so no damping either."""
    m = _model("cartpole-swingup")
    assert m.hs_stiffness.tolist() == [0.0, 0.0]
    assert m.dof_damping.tolist() == [0.0, 0.0]
    assert m.dof_armature.tolist() == [0.01, 0.01]


@pytest.mark.parametrize("name", ["cartpole", "cartpole-swingup"])
def test_cartpole_geometry_masses_limits_and_gear(name):
    """envs/assets/cartpole.urdf (identical in D.Va and DiffRL): cart collision box 0.5 x 0.5 x 0.2, pole
    box 0.05 x 0.05 x 1.0 centred 0.5 above the hinge, slider limit -4..4, continuous hinge; dflex
    ``add_shape_box`` density 1000 gives 50 kg and 2.5 kg (the URDF's <inertial> masses 1 and 10 are never
    read). ``urdf_load(..., limit_kd=1.)`` with the default ``limit_ke=100.0``; ``action_strength = 1000.``."""
    env = tasks.make(name, 1)
    m = env.model
    np.testing.assert_allclose(m.body_mass, [50.0, 2.5])
    np.testing.assert_allclose(m.body_ipos[1], [0.0, 0.0, 0.5])
    np.testing.assert_allclose(m.body_inertia[1], np.diag([2.5 * (0.05**2 + 1.0) / 12] * 2 + [2.5 * 0.005 / 12]))
    assert m.hs_limited.tolist() == [True, False]
    np.testing.assert_allclose(m.hs_range[0], [-4.0, 4.0])
    assert (env.config.limit_ke, env.config.limit_kd, env.config.limit_damping) == (100.0, 1.0, "always")
    assert m.act_gear.tolist() == [1000.0] and env.config.action_scale == 1.0
    assert m.ground_height is not None and m.nc == 0  # a floor to render, nothing collides with it
    assert not env.config.contact


def test_cartpole_passive_force_is_dflex_joint_law():
    """dflex sim.py ``jcalc_tau``: ``-target_ke (q - target) - target_kd qd`` plus the limit damping
    ``-limit_kd qd`` applied at every joint whether or not a limit is violated (ke 100, kd 10, limit kd 1)."""
    env = tasks.make("cartpole", 3, dtype=torch.float64)
    q = torch.tensor([[0.3, -math.pi], [-1.0, 0.5], [3.0, 2.0]], dtype=torch.float64)
    qd = torch.tensor([[1.0, -2.0], [0.0, 3.0], [-0.5, 0.25]], dtype=torch.float64)
    tau = env.sim.passive_force(q, qd, limits=True)
    assert torch.allclose(tau, -100.0 * q - 10.0 * qd - 1.0 * qd)
    q_out = torch.tensor([[4.5, 0.0]], dtype=torch.float64)  # past the slider's +4 m stop
    tau = env.sim.passive_force(q_out, torch.zeros(1, 2, dtype=torch.float64), limits=True)
    assert torch.allclose(tau, torch.tensor([[-100.0 * 4.5 + 100.0 * (4.0 - 4.5), 0.0]], dtype=torch.float64))


def test_cartpole_spring_gradient_matches_finite_differences():
    """The springs are differentiable: d(qacc)/d(qpos) through ``-ke q`` against central differences (float64)."""
    env = tasks.make("cartpole", 2, dtype=torch.float64)
    q = torch.tensor([[0.2, -2.5], [-0.4, 0.7]], dtype=torch.float64, requires_grad=True)
    qd = torch.tensor([[0.3, 1.0], [-1.0, 0.0]], dtype=torch.float64)
    tau = torch.zeros(2, 2, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: env.sim.acceleration(x, qd, tau), (q,), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize(
    ("name", "offset", "early", "q_noise", "qd_noise"),
    [("cartpole", 10.0, True, math.pi / 12, 0.05), ("cartpole-swingup", 0.0, False, math.pi / 2, 0.25)],
)
def test_cartpole_task_constants(name, offset, early, q_noise, qd_noise):
    """D.Va envs/cartpole.py: ``health_offset = 10.``, penalties pole angle 1.0 / pole velocity 0.1 / cart
    position 0.05 / cart velocity 0.1 / action 0.0, ``termination_pos = 2.5`` (early termination on),
    reset noise ``np.pi / 6 * (rand - 0.5)`` on q and ``0.1 * (rand - 0.5)`` on qd. DiffRL
    envs/cartpole_swing_up.py: the same penalties without the offset, no termination but the episode end,
    noise ``np.pi * (rand - 0.5)`` and ``0.5 * (rand - 0.5)``. Both: ``sim_substeps = 4``, 240-step episodes
    (examples/cfg yaml ``episode_length: 240``), start ``joint_q[1] = -math.pi``."""
    env = tasks.make(name, 4096, seed=1, dtype=torch.float64)
    c = env.config
    assert (c.substeps, c.episode_length, c.early_termination, c.x_limit) == (4, 240, early, 2.5)
    assert (c.reward_offset, c.q_noise, c.qd_noise) == (offset, q_noise, qd_noise)
    qpos = torch.tensor([[0.0, 0.0], [1.0, 0.5], [-2.0, -math.pi + 0.25]], dtype=torch.float64)
    qvel = torch.tensor([[0.0, 0.0], [2.0, -3.0], [0.5, 1.0]], dtype=torch.float64)
    a = torch.ones(3, 1, dtype=torch.float64)  # no action penalty
    expected = torch.tensor(
        [0.0, -0.25 - 0.9 - 0.05 - 0.4, -((math.pi - 0.25) ** 2) - 0.1 - 0.2 - 0.025], dtype=torch.float64
    )
    assert torch.allclose(env.compute_reward(qpos[:3], qvel, a), offset + expected)
    env.reset()
    x, th = env.qpos[:, 0], env.qpos[:, 1]
    assert x.abs().max() <= q_noise and (th + math.pi).abs().max() <= q_noise and x.abs().max() > 0.95 * q_noise
    assert env.qvel.abs().max() <= qd_noise and env.qvel.abs().max() > 0.95 * qd_noise


# ---------------------------------------------------------------------------------------------------------------
# hopper
def test_hopper_joints_armature_damping_ranges():
    """D.Va (and DiffRL) envs/hopper.py: ``parse_mjcf(..., stiffness=0.0, damping=2.0, armature=1.0,
    radians=True, load_stiffness=True)``; parse_mjcf reads no armature from the file, so armature 1.0 is on
    every joint, the root slides and hinge included; damping comes from the joint's own attribute (0 on
    rootx/rootz/rooty in envs/assets/hopper.xml) else 2.0. Ranges from hopper.xml: thigh and leg
    -2.61799..0 rad, foot -0.785398..0.785398 rad; root joints unlimited."""
    m = _model("hopper")
    assert m.hs_names == ("rootx", "rootz", "rooty", "thigh_joint", "leg_joint", "foot_joint")
    assert m.dof_armature.tolist() == [1.0] * 6
    assert m.dof_damping.tolist() == [0.0, 0.0, 0.0, 2.0, 2.0, 2.0]
    assert m.hs_stiffness.tolist() == [0.0] * 6
    assert m.hs_limited.tolist() == [False, False, False, True, True, True]
    np.testing.assert_allclose(m.hs_range[3:], [[-2.61799, 0.0], [-2.61799, 0.0], [-0.785398, 0.785398]], atol=1e-5)


def test_hopper_geometry():
    """envs/assets/hopper.xml (D.Va = DiffRL): torso capsule r 0.05 half 0.2 at 1.25 m, thigh r 0.05 half
    0.225 below a joint 0.2 m down, leg r 0.04 half 0.25 below a joint 0.45 m further, foot r 0.06 half 0.195
    along x centred 0.06 m ahead of the ankle (0.5 m below the knee); density 1000 (parse_mjcf default)."""
    path = str(ASSETS / "hopper.xml")
    mj = mujoco.MjModel.from_xml_path(path)
    d = mujoco.MjData(mj)
    mujoco.mj_forward(mj, d)
    size = {mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_GEOM, g): mj.geom_size[g, :2] for g in range(mj.ngeom)}
    np.testing.assert_allclose(size["torso_geom"], [0.05, 0.2])
    np.testing.assert_allclose(size["thigh_geom"], [0.05, 0.225])
    np.testing.assert_allclose(size["leg_geom"], [0.04, 0.25])
    np.testing.assert_allclose(size["foot_geom"], [0.06, 0.195])
    anchor = {mj.joint(j).name: d.xanchor[j].copy() for j in range(mj.njnt)}
    np.testing.assert_allclose(anchor["thigh_joint"], [0, 0, 1.05], atol=1e-12)
    np.testing.assert_allclose(anchor["leg_joint"], [0, 0, 0.6], atol=1e-12)
    np.testing.assert_allclose(anchor["foot_joint"], [0, 0, 0.1], atol=1e-12)
    np.testing.assert_allclose(d.geom_xpos[mj.geom("foot_geom").id], [0.06, 0, 0.1], atol=1e-12)
    np.testing.assert_allclose(d.geom_xpos[mj.geom("torso_geom").id], [0, 0, 1.25], atol=1e-12)


def test_hopper_task_constants():
    """D.Va envs/hopper.py: contact ke 2e4, kd 1e3, kf 1e3, mu 0.9; limit ke 1e3, kd 1e1; ``sim_substeps =
    16``; ``action_strength = 200.0``; ``action_penalty = -1e-1``; ``termination_height = -0.45`` with
    tolerance 0.15 (height term clipped to [-1, 0.3]); ``termination_angle = np.pi / 6``; reset noise
    ``0.05 * (rand - 0.5) * 2`` on x, z, the joints and all rates, ``(rand - 0.5) * 0.1`` on the pitch;
    1000-step episodes (examples/cfg/dva/hopper.yaml)."""
    env = tasks.make("hopper", 1)
    c = env.config
    assert (c.contact_ke, c.contact_kd, c.contact_kf, c.contact_mu) == (2e4, 1e3, 1e3, 0.9)
    assert (c.limit_ke, c.limit_kd, c.limit_damping) == (1e3, 1e1, "always")
    assert (c.substeps, c.episode_length, c.early_termination) == (16, 1000, True)
    assert (c.termination_drop, c.action_penalty, c.q_noise, c.qd_noise, c.start_height) == (
        0.45,
        0.1,
        0.05,
        0.05,
        1.25,
    )
    assert env.model.act_gear.tolist() == [200.0] * 3 and c.action_scale == 1.0


# ---------------------------------------------------------------------------------------------------------------
# ant
def test_ant_joint_ranges_are_the_references():
    """envs/assets/ant.xml (D.Va = DiffRL): hips ``range="-40 40"`` deg, ankles ``range="30 100"`` (legs 1
    and 4) and ``range="-100 -30"`` (legs 2 and 3); parse_mjcf converts degrees to radians."""
    m = _model("ant")
    rng = {n: tuple(np.round(m.hs_range[h] / DEG, 6)) for h, n in enumerate(m.hs_names)}
    assert rng == {
        "hip_1": (-40, 40),
        "ankle_1": (30, 100),
        "hip_2": (-40, 40),
        "ankle_2": (-100, -30),
        "hip_3": (-40, 40),
        "ankle_3": (-100, -30),
        "hip_4": (-40, 40),
        "ankle_4": (30, 100),
    }
    assert m.hs_limited.all()


def test_ant_joints_and_task_constants():
    """D.Va envs/ant.py: ``parse_mjcf(..., density=1000.0, stiffness=0.0, damping=1.0, contact_ke=4.e+4,
    contact_kd=1.e+4, contact_kf=3.e+3, contact_mu=0.75, limit_ke=1.e+3, limit_kd=1.e+1, armature=0.05)``;
    ``sim_substeps = 16``; ``action_strength = 200.0``; ``termination_height = 0.27``; start height 0.75 and
    joints (0, 1, 0, -1, 0, -1, 0, 1); reset noise ``0.1 * (rand - 0.5) * 2`` on the position, a rotation
    of ``(rand - 0.5) * np.pi / 12`` about a random axis, ``0.2 * (rand - 0.5) * 2`` on the joints and
    ``0.5 * (rand - 0.5)`` on every rate."""
    env = tasks.make("ant", 1)
    m, c = env.model, env.config
    assert m.dof_armature[6:].tolist() == [0.05] * 8 and m.dof_damping[6:].tolist() == [1.0] * 8
    assert m.dof_armature[:6].tolist() == [0.0] * 6 and m.dof_damping[:6].tolist() == [0.0] * 6
    assert m.hs_stiffness.tolist() == [0.0] * 8
    assert (c.contact_ke, c.contact_kd, c.contact_kf, c.contact_mu) == (4e4, 1e4, 3e3, 0.75)
    assert (c.limit_ke, c.limit_kd, c.substeps, c.episode_length) == (1e3, 1e1, 16, 1000)
    assert m.act_gear.tolist() == [200.0] * 8 and c.action_scale == 1.0
    assert c.termination_height == 0.27 and env.start_height == 0.75
    assert env.start_joints == (0.0, 1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0)
    assert (c.pos_noise, c.rot_noise, c.joint_noise, c.vel_noise) == (0.1, math.pi / 24, 0.2, 0.25)


# ---------------------------------------------------------------------------------------------------------------
# humanoid
HUMANOID_JOINTS = {
    # name: (stiffness, damping, armature, range in degrees, motor strength); D.Va envs/assets/humanoid.xml
    # per-joint attributes (else its parse_mjcf defaults stiffness 5, damping 0.1, armature 0.007) and
    # envs/humanoid.py ``motor_strengths``
    "abdomen_z": (20, 5, 0.02, (-45, 45), 200),
    "abdomen_y": (20, 5, 0.01, (-75, 30), 200),
    "abdomen_x": (10, 5, 0.01, (-35, 35), 200),
    "right_hip_x": (10, 5, 0.01, (-25, 5), 200),
    "right_hip_z": (10, 5, 0.01, (-60, 35), 200),
    "right_hip_y": (20, 5, 0.01, (-80, 20), 600),
    "right_knee": (5, 0.1, 0.007, (-160, 2), 400),
    "right_ankle_y": (2, 1, 0.006, (-50, 50), 100),
    "right_ankle_x": (2, 1, 0.006, (-50, 50), 100),
    "left_hip_x": (10, 5, 0.01, (-25, 5), 200),
    "left_hip_z": (10, 5, 0.01, (-60, 35), 200),
    "left_hip_y": (20, 5, 0.01, (-80, 20), 600),
    "left_knee": (5, 0.1, 0.007, (-160, 2), 400),
    "left_ankle_y": (2, 1, 0.006, (-50, 50), 100),
    "left_ankle_x": (2, 1, 0.006, (-50, 50), 100),
    "right_shoulder1": (10, 5, 0.01, (-60, 60), 100),
    "right_shoulder2": (10, 5, 0.01, (-60, 60), 100),
    "right_elbow": (2, 1, 0.006, (-90, 50), 200),
    "left_shoulder1": (10, 5, 0.01, (-60, 60), 100),
    "left_shoulder2": (10, 5, 0.01, (-60, 60), 100),
    "left_elbow": (2, 1, 0.006, (-90, 50), 200),
}


def test_humanoid_joints_match_the_reference_asset():
    """D.Va envs/humanoid.py ``parse_mjcf(..., stiffness=5.0, damping=0.1, armature=0.007,
    load_stiffness=True, load_armature=True)`` on envs/assets/humanoid.xml (per joint: HUMANOID_JOINTS);
    ``motor_strengths`` 100-600 in joint order; springs towards 0 (the start pose's joint targets)."""
    m = _model("humanoid")
    assert m.hs_names == tuple(HUMANOID_JOINTS)
    stiff = dict(zip(m.hs_names, m.hs_stiffness.tolist()))
    damp, arm = _by_name(m, m.dof_damping), _by_name(m, m.dof_armature)
    gear = dict(zip(m.act_names, m.act_gear.tolist()))
    for h, (name, (ks, kd, ar, (lo, hi), strength)) in enumerate(HUMANOID_JOINTS.items()):
        assert (stiff[name], damp[name], arm[name], gear[name]) == pytest.approx((ks, kd, ar, strength)), name
        np.testing.assert_allclose(m.hs_range[h] / DEG, [lo, hi], atol=1e-6, err_msg=name)
    assert m.hs_springref.tolist() == [0.0] * 21


def test_humanoid_task_constants():
    """D.Va envs/humanoid.py: contact ke 2e4, kd 5e3, kf 1e3, mu 0.75; limit ke 1e3, kd 1e1;
    ``sim_substeps = 48``; ``motor_scale = 0.35``; ``termination_height = 0.74`` with
    ``termination_tolerance = 0.1`` (height target 0.84); ``height_rew_scale = 10.0``; ``action_penalty =
    -0.002``; start height 1.35 with all joints 0; reset noise as the ant's."""
    env = tasks.make("humanoid", 1)
    c = env.config
    assert (c.contact_ke, c.contact_kd, c.contact_kf, c.contact_mu) == (2e4, 5e3, 1e3, 0.75)
    assert (c.limit_ke, c.limit_kd, c.substeps, c.episode_length) == (1e3, 1e1, 48, 1000)
    assert (c.action_scale, c.termination_height, c.target_height, c.action_penalty) == (0.35, 0.74, 0.84, 0.002)
    assert env.start_height == 1.35 and env.start_joints == (0.0,) * 21
    assert (c.pos_noise, c.rot_noise, c.joint_noise, c.vel_noise) == (0.1, math.pi / 24, 0.2, 0.25)
    qpos = env.qpos.double().repeat(2, 1)
    qpos[0, 2], qpos[1, 2] = 0.84 + 0.05, 0.84 - 0.1  # 5 cm above / 10 cm below the target height
    r = env.compute_reward(qpos, torch.zeros(2, 27, dtype=torch.float64), torch.zeros(2, 21, dtype=torch.float64))
    assert r.tolist() == pytest.approx([0.1 + 1 + 10 * 0.05, 0.1 + 1 - 200 * 0.1**2])


# ---------------------------------------------------------------------------------------------------------------
# cheetah
CHEETAH_JOINTS = {
    # name: (stiffness, damping, range [rad]); D.Va = DiffRL envs/assets/half_cheetah.xml, each joint's own
    # attributes (parse_mjcf reads no <default>)
    "bthigh": (240, 6, (-0.52, 1.05)),
    "bshin": (180, 4.5, (-0.785, 0.785)),
    "bfoot": (120, 3, (-0.4, 0.785)),
    "fthigh": (180, 4.5, (-1.5, 0.8)),
    "fshin": (120, 3, (-1.2, 1.1)),
    "ffoot": (60, 1.5, (-3.1, -0.3)),
}


def test_cheetah_joints_armature_springs_ranges():
    """D.Va (= DiffRL) envs/cheetah.py: ``parse_mjcf(..., density=1000.0, stiffness=0.0, damping=1.0,
    armature=0.1, radians=True, load_stiffness=True)`` without ``load_armature``, so armature 0.1 is on all nine
    dofs, the root slides and hinge included (the file's ``armature="0"`` on them is not read); stiffness and
    damping from each joint's attributes in envs/assets/half_cheetah.xml (CHEETAH_JOINTS; 0 on the root
    joints); ``joint_target`` 0, so the springs pull towards 0; root joints ``limited="false"``."""
    m = _model("cheetah")
    assert m.hs_names == ("rootx", "rootz", "rooty", *CHEETAH_JOINTS)
    assert m.dof_armature.tolist() == [0.1] * 9
    assert m.dof_damping.tolist() == [0.0] * 3 + [v[1] for v in CHEETAH_JOINTS.values()]
    assert m.hs_stiffness.tolist() == [0.0] * 3 + [v[0] for v in CHEETAH_JOINTS.values()]
    assert m.hs_springref.tolist() == [0.0] * 9
    assert m.hs_limited.tolist() == [False] * 3 + [True] * 6
    np.testing.assert_allclose(m.hs_range[3:], [v[2] for v in CHEETAH_JOINTS.values()], atol=1e-12)


def test_cheetah_geometry_masses_and_contacts():
    """envs/assets/half_cheetah.xml: eight capsules of radius 0.046 (torso ``fromto="-.5 0 0 .5 0 0"``, head
    half 0.15 at (.6, 0, .1) tilted .87 rad, thighs/shins/feet as CHEETAH_GEOMS); dflex at density 1000 ignores
    ``settotalmass="14"``: 21.18 kg (torso + head 9.457 kg); every dflex shape collides with the ground, two
    end-cap points per capsule (dflex model.py), so 16 contact points, where the file as MuJoCo reads it
    (``conaffinity="0"`` on its ground and its geom defaults) has none. The root frame is 1.0 m above
    dflex's ground (envs/cheetah.py ``joint_X_pj`` of the first link, ``(0.0, 1.0, 0.0)``)."""
    geoms = {  # name: (half-length, pos, axis-angle about y [rad])
        "head": (0.15, (0.6, 0, 0.1), 0.87),
        "bthigh": (0.145, (0.1, 0, -0.13), -3.8),
        "bshin": (0.15, (-0.14, 0, -0.07), -2.03),
        "bfoot": (0.094, (0.03, 0, -0.097), -0.27),
        "fthigh": (0.133, (-0.07, 0, -0.12), 0.52),
        "fshin": (0.106, (0.065, 0, -0.09), -0.6),
        "ffoot": (0.07, (0.045, 0, -0.07), -0.6),
    }
    mj = mujoco.MjModel.from_xml_path(str(ASSETS / "cheetah.xml"))
    for name, (half, pos, angle) in geoms.items():
        g = mj.geom(name).id
        np.testing.assert_allclose(mj.geom_size[g, :2], [0.046, half], err_msg=name)
        np.testing.assert_allclose(mj.geom_pos[g], pos, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(mj.geom_quat[g], [math.cos(angle / 2), 0, math.sin(angle / 2), 0], atol=1e-12)
    np.testing.assert_allclose(mj.geom_size[mj.geom("torso").id, :2], [0.046, 0.5])
    body_pos = {"bthigh": (-0.5, 0, 0), "bshin": (0.16, 0, -0.25), "bfoot": (-0.28, 0, -0.14),
                "fthigh": (0.5, 0, 0), "fshin": (-0.14, 0, -0.24), "ffoot": (0.13, 0, -0.18)}
    for name, pos in body_pos.items():
        np.testing.assert_allclose(mj.body(name).pos, pos, atol=1e-12, err_msg=name)
    m = _model("cheetah")
    np.testing.assert_allclose(m.body_mass, [9.457333, 2.335527, 2.402003, 1.657471, 2.175984, 1.817013, 1.338385],
                               atol=1e-6)
    assert m.body_mass.sum() == pytest.approx(21.183717, rel=1e-6)
    assert m.nc == 16 and m.contact_dist.tolist() == [0.046] * 16
    assert np.bincount(m.contact_body).tolist() == [4, 2, 2, 2, 2, 2, 2]  # the torso holds the head
    assert m.ground_height == 0.0 and mj.body("torso").pos.tolist() == [0.0, 0.0, 1.0]


def test_cheetah_task_constants():
    """D.Va (= DiffRL) envs/cheetah.py: contact ke 2e4, kd 1e3, kf 1e3, mu 1.0; limit ke 1e3, kd 1e1;
    ``sim_substeps = 16``; ``action_strength = 200.0`` on every leg joint (``joint_act[:, 3:] = actions *
    action_strength``; the file's gears 120/90/60/120/60/30 are not read); ``action_penalty = -0.1``;
    ``start_height = -0.2`` (rootz), start rotation 0, ``start_joint_q`` all 0; reset noise ``0.1 * (rand - 0.5)
    * 2`` on rootx, rootz and the joints, ``(rand - 0.5) * 0.2`` on rooty, ``0.5 * (rand - 0.5)`` on all nine
    rates; no termination (``early_termination`` is stored, never read); 1000-step episodes
    (examples/cfg/dva/cheetah.yaml ``episode_length: 1000``)."""
    env = tasks.make("cheetah", 1, dtype=torch.float64)
    c = env.config
    assert (c.contact_ke, c.contact_kd, c.contact_kf, c.contact_mu) == (2e4, 1e3, 1e3, 1.0)
    assert (c.limit_ke, c.limit_kd, c.limit_damping) == (1e3, 1e1, "always")
    assert (c.substeps, c.episode_length, c.mass_matrix_every) == (16, 1000, None)
    assert (c.start_height, c.action_penalty, c.q_noise, c.qd_noise) == (-0.2, 0.1, 0.1, 0.25)
    assert env.model.act_gear.tolist() == [200.0] * 6 and c.action_scale == 1.0
    assert env.model.act_dof.tolist() == [3, 4, 5, 6, 7, 8]
    assert env.qpos.tolist() == [[0.0, -0.2] + [0.0] * 7] and env.qvel.abs().sum() == 0
    assert env.sim.frames(env.qpos).pos[0, 0, 2].item() == pytest.approx(0.8)  # torso 0.8 m up


def test_cheetah_start_pose_has_ffoot_past_its_limit():
    """envs/cheetah.py starts every joint at 0 while half_cheetah.xml limits ffoot to [-3.1, -0.3]: the
    reference's start pose is 0.3 rad past that limit, so dflex's limit penalty ``limit_ke (upper - q)`` =
    -300 N m acts on ffoot from the first substep (and on no other joint). Faithful to the reference: the foot
    is pushed back into its range within the first control step."""
    env = tasks.make("cheetah", 1, dtype=torch.float64, reset_noise=False)
    q, qd = env.qpos.clone(), env.qvel.clone()
    passive = env.sim.passive_force(q, qd, limits=True)
    assert passive[0].tolist() == [0.0] * 8 + [-300.0]
    assert env.sim.passive_force(q, qd, limits=False).abs().sum() == 0  # the springs pull to 0: no force there
    env.step(torch.zeros(1, 6, dtype=torch.float64))
    assert env.qpos[0, 8] < -0.1  # ffoot moved towards its range in one control step


# ---------------------------------------------------------------------------------------------------------------
# every robot
@pytest.mark.parametrize(
    ("name", "total"),
    [
        ("cartpole", 52.5),
        ("cartpole-swingup", 52.5),
        ("hopper", 15.820013),
        ("ant", 182.176017),
        ("humanoid", 40.844021),
        ("cheetah", 21.183717),
    ],
)
def test_body_masses_are_dflex_shape_masses_at_density_1000(name, total):
    """dflex model.py ``_add_shape`` adds each shape's mass to its body at the loader's density (parse_mjcf
    ``density=1000.0``; ``add_shape_box``'s default 1000 for the cartpole): every body weighs the dflex
    masses of its geoms, which MuJoCo's inertia-from-geom computes the same way."""
    mj = mujoco.MjModel.from_xml_path(str(ASSETS / f"{name}.xml"))
    m = _model(name)
    for b in range(1, mj.nbody):
        geoms = [g for g in range(mj.ngeom) if mj.geom_bodyid[g] == b]
        assert m.body_mass[b - 1] == pytest.approx(sum(_dflex_shape_mass(mj, g) for g in geoms), rel=1e-9)
    assert m.body_mass.sum() == pytest.approx(total, rel=1e-6)


@pytest.mark.parametrize("name", tasks.TASKS)
def test_control_step_and_gravity(name):
    """dflex envs: ``self.dt = 1.0/60.0`` per control step, gravity 9.81 m/s^2 down (dflex's -y in its y-up
    world, -z here)."""
    env = tasks.make(name, 1)
    assert env.dt == pytest.approx(1 / 60)
    np.testing.assert_allclose(env.model.gravity, [0.0, 0.0, -9.81])


# ---------------------------------------------------------------------------------------------------------------
# return floors
@pytest.mark.slow
def test_cartpole_floors_reproduce_the_fidelity_review():
    """With D.Va's joint springs, zero action swings the pole up and scores ~2098 of 2400 per 240-step episode
    (docs/floors.json); a random policy scores a little less (its cart now and then leaves |x| <= 2.5)."""
    r = action_floors("cartpole", episodes=64, num_envs=64, seed=0)
    assert r["zero"]["mean"] == pytest.approx(2098, abs=10)
    assert r["zero"]["mean_length"] == 240
    assert 1900 < r["random"]["mean"] < r["zero"]["mean"]


@pytest.mark.slow
def test_spring_free_cartpole_floors_are_low():
    """Without springs (cartpole-swingup's joints) but with D.Va's reward offset, termination and reset noise,
    the pole just hangs and swings: zero action scores ~74 and random actions ~198 per episode (64 episodes,
    seed 0; the fidelity review measured 77 and 178 with the earlier armature of 0.1)."""
    env = tasks.make(
        "cartpole-swingup", 64, seed=0, reward_offset=10.0, early_termination=True, q_noise=math.pi / 12, qd_noise=0.05
    )
    zero, _ = rollout_returns(env, policy="zero", episodes_per_env=1)
    rand, _ = rollout_returns(env, policy="random", episodes_per_env=1, generator=torch.Generator().manual_seed(0))
    assert 60 < zero.mean().item() < 90
    assert 160 < rand.mean().item() < 240


def test_rollout_returns_sums_whole_episodes():
    """Every environment contributes exactly ``episodes_per_env`` whole episodes, each return the plain sum of
    its rewards, whether episodes end by truncation or by termination."""
    env = tasks.make("cartpole", 3, seed=2, dtype=torch.float64, episode_length=6)
    ret, length = rollout_returns(env, policy="zero", episodes_per_env=2)
    assert ret.shape == (6,) and length.tolist() == [6.0] * 6
    again = tasks.make("cartpole", 3, seed=2, dtype=torch.float64, episode_length=6)
    again.reset()  # the same seed's first reset: each env's first episode again, summed by hand
    total = torch.zeros(3, dtype=torch.float64)
    for _ in range(6):
        total += again.step(torch.zeros(3, 1, dtype=torch.float64))[1]
    assert torch.allclose(ret.reshape(3, 2)[:, 0], total)
    # a tight rail ends random episodes early; they are counted once each, at their own length
    env = tasks.make("cartpole", 4, seed=2, episode_length=50, x_limit=0.05)
    ret, length = rollout_returns(env, policy="random", episodes_per_env=3, generator=torch.Generator().manual_seed(1))
    assert ret.shape == (12,) and (length >= 1).all() and (length <= 50).all() and (length < 50).any()
    with pytest.raises(ValueError, match="policy"):
        rollout_returns(env, policy="greedy", episodes_per_env=1)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="Generator"):
        rollout_returns(env, policy="random", episodes_per_env=1)


def test_action_floors_reports_both_policies():
    r = action_floors("cartpole", episodes=5, num_envs=2, seed=0, overrides={"episode_length": 4})
    assert r["episodes"] == 6 and r["episode_length"] == 4 and r["device"] == "cpu"
    for policy in ("zero", "random"):
        p = r[policy]
        assert p["episodes"] == 6 and p["mean_length"] == 4
        assert p["min"] <= p["mean"] <= p["max"] and p["std"] >= 0
    assert r["zero"] != r["random"]
    with pytest.raises(ValueError, match="episodes"):
        action_floors("cartpole", episodes=0, num_envs=2)
    with pytest.raises(ValueError, match="num_envs"):
        action_floors("cartpole", episodes=1, num_envs=0)


def test_task_floors_cli_writes_json_and_merges(tmp_path, capsys, monkeypatch):
    """``task-floors`` writes the file (merging into an existing one unless --fresh) and prints a table."""
    import json

    from tasks import floors

    out = tmp_path / "floors.json"
    out.write_text(json.dumps({"tasks": {"ant": {"kept": True}}}))
    args = ["--tasks", "cartpole", "--episodes", "1", "--num-envs", "1", "--device", "cpu", "--no-progress"]
    # 4-step episodes: the command's plumbing is under test here, the physics elsewhere
    monkeypatch.setattr(floors, "make", lambda name, n, **kw: tasks.make(name, n, **kw, episode_length=4))
    assert floors.main([*args, "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["tasks"]["ant"] == {"kept": True}
    entry = data["tasks"]["cartpole"]
    assert entry["episode_length"] == 4 and entry["zero"]["mean_length"] == 4 and entry["random"]["episodes"] == 1
    assert "cartpole" in capsys.readouterr().out
    assert not list(tmp_path.glob(".*.tmp"))  # the temporary file was moved into place
    measured = json.loads(out.read_text())["tasks"]["cartpole"]
    monkeypatch.setattr(floors, "action_floors", lambda name, **kw: {**measured, "task": name})  # no rerun
    assert floors.main([*args, "--out", str(out), "--fresh"]) == 0
    assert set(json.loads(out.read_text())["tasks"]) == {"cartpole"}


def test_task_floors_cli_rejects_bad_flags(capsys):
    from tasks import floors

    with pytest.raises(SystemExit):
        floors.main(["--tasks", "walker"])
    assert "unknown task" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        floors.main(["--episodes", "0"])
    assert "--episodes" in capsys.readouterr().err
    if not torch.cuda.is_available():
        with pytest.raises(SystemExit):
            floors.main(["--device", "cuda", "--tasks", "cartpole"])
        assert "CUDA" in capsys.readouterr().err
