"""Humanoid (SHAC's 21-joint dflex humanoid with ankles), reward for running along +x.

Start: torso at 1.35 m, all joints at 0. Actions: 21 motors, torque = a * 0.35 * gear (gears 100-600, the
per-joint strengths in the asset). Joint stiffness, damping and armature from the asset; contact (dflex):
ke 2e4, kd 5e3, kf 1e3, mu 0.75; joint limits ke 1e3, kd 1e1; 48 substeps; episodes of 1000 steps.
Reward (SHAC): ``v_x + 0.1 up + heading + height - 0.002 |a|^2`` with ``d = clip(z - 0.84, -1, 0.1)``,
``height = -200 d^2 if d < 0 else 10 d``; terminates when the torso height z < 0.74.
Reset noise and the 76-number observation: :mod:`tasks.locomotion`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .locomotion import LocomotionConfig, LocomotionTask
from .task import CameraSpec

__all__ = ["HumanoidConfig", "HumanoidTask"]


@dataclass(frozen=True)
class HumanoidConfig(LocomotionConfig):
    """Humanoid defaults (see :class:`tasks.task.TaskConfig` and :class:`tasks.locomotion.LocomotionConfig`)."""

    episode_length: int = 1000
    substeps: int = 48
    contact_ke: float = 2.0e4
    contact_kd: float = 5.0e3
    contact_kf: float = 1.0e3
    contact_mu: float = 0.75
    action_scale: float = 0.35
    termination_height: float = 0.74
    target_height: float = 0.84
    action_penalty: float = 0.002


class HumanoidTask(LocomotionTask):
    """Humanoid; see the module docstring."""

    name = "humanoid"
    asset = "humanoid.xml"
    camera = CameraSpec(eye=(-3.0, 0.0, 1.0), target=(0.0, 0.0, 0.0), fov_deg=45.0, track="xyz", root_body="torso")
    Config = HumanoidConfig
    num_obs = 76
    noise_dim = 7 + 21 + 27
    start_height = 1.35
    start_joints = (0.0,) * 21

    def compute_reward(self, qpos, qvel, action):
        c = self.config
        d = torch.clamp(qpos[:, 2] - c.target_height, -1.0, 0.1)
        height = torch.where(d < 0, -200.0 * d * d, 10.0 * d)
        return self._common_reward(qpos, qvel) + height - c.action_penalty * (action**2).sum(-1)
