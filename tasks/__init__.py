"""Differentiable, batched articulated-body simulation in pure PyTorch and the SHAC tasks.

>>> import torch, tasks
>>> env = tasks.make("ant", 64)            # tasks.TASKS: cartpole, cartpole-swingup, hopper, ant, humanoid
>>> obs = env.reset()                       # (64, 37), seeded
>>> action = torch.zeros(64, env.num_act, requires_grad=True)
>>> obs, reward, done, info = env.step(action)
>>> reward.sum().backward()                 # d(reward)/d(action) through 16 physics substeps

``env.compile()`` compiles the physics substep and the reward/reset step with torch.compile; the step has
static shapes and no host synchronisation, so a whole SHAC iteration can be captured in one CUDA graph
(``benchmarks/sim.py`` shows how). ``env.sim.forward_dynamics(qpos, qvel, tau)`` is the contact-free
dynamics that equals MuJoCo's ``qacc``.
"""

from .device import resolve_device
from .dynamics import ContactParams, LimitParams, Simulator
from .model import ArticulatedModel, UnsupportedModelError, load_model
from .registry import TASKS, make
from .task import PHYSICS_PARTS, CameraSpec, CompiledCall, Task, TaskConfig

__all__ = [
    "PHYSICS_PARTS",
    "TASKS",
    "ArticulatedModel",
    "CameraSpec",
    "CompiledCall",
    "ContactParams",
    "LimitParams",
    "Simulator",
    "Task",
    "TaskConfig",
    "UnsupportedModelError",
    "load_model",
    "make",
    "resolve_device",
]
