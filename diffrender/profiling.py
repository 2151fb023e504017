"""Measuring what a computation keeps alive for its backward pass."""

from __future__ import annotations

import weakref
from collections.abc import Iterable

import torch

__all__ = ["SavedTensorMeter"]


class SavedTensorMeter:
    """Bytes autograd saves for backward inside the region and still holds when the region ends.

    Every tensor packed for backward while the context is active is tracked by a weak reference; at exit the
    storages of those still alive (held by a graph the caller kept) are summed, each storage once, so views
    and repeated saves of one tensor are not double counted. Tensors saved by graph branches that were dropped
    before the region ended are not counted (their memory is gone), and because every counted storage is alive
    at the same moment no address can stand for two of them. Works on every device (it reads storages, not
    allocator statistics). This is the memory a rendered image or a SHAC window keeps until ``backward``.

    ``exclude`` lists tensors that exist anyway (e.g. a model's constant faces); storages they share are
    reported in :attr:`excluded_bytes` instead of :attr:`bytes`.

    Example::

        with SavedTensorMeter(exclude=[faces]) as meter:
            img = render(verts, faces, colors, camera, settings)   # img (and its graph) kept
        meter.bytes, meter.mb
    """

    def __init__(self, exclude: Iterable[torch.Tensor] = ()) -> None:
        self._exclude = {self._key(t) for t in exclude}
        self._refs: list[weakref.ref] = []
        self._hooks = None
        self.bytes = 0
        """Bytes of the saved storages alive at exit, excluding those of ``exclude`` (0 before exit)."""
        self.excluded_bytes = 0
        """Bytes of the saved storages alive at exit that ``exclude`` shares."""
        self.num_storages = 0
        """Distinct saved storages alive at exit (excluded ones included)."""

    @staticmethod
    def _key(t: torch.Tensor) -> tuple:
        return (t.device, t.untyped_storage().data_ptr())

    def _pack(self, t: torch.Tensor) -> torch.Tensor:
        # A detached alias (same storage): returning ``t`` itself would tie a saved OUTPUT to its own grad_fn
        # in a reference cycle, keeping dropped graphs alive until the garbage collector runs.
        alias = t.detach()
        self._refs.append(weakref.ref(alias))
        return alias

    @staticmethod
    def _unpack(t: torch.Tensor) -> torch.Tensor:
        return t

    def __enter__(self) -> SavedTensorMeter:
        self._refs.clear()
        self._hooks = torch.autograd.graph.saved_tensors_hooks(self._pack, self._unpack)
        self._hooks.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._hooks.__exit__(*exc)
        seen: dict[tuple, int] = {}
        for ref in self._refs:
            t = ref()
            if t is None or t.device.type == "meta":
                continue
            try:
                seen[self._key(t)] = t.untyped_storage().nbytes()
            except (RuntimeError, NotImplementedError):  # tensors without a storage (e.g. functionalised)
                seen[("no storage", id(t))] = t.numel() * t.element_size()
        self._refs.clear()
        self.bytes = sum(n for k, n in seen.items() if k not in self._exclude)
        self.excluded_bytes = sum(n for k, n in seen.items() if k in self._exclude)
        self.num_storages = len(seen)

    @property
    def mb(self) -> float:
        """:attr:`bytes` in MB (2**20 bytes)."""
        return self.bytes / 2**20
