"""Honest timers and memory probes.

CUDA work is asynchronous: a region is timed with CUDA events recorded on the current stream and read after
a synchronisation, so the number is the device time of everything launched inside the region. On the CPU a
perf_counter pair is the same thing. Peak memory is read after ``reset_peak_memory_stats`` so each region
reports its own peak, allocated (tensors) and reserved (the caching allocator's footprint). What a region
keeps for backward is measured by :class:`diffrender.profiling.SavedTensorMeter` (re-exported here), the one
meter the renderer's tests, its benchmark and the trainer share.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import torch

from diffrender.profiling import SavedTensorMeter

__all__ = ["RegionTimer", "MemoryProbe", "SavedTensorMeter", "median"]


def median(xs: list[float]) -> float:
    s = sorted(xs)
    n = len(s)
    if n == 0:
        return float("nan")
    return s[n // 2] if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])


@dataclass
class RegionTimer:
    """Milliseconds per named region; CUDA-synchronised on CUDA devices.

    Usage::

        timer = RegionTimer(device)
        with timer("fwd"):
            ...
        timer.ms["fwd"]
    """

    device: torch.device
    ms: dict[str, float] = field(default_factory=dict)

    @contextmanager
    def __call__(self, name: str):
        if self.device.type == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            torch.cuda.synchronize(self.device)
            start.record()
            try:
                yield
            finally:
                end.record()
                torch.cuda.synchronize(self.device)
                self.ms[name] = self.ms.get(name, 0.0) + start.elapsed_time(end)
        else:
            t0 = time.perf_counter()
            try:
                yield
            finally:
                self.ms[name] = self.ms.get(name, 0.0) + (time.perf_counter() - t0) * 1e3

    def reset(self) -> None:
        self.ms.clear()


class MemoryProbe:
    """Peak allocated / reserved MB of a region on CUDA (None on the CPU, where torch keeps no such stats)."""

    def __init__(self, device: torch.device):
        self.device = device
        self.peak_alloc_mb: float | None = None
        self.peak_reserved_mb: float | None = None

    def __enter__(self) -> MemoryProbe:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
        return self

    def __exit__(self, *exc) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.peak_alloc_mb = torch.cuda.max_memory_allocated(self.device) / 2**20
            self.peak_reserved_mb = torch.cuda.max_memory_reserved(self.device) / 2**20
