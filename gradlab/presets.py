"""Training presets: the reference code's per-task hyperparameters, as data.

A preset fills every :class:`gradlab.SHACConfig` field left at ``None``; a field given explicitly (a flag)
overrides it, and ``config.json`` records both (:func:`preset_record`). Sources, read at
HaoxiangYou/D.VA ``01b2be4`` and NVlabs/DiffRL ``a4c0dd1`` (facts, no code):

``dva`` (the default)
    D.Va's ``examples/cfg/dva/{cartpole,hopper,ant,humanoid,cheetah}.yaml``: actor/critic learning rates, target
    alpha, MLP widths, ``max_epochs`` as the length of the linear learning-rate decay (4000 cartpole, 30000
    hopper, ant and cheetah, 60000 humanoid), 64 envs. The encoder's trunk width is the actor's first MLP width
    (``models/actor.py``: ``output_dim=units[0]``). The actor's linear layers keep PyTorch's default
    initialisation (``ActorStochasticMLP`` wraps plain ``nn.Linear``), observations are normalised without
    clipping (``utils/running_mean_std.py``), and an episode that ends on its last step is bootstrapped with
    the target critic even if it failed there (``algorithms/dva.py``: only ``episode_length <
    max_episode_length`` counts as early termination). In ``--mode state`` the values are SHAC's state-based
    ones where they differ (DiffRL ``examples/cfg/shac/*.yaml``: cartpole actor lr 1e-2, critic 1e-3, decay
    500; hopper 256 envs; decay 2000 for hopper, ant, humanoid and cheetah).
``shac-diffrender``
    The paper's full-APG baseline, D.Va's ``examples/cfg/dva/diff_render_*.yaml``: the same learning rates
    and networks as ``dva``, decay over ``max_epochs`` 800 (cartpole) or 2000 (others), and the hard
    rasterizer (PyTorch3D ``MeshRasterizer`` at its default ``blur_radius=0, faces_per_pixel=1``).

``teacher``
    The experts of ``--mode distill``, D.Va's ``examples/cfg/teacher_student/teacher/<task>.yaml``: SHAC on the
    state with D.Va's networks and learning rates, 64 envs (the hopper too), and ``max_epochs`` 4000 (cartpole,
    whose actor and critic learning rates are 1e-2 and 1e-3) or 2000 (others) as the decay length.

In ``--mode distill`` (any preset) the student is D.Va's ``examples/cfg/teacher_student/<task>.yaml``: the actor
widths (the encoder's trunk their first), actor learning rate 2e-3, 64 envs, and ``max_epochs`` 10000 (humanoid
40000) as the decay length, over which ``gradlab.distill`` decays the rate per Adam step.

Other trainer choices are flags over a preset (``--actor-init orthogonal``, ``--obs-clip 5``,
``--bootstrap-last-step False``, ``--lr-decay-iters``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from vocabulary import PRESET_FIELDS, PRESET_RASTER_MODEL, PRESETS, SILHOUETTE_RASTER_MODEL

__all__ = ["PRESETS", "PRESET_FIELDS", "SILHOUETTE_RASTER_MODEL", "preset_values", "preset_record"]

# The names (the presets, the fields they set, each one's raster model) are vocabulary's; the values are here.

# D.Va examples/cfg/dva/<task>.yaml (cartpole-swingup: the spring-free variant takes D.Va's cartpole networks).
_DVA_TASKS: dict[str, dict[str, Any]] = {
    "cartpole": dict(critic_lr=2e-4, target_alpha=0.2, actor_hidden=(64, 64), critic_hidden=(64, 64),
                     lr_decay_iters=4000),
    "hopper": dict(critic_lr=2e-4, target_alpha=0.2, actor_hidden=(128, 64, 32), critic_hidden=(64, 64),
                   lr_decay_iters=30000),
    "ant": dict(critic_lr=2e-3, target_alpha=0.2, actor_hidden=(128, 64, 32), critic_hidden=(64, 64),
                lr_decay_iters=30000),
    "humanoid": dict(critic_lr=5e-4, target_alpha=0.995, actor_hidden=(256, 128), critic_hidden=(128, 128),
                     lr_decay_iters=60000),
}
_DVA_TASKS["cartpole-swingup"] = dict(_DVA_TASKS["cartpole"])
_DVA_TASKS["cheetah"] = dict(critic_lr=2e-3, target_alpha=0.2, actor_hidden=(128, 64, 32), critic_hidden=(64, 64),
                             lr_decay_iters=30000)

# D.Va examples/cfg/dva/diff_render_<task>.yaml: max_epochs only differs.
_DIFFRENDER_DECAY = {"cartpole": 800, "cartpole-swingup": 800, "hopper": 2000, "ant": 2000, "humanoid": 2000}
_DIFFRENDER_DECAY["cheetah"] = 2000

# DiffRL examples/cfg/shac/<task>.yaml, where they differ from D.Va's (state-based SHAC).
_SHAC_STATE = {
    "cartpole": dict(actor_lr=1e-2, critic_lr=1e-3, lr_decay_iters=500),
    "cartpole-swingup": dict(actor_lr=1e-2, critic_lr=1e-3, lr_decay_iters=500),
    "hopper": dict(num_envs=256, lr_decay_iters=2000),
    "ant": dict(lr_decay_iters=2000),
    "humanoid": dict(lr_decay_iters=2000),
}
_SHAC_STATE["cheetah"] = dict(lr_decay_iters=2000)

# D.Va examples/cfg/teacher_student/teacher/<task>.yaml, where they differ from dva/<task>.yaml (state SHAC, 64 envs).
_TEACHER = {
    "cartpole": dict(actor_lr=1e-2, critic_lr=1e-3, lr_decay_iters=4000),
    "cartpole-swingup": dict(actor_lr=1e-2, critic_lr=1e-3, lr_decay_iters=4000),
    "hopper": dict(lr_decay_iters=2000),
    "ant": dict(lr_decay_iters=2000),
    "humanoid": dict(lr_decay_iters=2000),
    # teacher/cheetah.yaml: max_epochs 2000, the rest as dva/cheetah.yaml (DiffRL's shac/cheetah.yaml agrees)
    "cheetah": dict(lr_decay_iters=2000),
}

# D.Va examples/cfg/teacher_student/<task>.yaml: the student's actor_mlp units and max_epochs.
_STUDENT = {
    "cartpole": dict(actor_hidden=(64, 64), lr_decay_iters=10000),
    "cartpole-swingup": dict(actor_hidden=(64, 64), lr_decay_iters=10000),
    "hopper": dict(actor_hidden=(128, 64, 32), lr_decay_iters=10000),
    "ant": dict(actor_hidden=(128, 64, 32), lr_decay_iters=10000),
    "humanoid": dict(actor_hidden=(128, 64, 32), lr_decay_iters=40000),
    "cheetah": dict(actor_hidden=(128, 64, 32), lr_decay_iters=10000),
}

_REFERENCE_TRAINER = dict(num_envs=64, actor_lr=2e-3, actor_init="default", obs_clip=0.0, bootstrap_last_step=True)


def preset_values(preset: str, task: str, mode: str) -> dict[str, Any]:
    """The values ``preset`` gives every field of :data:`PRESET_FIELDS` for ``task`` trained in ``mode``.

    Raises ValueError naming the valid presets or tasks.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; valid presets: {', '.join(PRESETS)}")
    if task not in _DVA_TASKS:
        raise ValueError(f"no preset values for task {task!r}; tasks with presets: {', '.join(_DVA_TASKS)}")
    base = _DVA_TASKS[task]
    values: dict[str, Any] = {**_REFERENCE_TRAINER, **base, "trunk_dim": base["actor_hidden"][0],
                              "raster_model": PRESET_RASTER_MODEL[preset]}
    if preset == "dva" and mode == "state":
        values.update(_SHAC_STATE[task])
    elif preset == "shac-diffrender":
        values.update(lr_decay_iters=_DIFFRENDER_DECAY[task])
    elif preset == "teacher":
        values.update(_TEACHER[task])
    if mode == "distill":
        values.update(_STUDENT[task], actor_lr=2e-3, num_envs=64, trunk_dim=_STUDENT[task]["actor_hidden"][0])
    return values


def preset_record(given: Any, resolved: Any) -> dict[str, Any]:
    """What ``config.json`` stores about the preset: its name, the values it supplied, and the fields the user
    set explicitly (flag value and the preset's value beside it).

    given: the config as the user built it (None fields unset); resolved: the same after resolution.
    """
    table = preset_values(resolved.preset, resolved.task, resolved.mode)
    given_d = dataclasses.asdict(given)
    supplied = {k: table[k] for k in PRESET_FIELDS if given_d[k] is None}
    overridden = {k: {"flag": given_d[k], "preset": table[k]} for k in PRESET_FIELDS
                  if given_d[k] is not None}
    return {"name": resolved.preset, "supplied": supplied, "overridden": overridden}
