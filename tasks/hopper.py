"""Hopper (SHAC's dflex hopper): a planar one-legged robot, reward for hopping forward.

qpos = [x, z, pitch, thigh, leg, foot] with z the absolute torso height (the asset's rootz has ref 1.25, so
z = 1.25 at the start); qvel the matching rates. Actions: 3 motors (thigh, leg, foot), torque = a * 200 N m.
Contact (dflex): ke 2e4, kd 1e3, kf 1e3, mu 0.9; joint limits ke 1e3, kd 1e1; 16 substeps. Armature 1.0 on
every joint, the root slides and hinge included, and joint damping 2 on the leg joints (D.Va's parse_mjcf
arguments; docs/tasks.md lists every constant with its source).

Reward (SHAC): ``v_x + height + angle - 0.1 |a|^2`` where, with ``dz = z - 1.25`` the height relative to the
start, ``h = clip(dz + 0.3, -1, 0.3)``, ``height = -200 h^2 if h < 0 else h``, ``angle = 1 - pitch^2/(pi/6)^2``.
Terminates when the torso is 0.45 m below its start height (dz < -0.45).
Reset (SHAC's stochastic init): uniform noise +-0.05 on x, z (m), pitch and the three joint angles (rad) and
+-0.05 on all six velocities, around the upright start (x = 0, z = 1.25, all angles 0).
Observation (11): ``[qpos[1:], qvel]`` = [z, pitch, thigh, leg, foot, xd, zd, pitchd, thighd, legd, footd].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .task import CameraSpec, Task, TaskConfig

__all__ = ["HopperConfig", "HopperTask"]


@dataclass(frozen=True)
class HopperConfig(TaskConfig):
    """Hopper defaults (see :class:`tasks.task.TaskConfig` for the shared fields)."""

    episode_length: int = 1000
    substeps: int = 16
    contact_ke: float = 2.0e4
    contact_kd: float = 1.0e3
    contact_kf: float = 1.0e3
    contact_mu: float = 0.9
    q_noise: float = 0.05
    qd_noise: float = 0.05
    start_height: float = 1.25
    termination_drop: float = 0.45
    action_penalty: float = 0.1


class HopperTask(Task):
    """Hopper; see the module docstring."""

    name = "hopper"
    asset = "hopper.xml"
    # D.Va's hopper camera, eye (0,-2.8,1.35) -> (0,0,1.25), is relative to SHAC's start-relative root height
    # (0 at the start pose). Our torso's world height starts at 1.25 m, so the same view is these offsets from
    # the torso: at the start the camera sits at z = 1.35 and looks at z = 1.25, as there.
    camera = CameraSpec(eye=(0.0, -2.8, 0.1), target=(0.0, 0.0, 0.0), fov_deg=45.0, track="xz", root_body="torso")
    Config = HopperConfig
    num_obs = 11
    noise_dim = 12
    config: HopperConfig

    def initial_state(self, u):
        c = self.config
        B = self.num_envs
        start = self._const([0.0, c.start_height, 0.0, 0.0, 0.0, 0.0])
        qpos = start.expand(B, 6) + self._noise(u, 6, 0, c.q_noise)
        qvel = torch.zeros(B, 6, dtype=self.dtype, device=self.device) + self._noise(u, 6, 6, c.qd_noise)
        return qpos, qvel

    def observe(self, qpos, qvel, prev_actions):
        return torch.cat((qpos[:, 1:], qvel), dim=-1)

    def compute_reward(self, qpos, qvel, action):
        c = self.config
        # SHAC: h = dz - (termination height + tolerance) = dz - (-0.45 + 0.15)
        h = torch.clamp(qpos[:, 1] - c.start_height + 0.3, -1.0, 0.3)
        height = torch.where(h < 0, -200.0 * h * h, h)
        angle = 1.0 - qpos[:, 2] ** 2 / (math.pi / 6) ** 2
        return qvel[:, 0] + height + angle - c.action_penalty * (action**2).sum(-1)

    def compute_terminated(self, qpos, qvel):
        c = self.config
        return qpos[:, 1] - c.start_height < -c.termination_drop
