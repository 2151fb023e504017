"""Internals shared by the raster package's modules (not part of diffrender's public API)."""

from __future__ import annotations

from collections.abc import Iterator

import torch

__all__ = ["AREA_EPS", "BBOX_MARGIN", "chunks", "rows"]

#: [px^2] faces with a smaller projected area are dropped (their barycentrics are undefined)
AREA_EPS = 1e-9
#: [px] extra binning radius: binning never misses a pair the kernel would keep
BBOX_MARGIN = 1e-3


def rows(x: torch.Tensor | None, sl: slice, *, shared_ok: bool = False) -> torch.Tensor | None:
    """Slice a per-environment tensor; shared (V, 3) colours (``shared_ok``) are used whole."""
    if x is None or (shared_ok and x.ndim == 2):
        return x
    return x[sl]


def chunks(b: int, chunk: int) -> Iterator[slice]:
    """Consecutive slices of ``chunk`` environments (the last one ragged) covering ``range(b)``."""
    for b0 in range(0, b, chunk):
        yield slice(b0, min(b, b0 + chunk))
