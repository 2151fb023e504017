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

import importlib

# Names resolve on first use (PEP 562), so that ``gradlab.cache_dirs`` can be imported before torch (``ablate``'s
# first line) without importing the trainer.
_HOMES = {
    "COMPILE_PARTS": "shac", "SHAC": "shac",
    "CompileCache": "compiling", "CompileCacheWarning": "compiling", "CompileWatch": "compiling",
    "resolve_cache_root": "cache_dirs",
    "MODES": "config", "ModePlan": "config", "SHACConfig": "config", "resolve_config": "config",
    "PRESETS": "presets", "preset_record": "presets", "preset_values": "presets",
    "ImageGate": "probes", "NonFiniteError": "probes", "cosine": "probes", "flat_grad": "probes",
    "resolve_device": "seeding", "seed_everything": "seeding",
}

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


def __getattr__(name: str):
    if name not in _HOMES:
        raise AttributeError(f"module 'gradlab' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"gradlab.{_HOMES[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
