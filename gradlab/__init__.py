"""gradlab: the SHAC / D.Va trainer and the gradient probes.

One switch (``SHACConfig.mode``) decides what the actor sees: ``full`` (images with their graph: analytic
policy gradients through the renderer), ``decoupled`` (D.Va: the image detached at the actor's input),
``state`` (the state vector: the ceiling) or ``blind`` (a constant image: the floor); ``ModePlan`` holds what
the mode decides; presets (``gradlab.presets``) hold the reference code's hyperparameters. Probes measure
both gradients of one rollout, their norms, cosine and split by parameter group, and the policy's sensitivity
to each frame; every iteration reports CUDA-synchronised times and peak memory; a NaN/inf stops the run
naming the iteration, the horizon step and the tensor. With ``--compile`` the trainer compiles the parts of its
``compile_table`` (``COMPILE_PARTS``) and replays its iterations from CUDA graphs on a GPU.
"""

from gradlab.config import MODES, ModePlan, SHACConfig, resolve_config
from gradlab.presets import PRESETS, preset_record, preset_values
from gradlab.probes import ImageGate, NonFiniteError, cosine, flat_grad
from gradlab.seeding import resolve_device, seed_everything
from gradlab.shac import COMPILE_PARTS, SHAC

__all__ = [
    "COMPILE_PARTS",
    "MODES",
    "ModePlan",
    "SHAC",
    "SHACConfig",
    "PRESETS",
    "ImageGate",
    "NonFiniteError",
    "cosine",
    "flat_grad",
    "preset_record",
    "preset_values",
    "resolve_device",
    "resolve_config",
    "seed_everything",
]
