"""Where a ``--device`` flag becomes a ``torch.device``: one function for every command and benchmark.

:func:`resolve_device` is the one place a ``--device`` flag (``auto``, ``cpu``, ``cuda``, ``cuda:N``) becomes a
``torch.device``: the trainer, ``ablate``, ``ablate-memory``, ``task-floors`` and the benchmarks all call it (it
lives in the lowest package that needs it; ``gradlab`` re-exports it), so ``auto`` means the same thing everywhere
and asking for a GPU that is not there is an error, never a silent fallback to the CPU.
"""

from __future__ import annotations

import torch

__all__ = ["resolve_device"]


def resolve_device(device: str | torch.device) -> torch.device:
    """``auto`` -> CUDA when present, else CPU; ``cpu``; ``cuda`` or ``cuda:N``, which must exist.

    Raises ValueError naming the ``--device`` value for an unknown device or a CUDA device torch cannot see.
    """
    if isinstance(device, torch.device):
        device = str(device)
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device != "cpu" and not device.startswith("cuda"):
        raise ValueError(f"unknown device {device!r}: use auto, cpu or cuda[:N]")
    try:
        resolved = torch.device(device)
    except RuntimeError:
        raise ValueError(f"unknown device {device!r}: use auto, cpu or cuda[:N]") from None
    if resolved.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"--device {device} asked for, but torch sees no CUDA device (use auto or cpu)")
        if resolved.index is not None and resolved.index >= torch.cuda.device_count():
            raise ValueError(f"--device {device}: torch sees {torch.cuda.device_count()} CUDA device(s), "
                             f"numbered from 0")
    return resolved
