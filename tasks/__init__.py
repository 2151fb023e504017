"""Differentiable, batched articulated-body simulation in pure PyTorch and the SHAC tasks.

>>> import tasks
>>> env = tasks.make("cartpole", 64)
>>> obs = env.reset()
>>> obs, reward, done, info = env.step(torch.zeros(64, env.num_act))
"""

from .dynamics import ContactParams, LimitParams, Simulator
from .model import ArticulatedModel, UnsupportedModelError, load_model
from .registry import TASKS, make
from .task import CameraSpec, Task, TaskConfig

__all__ = [
    "TASKS",
    "ArticulatedModel",
    "CameraSpec",
    "ContactParams",
    "LimitParams",
    "Simulator",
    "Task",
    "TaskConfig",
    "UnsupportedModelError",
    "load_model",
    "make",
]
