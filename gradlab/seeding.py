"""Where a run's randomness and its device come from: one seed drives every RNG; one function picks the device.

:func:`resolve_device` (``tasks.device``, re-exported here) is the one place a ``--device`` flag becomes a
``torch.device``.
"""

from __future__ import annotations

import os
import random

import numpy as np
import torch

from tasks import resolve_device

__all__ = ["seed_everything", "rng_state", "set_rng_state", "resolve_device"]


def seed_everything(seed: int) -> None:
    """Seed Python, NumPy and torch (CPU and every CUDA device)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002 - seeds the legacy global RNG that user code may use
    torch.manual_seed(seed)
    os.environ.setdefault("PYTHONHASHSEED", str(seed))


def rng_state() -> dict:
    """Every global RNG state, for checkpoints (resume must continue the same random stream)."""
    state = {
        "python": random.getstate(),
        "numpy": np.random.get_state(),  # noqa: NPY002
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])  # noqa: NPY002
    # Generator states are host ByteTensors; a checkpoint loaded with map_location="cuda" holds them on the GPU.
    torch.set_rng_state(state["torch"].cpu())
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])
