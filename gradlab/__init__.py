"""gradlab: the SHAC / D.Va trainer and the gradient probes.

One switch (``SHACConfig.mode``) decides what the actor sees: ``full`` (images with their graph: analytic
policy gradients through the renderer), ``decoupled`` (D.Va: the image detached at the actor's input),
``state`` (the state vector: the ceiling) or ``blind`` (a constant image: the floor); ``ModePlan`` holds what
the mode decides; presets (``gradlab.presets``) hold the reference code's hyperparameters. Probes measure
both gradients of one rollout, their norms, cosine and split by parameter group, and the policy's sensitivity
to each frame; every iteration reports CUDA-synchronised times and peak memory; a NaN/inf stops the run
naming the iteration, the horizon step and the tensor. ``CompileCache`` keeps what ``--compile`` compiled in a
folder the user can see and clear; ``CompileWatch`` names the part being compiled for a progress display.
"""

from gradlab.compiling import CompileCache, CompileCacheWarning, CompileWatch, resolve_cache_root
from gradlab.config import MODES, ModePlan, SHACConfig, resolve_config
from gradlab.presets import PRESETS, preset_record, preset_values
from gradlab.probes import ImageGate, NonFiniteError, cosine, flat_grad
from gradlab.seeding import resolve_device, seed_everything
from gradlab.shac import COMPILE_PARTS, SHAC

__all__ = [
    "COMPILE_PARTS",
    "CompileCache",
    "CompileCacheWarning",
    "CompileWatch",
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
    "resolve_cache_root",
    "resolve_config",
    "seed_everything",
]
