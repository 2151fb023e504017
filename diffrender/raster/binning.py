"""Face-to-tile binning into a fixed-capacity pair list (no gradients, static shapes, no host sync).

For each environment, every valid face's screen bounding box is expanded by the coverage cut-off radius
(plus a small margin) and cut into the tiles it touches; the (environment, face, tile) triples of all the
environments binned together are written into one buffer of ``capacity`` slots. Pooling the slots over
environments (instead of a fixed share per environment) means the padding only has to absorb the variation
of the *total*, which is much smaller than that of the busiest environment.

The variable-length "one face -> several tiles" expansion is done with a prefix sum and ``searchsorted``
instead of a host-sized ``repeat_interleave``: slot ``s`` belongs to the (environment, face) whose inclusive
count prefix first exceeds ``s``. Nothing is sized from data, so the shapes are static and the whole step can
be compiled or captured. Slots beyond the total are padding (``valid`` False); the per-environment counts are
returned so the caller can detect overflow.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .common import BBOX_MARGIN
from .kernel import Static, face_validity, project

__all__ = ["Bins", "bin_faces", "count_pairs"]


@dataclass(frozen=True)
class Bins:
    """Pooled pair list of B environments.

    Attributes:
        env, face, tile: (capacity,) long; valid: (capacity,) bool.
        count: (B,) long, pairs each environment needs; ``count.sum() > capacity`` means overflow (pairs
            were dropped).
    """

    env: torch.Tensor
    face: torch.Tensor
    tile: torch.Tensor
    valid: torch.Tensor
    count: torch.Tensor


def _pixel_range(lo: torch.Tensor, hi: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pixels whose centre (i + 0.5) lies in [lo, hi], clamped to the image: (first, last, nonempty)."""
    # clamp before converting: far-off or non-finite coordinates must not overflow the integer cast
    lo = torch.nan_to_num(lo, nan=1e9).clamp(-2.0, size + 2.0)
    hi = torch.nan_to_num(hi, nan=-1e9).clamp(-2.0, size + 2.0)
    first = torch.ceil(lo - 0.5).long()
    last = torch.floor(hi - 0.5).long()
    nonempty = (first <= last) & (last >= 0) & (first <= size - 1)
    return first.clamp(0, size - 1), last.clamp(0, size - 1), nonempty


def _face_tiles(verts, rotation, eye, faces, st: Static):
    """Per face: first tile column/row, tile-range width, and the number of (face, tile) pairs (B, F)."""
    fuvz = project(verts, rotation, eye, st)[:, faces]  # (B, F, 3, 3)
    valid = face_validity(fuvz, st)
    r = st.cutoff_radius + BBOX_MARGIN
    u, v = fuvz[..., 0], fuvz[..., 1]
    x0, x1, xok = _pixel_range(u.amin(-1) - r, u.amax(-1) + r, st.width)
    y0, y1, yok = _pixel_range(v.amin(-1) - r, v.amax(-1) + r, st.height)
    tx0, tx1 = x0 // st.tile_w, x1 // st.tile_w
    ty0, ty1 = y0 // st.tile_h, y1 // st.tile_h
    nx = (tx1 - tx0 + 1).clamp(min=1)  # >= 1 even for empty ranges: it is a divisor below
    count = torch.where(valid & xok & yok, nx * (ty1 - ty0 + 1), torch.zeros_like(nx))
    return tx0, ty0, nx, count


@torch.no_grad()
def count_pairs(verts: torch.Tensor, rotation: torch.Tensor, eye: torch.Tensor, faces: torch.Tensor,
                st: Static) -> torch.Tensor:
    """(B,) long: the (face, tile) pairs each environment needs (what :func:`bin_faces` would fill)."""
    if faces.shape[0] == 0:
        return torch.zeros(verts.shape[0], dtype=torch.long, device=verts.device)
    return _face_tiles(verts, rotation, eye, faces, st)[3].sum(1)


@torch.no_grad()
def bin_faces(verts: torch.Tensor, rotation: torch.Tensor, eye: torch.Tensor, faces: torch.Tensor,
              st: Static, capacity: int) -> Bins:
    """Bin the faces of B environments into tiles, pooling ``capacity`` slots over the environments.

    Args:
        verts: (B, V, 3) [m]; rotation (B, 3, 3), eye (B, 3): camera; faces: (F, 3) long (F >= 1).
        st: static settings (tile size, cut-off radius, culling); capacity: slots for all B environments.
    """
    nf = faces.shape[0]
    tx0, ty0, nx, count = _face_tiles(verts, rotation, eye, faces, st)  # (B, F) each
    flat = count.reshape(-1)
    cum = torch.cumsum(flat, dim=0)
    slots = torch.arange(capacity, device=verts.device)
    idx = torch.searchsorted(cum, slots, right=True).clamp(max=flat.shape[0] - 1)  # flat (env, face)
    valid = slots < cum[-1]
    local = slots - (cum[idx] - flat[idx])
    nxf = nx.reshape(-1)[idx]
    tile = (ty0.reshape(-1)[idx] + local // nxf) * st.tiles_x + tx0.reshape(-1)[idx] + local % nxf
    zero = torch.zeros_like(idx)
    return Bins(env=torch.where(valid, idx // nf, zero), face=torch.where(valid, idx % nf, zero),
                tile=torch.where(valid, tile, zero), valid=valid, count=count.sum(1))
