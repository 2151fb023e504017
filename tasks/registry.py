"""Task registry: :func:`make` builds a task by name with config overrides."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch

from vocabulary import TASKS

from .ant import AntTask
from .cartpole import CartpoleSwingUpTask, CartpoleTask
from .cheetah import CheetahTask
from .hopper import HopperTask
from .humanoid import HumanoidTask
from .task import Task, config_fields

__all__ = ["TASKS", "make"]

_REGISTRY: dict[str, type[Task]] = {
    "cartpole": CartpoleTask,
    "cartpole-swingup": CartpoleSwingUpTask,
    "hopper": HopperTask,
    "ant": AntTask,
    "humanoid": HumanoidTask,
    "cheetah": CheetahTask,
}
if tuple(_REGISTRY) != TASKS:  # the names are vocabulary's; a task class without its name there is refused here
    raise ImportError(f"tasks/registry.py registers {tuple(_REGISTRY)}, vocabulary.TASKS names {TASKS}")


def make(
    name: str,
    num_envs: int,
    *,
    device: torch.device | str = "cpu",
    seed: int | Sequence[int] = 0,
    dtype: torch.dtype = torch.float32,
    **overrides,
) -> Task:
    """Build ``num_envs`` environments of task ``name`` (one of :data:`TASKS`).

    ``overrides`` replace fields of the task's config (e.g. ``episode_length=50``, ``substeps=8``,
    ``early_termination=False``, ``contact=False``); an unknown name raises ValueError listing the valid ones.
    The state starts at the nominal start pose; call :meth:`Task.reset` for a seeded random start.
    """
    if name not in _REGISTRY:
        raise ValueError(f"unknown task {name!r}; known tasks: {', '.join(TASKS)}")
    cls = _REGISTRY[name]
    valid = config_fields(cls.Config)
    unknown = sorted(set(overrides) - set(valid))
    if unknown:
        raise ValueError(f"unknown override(s) {unknown} for task {name!r}; valid: {', '.join(valid)}")
    config = dataclasses.replace(cls.Config(), **overrides)
    return cls(num_envs, device=device, seed=seed, dtype=dtype, config=config)
