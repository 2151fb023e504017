"""PyTorch references of the fused backend's setup kernels (:mod:`..setup_kernels`), which the tests hold
them to: :func:`face_coefficients` (the per-face coefficients and face and block boxes of
:func:`..setup_kernels.face_setup`), :func:`super_block_boxes` (its padded block boxes and super-block boxes)
and :func:`floor_planes` (:func:`..setup_kernels.floor_planes`). Differentiable by autograd; slow (dozens of
kernels and (B, 45, F) temporaries), which is why the renderer uses the kernels.
"""

from __future__ import annotations

import torch

from ...floor import floor_candidate
from ..common import BBOX_MARGIN
from ..kernel import Static, face_validity, project, vertex_normals
from ..setup_kernels import EMPTY_EXTENT, NUM_COEFFS
from . import tuning


def face_coefficients(verts: torch.Tensor, normals: torch.Tensor | None, colors: torch.Tensor,
                      rotation: torch.Tensor, eye: torch.Tensor, faces: torch.Tensor, st: Static,
                      face_block: int = tuning.FACE_BLOCK) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-face constants of the per-pixel quantities, differentiable in every input.

    Args:
        verts: (B, V, 3) [m]; normals: (B, V, 3) or None (area-weighted mesh normals); colors: (V, 3) or
            (B, V, 3); rotation (B, 3, 3), eye (B, 3): camera; faces (F, 3) long; st: static settings.
    Returns:
        coef: (B, 45, Fp) with Fp = F rounded up to ``face_block`` (padding faces are dropped faces); its rows
            (k: the edge opposite vertex k, or corner k): LA_k 0-2, LX_k 3-5, LY_k 6-8, PA_k 9-11, PX_k 12-14,
            PY_k 15-17, H_k 18-20, |e_k|^2 21-23, 1/z_k 24-26, normal_k 27-35, albedo_k 36-44;
        face_box: (B, 4, Fp) (x_min, x_max, y_min, y_max) [px] of the pixel centres a face can touch
            (its bounding box grown by the coverage cut-off; empty for dropped faces), no grad;
        block_box: (B, 4, Fp // face_block), the union of each block's face boxes, no grad.
    """
    b, nv, _ = verts.shape
    nf = faces.shape[0]
    if nf == 0:  # one block of padding faces keeps the kernels' shapes valid
        coef = verts.new_zeros(b, NUM_COEFFS, face_block)
        box = _empty_box(b, verts.dtype, verts.device).expand(b, 4, face_block).contiguous()
        return coef, box, box[:, :, :1].contiguous()
    uvz = project(verts, rotation, eye, st)
    if normals is None:
        normals = vertex_normals(verts, faces)
    if colors.ndim == 2:
        colors = colors.expand(b, nv, 3)
    nfp = -(-nf // face_block) * face_block
    pad = nfp - nf
    # Built in the kernels' (B, C, Fp) layout from the start, padding faces included, so the largest array
    # (45 numbers per face) is written once: at 100k faces it is most of the setup's memory traffic.
    fuvz = torch.nn.functional.pad(uvz[:, faces], (0, 0, 0, 0, 0, pad))  # (B, Fp, 3 corners, 3)
    valid = torch.nn.functional.pad(face_validity(fuvz[:, :nf].detach(), st), (0, pad), value=False)  # (B, Fp)
    # dropped faces get a harmless unit triangle so no inf/NaN is ever formed (they are never drawn)
    # (corners (0, 0), (1, 0), (0, 1) at depth 1, built from eye(3): item assignment would copy from the host)
    eye3 = torch.eye(3, dtype=verts.dtype, device=verts.device)
    dummy = torch.stack([eye3[:, 1], eye3[:, 2], torch.ones_like(eye3[:, 0])], dim=-1)
    fuvz = torch.where(valid[..., None, None], fuvz, dummy)
    u, v, z = (c.transpose(1, 2) for c in fuvz.unbind(-1))  # (B, 3 corners, Fp)
    # edge k runs from vertex k+1 (ua, va) to vertex k+2, as in kernel.render_pairs
    ua, va = u.roll(-1, 1), v.roll(-1, 1)
    ex, ey = u.roll(-2, 1) - ua, v.roll(-2, 1) - va
    area2 = ex[:, :1] * (v[:, :1] - va[:, :1]) - ey[:, :1] * (u[:, :1] - ua[:, :1])
    area2 = torch.where(area2 == 0, torch.ones_like(area2), area2)
    inv_area = 1.0 / area2
    len2 = ex * ex + ey * ey
    inv_len2 = 1.0 / len2

    def corners(attr):  # (B, V, 3) -> (B, 9, Fp), corner-major as the kernels read it
        return torch.nn.functional.pad(attr[:, faces].reshape(b, nf, 9), (0, 0, 0, pad)).transpose(1, 2)

    coef = torch.cat([
        (ey * ua - ex * va) * inv_area, -ey * inv_area, ex * inv_area,  # lambda_k
        -(ex * ua + ey * va) * inv_len2, ex * inv_len2, ey * inv_len2,  # s_k, position along edge k
        area2.abs() * torch.sqrt(inv_len2), len2, 1.0 / z,  # H_k, |e_k|^2, 1 / z_k
        corners(normals), corners(colors),
    ], dim=1).contiguous()  # (B, 45, Fp); the kernels index it as contiguous (compiled setups included)
    with torch.no_grad():
        r = st.cutoff_radius + BBOX_MARGIN
        box = torch.stack([u.amin(1) - r, u.amax(1) + r, v.amin(1) - r, v.amax(1) + r], dim=1)  # (B, 4, Fp)
        box = torch.where(valid[:, None, :], box, _empty_box(b, box.dtype, box.device)).contiguous()
        block_box = _union_boxes(box, face_block)
    return coef, box, block_box


def _union_boxes(box: torch.Tensor, group: int) -> torch.Tensor:
    """(B, 4, N) boxes -> (B, 4, N // group): the union of each run of ``group`` consecutive boxes."""
    g = box.view(box.shape[0], 4, -1, group)
    return torch.stack([g[:, 0].amin(-1), g[:, 1].amax(-1), g[:, 2].amin(-1), g[:, 3].amax(-1)], dim=1).contiguous()


def super_block_boxes(block_box: torch.Tensor, super_block: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The coarse level of the kernels' face walk: block boxes (B, 4, NB) padded with empty boxes to a
    multiple of ``super_block`` blocks, and the union of each run of ``super_block`` blocks (B, 4, NSB).
    A tile skips a whole super-block (``super_block`` x ``FACE_BLOCK`` faces) with one test, so a program's
    walk costs O(F / (FACE_BLOCK super_block)) tests plus the blocks near its tile, not O(F / FACE_BLOCK)."""
    b, _, nb = block_box.shape
    nsb = max(1, -(-nb // super_block))
    empty = _empty_box(b, block_box.dtype, block_box.device)
    padded = torch.cat([block_box, empty.expand(b, 4, nsb * super_block - nb)], dim=2).contiguous()
    return padded, _union_boxes(padded, super_block)


def _empty_box(b: int, dtype, device) -> torch.Tensor:
    """(1, 4, 1) box that touches no pixel, built on the device (a host list or item assignment would be a
    host-to-device copy, which a CUDA graph cannot capture)."""
    sign = 1 - 2 * (torch.arange(4, device=device) % 2)  # (1, -1, 1, -1)
    return (EMPTY_EXTENT * sign.to(dtype)).view(1, 4, 1)


def floor_planes(rotation, eye, st: Static, dtype, device) -> torch.Tensor:
    """(B, 5, H, W): the floor's normalised depth, lit colour (3) and hit flag (1.0 / 0.0) per pixel;
    differentiable in the camera except the flag. Without a floor: never hit. PyTorch, the reference of
    :func:`..setup_kernels.floor_planes` (which renders use)."""
    b = rotation.shape[0]
    if st.floor is None:
        return torch.zeros(b, 5, st.height, st.width, dtype=dtype, device=device)
    py, px = torch.meshgrid(torch.arange(st.height, dtype=dtype, device=device) + 0.5,
                            torch.arange(st.width, dtype=dtype, device=device) + 0.5, indexing="ij")
    light_factor = st.ambient + st.diffuse * max(0.0, st.light[2])
    zn, col, hit = floor_candidate(rotation, eye, px, py, focal=st.focal, cx=st.cx, cy=st.cy, znear=st.znear,
                                   zfar=st.zfar, gamma=st.gamma, floor=st.floor, light_factor=light_factor)
    return torch.cat([zn[:, None], col.permute(0, 3, 1, 2), hit[:, None].to(dtype)], dim=1).contiguous()

