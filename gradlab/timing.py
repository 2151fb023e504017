"""Honest timers and memory probes.

CUDA work is asynchronous: a region is timed with CUDA events recorded on the current stream and read after
a synchronisation, so the number is the device time of everything launched inside the region. Work launched on
a second stream to run alongside a region is timed by events on that stream (``RegionTimer.concurrent``). On
the CPU a perf_counter pair is the same thing. Peak memory is read after ``reset_peak_memory_stats`` so each
region reports its own peak, allocated (tensors) and reserved (the caching allocator's footprint). What a region
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
    _pending: list = field(default_factory=list)  # (name, start, end) events of concurrent regions

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
                self._add(name, start.elapsed_time(end))
                self._settle()
        else:
            t0 = time.perf_counter()
            try:
                yield
            finally:
                self._add(name, (time.perf_counter() - t0) * 1e3)

    @contextmanager
    def concurrent(self, name: str, stream: torch.cuda.Stream):
        """Time CUDA work launched on ``stream`` while another region runs on the current stream (CUDA only).

        Events on ``stream`` bracket the work, without a synchronisation (which would serialise the two); its
        milliseconds are added when the enclosing region ends (its device-wide synchronisation has completed
        them). Use it inside a region: ``with timer("bwd"): ... with timer.concurrent("critic", side): ...``.
        """
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record(stream)
        try:
            yield
        finally:
            end.record(stream)
            self._pending.append((name, start, end))

    def _add(self, name: str, ms: float) -> None:
        self.ms[name] = self.ms.get(name, 0.0) + ms

    def _settle(self) -> None:
        pending, self._pending = self._pending, []
        for name, start, end in pending:
            self._add(name, start.elapsed_time(end))

    def reset(self) -> None:
        self.ms.clear()
        self._pending.clear()


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
