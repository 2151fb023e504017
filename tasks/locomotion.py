"""Shared parts of the floating-base locomotion tasks (ant, humanoid): start pose, reset noise, observation.

qpos = [torso position (3), torso quaternion w,x,y,z (4), joint angles], qvel = [torso linear velocity (world
frame, 3), torso angular velocity (body frame, 3), joint rates] (MuJoCo's free-joint convention).

Reset (SHAC): torso position + uniform +-0.1 m per axis, torso orientation rotated by an angle uniform in
+-pi/24 about a uniformly random direction (normalize(U[-0.5, 0.5]^3)), joint angles + uniform +-0.2 rad,
every velocity (root included) uniform +-0.25.

Observation (SHAC's layout, z up): ``[torso height (1), torso quaternion (4), torso linear velocity (3, world),
torso angular velocity (3, world frame as in SHAC), joint angles (n), 0.1 x joint rates (n),
up = z component of the torso z axis (1), heading = x component of the torso x axis (the target direction is
+x) (1), previous actions (n)]``: 13 + 3n numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch

from .spatial import quat_mul, quat_to_mat
from .task import Task, TaskConfig

__all__ = ["LocomotionConfig", "LocomotionTask"]


@dataclass(frozen=True)
class LocomotionConfig(TaskConfig):
    """Floating-base task defaults; noise amplitudes are half-widths of uniform distributions."""

    pos_noise: float = 0.1
    rot_noise: float = math.pi / 24
    joint_noise: float = 0.2
    vel_noise: float = 0.25
    termination_height: float = 0.27


class LocomotionTask(Task):
    """Base of ant and humanoid: subclasses set ``start_height``, ``start_joints`` and the reward."""

    start_height: ClassVar[float]
    start_joints: ClassVar[tuple[float, ...]]
    config: LocomotionConfig

    @property
    def _nj(self) -> int:
        return self.model.nq - 7

    def initial_state(self, u):
        c = self.config
        B, nj, nv = self.num_envs, self._nj, self.model.nv
        pos = self._const([0.0, 0.0, self.start_height]).expand(B, 3) + self._noise(u, 3, 0, c.pos_noise)
        quat = self._const([1.0, 0.0, 0.0, 0.0]).expand(B, 4)
        if u is not None and self.config.reset_noise:
            axis = u[:, 3:6] - 0.5
            axis = axis / torch.linalg.vector_norm(axis, dim=-1, keepdim=True).clamp_min(1e-9)
            half = 0.5 * (2.0 * u[:, 6:7] - 1.0) * c.rot_noise
            dq = torch.cat((torch.cos(half), torch.sin(half) * axis), dim=-1)
            quat = quat_mul(dq, quat)
        joints = self._const(self.start_joints).expand(B, nj) + self._noise(u, nj, 7, c.joint_noise)
        qpos = torch.cat((pos, quat, joints), dim=-1)
        qvel = torch.zeros(B, nv, dtype=self.dtype, device=self.device) + self._noise(u, nv, 7 + nj, c.vel_noise)
        return qpos, qvel

    def _torso_axes(self, qpos):
        return quat_to_mat(qpos[:, 3:7])

    def observe(self, qpos, qvel, prev_actions):
        R = self._torso_axes(qpos)
        ang_world = (R @ qvel[:, 3:6, None]).squeeze(-1)
        return torch.cat(
            (
                qpos[:, 2:3],
                qpos[:, 3:7],
                qvel[:, 0:3],
                ang_world,
                qpos[:, 7:],
                0.1 * qvel[:, 6:],
                R[:, 2, 2:3],
                R[:, 0, 0:1],
                prev_actions,
            ),
            dim=-1,
        )

    def _common_reward(self, qpos, qvel):
        """Forward velocity + 0.1 up + heading (SHAC's progress, up and heading terms)."""
        R = self._torso_axes(qpos)
        return qvel[:, 0] + 0.1 * R[:, 2, 2] + R[:, 0, 0]

    def compute_terminated(self, qpos, qvel):
        return qpos[:, 2] < self.config.termination_height
