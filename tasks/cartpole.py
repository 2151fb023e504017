"""Cartpole: a cart on a rail with a pole on a hinge, the pole starting hanging down.

Two variants share the robot, the observation and the reward's form:

* ``cartpole`` is D.Va's (HaoxiangYou/D.VA ``envs/cartpole.py``): every joint has a spring of stiffness 100
  and damping 10 towards q = 0 (``tasks/assets/cartpole.xml`` says where they come from), which swings the
  pole up and holds it there even without any action; the reward carries a +10 offset and an episode
  ends when the cart leaves ``|x| <= 2.5``; reset noise +-pi/12 on both coordinates, +-0.05 on both rates.
* ``cartpole-swingup`` is SHAC's (NVlabs/DiffRL ``envs/cartpole_swing_up.py``): no springs, no joint
  damping, armature 0.01, no reward offset, no early termination; reset noise +-pi/2 on both coordinates
  and +-0.25 on both rates.

qpos = [x (cart position, m), th (pole angle, rad; 0 = up)], qvel = [xd, thd]. Action: one motor on the
slider, force = a * 1000 N. No ground contact. Both have dflex's cartpole joint limits: the slider stops
at +-4 m with ke 1e2, and kd 1 damps both joints always (dflex applies limit damping at every joint).
4 substeps per 1/60 s control step; episodes last 240 steps.

Reward: ``offset - th^2 - 0.1 thd^2 - 0.05 x^2 - 0.1 xd^2`` with ``th`` wrapped to (-pi, pi] (both
references take ``atan2(sin th, cos th)``), so swinging up either way is rewarded.
Observation (5): ``[x, xd, sin th, cos th, thd]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .task import CameraSpec, Task, TaskConfig

__all__ = ["CartpoleConfig", "CartpoleSwingUpConfig", "CartpoleSwingUpTask", "CartpoleTask"]


@dataclass(frozen=True)
class CartpoleConfig(TaskConfig):
    """D.Va's cartpole (see :class:`tasks.task.TaskConfig` for the shared fields).

    q_noise [m and rad], qd_noise [m/s and rad/s]: half-widths of the uniform reset noise on both
    coordinates and both rates. x_limit [m]: the episode ends when ``|x| > x_limit`` (with
    ``early_termination``). reward_offset: constant added to every step's reward.
    """

    episode_length: int = 240
    substeps: int = 4
    contact: bool = False
    limit_ke: float = 1.0e2
    limit_kd: float = 1.0
    q_noise: float = math.pi / 12
    qd_noise: float = 0.05
    x_limit: float = 2.5
    reward_offset: float = 10.0


@dataclass(frozen=True)
class CartpoleSwingUpConfig(CartpoleConfig):
    """SHAC's swing-up: no reward offset, no early termination and a wider reset."""

    early_termination: bool = False
    q_noise: float = math.pi / 2
    qd_noise: float = 0.25
    reward_offset: float = 0.0


class CartpoleTask(Task):
    """D.Va's cartpole; see the module docstring."""

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
        return self.config.reward_offset - th**2 - 0.1 * thd**2 - 0.05 * x**2 - 0.1 * xd**2

    def compute_terminated(self, qpos, qvel):
        return qpos[:, 0].abs() > self.config.x_limit


class CartpoleSwingUpTask(CartpoleTask):
    """SHAC's spring-free cartpole swing-up; see the module docstring."""

    name = "cartpole-swingup"
    asset = "cartpole-swingup.xml"
    Config = CartpoleSwingUpConfig
    config: CartpoleSwingUpConfig
