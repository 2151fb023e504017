"""Measuring what a computation keeps alive for its backward pass."""

from __future__ import annotations

from collections.abc import Iterable

import torch

__all__ = ["SavedTensorMeter"]


class SavedTensorMeter:
    """Context manager that records every tensor autograd saves for backward while it is active.

    Bytes are counted once per storage (views and repeated saves of one tensor are not double counted).
    ``exclude`` lists tensors that exist anyway (e.g. a model's constant faces); storages they share are
    reported separately in :attr:`excluded_bytes` instead of :attr:`bytes`.

    Example::

        with SavedTensorMeter() as meter:
            img = render(verts, faces, colors, camera, settings)
        print(meter.bytes)
    """

    def __init__(self, exclude: Iterable[torch.Tensor] = ()) -> None:
        self._exclude = {self._key(t) for t in exclude}
        self._seen: dict[tuple, int] = {}
        self._hooks = torch.autograd.graph.saved_tensors_hooks(self._pack, self._unpack)

    @staticmethod
    def _key(t: torch.Tensor) -> tuple:
        s = t.untyped_storage()
        return (t.device, s.data_ptr())

    def _pack(self, t: torch.Tensor) -> torch.Tensor:
        if t.device.type != "meta":
            self._seen.setdefault(self._key(t), t.untyped_storage().nbytes())
        return t

    @staticmethod
    def _unpack(t: torch.Tensor) -> torch.Tensor:
        return t

    def __enter__(self) -> SavedTensorMeter:
        self._hooks.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._hooks.__exit__(*exc)

    @property
    def bytes(self) -> int:
        """Bytes of saved storages, excluding those of ``exclude``."""
        return sum(n for k, n in self._seen.items() if k not in self._exclude)

    @property
    def excluded_bytes(self) -> int:
        return sum(n for k, n in self._seen.items() if k in self._exclude)

    @property
    def num_storages(self) -> int:
        return len(self._seen)
