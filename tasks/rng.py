"""Counter-based random numbers for resets: deterministic, device-independent and CUDA-graph safe.

Every call hashes (seed, counter, env, slot) with integer arithmetic on int64 tensors. There is no generator
object whose state lives on the host: the whole state is one small int64 tensor ``[seed..., counter]`` on the
task's device, and the counter is advanced IN PLACE, so a captured CUDA graph advances it on every replay
and ``torch.compile`` sees ordinary tensor ops. The same seed gives bit-identical numbers on every device.

The rows may be split into equal groups with a seed each (a population of runs simulated as one batch): group
``g`` then draws exactly the numbers that a generator of ``rows / groups`` rows and seed ``seeds[g]`` draws, so
each run's resets are those it would have alone.

The hash is a 32-bit integer finaliser (xor-shift / multiply, the "lowbias32" constants). Multiplications are
split into 16-bit halves so that no intermediate exceeds 2^48: signed int64 overflow never happens.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

__all__ = ["CounterRNG"]

_M32 = 0xFFFFFFFF


def _mul32(x: torch.Tensor, c: int) -> torch.Tensor:
    """``x * c mod 2^32`` for int64 ``x`` in [0, 2^32) without overflow."""
    lo = x & 0xFFFF
    hi = x >> 16
    return (lo * c + (((hi * (c & 0xFFFF)) & 0xFFFF) << 16)) & _M32


def _hash32(x: torch.Tensor) -> torch.Tensor:
    x = x ^ (x >> 16)
    x = _mul32(x, 0x7FEB352D)
    x = x ^ (x >> 15)
    x = _mul32(x, 0x846CA68B)
    return x ^ (x >> 16)


class CounterRNG:
    """Uniform numbers in [0, 1) for a fixed (rows, cols) shape, one fresh draw per :meth:`uniform` call.

    Args:
        rows, cols: shape of every draw (environments x random slots).
        seed: any Python int (only its low 32 bits matter), or one seed per group of rows: ``rows`` must then be
            a multiple of ``len(seed)``, and group ``g`` (rows ``g * rows / G`` onwards) draws what a generator
            of ``rows / G`` rows seeded ``seed[g]`` draws.
        device: where the state and the draws live.
    """

    def __init__(self, rows: int, cols: int, *, seed: int | Sequence[int], device: torch.device | str) -> None:
        seeds = [seed] if isinstance(seed, int) else [int(s) for s in seed]
        if not seeds or rows % len(seeds):
            raise ValueError(f"CounterRNG: {rows} rows cannot be split into {len(seeds)} equal seed groups")
        self.shape = (rows, cols)
        self.groups = len(seeds)
        self.device = torch.device(device)
        self.state = torch.tensor([*(s & _M32 for s in seeds), 0], dtype=torch.long, device=self.device)
        # distinct 32-bit counters per element of a group; rows * cols < 2^32 for any realistic batch
        per_group = rows // self.groups
        self._index = torch.arange(per_group * cols, dtype=torch.long, device=self.device).reshape(1, per_group, cols)

    def uniform(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """Return a (rows, cols) tensor of uniforms in [0, 1) and advance the counter in place."""
        seeds, counter = self.state[:-1], self.state[-1]
        k1 = _hash32(_hash32(seeds) ^ (counter & _M32))[:, None, None]
        k2 = _hash32((k1 + 0x9E3779B9) & _M32)
        x = _hash32(_hash32(self._index ^ k1) ^ k2).reshape(self.shape)
        self.state[-1:].add_(1)
        # 24 random bits: exact in float32 and float64, never 1.0
        return (x >> 8).to(dtype) * (1.0 / (1 << 24))

    def get_state(self) -> torch.Tensor:
        """A copy of ``[seed..., counter]`` (int64, on the device): ``groups + 1`` entries."""
        return self.state.clone()

    def set_state(self, state: torch.Tensor) -> None:
        """Restore a state from :meth:`get_state` (copied in place, so captured graphs keep working)."""
        if tuple(state.shape) != tuple(self.state.shape):
            raise ValueError(f"CounterRNG.set_state: state has shape {tuple(state.shape)}, expected "
                             f"{tuple(self.state.shape)} ({self.groups} seed(s) and the counter)")
        self.state.copy_(state.to(self.state.device))
