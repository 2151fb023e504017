"""Compiling the physics before the first reset, with the training windows' guards.

A process that compiles only some of a trainer's parts (the run its own share while compile helpers compile the
others, or one helper its share) steps the physics twice and differentiates, so that the parts' graphs and their
backward are compiled before the first iteration, under exactly the guards the training windows will check.
"""

from __future__ import annotations

from collections.abc import Collection

import torch

from tasks import PHYSICS_PARTS

__all__ = ["compile_physics_ahead"]


def compile_physics_ahead(trainer, parts: Collection[str] | None = None) -> None:
    """Compile the physics step's ``parts`` (of ``tasks.PHYSICS_PARTS``; None: every one ``trainer`` compiles) and
    their backward before the first reset, with the training windows' guards (the cut state and the action require
    grad, grad mode on), by stepping ``trainer.task`` twice and differentiating; the other physics parts run
    eagerly meanwhile. The task's state and reset RNG are restored, so the run goes on as without this call. Does
    nothing for parts ``trainer`` does not compile.

    trainer: a ``gradlab.SHAC`` whose compiled parts are set (``trainer.compile``); its task's ``step`` is
    called as the trainer calls it (under the progress display's label, where one is set)."""
    compiled = trainer.compiled or ()
    parts = [p for p in (PHYSICS_PARTS if parts is None else parts) if p in compiled and p in PHYSICS_PARTS]
    if not parts:
        return
    task = trainer.task
    state = task.get_state()
    with torch.enable_grad(), task.running_eagerly([p for p in PHYSICS_PARTS if p not in parts]):
        task.detach(requires_grad=True)
        action = torch.zeros(task.num_envs, task.num_act, device=task.device, dtype=task.dtype, requires_grad=True)
        obs, reward, _, _ = task.step(action)
        _, reward2, _, info2 = task.step(torch.tanh(obs.sum(-1, keepdim=True)) * action)  # a later step's guards
        loss = reward.sum() + reward2.sum() + info2["obs_before_reset"].sum() + task.qpos.sum()
        loss.backward()
    task.set_state(state)
