"""Ant (SHAC's dflex ant): a four-legged 182 kg robot (density 1000), reward for running along +x.

Start: torso at 0.75 m, hip/ankle angles (0, 1, 0, -1, 0, -1, 0, 1) (legs bent down). Actions: 8 motors,
torque = a * 200 N m. Joint ranges: hips -40..40 deg, ankles 30..100 deg (sign per leg), as the reference's
ant.xml. Contact (dflex): ke 4e4, kd 1e4, kf 3e3, mu 0.75; joint limits ke 1e3, kd 1e1; 16 substeps; episodes
of 1000 steps (docs/tasks.md lists every constant with its source).
Reward (SHAC): ``v_x + 0.1 up + heading + (z - 0.27)``; terminates when the torso height z < 0.27.
Reset noise and the 37-number observation: :mod:`tasks.locomotion`.
"""

from __future__ import annotations

from dataclasses import dataclass

from .locomotion import LocomotionConfig, LocomotionTask
from .task import CameraSpec

__all__ = ["AntConfig", "AntTask"]


@dataclass(frozen=True)
class AntConfig(LocomotionConfig):
    """Ant defaults (see :class:`tasks.task.TaskConfig` and :class:`tasks.locomotion.LocomotionConfig`)."""

    episode_length: int = 1000
    substeps: int = 16
    contact_ke: float = 4.0e4
    contact_kd: float = 1.0e4
    contact_kf: float = 3.0e3
    contact_mu: float = 0.75
    termination_height: float = 0.27


class AntTask(LocomotionTask):
    """Ant; see the module docstring."""

    name = "ant"
    asset = "ant.xml"
    camera = CameraSpec(eye=(0.5, -2.0, 1.0), target=(0.0, 0.0, 1.0), fov_deg=90.0, track="xyz", root_body="torso")
    Config = AntConfig
    num_obs = 37
    noise_dim = 7 + 8 + 14
    start_height = 0.75
    start_joints = (0.0, 1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0)

    def compute_reward(self, qpos, qvel, action):
        return self._common_reward(qpos, qvel) + (qpos[:, 2] - self.config.termination_height)
