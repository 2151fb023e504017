"""Honest timers and memory probes.

CUDA work is asynchronous: a region is timed with CUDA events recorded on the current stream and read after
a synchronisation, so the number is the device time of everything launched inside the region. On the CPU a
perf_counter pair is the same thing. Peak memory is read after ``reset_peak_memory_stats`` so each region
reports its own peak, allocated (tensors) and reserved (the caching allocator's footprint).
"""

from __future__ import annotations

import time
import weakref
from contextlib import contextmanager
from dataclasses import dataclass, field

import torch

__all__ = ["RegionTimer", "MemoryProbe", "SavedTensorBytes", "median"]


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


class SavedTensorBytes:
    """Bytes autograd keeps for backward from the region (device-independent; works on the CPU).

    Every tensor packed for backward inside the region is tracked by a weak reference; at exit, the storages
    of those still alive (held by the graph) are summed, each storage once. Tensors saved by graph branches
    that were dropped before the region ended are not counted (their memory is gone), and no address can be
    counted twice. This is the memory a 32-step SHAC window keeps alive until ``backward``: the quantity
    that grows with mesh complexity in full mode.
    """

    def __init__(self):
        self.bytes = 0
        self._refs: list[weakref.ref] = []
        self._ctx = None

    def _pack(self, t: torch.Tensor):
        # A detached alias (same storage): returning ``t`` itself would tie a saved OUTPUT to its own grad_fn
        # in a reference cycle, keeping dropped graphs alive until the garbage collector runs.
        alias = t.detach()
        self._refs.append(weakref.ref(alias))
        return alias

    def __enter__(self) -> SavedTensorBytes:
        self._refs.clear()
        self._ctx = torch.autograd.graph.saved_tensors_hooks(self._pack, lambda t: t)
        self._ctx.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._ctx.__exit__(*exc)
        seen: dict[int, int] = {}
        for ref in self._refs:
            t = ref()
            if t is None:
                continue
            try:
                storage = t.untyped_storage()
                seen[storage.data_ptr()] = storage.nbytes()
            except (RuntimeError, NotImplementedError):  # tensors without storage (e.g. functionalised)
                seen[id(t)] = t.numel() * t.element_size()
        self._refs.clear()
        self.bytes = sum(seen.values())

    @property
    def mb(self) -> float:
        return self.bytes / 2**20
