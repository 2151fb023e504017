"""Differentiable, batched articulated-body simulation in pure PyTorch and the SHAC tasks.

>>> import torch, tasks
>>> env = tasks.make("ant", 64)            # tasks.TASKS: cartpole, cartpole-swingup, hopper, ant, humanoid, cheetah
>>> obs = env.reset()                       # (64, 37), seeded
>>> action = torch.zeros(64, env.num_act, requires_grad=True)
>>> obs, reward, done, info = env.step(action)
>>> reward.sum().backward()                 # d(reward)/d(action) through 16 physics substeps

``env.compile()`` compiles the physics substep and the reward/reset step with torch.compile; the step has
static shapes and no host synchronisation, so a whole SHAC iteration can be captured in one CUDA graph
(``benchmarks/sim.py`` shows how). ``env.sim.forward_dynamics(qpos, qvel, tau)`` is the contact-free
dynamics that equals MuJoCo's ``qacc``.
"""

from tasks.lazy import lazy_names

# The names below are loaded at first use (PEP 562): the submodules that define them import torch, and a
# torch-free submodule (tasks.command_line, which every command parses its flags with) can then be imported
# alone, so that a command line is refused before torch is loaded.
_WHERE = {
    "resolve_device": ".device", "ContactParams": ".dynamics", "LimitParams": ".dynamics", "Simulator": ".dynamics",
    "ArticulatedModel": ".model", "UnsupportedModelError": ".model", "load_model": ".model", "TASKS": ".registry",
    "make": ".registry", "PHYSICS_PARTS": ".task", "CameraSpec": ".task", "CompiledCall": ".task", "Task": ".task",
    "TaskConfig": ".task",
}

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

__getattr__, __dir__ = lazy_names(globals(), _WHERE)
del lazy_names
