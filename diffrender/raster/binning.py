"""Face-to-tile binning into fixed-capacity pair lists (no gradients, static shapes, no host sync).

For each environment, every valid face's screen bounding box is expanded by the coverage cut-off radius
(plus a small margin) and cut into the tiles it touches; the (face, tile) pairs are written into a buffer of
``capacity`` slots per environment. The variable-length "one face -> several tiles" expansion is done with a
prefix sum and ``searchsorted`` instead of a host-sized ``repeat_interleave``: slot ``s`` belongs to the face
whose inclusive count prefix first exceeds ``s``. Nothing is sized from data, so the shapes are static and the
whole step can be compiled or captured. Slots beyond an environment's pair count are padding
(``pair_valid`` False); the count itself is returned so the caller can detect overflow.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .kernel import _BBOX_MARGIN, Static, face_validity, project

__all__ = ["Bins", "bin_faces", "count_pairs"]


@dataclass(frozen=True)
class Bins:
    """Pair lists of B environments.

    Attributes:
        face, tile: (B, capacity) long; valid: (B, capacity) bool.
        count: (B,) long, pairs each environment needs (> capacity means overflow: pairs were dropped).
    """

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
    r = st.cutoff_radius + _BBOX_MARGIN
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
    """Bin faces into tiles.

    Args:
        verts: (B, V, 3) [m]; rotation (B, 3, 3), eye (B, 3): camera; faces: (F, 3) long (F >= 1).
        st: static settings (tile size, cut-off radius, culling); capacity: slots per environment.
    """
    b = verts.shape[0]
    nf = faces.shape[0]
    tx0, ty0, nx, count = _face_tiles(verts, rotation, eye, faces, st)  # (B, F) each
    cum = torch.cumsum(count, dim=1)
    total = cum[:, -1]
    slots = torch.arange(capacity, device=verts.device)
    face = torch.searchsorted(cum, slots.expand(b, capacity).contiguous(), right=True).clamp(max=nf - 1)
    pair_valid = slots < total[:, None]
    local = slots - (cum.gather(1, face) - count.gather(1, face))
    nxf = nx.gather(1, face)
    tile = (ty0.gather(1, face) + local // nxf) * st.tiles_x + tx0.gather(1, face) + local % nxf
    zero = torch.zeros_like(face)
    return Bins(face=torch.where(pair_valid, face, zero), tile=torch.where(pair_valid, tile, zero),
                valid=pair_valid, count=total)
