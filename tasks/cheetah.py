"""Half cheetah (D.Va's and SHAC's dflex cheetah, envs/cheetah.py; the two agree): a planar 21.18 kg robot,
reward for running forward.

qpos = [x, z, pitch, bthigh, bshin, bfoot, fthigh, fshin, ffoot] with z the root slide as dflex's joint_q[1]: the
torso is 1.0 + z above the floor (dflex's root frame is 1.0 m up), so z = -0.2 and 0.8 m at the start; qvel the
matching rates. Actions: 6 motors, torque = a * 200 N m on every leg joint (the reference's action_strength).
Contact (dflex): ke 2e4, kd 1e3, kf 1e3, mu 1.0; joint limits ke 1e3, kd 1e1; 16 substeps. Armature 0.1 on all
nine dofs; the leg joints' springs (240/180/120/180/120/60 N m/rad towards 0) and damping from the asset.

Reward (SHAC): ``v_x - 0.1 |a|^2``. No termination: episodes end at their length only (the reference stores an
``early_termination`` flag and never reads it).
Start: x = 0, z = -0.2, every angle 0. ffoot's range is [-3.1, -0.3] rad, so the start pose is 0.3 rad past its
upper limit and the limit force (ke 1e3: about 300 N m) acts from the first substep, as in the reference.
Reset (SHAC's stochastic init): uniform +-0.1 on x, z, the pitch and the six joint angles, +-0.25 on all nine
velocities.
Observation (17): ``[qpos[1:], qvel]`` = [z, pitch, 6 joint angles, 9 velocities]; entry 8 is the forward velocity.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .task import CameraSpec, Task, TaskConfig

__all__ = ["CheetahConfig", "CheetahTask"]


@dataclass(frozen=True)
class CheetahConfig(TaskConfig):
    """Cheetah defaults (see :class:`tasks.task.TaskConfig` for the shared fields). ``start_height`` [m] is the
    root slide's start value (dflex's joint_q[1]), ``q_noise`` [m or rad] and ``qd_noise`` [m/s or rad/s] the
    half-widths of the uniform reset noise."""

    episode_length: int = 1000
    substeps: int = 16
    contact_ke: float = 2.0e4
    contact_kd: float = 1.0e3
    contact_kf: float = 1.0e3
    contact_mu: float = 1.0
    q_noise: float = 0.1
    qd_noise: float = 0.25
    start_height: float = -0.2
    action_penalty: float = 0.1


class CheetahTask(Task):
    """Cheetah; see the module docstring."""

    name = "cheetah"
    asset = "cheetah.xml"
    # D.Va's differentiable renderer (viewer/torch3d_robo cheetah_renderer.py) looks from (0, -3, 0.25) at
    # (0, 0, 0.25), both moved by (q_x, 0, q_z), with the torso drawn at 0.75 + q_z and the floor at -0.35: 0.1 m
    # below the physics ground, which lies at -0.25 in that frame. Our floor is drawn at the physics ground. The
    # offsets keep D.Va's camera-to-floor geometry (the eye 0.6 + q_z above the floor: 0.4 m at the start, about
    # 0.14 m with the cheetah at rest, and under the floor for a torso below 0.4 m, as there), not its
    # camera-to-robot offset (-0.5), which would put the eye 0.04 m above the floor at rest: the robot is drawn
    # 0.1 m lower in the frame than D.Va draws it, feet on the floor rather than 0.1 m above it.
    camera = CameraSpec(eye=(0.0, -3.0, -0.4), target=(0.0, 0.0, -0.4), fov_deg=45.0, track="xz", root_body="torso")
    Config = CheetahConfig
    num_obs = 17
    noise_dim = 18
    config: CheetahConfig

    def initial_state(self, u):
        c = self.config
        B = self.num_envs
        start = self._const([0.0, c.start_height] + [0.0] * 7)
        qpos = start.expand(B, 9) + self._noise(u, 9, 0, c.q_noise)
        qvel = torch.zeros(B, 9, dtype=self.dtype, device=self.device) + self._noise(u, 9, 9, c.qd_noise)
        return qpos, qvel

    def observe(self, qpos, qvel, prev_actions):
        return torch.cat((qpos[:, 1:], qvel), dim=-1)

    def compute_reward(self, qpos, qvel, action):
        return qvel[:, 0] - self.config.action_penalty * (action**2).sum(-1)

    def compute_terminated(self, qpos, qvel):
        return torch.zeros(qpos.shape[0], dtype=torch.bool, device=qpos.device)
