"""Cartpole swing-up (SHAC / D.Va): a cart on a rail, the pole starts hanging down.

qpos = [x (cart position, m), th (pole angle, rad; 0 = up)], qvel = [xd, thd]. Action: one motor on the
slider, force = a * 1000 N. No ground contact. The slider has dflex's cartpole limit (ke 1e2, kd 1).

Reward (SHAC's cartpole with D.Va's +10 offset): ``10 - th^2 - 0.1 thd^2 - 0.05 x^2 - 0.1 xd^2`` with ``th``
wrapped to (-pi, pi] as SHAC does (``atan2(sin th, cos th)``), so swinging up either way is rewarded.
Terminates when ``|x| > 2.5``; episodes last 240 steps. Reset: hanging (th = -pi) with uniform noise
+-pi/12 on both coordinates and +-0.05 on both velocities.
Observation (5): ``[x, xd, sin th, cos th, thd]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .task import CameraSpec, Task, TaskConfig

__all__ = ["CartpoleConfig", "CartpoleTask"]


@dataclass(frozen=True)
class CartpoleConfig(TaskConfig):
    """Cartpole defaults (see :class:`tasks.task.TaskConfig` for the fields)."""

    episode_length: int = 240
    substeps: int = 4
    contact: bool = False
    limit_ke: float = 1.0e2
    limit_kd: float = 1.0
    q_noise: float = math.pi / 12
    qd_noise: float = 0.05
    x_limit: float = 2.5


class CartpoleTask(Task):
    """Cartpole swing-up; see the module docstring."""

    name = "cartpole"
    asset = "cartpole.xml"
    camera = CameraSpec(eye=(0.0, -2.8, 1.2), target=(0.0, 0.0, 1.2), fov_deg=90.0, track="none", root_body="cart")
    Config = CartpoleConfig
    num_obs = 5
    noise_dim = 4
    config: CartpoleConfig

    def initial_state(self, u):
        c = self.config
        B = self.num_envs
        qpos = self._const([0.0, -math.pi]).expand(B, 2) + self._noise(u, 2, 0, c.q_noise)
        qvel = torch.zeros(B, 2, dtype=self.dtype, device=self.device) + self._noise(u, 2, 2, c.qd_noise)
        return qpos, qvel

    def observe(self, qpos, qvel, prev_actions):
        x, th = qpos[:, 0:1], qpos[:, 1:2]
        return torch.cat((x, qvel[:, 0:1], torch.sin(th), torch.cos(th), qvel[:, 1:2]), dim=-1)

    def compute_reward(self, qpos, qvel, action):
        x, xd, thd = qpos[:, 0], qvel[:, 0], qvel[:, 1]
        th = torch.atan2(torch.sin(qpos[:, 1]), torch.cos(qpos[:, 1]))
        return 10.0 - th**2 - 0.1 * thd**2 - 0.05 * x**2 - 0.1 * xd**2

    def compute_terminated(self, qpos, qvel):
        return qpos[:, 0].abs() > self.config.x_limit
