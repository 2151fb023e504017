"""gradlab: the SHAC / D.Va trainer and the gradient probes.

One switch (``SHACConfig.mode``) decides what the actor sees: ``full`` (images with their graph: analytic
policy gradients through the renderer), ``decoupled`` (D.Va: the image detached at the actor's input),
``state`` (the state vector: the ceiling) or ``blind`` (a constant image: the floor); ``ModePlan`` holds what
the mode decides; presets (``gradlab.presets``) hold the reference code's hyperparameters. Probes measure
both gradients of one rollout, their norms, cosine and split by parameter group, and the policy's sensitivity
to each frame; every iteration reports CUDA-synchronised times and peak memory; a NaN/inf stops the run
naming the iteration, the horizon step and the tensor. The trainer trains members (``SHAC([cfg, ...])``, a run
alone ``SHAC([cfg])``), built once as a ``Roster``, and answers with one entry per member. With ``--compile``
the trainer compiles the parts of its ``compile_table`` (``COMPILE_PARTS``) and replays its iterations from CUDA
graphs on a GPU.
"""

from tasks.lazy import lazy_names

# The names below are loaded at first use (PEP 562): the modules that define them import torch, and a torch-free
# submodule (gradlab.files, the atomic writers the reports use) can then be imported alone.
_WHERE = {
    "MODES": ".config", "ModePlan": ".config", "SHACConfig": ".config", "resolve_config": ".config",
    "PRESETS": ".presets", "preset_record": ".presets", "preset_values": ".presets", "ImageGate": ".probes",
    "NonFiniteError": ".probes", "cosine": ".probes", "flat_grad": ".probes", "resolve_device": ".seeding",
    "seed_everything": ".seeding", "COMPILE_PARTS": ".shac", "SHAC": ".shac", "Roster": ".roster",
}

__all__ = [
    "COMPILE_PARTS",
    "MODES",
    "ModePlan",
    "SHAC",
    "SHACConfig",
    "PRESETS",
    "ImageGate",
    "Roster",
    "NonFiniteError",
    "cosine",
    "flat_grad",
    "preset_record",
    "preset_values",
    "resolve_device",
    "resolve_config",
    "seed_everything",
]

__getattr__, __dir__ = lazy_names(globals(), _WHERE)
del lazy_names
