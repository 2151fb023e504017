"""Fused backend: the rasterizer as two Triton kernels (forward, and a recomputing backward).

Same image model and the same per-pixel arithmetic as :mod:`.kernel` (the dense reference and the tiled
backend), organised for the GPU:

* **Per-face coefficients** (O(B * F)): the projected triangles become the constants of every per-pixel
  quantity, each affine in the pixel centre ``(x, y)`` [px]: screen barycentrics
  ``lambda_k = LA_k + LX_k x + LY_k y``, the position along each edge ``s_k = PA_k + PX_k x + PY_k y``, edge
  heights ``H_k``, squared edge lengths, inverse corner depths and the corners' normals and albedos: ``C = 45``
  numbers per face, laid out (B, C, F) so a kernel reads one coefficient of a block of consecutive faces with
  one coalesced load. Projection and vertex normals are PyTorch (a few ops, differentiated by autograd); the
  rest is two Triton kernels with a hand-written backward (:func:`.setup_kernels.face_setup`: coefficients,
  face boxes, block and super-block boxes); :func:`face_coefficients` is its PyTorch reference. The floor's
  per-pixel depth and colour are one more kernel (:func:`.setup_kernels.floor_planes`).
* **Forward kernel**: one program per (tile of TILE x TILE pixels, environment; 4 x 4 by default). It walks
  the faces in blocks of ``FACE_BLOCK`` on two levels (a super-block of ``SUPER_BLOCK`` blocks, then its blocks),
  skips a super-block or block whose screen bounding box misses the tile, evaluates
  the block's faces at all the tile's pixels as one (FACE_BLOCK, TILE^2) array, and blends with an online
  softmax (a running per-pixel maximum, rescaling the sums when it grows; as in flash attention). It writes
  the image and, when asked, each pixel's blend state (final maximum, denominator, the faces' weight and
  coverage sums): no pair lists, no bins, no capacity to overflow. Where the faces make many super-blocks
  (:func:`forward_splits`), each tile's walk is split between several programs, each blending its share of
  the super-blocks from an empty start, and a merge kernel combines their parts with the floor and background
  (online softmaxes merge exactly; the hard model keeps the nearest part, ties to the lowest face index).
* **Backward kernel**: one program per (tile of BWD_TILE x BWD_TILE pixels, environment; BWD_TILE_DENSE where
  faces crowd, :func:`backward_tile`) and per split of the super-blocks (:func:`backward_splits`: one split
  per 2k faces, up to 16), walking its faces as the forward does. From each pixel's
  blend state and colour (kept by the forward, or from a second forward pass), it forms the gradient of
  every pixel-face pair in closed form. Faces are taken in sub-blocks of ``BWD_SUB_BLOCK``, one face per lane:
  the face's 45 coefficients stay in registers while a loop over the tile's pixels inside the sub-block's
  face boxes (all the pixels a pair can be kept at) accumulates its 45 coefficient gradients (no cross-lane
  reductions), then one atomic add per face, coefficient and tile. A pixel
  where none of the sub-block's faces is kept is skipped, and a face whose blend weight is exactly 0 on all of
  the tile's pixels (hidden, or only inside its box's margin) and that touches no partly covered pixel
  (``sum D < 1``, where its coverage acts through ``A``) issues no atomics: every other term of its gradient
  carries that weight. A per-pixel kernel runs first: it forms the floor's gradients and, once per pixel,
  what the gradients of all the pixel's pairs share (8 numbers the backward reads per pixel instead of the
  image, state, floor and incoming gradient). The setup's backward kernel maps the coefficient
  gradients to the projected vertices, normals and colours, and autograd the rest of the way to vertices and
  camera (recomputing projection, normals, the floor and the setup's forward kernel from the saved inputs).

Every image model (``RasterSettings.raster_model``) is one pair of kernels with a compile-time ``MODEL``:
the soft models add the faces' weight and coverage sums to the online softmax and compose the colour at the
end (the floor and background start the softmax for "softmax" only); "hard" keeps a running nearest face
instead (coverage a step, no sums), and its backward differentiates only the chosen face's colour.

Saved for backward: the inputs (O(B * V)); with ``RasterSettings.save_blend_state`` also the image and four
numbers of each pixel's blend (7 numbers, O(B * H * W)), which spares the backward a second forward pass.
Flat in the number of faces either way. Requires CUDA tensors, or, for testing on a CPU,
``TRITON_INTERPRET=1`` in the environment before this module is imported (Triton's interpreter).
"""

from __future__ import annotations

import functools
import os

import torch

from ..camera import Camera
from ..floor import floor_candidate
from ..settings import RasterSettings
from .common import BBOX_MARGIN, chunks, rows
from .kernel import Static, face_validity, project, vertex_normals
from .setup_kernels import EMPTY_EXTENT, NUM_COEFFS, face_setup, floor_planes

try:  # Triton ships with CUDA builds of PyTorch; CPU-only installs usually lack it
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - exercised on machines without triton
    triton = None

__all__ = ["NUM_COEFFS", "available", "backward_splits", "backward_tile", "face_coefficients", "face_setup",
           "forward_splits", "rasterize_fused", "super_block_boxes"]

# Rows of the (B, C, F) layout (k: the edge opposite vertex k, or corner k): LA_k 0-2, LX_k 3-5, LY_k 6-8,
# PA_k 9-11, PX_k 12-14, PY_k 15-17, H_k 18-20, |e_k|^2 21-23, 1/z_k 24-26, normal_k 27-35, albedo_k 36-44.
#: pixels per tile side and faces per block of the kernels (tuned on an H200, see BENCHMARKS.md)
TILE = 4
FACE_BLOCK = 64
#: The backward kernel's tile side [px] (its own: it reads the forward's per-pixel state, not its tiling),
#: faces per sub-block (one face per lane, <= FACE_BLOCK) and warps (None: one per 32 faces).
BWD_TILE = 8
BWD_SUB_BLOCK = 64  # H100, 64 ants at 84 px, state kept: 4.35 ms forward + backward (32: 4.52; tile 4: 4.52)
BWD_WARPS: int | None = None
#: Where faces crowd (more than DENSE_FACES_PER_PIXEL per image pixel), the backward's tile side [px]
#: (see :func:`backward_tile`).
BWD_TILE_DENSE = 8
DENSE_FACES_PER_PIXEL = 1.0
#: The backward's walk over the super-blocks is split between up to BWD_MAX_SPLITS programs per tile (program s
#: takes super-blocks s, s + S, ...), one per BWD_SPLIT_SUPER_BLOCKS super-blocks (see :func:`backward_splits`).
BWD_MAX_SPLITS = 16
BWD_SPLIT_SUPER_BLOCKS = 2
#: The forward's walk is split likewise (see :func:`forward_splits`), its parts merged by a second kernel over
#: MERGE_BLOCK pixels per program (as the backward's per-pixel kernel).
FWD_MAX_SPLITS = 8
FWD_SPLIT_SUPER_BLOCKS = 4
#: numbers the split forward's parts may hold at once (fewer splits for large batches or images)
PART_ELEMS = 1 << 27
#: faces the forward evaluates at once (a block in parts of this many; <= FACE_BLOCK) and its warps (None: 4,
#: or 8 for more than 1024 face-pixel pairs at once)
FWD_SUB_BLOCK = 64
FWD_WARPS: int | None = None
#: registers per thread the forward kernel and the soft and hard models' backward kernels may use (None: the
#: compiler's choice, 255 for the backward kernels, so that only 8 warps fit on a multiprocessor). Capped, more
#: programs share a multiprocessor at the cost of spills: the soft backward, whose every pixel keeps many
#: pairs, gains (H100, 100k faces: 14.6 -> 10.6 ms; BENCHMARKS.md, section 2); the hard one and the forward lose.
FWD_MAXNREG: int | None = None
BWD_MAXNREG: int | None = 128
BWD_MAXNREG_HARD: int | None = None
MERGE_BLOCK = 256
#: face blocks per super-block: the coarse level of the kernels' walk over the faces (see
#: :func:`super_block_boxes`)
SUPER_BLOCK = 16
_BIG = EMPTY_EXTENT  # empty bounding box of a dropped face
#: per-face coefficients held at once (environments are rendered in chunks of at most this many
#: coefficients): bounds the renderer's working set at any face count. Every chunk is a kernel launch whose
#: time is at least that of its busiest tile, and a few hundred setup kernels: 64 images of 100k faces
#: fit in one chunk (1.2 GB of coefficients at float32; peak memory in BENCHMARKS.md, section 2).
COEF_ELEMS = 1 << 29
#: numbers per pixel the forward keeps for the backward besides the image (see ``_fused_forward``)
STATE_PER_PIXEL = 4
#: numbers per pixel of one part of a split forward (see ``_fused_forward``), and of the backward's per-pixel
#: part (see ``_pixel_backward``)
PART_PER_PIXEL = 6
PIX_PER_PIXEL = 8
_MODEL_CODE = {"hard": 0, "softmax": 1, "alpha": 2}  # the kernels' MODEL constant


def interpreting() -> bool:
    return os.environ.get("TRITON_INTERPRET", "0") == "1"


def available(device: torch.device) -> bool:
    """Whether the fused kernels can run on ``device`` (CUDA with Triton, or Triton's CPU interpreter)."""
    if triton is None:
        return False
    return device.type == "cuda" or (device.type == "cpu" and interpreting())


def face_coefficients(verts: torch.Tensor, normals: torch.Tensor | None, colors: torch.Tensor,
                      rotation: torch.Tensor, eye: torch.Tensor, faces: torch.Tensor, st: Static,
                      face_block: int = FACE_BLOCK) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-face constants of the per-pixel quantities, differentiable in every input.

    Args:
        verts: (B, V, 3) [m]; normals: (B, V, 3) or None (area-weighted mesh normals); colors: (V, 3) or
            (B, V, 3); rotation (B, 3, 3), eye (B, 3): camera; faces (F, 3) long; st: static settings.
    Returns:
        coef: (B, 45, Fp) with Fp = F rounded up to ``face_block`` (padding faces are dropped faces);
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
    return (_BIG * sign.to(dtype)).view(1, 4, 1)


@functools.cache
def _params(st: Static, dtype, device) -> torch.Tensor:
    """The kernels' float constants as a tensor of the images' dtype (Python floats would reach a Triton
    kernel as float32, which would cost float64 tests their precision). Cached: made once, outside any CUDA
    graph capture, and only read afterwards."""
    cap = max(0.02, 100.0 * torch.finfo(dtype).eps / st.gamma)
    vals = [st.sigma, st.gamma, st.znear, st.zfar, st.cutoff_radius, cap, st.ambient, st.diffuse,
            *st.light, *st.background]
    return torch.tensor(vals, dtype=dtype, device=device)


if triton is not None:

    @triton.jit
    def _load_params(prm):
        return (tl.load(prm + 0), tl.load(prm + 1), tl.load(prm + 2), tl.load(prm + 3), tl.load(prm + 4),
                tl.load(prm + 5), tl.load(prm + 6), tl.load(prm + 7), tl.load(prm + 8), tl.load(prm + 9),
                tl.load(prm + 10))

    @triton.jit
    def _tile_pixels(tile, W, H, TX, like, TILE_: tl.constexpr):
        """The tile's pixel centres (in ``like``'s dtype), flat indices, in-image mask and centre range."""
        ty = tile // TX
        tx = tile % TX
        k = tl.arange(0, TILE_ * TILE_)
        px = tx * TILE_ + k % TILE_
        py = ty * TILE_ + k // TILE_
        inb = (px < W) & (py < H)
        x_lo = (tx * TILE_).to(tl.float32) + 0.5
        x_hi = (tl.minimum(tx * TILE_ + TILE_, W)).to(tl.float32) - 0.5
        y_lo = (ty * TILE_).to(tl.float32) + 0.5
        y_hi = (tl.minimum(ty * TILE_ + TILE_, H)).to(tl.float32) - 0.5
        return px.to(like.dtype) + 0.5, py.to(like.dtype) + 0.5, py * W + px, inb, x_lo, x_hi, y_lo, y_hi

    @triton.jit
    def _block_touches_tile(bbox_ptr, env, NB, blk, x_lo, x_hi, y_lo, y_hi):
        """Whether face block ``blk``'s box touches the tile (a scalar)."""
        bb = bbox_ptr + env * 4 * NB + blk
        return ((tl.load(bb + NB) >= x_lo) & (tl.load(bb) <= x_hi)
                & (tl.load(bb + 3 * NB) >= y_lo) & (tl.load(bb + 2 * NB) <= y_hi))

    @triton.jit
    def _in_face_box(box_ptr, f, Fp, xc, yc):
        """(F, P): whether each pixel centre lies in each face's box. A pair outside is never kept, in the
        forward as in the backward (which walks only pixels inside its faces' boxes), so that both keep the
        same pairs even where float32 rounding puts a pixel just past a sliver's tip inside the triangle."""
        bx0 = tl.load(box_ptr + f)[:, None]
        bx1 = tl.load(box_ptr + Fp + f)[:, None]
        by0 = tl.load(box_ptr + 2 * Fp + f)[:, None]
        by1 = tl.load(box_ptr + 3 * Fp + f)[:, None]
        x = xc[None, :]
        y = yc[None, :]
        return (bx0 <= x) & (x <= bx1) & (by0 <= y) & (y <= by1)

    @triton.jit
    def _edge(cp, Fp, k: tl.constexpr, xc, yc):
        """Barycentric, signed line distance, position along the edge and squared segment distance of
        edge k at the pixels: each (FB, P)."""
        lam = tl.load(cp + (0 + k) * Fp) + tl.load(cp + (3 + k) * Fp) * xc + tl.load(cp + (6 + k) * Fp) * yc
        s = tl.load(cp + (9 + k) * Fp) + tl.load(cp + (12 + k) * Fp) * xc + tl.load(cp + (15 + k) * Fp) * yc
        h = tl.load(cp + (18 + k) * Fp)
        l2 = tl.load(cp + (21 + k) * Fp)
        dl = lam * h
        ov = s - tl.minimum(tl.maximum(s, 0.0), 1.0)
        ds = dl * dl + l2 * (ov * ov)
        return lam, s, h, l2, dl, ov, ds

    @triton.jit
    def _candidate(cp, Fp, xc, yc, zfar, znear, lx, ly, lz, ambient, diffuse):
        """Signed distance [px], normalised depth and shaded colour of every face-pixel pair: (FB, P)."""
        lam0, _, _, _, dl0, _, ds0 = _edge(cp, Fp, 0, xc, yc)
        lam1, _, _, _, dl1, _, ds1 = _edge(cp, Fp, 1, xc, yc)
        lam2, _, _, _, dl2, _, ds2 = _edge(cp, Fp, 2, xc, yc)
        dmin = tl.minimum(tl.minimum(dl0, dl1), dl2)
        dsmin = tl.minimum(tl.minimum(ds0, ds1), ds2)
        sd = tl.where(dmin >= 0, dmin, -tl.sqrt(dsmin + 1e-20))
        q0 = tl.maximum(lam0, 0.0) * tl.load(cp + 24 * Fp)
        q1 = tl.maximum(lam1, 0.0) * tl.load(cp + 25 * Fp)
        q2 = tl.maximum(lam2, 0.0) * tl.load(cp + 26 * Fp)
        qs = q0 + q1 + q2
        inv_q = 1.0 / tl.where(qs > 0, qs, 1.0)
        depth = (tl.maximum(lam0, 0.0) + tl.maximum(lam1, 0.0) + tl.maximum(lam2, 0.0)) * inv_q
        zn = (zfar - depth) / (zfar - znear)
        b0 = q0 * inv_q
        b1 = q1 * inv_q
        b2 = q2 * inv_q
        nx = b0 * tl.load(cp + 27 * Fp) + b1 * tl.load(cp + 30 * Fp) + b2 * tl.load(cp + 33 * Fp)
        ny = b0 * tl.load(cp + 28 * Fp) + b1 * tl.load(cp + 31 * Fp) + b2 * tl.load(cp + 34 * Fp)
        nz = b0 * tl.load(cp + 29 * Fp) + b1 * tl.load(cp + 32 * Fp) + b2 * tl.load(cp + 35 * Fp)
        ar = b0 * tl.load(cp + 36 * Fp) + b1 * tl.load(cp + 39 * Fp) + b2 * tl.load(cp + 42 * Fp)
        ag = b0 * tl.load(cp + 37 * Fp) + b1 * tl.load(cp + 40 * Fp) + b2 * tl.load(cp + 43 * Fp)
        ab = b0 * tl.load(cp + 38 * Fp) + b1 * tl.load(cp + 41 * Fp) + b2 * tl.load(cp + 44 * Fp)
        nl = nx * lx + ny * ly + nz * lz
        il = 1.0 / tl.sqrt(nx * nx + ny * ny + nz * nz + 1e-20)
        shade = ambient + diffuse * tl.maximum(nl * il, 0.0)
        return sd, zn, ar * shade, ag * shade, ab * shade

    @triton.jit
    def _face_chunk(cbase, fbox, fo, Fp, blk, h, xc, yc, zfar, znear, lx, ly, lz, ambient, diffuse,
                    FB: tl.constexpr, FS: tl.constexpr):
        """The ``FS`` faces ``h`` of block ``blk`` at the tile's pixels, as both forward passes walk them
        (``cbase``, ``fbox``: the environment's coefficients and face boxes; ``fo``: ``arange(FS)``): their
        indices (FS,), whether each pixel centre lies in each face's box, and each pair's signed distance,
        normalised depth and colour (``_candidate``), each (FS, P)."""
        f = blk * FB + h * FS + fo
        inbox = _in_face_box(fbox, f, Fp, xc, yc)
        sd, zn, cr, cg, cb = _candidate(cbase + f[:, None], Fp, xc[None, :], yc[None, :], zfar, znear, lx, ly, lz,
                                        ambient, diffuse)
        return f, inbox, sd, zn, cr, cg, cb

    @triton.jit
    def _blend_pass(coef_ptr, box_ptr, bbox_ptr, sbox_ptr, num_r, num_g, num_b, den, w_sum, cov_sum, m, env, Fp,
                    NB, NSB, sb0, NSPLIT,
                    xc, yc, inb, x_lo, x_hi, y_lo, y_hi,
                    sigma, gamma, znear, zfar, cutoff, cap, ambient, diffuse, lx, ly, lz,
                    FB: tl.constexpr, SB: tl.constexpr, FS: tl.constexpr):
        """Soft models: online depth softmax over the faces of super-blocks sb0, sb0 + NSPLIT, ..., starting
        from the given sums (floor and background for "softmax", zero for "alpha" and for a split's part);
        also the faces' weight sum and coverage sum."""
        fo = tl.arange(0, FS)
        cbase = coef_ptr + env * 45 * Fp
        fbox = box_ptr + env * 4 * Fp
        for sb in range(sb0, NSB, NSPLIT):  # coarse: a super-block's box, then its blocks' boxes
            if _block_touches_tile(sbox_ptr, env, NSB, sb, x_lo, x_hi, y_lo, y_hi):
                for j in range(0, SB):
                    blk = sb * SB + j
                    if _block_touches_tile(bbox_ptr, env, NB, blk, x_lo, x_hi, y_lo, y_hi):
                        for h in range(0, FB // FS):  # FS faces at a time: fewer registers per thread
                            _, inbox, sd, zn, cr, cg, cb = _face_chunk(cbase, fbox, fo, Fp, blk, h, xc, yc, zfar, znear,
                                                                       lx, ly, lz, ambient, diffuse, FB, FS)
                            keep = inbox & inb[None, :] & (sd > -cutoff)
                            m_new = tl.maximum(m, tl.max(tl.where(keep, zn, -float("inf")), axis=0))
                            scale = tl.exp((m - m_new) / gamma)
                            cov = 1.0 / (1.0 + tl.exp(tl.minimum(-sd / sigma, 80.0)))
                            w = tl.where(keep, cov * tl.exp(tl.minimum((zn - m_new[None, :]) / gamma, cap)), 0.0)
                            num_r = num_r * scale + tl.sum(w * cr, axis=0)
                            num_g = num_g * scale + tl.sum(w * cg, axis=0)
                            num_b = num_b * scale + tl.sum(w * cb, axis=0)
                            den = den * scale + tl.sum(w, axis=0)
                            w_sum = w_sum * scale + tl.sum(w, axis=0)
                            cov_sum = cov_sum + tl.sum(tl.where(keep, cov, 0.0), axis=0)
                            m = m_new
        return num_r, num_g, num_b, den, w_sum, cov_sum, m

    @triton.jit
    def _nearest_pass(coef_ptr, box_ptr, bbox_ptr, sbox_ptr, col_r, col_g, col_b, nearest, m, env, Fp, NB,
                      NSB, sb0, NSPLIT,
                      xc, yc, inb, x_lo, x_hi, y_lo, y_hi, znear, zfar, ambient, diffuse, lx, ly, lz,
                      FB: tl.constexpr, SB: tl.constexpr, FS: tl.constexpr):
        """Hard model: among the faces of super-blocks sb0, sb0 + NSPLIT, ..., the nearest face whose
        triangle contains the pixel centre, strictly nearer than ``m`` (the floor or background); the lowest
        face index among exact ties, as the faces come in order. Returns its colour, its index (as a float;
        -1 for none) and its normalised depth."""
        fo = tl.arange(0, FS)
        cbase = coef_ptr + env * 45 * Fp
        fbox = box_ptr + env * 4 * Fp
        for sb in range(sb0, NSB, NSPLIT):  # coarse: a super-block's box, then its blocks' boxes
            if _block_touches_tile(sbox_ptr, env, NSB, sb, x_lo, x_hi, y_lo, y_hi):
                for j in range(0, SB):
                    blk = sb * SB + j
                    if _block_touches_tile(bbox_ptr, env, NB, blk, x_lo, x_hi, y_lo, y_hi):
                        for h in range(0, FB // FS):
                            f, inbox, sd, zn, cr, cg, cb = _face_chunk(cbase, fbox, fo, Fp, blk, h, xc, yc, zfar, znear,
                                                                       lx, ly, lz, ambient, diffuse, FB, FS)
                            keep = inbox & inb[None, :] & (sd >= 0)
                            zk = tl.where(keep, zn, -float("inf"))
                            best = tl.max(zk, axis=0)
                            first = tl.min(tl.where(keep & (zk == best[None, :]), f[:, None], 2147483647), axis=0)
                            one = f[:, None] == first[None, :]
                            upd = best > m
                            col_r = tl.where(upd, tl.sum(tl.where(one, cr, 0.0), axis=0), col_r)
                            col_g = tl.where(upd, tl.sum(tl.where(one, cg, 0.0), axis=0), col_g)
                            col_b = tl.where(upd, tl.sum(tl.where(one, cb, 0.0), axis=0), col_b)
                            nearest = tl.where(upd, first.to(nearest.dtype), nearest)
                            m = tl.where(upd, best, m)
        return col_r, col_g, col_b, nearest, m

    @triton.jit
    def _floor_start(floor_ptr, prm, env, pix, inb, HW, gamma):
        """Per pixel: the floor's normalised depth, colour and hit flag; its relative weight against the
        background ``r_f = sigmoid(z_f / gamma)`` (0 without a hit); the colour behind the faces
        ``C_b = bg + r_f (floor - bg)``; and the background's colour."""
        bg_r = tl.load(prm + 11)
        bg_g = tl.load(prm + 12)
        bg_b = tl.load(prm + 13)
        fp = floor_ptr + env * 5 * HW + pix
        fzn = tl.load(fp, mask=inb, other=0.0)
        fr = tl.load(fp + HW, mask=inb, other=0.0)
        fg = tl.load(fp + 2 * HW, mask=inb, other=0.0)
        fb = tl.load(fp + 3 * HW, mask=inb, other=0.0)
        fhit = tl.load(fp + 4 * HW, mask=inb, other=0.0) > 0.5
        r_f = tl.where(fhit, 1.0 / (1.0 + tl.exp(-tl.where(fhit, fzn, 0.0) / gamma)), 0.0)
        return (fzn, fr, fg, fb, fhit, r_f, bg_r + r_f * (fr - bg_r), bg_g + r_f * (fg - bg_g),
                bg_b + r_f * (fb - bg_b), bg_r, bg_g, bg_b)

    @triton.jit
    def _cover_coefficients(den, w_sum, cov_sum):
        """The soft models' colour is ``kn num + kc C_b`` with ``kn = A / Q``, ``kc = (1 - A) W / Q``,
        ``Q = A den + (1 - A) W``, ``A = min(1, sum D)`` (``C_b`` alone where no face is kept). Also returns
        ``A``, ``1 / Q`` and whether a face is kept."""
        has = cov_sum > 0
        a = tl.minimum(cov_sum, 1.0)
        inv_q = 1.0 / tl.where(has, a * den + (1.0 - a) * w_sum, 1.0)
        kn = tl.where(has, a * inv_q, 0.0)
        kc = tl.where(has, (1.0 - a) * w_sum * inv_q, 1.0)
        return a, inv_q, kn, kc, has

    @triton.jit
    def _store_pixels(out_ptr, state_ptr, env, pix, inb, HW, out_r, out_g, out_b, m, s1, s2, s3,
                      SAVE: tl.constexpr):
        """Store the image at a set of pixels and, with SAVE, the blend state the backward reads."""
        op = out_ptr + env * 3 * HW + pix
        tl.store(op, out_r, mask=inb)
        tl.store(op + HW, out_g, mask=inb)
        tl.store(op + 2 * HW, out_b, mask=inb)
        if SAVE:  # what the backward needs besides the image: its first pass, done
            sp = state_ptr + env * 4 * HW + pix
            tl.store(sp, m, mask=inb)
            tl.store(sp + HW, s1, mask=inb)
            tl.store(sp + 2 * HW, s2, mask=inb)
            tl.store(sp + 3 * HW, s3, mask=inb)

    @triton.jit
    def _soft_start(fzn, fr, fg, fb, fhit, bg_r, bg_g, bg_b, gamma, MODEL: tl.constexpr):
        """The soft models' blend before any face: "softmax" starts from the background (normalised depth 0)
        and the floor as softmax candidates at the maximum ``m`` (the floor's depth where the ray hits it),
        "alpha" from nothing, with ``m`` below every face's depth (its scale underflows to 0). Returns
        ``num_r, num_g, num_b, den, m``."""
        if MODEL == 1:
            m = tl.where(fhit, fzn, 0.0)
            w_bg = tl.exp(-m / gamma)
            w_f = tl.where(fhit, 1.0, 0.0)
            num_r = w_bg * bg_r + w_f * fr
            num_g = w_bg * bg_g + w_f * fg
            num_b = w_bg * bg_b + w_f * fb
            den = w_bg + w_f
        else:
            num_r = tl.zeros_like(fzn)
            num_g = num_r
            num_b = num_r
            den = num_r
            m = num_r - 1e4
        return num_r, num_g, num_b, den, m

    @triton.jit
    def _hard_start(fzn, fr, fg, fb, fhit, bg_r, bg_g, bg_b):
        """The hard model before any face: the floor where the ray hits it, else the background (normalised
        depth 0), and no face chosen (-1). Returns the colour (3), the chosen face and ``m``."""
        m = tl.where(fhit, fzn, 0.0)
        return (tl.where(fhit, fr, bg_r), tl.where(fhit, fg, bg_g), tl.where(fhit, fb, bg_b),
                tl.full(m.shape, -1.0, m.dtype), m)

    @triton.jit
    def _soft_colour(num_r, num_g, num_b, den, w_sum, cov_sum, cb_r, cb_g, cb_b):
        """The soft models' pixel colour from the blend's sums and the colour behind the faces ``C_b``."""
        _a, _icq, kn, kc, _has = _cover_coefficients(den, w_sum, cov_sum)
        return kn * num_r + kc * cb_r, kn * num_g + kc * cb_g, kn * num_b + kc * cb_b

    @triton.jit
    def _fused_forward(coef_ptr, box_ptr, bbox_ptr, sbox_ptr, floor_ptr, prm, out_ptr, state_ptr, part_ptr, Fp,
                       NB, NSB, NSPLIT, H, W, TX, TILE_: tl.constexpr, FB: tl.constexpr, SB: tl.constexpr,
                       FS: tl.constexpr, SAVE: tl.constexpr, SPLIT: tl.constexpr, MODEL: tl.constexpr):
        """One program per (tile, environment, split). MODEL: 0 hard, 1 softmax, 2 alpha. State per pixel
        (SAVE): soft models the blend's maximum, its denominator, the faces' weight sum and coverage sum; hard
        the maximum and the chosen face (-1: none).

        Unsplit (``SPLIT`` False, one program per tile): the walk over all faces, the image and the state.
        Split: program s walks super-blocks s, s + NSPLIT, ... from an empty start and stores its part of the
        blend in ``part_ptr`` (NSPLIT, B, PART_PER_PIXEL, H, W): soft models the part's maximum, its colour
        sums (3), weight sum and coverage sum; hard the part's nearest depth, face and colour (3).
        ``_merge_forward`` then combines the parts with the floor and background."""
        tile = tl.program_id(0)
        env = tl.program_id(1).to(tl.int64)  # offsets below pass 2^31 elements for large batches and images
        split = tl.program_id(2).to(tl.int64)
        sigma, gamma, znear, zfar, cutoff, cap, ambient, diffuse, lx, ly, lz = _load_params(prm)
        xc, yc, pix, inb, x_lo, x_hi, y_lo, y_hi = _tile_pixels(tile, W, H, TX, sigma, TILE_)
        HW = H * W
        if SPLIT:
            zero = tl.zeros_like(xc)
            if MODEL == 0:
                c_r, c_g, c_b, nearest, m = _nearest_pass(
                    coef_ptr, box_ptr, bbox_ptr, sbox_ptr, zero, zero, zero, zero - 1.0, zero - 1e4, env, Fp, NB,
                    NSB, split, NSPLIT, xc, yc, inb, x_lo, x_hi, y_lo, y_hi, znear, zfar, ambient, diffuse, lx, ly,
                    lz, FB, SB, FS)
                p1, p2, p3, p4, p5 = nearest, c_r, c_g, c_b, zero
            else:
                p1, p2, p3, _den, p4, p5, m = _blend_pass(
                    coef_ptr, box_ptr, bbox_ptr, sbox_ptr, zero, zero, zero, zero, zero, zero, zero - 1e4, env, Fp,
                    NB, NSB, split, NSPLIT, xc, yc, inb, x_lo, x_hi, y_lo, y_hi, sigma, gamma, znear, zfar, cutoff,
                    cap, ambient, diffuse, lx, ly, lz, FB, SB, FS)
            pp = part_ptr + ((split * tl.num_programs(1) + env) * 6) * HW + pix
            tl.store(pp, m, mask=inb)
            tl.store(pp + HW, p1, mask=inb)
            tl.store(pp + 2 * HW, p2, mask=inb)
            tl.store(pp + 3 * HW, p3, mask=inb)
            tl.store(pp + 4 * HW, p4, mask=inb)
            tl.store(pp + 5 * HW, p5, mask=inb)
        else:
            fzn, fr, fg, fb, fhit, _, cb_r, cb_g, cb_b, bg_r, bg_g, bg_b = _floor_start(floor_ptr, prm, env, pix,
                                                                                        inb, HW, gamma)
            if MODEL == 0:
                c_r, c_g, c_b, nearest, m = _hard_start(fzn, fr, fg, fb, fhit, bg_r, bg_g, bg_b)
                out_r, out_g, out_b, nearest, m = _nearest_pass(
                    coef_ptr, box_ptr, bbox_ptr, sbox_ptr, c_r, c_g, c_b, nearest, m, env, Fp, NB, NSB, 0, 1, xc,
                    yc, inb, x_lo, x_hi, y_lo, y_hi, znear, zfar, ambient, diffuse, lx, ly, lz, FB, SB, FS)
                s1, s2, s3 = nearest, tl.zeros_like(m), tl.zeros_like(m)
            else:
                zero = tl.zeros_like(fzn)
                num_r, num_g, num_b, den, m = _soft_start(fzn, fr, fg, fb, fhit, bg_r, bg_g, bg_b, gamma, MODEL)
                num_r, num_g, num_b, den, w_sum, cov_sum, m = _blend_pass(
                    coef_ptr, box_ptr, bbox_ptr, sbox_ptr, num_r, num_g, num_b, den, zero, zero, m, env, Fp, NB,
                    NSB, 0, 1, xc, yc, inb, x_lo, x_hi, y_lo, y_hi, sigma, gamma, znear, zfar, cutoff, cap,
                    ambient, diffuse, lx, ly, lz, FB, SB, FS)
                out_r, out_g, out_b = _soft_colour(num_r, num_g, num_b, den, w_sum, cov_sum, cb_r, cb_g, cb_b)
                s1, s2, s3 = den, w_sum, cov_sum
            _store_pixels(out_ptr, state_ptr, env, pix, inb, HW, out_r, out_g, out_b, m, s1, s2, s3, SAVE)

    @triton.jit
    def _merge_forward(part_ptr, floor_ptr, prm, out_ptr, state_ptr, NSPLIT, H, W, BLOCK: tl.constexpr,
                       SAVE: tl.constexpr, MODEL: tl.constexpr):
        """The split forward's second step, one program per BLOCK pixels of one environment: the parts of
        ``_fused_forward`` combined in split order with the floor and background, then the image and state
        exactly as the unsplit forward makes them. Soft models: the parts' online softmaxes merged (each
        rescaled to the common maximum, as flash attention merges its partial blocks). Hard: the nearest
        part's face, the lowest face index among exact depth ties (the parts hold disjoint faces), kept
        only when strictly nearer than the floor or background."""
        env = tl.program_id(1).to(tl.int64)
        nenv = tl.num_programs(1)
        HW = H * W
        pix = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        inb = pix < HW
        gamma = tl.load(prm + 1)
        fzn, fr, fg, fb, fhit, _, cb_r, cb_g, cb_b, bg_r, bg_g, bg_b = _floor_start(floor_ptr, prm, env, pix, inb,
                                                                                    HW, gamma)
        if MODEL == 0:
            out_r, out_g, out_b, nearest, m = _hard_start(fzn, fr, fg, fb, fhit, bg_r, bg_g, bg_b)
            for s in range(0, NSPLIT):
                pp = part_ptr + ((s * nenv + env) * 6) * HW + pix
                m_s = tl.load(pp, mask=inb, other=-1e4)
                f_s = tl.load(pp + HW, mask=inb, other=-1.0)
                take = (f_s >= 0) & ((m_s > m) | ((m_s == m) & (nearest >= 0) & (f_s < nearest)))
                out_r = tl.where(take, tl.load(pp + 2 * HW, mask=inb, other=0.0), out_r)
                out_g = tl.where(take, tl.load(pp + 3 * HW, mask=inb, other=0.0), out_g)
                out_b = tl.where(take, tl.load(pp + 4 * HW, mask=inb, other=0.0), out_b)
                nearest = tl.where(take, f_s, nearest)
                m = tl.where(take, m_s, m)
            s1, s2, s3 = nearest, tl.zeros_like(m), tl.zeros_like(m)
        else:
            num_r, num_g, num_b, den, m = _soft_start(fzn, fr, fg, fb, fhit, bg_r, bg_g, bg_b, gamma, MODEL)
            w_sum = tl.zeros_like(m)
            cov_sum = tl.zeros_like(m)
            for s in range(0, NSPLIT):
                pp = part_ptr + ((s * nenv + env) * 6) * HW + pix
                m_s = tl.load(pp, mask=inb, other=-1e4)
                m_new = tl.maximum(m, m_s)
                scale = tl.exp((m - m_new) / gamma)
                scale_s = tl.exp((m_s - m_new) / gamma)
                w_s = tl.load(pp + 4 * HW, mask=inb, other=0.0) * scale_s
                num_r = num_r * scale + tl.load(pp + HW, mask=inb, other=0.0) * scale_s
                num_g = num_g * scale + tl.load(pp + 2 * HW, mask=inb, other=0.0) * scale_s
                num_b = num_b * scale + tl.load(pp + 3 * HW, mask=inb, other=0.0) * scale_s
                den = den * scale + w_s
                w_sum = w_sum * scale + w_s
                cov_sum = cov_sum + tl.load(pp + 5 * HW, mask=inb, other=0.0)
                m = m_new
            out_r, out_g, out_b = _soft_colour(num_r, num_g, num_b, den, w_sum, cov_sum, cb_r, cb_g, cb_b)
            s1, s2, s3 = den, w_sum, cov_sum
        _store_pixels(out_ptr, state_ptr, env, pix, inb, HW, out_r, out_g, out_b, m, s1, s2, s3, SAVE)

    @triton.jit
    def _affine_acc(ga, gx, gy, g, x, y):
        """Add one pixel's gradient ``g`` of ``c0 + c1 x + c2 y`` to the running gradients of (c0, c1, c2)."""
        return ga + g, gx + g * x, gy + g * y

    @triton.jit
    def _store_grads(gq, Fp, row: tl.constexpr, g0, g1, g2, g3, g4, g5, g6, g7, g8, live):
        """Atomically add nine consecutive coefficient rows' gradients (rows row .. row + 8) of the live faces."""
        tl.atomic_add(gq + row * Fp, g0, mask=live)
        tl.atomic_add(gq + (row + 1) * Fp, g1, mask=live)
        tl.atomic_add(gq + (row + 2) * Fp, g2, mask=live)
        tl.atomic_add(gq + (row + 3) * Fp, g3, mask=live)
        tl.atomic_add(gq + (row + 4) * Fp, g4, mask=live)
        tl.atomic_add(gq + (row + 5) * Fp, g5, mask=live)
        tl.atomic_add(gq + (row + 6) * Fp, g6, mask=live)
        tl.atomic_add(gq + (row + 7) * Fp, g7, mask=live)
        tl.atomic_add(gq + (row + 8) * Fp, g8, mask=live)

    @triton.jit
    def _pixel_backward(floor_ptr, prm, img_ptr, state_ptr, gout_ptr, gfloor_ptr, pix_ptr, H, W,
                        BLOCK: tl.constexpr, MODEL: tl.constexpr):
        """The backward's per-pixel part, one program per BLOCK pixels of one environment: the floor's
        gradients (depth, colour) and what every face's gradient at the pixel shares, stored for
        ``_fused_backward`` as PIX_PER_PIXEL numbers per pixel (consecutive, so that one memory sector holds
        them all). The floor's colour and depth reach the image through C_b (soft models), through the
        softmax's floor weight exp((z_f - m) / gamma) (softmax), or directly where it is shown (hard).

        Soft models, with ``A, 1 / Q, kn`` of :func:`_cover_coefficients`, ``g`` the pixel's incoming
        gradient, ``g_out = g . colour`` and ``g_cb = g . C_b``: the blend maximum ``m``; ``g kn`` (3), the
        gradient of a pair's colour per unit weight; ``k0 = (1 - A) (g_cb - g_out) / Q - kn g_out``, so that a
        pair's weight gradient is ``(g kn) . colour + k0``; the coverage gradient ``g_A = W (g_out - g_cb) /
        (A Q)`` where ``sum D < 1`` (else 0); and 1.0 where ``sum D < 1`` (a kept face is live there even
        at weight 0). Hard: ``m``, ``g`` (3), then 0, 0, 0 and the chosen face (-1: none)."""
        env = tl.program_id(1).to(tl.int64)
        HW = H * W
        pix = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        inb = pix < HW
        gamma = tl.load(prm + 1)
        fzn, fr, fg, fb, fhit, r_f, cb_r, cb_g, cb_b, bg_r, bg_g, bg_b = _floor_start(floor_ptr, prm, env, pix, inb,
                                                                                    HW, gamma)
        sp = state_ptr + env * 4 * HW + pix
        m_t = tl.load(sp, mask=inb, other=0.0)
        s1_t = tl.load(sp + HW, mask=inb, other=1.0)
        s2_t = tl.load(sp + 2 * HW, mask=inb, other=0.0)
        s3_t = tl.load(sp + 3 * HW, mask=inb, other=0.0)
        gp = gout_ptr + env * 3 * HW + pix
        gr_t = tl.load(gp, mask=inb, other=0.0)
        gg_t = tl.load(gp + HW, mask=inb, other=0.0)
        gb_t = tl.load(gp + 2 * HW, mask=inb, other=0.0)
        zero = tl.zeros_like(m_t)
        if MODEL == 0:
            shown = tl.where((s1_t < 0) & fhit, 1.0, 0.0)  # no face chosen and the ray hits the floor
            g_fzn = zero
            k_fc = shown
            c_r, c_g, c_b, k0, g_a, partial, chosen = gr_t, gg_t, gb_t, zero, zero, zero, s1_t
        else:
            a_t, icq_t, kn_t, kc_t, has_t = _cover_coefficients(s1_t, s2_t, s3_t)
            g_fb = gr_t * (fr - bg_r) + gg_t * (fg - bg_g) + gb_t * (fb - bg_b)
            g_fzn = tl.where(fhit, kc_t * g_fb * r_f * (1.0 - r_f) / gamma, 0.0)
            k_fc = kc_t * r_f
            ip = img_ptr + env * 3 * HW + pix
            out_r = tl.load(ip, mask=inb, other=0.0)
            out_g = tl.load(ip + HW, mask=inb, other=0.0)
            out_b = tl.load(ip + 2 * HW, mask=inb, other=0.0)
            if MODEL == 1:
                w_f = tl.where(fhit, tl.exp(tl.minimum((fzn - m_t) / gamma, 0.0)), 0.0)  # m >= fzn; no inf
                g_wf = gr_t * (fr - out_r) + gg_t * (fg - out_g) + gb_t * (fb - out_b)
                g_fzn += tl.where(fhit, kn_t * g_wf * w_f / gamma, 0.0)
                k_fc += kn_t * w_f
            g_out = gr_t * out_r + gg_t * out_g + gb_t * out_b
            g_cb = gr_t * cb_r + gg_t * cb_g + gb_t * cb_b
            # d colour / d A = W (colour - C_b) / (A Q) while sum D < 1
            part_t = has_t & (s3_t < 1.0)
            g_a = tl.where(part_t, s2_t * (g_out - g_cb) * icq_t / tl.where(part_t, a_t, 1.0), 0.0)
            k0 = (1.0 - a_t) * icq_t * (g_cb - g_out) - kn_t * g_out
            c_r, c_g, c_b = gr_t * kn_t, gg_t * kn_t, gb_t * kn_t
            partial = tl.where(part_t, 1.0, 0.0)
            chosen = zero - 1.0
        gfp = gfloor_ptr + env * 4 * HW + pix
        tl.store(gfp, g_fzn, mask=inb)
        tl.store(gfp + HW, gr_t * k_fc, mask=inb)
        tl.store(gfp + 2 * HW, gg_t * k_fc, mask=inb)
        tl.store(gfp + 3 * HW, gb_t * k_fc, mask=inb)
        pp = pix_ptr + (env * HW + pix) * 8
        tl.store(pp, m_t, mask=inb)
        tl.store(pp + 1, c_r, mask=inb)
        tl.store(pp + 2, c_g, mask=inb)
        tl.store(pp + 3, c_b, mask=inb)
        tl.store(pp + 4, k0, mask=inb)
        tl.store(pp + 5, g_a, mask=inb)
        tl.store(pp + 6, partial, mask=inb)
        tl.store(pp + 7, chosen, mask=inb)

    @triton.jit
    def _fused_backward(coef_ptr, box_ptr, bbox_ptr, sbox_ptr, prm, pix_ptr, gcoef_ptr, Fp, NB, NSB, NSPLIT, H, W,
                        TX, TILE_: tl.constexpr, FB: tl.constexpr, SB: tl.constexpr, SUB: tl.constexpr,
                        MODEL: tl.constexpr):
        """One program per (tile, environment, split): split s walks super-blocks s, s + NSPLIT, ... (each
        face's gradient is a sum over tiles, so it may come from any program). Per sub-block of SUB faces (one
        face per lane), a loop over the tile's pixels inside the faces' boxes accumulates every kept pair's
        gradient in registers from the pair's recomputed forward and the pixel's part
        (``_pixel_backward``), then one atomic add per face and coefficient (no cross-lane reductions).
        MODEL: 0 hard (only the chosen face's colour has a gradient), 1 softmax, 2 alpha."""
        tile = tl.program_id(0)
        env = tl.program_id(1).to(tl.int64)  # offsets below pass 2^31 elements for large batches and images
        split = tl.program_id(2).to(tl.int64)
        sigma, gamma, znear, zfar, cutoff, cap, ambient, diffuse, lx, ly, lz = _load_params(prm)
        _, _, _, _, x_lo, x_hi, y_lo, y_hi = _tile_pixels(tile, W, H, TX, sigma, TILE_)
        HW = H * W

        # ---- faces
        fo = tl.arange(0, SUB)
        cbase = coef_ptr + env * 45 * Fp
        gbase = gcoef_ptr + env * 45 * Fp
        inv_zr = 1.0 / (zfar - znear)
        for sb in range(split, NSB, NSPLIT):  # coarse: a super-block's box, then its blocks' boxes
            if _block_touches_tile(sbox_ptr, env, NSB, sb, x_lo, x_hi, y_lo, y_hi):
                for j in range(0, SB):
                    blk = sb * SB + j
                    if _block_touches_tile(bbox_ptr, env, NB, blk, x_lo, x_hi, y_lo, y_hi):
                        for sub in range(0, FB // SUB):
                            f = blk * FB + sub * SUB + fo
                            fbp = box_ptr + env * 4 * Fp + f
                            bx0 = tl.load(fbp)
                            bx1 = tl.load(fbp + Fp)
                            by0 = tl.load(fbp + 2 * Fp)
                            by1 = tl.load(fbp + 3 * Fp)
                            fm = (bx1 >= x_lo) & (bx0 <= x_hi) & (by1 >= y_lo) & (by0 <= y_hi)
                            if tl.max(fm.to(tl.int32), axis=0) > 0:
                                # only the tile's pixels inside some face's box can keep a pair (the box holds
                                # every pixel within the cut-off): where faces are smaller than the tile, the
                                # loop walks a few of its pixels, not all
                                u_x0 = tl.min(tl.where(fm, bx0, x_hi), axis=0)
                                u_x1 = tl.max(tl.where(fm, bx1, x_lo), axis=0)
                                u_y0 = tl.min(tl.where(fm, by0, y_hi), axis=0)
                                u_y1 = tl.max(tl.where(fm, by1, y_lo), axis=0)
                                # pixel centres px + 0.5 in [u_x0, u_x1], within the tile
                                px_lo = tl.ceil(tl.maximum(u_x0, x_lo) - 0.5).to(tl.int32)
                                px_hi = tl.floor(tl.minimum(u_x1, x_hi) - 0.5).to(tl.int32)
                                py_lo = tl.ceil(tl.maximum(u_y0, y_lo) - 0.5).to(tl.int32)
                                py_hi = tl.floor(tl.minimum(u_y1, y_hi) - 0.5).to(tl.int32)
                                span = px_hi - px_lo + 1
                                cp = cbase + f
                                la0, la1, la2 = tl.load(cp), tl.load(cp + Fp), tl.load(cp + 2 * Fp)
                                lx0, lx1, lx2 = tl.load(cp + 3 * Fp), tl.load(cp + 4 * Fp), tl.load(cp + 5 * Fp)
                                ly0, ly1, ly2 = tl.load(cp + 6 * Fp), tl.load(cp + 7 * Fp), tl.load(cp + 8 * Fp)
                                pa0, pa1, pa2 = tl.load(cp + 9 * Fp), tl.load(cp + 10 * Fp), tl.load(cp + 11 * Fp)
                                px0, px1, px2 = tl.load(cp + 12 * Fp), tl.load(cp + 13 * Fp), tl.load(cp + 14 * Fp)
                                py0, py1, py2 = tl.load(cp + 15 * Fp), tl.load(cp + 16 * Fp), tl.load(cp + 17 * Fp)
                                h0, h1, h2 = tl.load(cp + 18 * Fp), tl.load(cp + 19 * Fp), tl.load(cp + 20 * Fp)
                                l20, l21, l22 = tl.load(cp + 21 * Fp), tl.load(cp + 22 * Fp), tl.load(cp + 23 * Fp)
                                iz0, iz1, iz2 = tl.load(cp + 24 * Fp), tl.load(cp + 25 * Fp), tl.load(cp + 26 * Fp)
                                n0x, n0y, n0z = tl.load(cp + 27 * Fp), tl.load(cp + 28 * Fp), tl.load(cp + 29 * Fp)
                                n1x, n1y, n1z = tl.load(cp + 30 * Fp), tl.load(cp + 31 * Fp), tl.load(cp + 32 * Fp)
                                n2x, n2y, n2z = tl.load(cp + 33 * Fp), tl.load(cp + 34 * Fp), tl.load(cp + 35 * Fp)
                                a0r, a0g, a0b = tl.load(cp + 36 * Fp), tl.load(cp + 37 * Fp), tl.load(cp + 38 * Fp)
                                a1r, a1g, a1b = tl.load(cp + 39 * Fp), tl.load(cp + 40 * Fp), tl.load(cp + 41 * Fp)
                                a2r, a2g, a2b = tl.load(cp + 42 * Fp), tl.load(cp + 43 * Fp), tl.load(cp + 44 * Fp)
                                zero = tl.zeros([SUB], dtype=la0.dtype)
                                # the 45 coefficient gradients of the sub-block's faces, summed over the pixels
                                gla0, gla1, gla2, glx0, glx1, glx2, gly0, gly1, gly2 = (
                                    zero, zero, zero, zero, zero, zero, zero, zero, zero)
                                gpa0, gpa1, gpa2, gpx0, gpx1, gpx2, gpy0, gpy1, gpy2 = (
                                    zero, zero, zero, zero, zero, zero, zero, zero, zero)
                                gh0, gh1, gh2, gl20, gl21, gl22, giz0, giz1, giz2 = (
                                    zero, zero, zero, zero, zero, zero, zero, zero, zero)
                                gn0x, gn0y, gn0z, gn1x, gn1y, gn1z, gn2x, gn2y, gn2z = (
                                    zero, zero, zero, zero, zero, zero, zero, zero, zero)
                                ga0r, ga0g, ga0b, ga1r, ga1g, ga1b, ga2r, ga2g, ga2b = (
                                    zero, zero, zero, zero, zero, zero, zero, zero, zero)
                                wmax = zero
                                for p in range(0, span * (py_hi - py_lo + 1)):
                                    pxi = px_lo + p % span
                                    pyi = py_lo + p // span
                                    pin = (pxi < W) & (pyi < H)
                                    x = pxi.to(sigma.dtype) + 0.5
                                    y = pyi.to(sigma.dtype) + 0.5
                                    # ---- forward recompute of the pairs (face, this pixel)
                                    lam0 = la0 + lx0 * x + ly0 * y
                                    lam1 = la1 + lx1 * x + ly1 * y
                                    lam2 = la2 + lx2 * x + ly2 * y
                                    s0 = pa0 + px0 * x + py0 * y
                                    s1 = pa1 + px1 * x + py1 * y
                                    s2 = pa2 + px2 * x + py2 * y
                                    dl0 = lam0 * h0
                                    dl1 = lam1 * h1
                                    dl2 = lam2 * h2
                                    ov0 = s0 - tl.minimum(tl.maximum(s0, 0.0), 1.0)
                                    ov1 = s1 - tl.minimum(tl.maximum(s1, 0.0), 1.0)
                                    ov2 = s2 - tl.minimum(tl.maximum(s2, 0.0), 1.0)
                                    ds0 = dl0 * dl0 + l20 * (ov0 * ov0)
                                    ds1 = dl1 * dl1 + l21 * (ov1 * ov1)
                                    ds2 = dl2 * dl2 + l22 * (ov2 * ov2)
                                    dmin = tl.minimum(tl.minimum(dl0, dl1), dl2)
                                    dsmin = tl.minimum(tl.minimum(ds0, ds1), ds2)
                                    inside = dmin >= 0
                                    root = tl.sqrt(dsmin + 1e-20)
                                    sd = tl.where(inside, dmin, -root)
                                    pp = pix_ptr + (env * HW + pyi * W + pxi) * 8
                                    if MODEL == 0:  # the face the forward chose (-1: none)
                                        keep = fm & pin & (f == tl.load(pp + 7, mask=pin, other=-1.0).to(tl.int32))
                                    else:
                                        keep = (fm & pin & (sd > -cutoff) & (bx0 <= x) & (x <= bx1) & (by0 <= y)
                                                & (y <= by1))
                                    if tl.max(keep.to(tl.int32), axis=0) > 0:
                                        m = tl.load(pp)
                                        c_r = tl.load(pp + 1)
                                        c_g = tl.load(pp + 2)
                                        c_b = tl.load(pp + 3)
                                        lc0 = tl.maximum(lam0, 0.0)
                                        lc1 = tl.maximum(lam1, 0.0)
                                        lc2 = tl.maximum(lam2, 0.0)
                                        q0 = lc0 * iz0
                                        q1 = lc1 * iz1
                                        q2 = lc2 * iz2
                                        qs = q0 + q1 + q2
                                        inv_q = 1.0 / tl.where(qs > 0, qs, 1.0)
                                        lcs = lc0 + lc1 + lc2
                                        zn = (zfar - lcs * inv_q) * inv_zr
                                        cov = 1.0 / (1.0 + tl.exp(tl.minimum(-sd / sigma, 80.0)))
                                        e = (zn - m) / gamma
                                        ew = tl.exp(tl.minimum(e, cap))
                                        if MODEL == 0:
                                            w = tl.where(keep, 1.0, 0.0)
                                        else:
                                            w = tl.where(keep, cov * ew, 0.0)
                                        b0 = q0 * inv_q
                                        b1 = q1 * inv_q
                                        b2 = q2 * inv_q
                                        nx = b0 * n0x + b1 * n1x + b2 * n2x
                                        ny = b0 * n0y + b1 * n1y + b2 * n2y
                                        nz = b0 * n0z + b1 * n1z + b2 * n2z
                                        ar = b0 * a0r + b1 * a1r + b2 * a2r
                                        ag = b0 * a0g + b1 * a1g + b2 * a2g
                                        ab = b0 * a0b + b1 * a1b + b2 * a2b
                                        nl = nx * lx + ny * ly + nz * lz
                                        il = 1.0 / tl.sqrt(nx * nx + ny * ny + nz * nz + 1e-20)
                                        cosl = nl * il
                                        shade = ambient + diffuse * tl.maximum(cosl, 0.0)
                                        # ---- backward: blend (c = g kn: the pair's colour gradient per unit weight)
                                        gcr = c_r * w
                                        gcg = c_g * w
                                        gcb = c_b * w
                                        if MODEL == 0:  # the chosen face's colour is the pixel's; nothing else
                                            gzn = tl.zeros_like(w)
                                            gsd = tl.zeros_like(w)
                                            wmax = tl.maximum(wmax, w)
                                        else:
                                            k0 = tl.load(pp + 4)
                                            g_a = tl.load(pp + 5)
                                            partial = tl.load(pp + 6) > 0.5
                                            # a face weight enters num, den and W
                                            gw = tl.where(keep, (c_r * ar + c_g * ag + c_b * ab) * shade + k0, 0.0)
                                            gzn = tl.where(e < cap, gw * w / gamma, 0.0)
                                            gsd = tl.where(keep, (gw * ew + g_a) * cov * (1.0 - cov) / sigma, 0.0)
                                            # where sum D < 1 a kept face reaches the image through A even when its
                                            # depth weight is 0 (hidden): it stays live
                                            wmax = tl.maximum(wmax, tl.where(keep, tl.where(partial, 1.0, w), 0.0))
                                        # ---- colour = albedo * shade(normal)
                                        gar = gcr * shade
                                        gag = gcg * shade
                                        gab = gcb * shade
                                        gsh = tl.where(cosl > 0, (gcr * ar + gcg * ag + gcb * ab) * diffuse, 0.0)
                                        il3 = il * il * il
                                        gnx = gsh * (lx * il - nl * nx * il3)
                                        gny = gsh * (ly * il - nl * ny * il3)
                                        gnz = gsh * (lz * il - nl * nz * il3)
                                        # per-corner normals and albedos enter through the barycentrics
                                        gn0x += gnx * b0
                                        gn0y += gny * b0
                                        gn0z += gnz * b0
                                        gn1x += gnx * b1
                                        gn1y += gny * b1
                                        gn1z += gnz * b1
                                        gn2x += gnx * b2
                                        gn2y += gny * b2
                                        gn2z += gnz * b2
                                        ga0r += gar * b0
                                        ga0g += gag * b0
                                        ga0b += gab * b0
                                        ga1r += gar * b1
                                        ga1g += gag * b1
                                        ga1b += gab * b1
                                        ga2r += gar * b2
                                        ga2g += gag * b2
                                        ga2b += gab * b2
                                        # ---- barycentrics b_k = q_k / sum q, depth = sum lc / sum q, q_k = lc_k / z_k
                                        gb0 = gnx * n0x + gny * n0y + gnz * n0z + gar * a0r + gag * a0g + gab * a0b
                                        gb1 = gnx * n1x + gny * n1y + gnz * n1z + gar * a1r + gag * a1g + gab * a1b
                                        gb2 = gnx * n2x + gny * n2y + gnz * n2z + gar * a2r + gag * a2g + gab * a2b
                                        gdep = -gzn * inv_zr
                                        gbb = gb0 * b0 + gb1 * b1 + gb2 * b2
                                        gq_common = -gbb * inv_q - gdep * lcs * inv_q * inv_q
                                        gq0 = gb0 * inv_q + gq_common
                                        gq1 = gb1 * inv_q + gq_common
                                        gq2 = gb2 * inv_q + gq_common
                                        giz0 += gq0 * lc0
                                        giz1 += gq1 * lc1
                                        giz2 += gq2 * lc2
                                        glc0 = gq0 * iz0 + gdep * inv_q
                                        glc1 = gq1 * iz1 + gdep * inv_q
                                        glc2 = gq2 * iz2 + gdep * inv_q
                                        # ---- signed distance: inside the nearest edge line, outside the nearest
                                        # segment
                                        a0 = (dl0 <= dl1) & (dl0 <= dl2)
                                        a1 = (~a0) & (dl1 <= dl2)
                                        a2 = (~a0) & (~a1)
                                        gsq = tl.where(inside, 0.0, -gsd * 0.5 / root)
                                        c0 = (ds0 <= ds1) & (ds0 <= ds2)
                                        c1 = (~c0) & (ds1 <= ds2)
                                        c2 = (~c0) & (~c1)
                                        gds0 = tl.where(c0, gsq, 0.0)
                                        gds1 = tl.where(c1, gsq, 0.0)
                                        gds2 = tl.where(c2, gsq, 0.0)
                                        gdl0 = tl.where(inside & a0, gsd, 0.0) + 2.0 * dl0 * gds0
                                        gdl1 = tl.where(inside & a1, gsd, 0.0) + 2.0 * dl1 * gds1
                                        gdl2 = tl.where(inside & a2, gsd, 0.0) + 2.0 * dl2 * gds2
                                        gh0 += gdl0 * lam0
                                        gh1 += gdl1 * lam1
                                        gh2 += gdl2 * lam2
                                        gl20 += gds0 * ov0 * ov0
                                        gl21 += gds1 * ov1 * ov1
                                        gl22 += gds2 * ov2 * ov2
                                        gs0 = tl.where((s0 < 0) | (s0 > 1), 2.0 * l20 * ov0 * gds0, 0.0)
                                        gs1 = tl.where((s1 < 0) | (s1 > 1), 2.0 * l21 * ov1 * gds1, 0.0)
                                        gs2 = tl.where((s2 < 0) | (s2 > 1), 2.0 * l22 * ov2 * gds2, 0.0)
                                        glam0 = tl.where(lam0 >= 0, glc0, 0.0) + gdl0 * h0
                                        glam1 = tl.where(lam1 >= 0, glc1, 0.0) + gdl1 * h1
                                        glam2 = tl.where(lam2 >= 0, glc2, 0.0) + gdl2 * h2
                                        gla0, glx0, gly0 = _affine_acc(gla0, glx0, gly0, glam0, x, y)
                                        gla1, glx1, gly1 = _affine_acc(gla1, glx1, gly1, glam1, x, y)
                                        gla2, glx2, gly2 = _affine_acc(gla2, glx2, gly2, glam2, x, y)
                                        gpa0, gpx0, gpy0 = _affine_acc(gpa0, gpx0, gpy0, gs0, x, y)
                                        gpa1, gpx1, gpy1 = _affine_acc(gpa1, gpx1, gpy1, gs1, x, y)
                                        gpa2, gpx2, gpy2 = _affine_acc(gpa2, gpx2, gpy2, gs2, x, y)
                                # Every term of a pair's gradient carries its weight w (coverage x depth softmax),
                                # except the coverage term where sum D < 1 (counted in wmax as 1): a face whose weight
                                # is exactly 0 at all of the tile's pixels (hidden behind nearer surfaces, or only
                                # within the box margin) and that touches no partly covered pixel adds nothing, so it
                                # issues no atomics.
                                live = fm & (wmax > 0.0)
                                gq = gbase + f
                                _store_grads(gq, Fp, 0, gla0, gla1, gla2, glx0, glx1, glx2, gly0, gly1, gly2, live)
                                _store_grads(gq, Fp, 9, gpa0, gpa1, gpa2, gpx0, gpx1, gpx2, gpy0, gpy1, gpy2, live)
                                _store_grads(gq, Fp, 18, gh0, gh1, gh2, gl20, gl21, gl22, giz0, giz1, giz2, live)
                                _store_grads(gq, Fp, 27, gn0x, gn0y, gn0z, gn1x, gn1y, gn1z, gn2x, gn2y, gn2z, live)
                                _store_grads(gq, Fp, 36, ga0r, ga0g, ga0b, ga1r, ga1g, ga1b, ga2r, ga2g, ga2b, live)


def _floor_planes(rotation, eye, st: Static, dtype, device) -> torch.Tensor:
    """(B, 5, H, W): the floor's normalised depth, lit colour (3) and hit flag (1.0 / 0.0) per pixel;
    differentiable in the camera except the flag. Without a floor: never hit. PyTorch, the reference of
    :func:`.setup_kernels.floor_planes` (which renders use)."""
    b = rotation.shape[0]
    if st.floor is None:
        return torch.zeros(b, 5, st.height, st.width, dtype=dtype, device=device)
    py, px = torch.meshgrid(torch.arange(st.height, dtype=dtype, device=device) + 0.5,
                            torch.arange(st.width, dtype=dtype, device=device) + 0.5, indexing="ij")
    light_factor = st.ambient + st.diffuse * max(0.0, st.light[2])
    zn, col, hit = floor_candidate(rotation, eye, px, py, focal=st.focal, cx=st.cx, cy=st.cy, znear=st.znear,
                                   zfar=st.zfar, gamma=st.gamma, floor=st.floor, light_factor=light_factor)
    return torch.cat([zn[:, None], col.permute(0, 3, 1, 2), hit[:, None].to(dtype)], dim=1).contiguous()


def _launch_grid(st: Static, b: int, tile: int) -> tuple[tuple[int, int], int]:
    tx = -(-st.width // tile)
    ty = -(-st.height // tile)
    return (tx * ty, b), tx


def _warps(tile: int, fb: int) -> int:
    return 4 if tile * tile * fb <= 1024 else 8


def _camera_space(verts, normals, rotation, eye, faces, st: Static):
    """The setup's PyTorch part: projected vertices (B, V, 3) ``(u [px], v [px], z [m])`` and vertex normals
    (B, V, 3) (the given ones, or area-weighted mesh normals)."""
    uvz = project(verts, rotation, eye, st)
    if normals is None:
        normals = vertex_normals(verts, faces)
    return uvz, normals


def _setup(verts, normals, colors, rotation, eye, faces, st: Static, fb: int, sb: int, *, camera_space=_camera_space):
    """Everything the kernels read for one chunk of environments: :func:`.setup_kernels.face_setup`'s
    coefficients (B, 45, Fp), face boxes (B, 4, Fp), block boxes padded to whole super-blocks and super-block
    boxes, and the floor planes (B, 5, H, W) (:func:`.setup_kernels.floor_planes`). Differentiable (autograd
    through ``camera_space``, the setup kernels' own backward), O(B * F + B * H * W)."""
    uvz, normals = camera_space(verts, normals, rotation, eye, faces, st)
    coef, box, bbox, sbox = face_setup(uvz, normals, colors, faces, st, face_block=fb, super_block=sb)
    if st.floor is None:
        floor = torch.zeros(verts.shape[0], 5, st.height, st.width, dtype=verts.dtype, device=verts.device)
    else:
        floor = floor_planes(rotation, eye, st)
    return coef, box, bbox, sbox, floor


@functools.cache
def _setup_fn(compile_: bool):
    """:func:`_setup`, with its PyTorch part ``torch.compile``'d (``RasterSettings.compile``): eager, projection
    and normals are a few dozen small kernels per render and as many in the backward. The Triton setup
    kernels (faces, floor) stay outside the compiled region: they are already one launch each, and an
    autograd.Function around user Triton kernels inside a compiled graph would have to be registered as a
    custom op (with fake-tensor rules for its outputs) for dynamo to trace it, for no fewer launches."""
    if not compile_:
        return _setup
    return functools.partial(_setup, camera_space=torch.compile(_camera_space, dynamic=False))


def _max_registers(n: int | None) -> dict:
    """Launch options capping a kernel's registers per thread (None: the compiler's choice)."""
    return {} if n is None else {"maxnreg": n}


def _launch_forward(coef, box, bbox, sbox, floor, st: Static, tile: int, fb: int, out: torch.Tensor,
                    state: torch.Tensor | None) -> None:
    """Blend one chunk's image into ``out`` (b, 3, H, W) and, if ``state`` (b, 4, H, W) is given, what the
    backward needs of each pixel's blend into it (see ``_fused_forward``): one launch, or, where the faces
    make enough super-blocks (:func:`forward_splits`), a split walk and a merge (two launches and a
    transient (splits, b, PART_PER_PIXEL, H, W) of parts)."""
    (ntiles, b), tx = _launch_grid(st, out.shape[0], tile)
    # the parts are a transient of splits x the chunk's pixels: bounded like the coefficients (PART_ELEMS)
    splits = max(1, min(forward_splits(sbox.shape[2]), PART_ELEMS // (b * PART_PER_PIXEL * st.height * st.width)))
    prm = _params(st, out.dtype, out.device)
    model = _MODEL_CODE[st.raster_model]
    save = state is not None
    state = out if state is None else state
    part = (torch.empty(splits, b, PART_PER_PIXEL, st.height, st.width, dtype=out.dtype, device=out.device)
            if splits > 1 else out)
    _fused_forward[(ntiles, b, splits)](
        coef, box, bbox, sbox, floor, prm, out, state, part, coef.shape[2], bbox.shape[2], sbox.shape[2], splits,
        st.height, st.width, tx, TILE_=tile, FB=fb, SB=bbox.shape[2] // sbox.shape[2], FS=min(fb, FWD_SUB_BLOCK),
        SAVE=save, SPLIT=splits > 1, MODEL=model, num_warps=FWD_WARPS or _warps(tile, min(fb, FWD_SUB_BLOCK)),
        **_max_registers(FWD_MAXNREG))
    if splits > 1:
        _merge_forward[(triton.cdiv(st.height * st.width, MERGE_BLOCK), b)](
            part, floor, prm, out, state, splits, st.height, st.width, BLOCK=MERGE_BLOCK, SAVE=save, MODEL=model,
            num_warps=4)


def backward_tile(num_faces: int, height: int, width: int) -> int:
    """The backward kernel's tile side [px]: ``BWD_TILE``, or ``BWD_TILE_DENSE`` where there are more than
    ``DENSE_FACES_PER_PIXEL`` faces per pixel of the image. Each backward program walks its tile's pixels once
    per block of faces near it, so its time grows with (faces near the tile) x (tile area); where small faces
    crowd together (many per pixel) the smaller tile splits the busiest tiles' work over more programs."""
    return BWD_TILE_DENSE if num_faces > DENSE_FACES_PER_PIXEL * height * width else BWD_TILE


def forward_splits(num_super_blocks: int) -> int:
    """Forward programs per tile: one per ``FWD_SPLIT_SUPER_BLOCKS`` super-blocks, 1 to ``FWD_MAX_SPLITS``.
    As in the backward (:func:`backward_splits`), the few tiles where detailed meshes crowd thousands of
    faces would otherwise finish long after the rest; split, their walk is shared out and a merge kernel
    combines the parts (worth its extra launch and memory traffic only for many super-blocks)."""
    return max(1, min(FWD_MAX_SPLITS, num_super_blocks // max(1, FWD_SPLIT_SUPER_BLOCKS)))


def backward_splits(num_super_blocks: int) -> int:
    """Programs per backward tile: one per ``BWD_SPLIT_SUPER_BLOCKS`` super-blocks, 1 to ``BWD_MAX_SPLITS``.
    A program's time grows with the faces near its tile; where detailed meshes crowd thousands of faces near a
    few tiles, those tiles' programs would run long after the rest of the GPU has finished, so their walk is
    shared out. Programs of a split whose faces are all far from the tile stop after the super-block tests."""
    return max(1, min(BWD_MAX_SPLITS, num_super_blocks // max(1, BWD_SPLIT_SUPER_BLOCKS)))


class _FusedRasterize(torch.autograd.Function):
    """Environments are processed ``chunk`` at a time: the per-face coefficients of a chunk (and the
    temporaries that form them) are the renderer's whole working set, so it is bounded by
    ``COEF_ELEMS`` however many faces there are."""

    @staticmethod
    def forward(ctx, verts, normals, colors, rotation, eye, faces, st: Static, tile: int, fb: int, chunk: int,
                compile_: bool, keep_state: bool, bwd_tile: int):
        b = verts.shape[0]
        dt, dev = verts.dtype, verts.device
        setup = _setup_fn(compile_)
        out = torch.empty(b, 3, st.height, st.width, dtype=dt, device=dev)
        # per pixel: the blend's final maximum and denominator (what the backward needs besides the image);
        # kept only when asked to (settings.save_blend_state) and a gradient is wanted
        save = keep_state and any(ctx.needs_input_grad[:5])
        state = torch.empty(b, STATE_PER_PIXEL, st.height, st.width, dtype=dt, device=dev) if save else None
        for sl in chunks(b, chunk):
            coef, box, bbox, sbox, floor = setup(verts[sl], rows(normals, sl), rows(colors, sl, shared_ok=True),
                                                 rotation[sl], eye[sl], faces, st, fb, SUPER_BLOCK)
            _launch_forward(coef, box, bbox, sbox, floor, st, tile, fb, out[sl],
                            None if state is None else state[sl])
        if save:
            ctx.save_for_backward(verts, normals, colors, rotation, eye, faces, out, state)
        else:
            ctx.save_for_backward(verts, normals, colors, rotation, eye, faces)
        ctx.cfg = (st, tile, fb, chunk, compile_, save, bwd_tile)
        # an undefined incoming gradient (e.g. gradlab's closed ImageGate) stays None: no recompute at all
        ctx.set_materialize_grads(False)
        return out

    @staticmethod
    def backward(ctx, grad_img):
        st, tile, fb, chunk, compile_, saved_state, bwd_tile = ctx.cfg
        if grad_img is None:
            return (None,) * 13
        verts, normals, colors, rotation, eye, faces, *kept = ctx.saved_tensors
        setup = _setup_fn(compile_)
        need = ctx.needs_input_grad[:5]
        inputs = (verts, normals, colors, rotation, eye)
        grads = [torch.zeros_like(x) if (nd and x is not None) else None for x, nd in zip(inputs, need)]
        grad_img = grad_img.contiguous()
        dt, dev = verts.dtype, verts.device
        sub = min(fb, BWD_SUB_BLOCK)
        for sl in chunks(verts.shape[0], chunk):
            with torch.enable_grad():
                leaves = [None if x is None else rows(x, sl, shared_ok=i == 2).detach().requires_grad_(bool(nd))
                          for i, (x, nd) in enumerate(zip(inputs, need))]
                coef, box, bbox, sbox, floor = setup(*leaves, faces, st, fb, SUPER_BLOCK)
                floor_diff = floor[:, :4]  # depth and colour (the hit flag has no gradient)
            wanted = [i for i, leaf in enumerate(leaves) if leaf is not None and leaf.requires_grad]
            gcoef = torch.zeros_like(coef)
            gfloor = torch.empty(floor_diff.shape, dtype=dt, device=dev)
            outs = [(t, g) for t, g in ((coef, gcoef), (floor_diff, gfloor)) if t.requires_grad]
            if not (wanted and outs):
                continue
            if saved_state:
                out, state = kept[0][sl], kept[1][sl]
            else:  # the forward pass again, this time keeping the blend state (chunk-sized temporaries)
                nb = sl.stop - sl.start
                out = torch.empty(nb, 3, st.height, st.width, dtype=dt, device=dev)
                state = torch.empty(nb, STATE_PER_PIXEL, st.height, st.width, dtype=dt, device=dev)
                _launch_forward(coef.detach(), box, bbox, sbox, floor.detach(), st, tile, fb, out, state)
            (ntiles, nb), tx = _launch_grid(st, sl.stop - sl.start, bwd_tile)
            splits = backward_splits(sbox.shape[2])
            prm, model = _params(st, dt, dev), _MODEL_CODE[st.raster_model]
            pixel_part = torch.empty(nb, st.height * st.width, PIX_PER_PIXEL, dtype=dt, device=dev)
            _pixel_backward[(triton.cdiv(st.height * st.width, MERGE_BLOCK), nb)](
                floor.detach(), prm, out, state, grad_img[sl], gfloor, pixel_part, st.height, st.width,
                BLOCK=MERGE_BLOCK, MODEL=model, num_warps=4)
            _fused_backward[(ntiles, nb, splits)](
                coef.detach(), box, bbox, sbox, prm, pixel_part, gcoef, coef.shape[2], bbox.shape[2], sbox.shape[2],
                splits, st.height, st.width, tx, TILE_=bwd_tile, FB=fb, SB=bbox.shape[2] // sbox.shape[2], SUB=sub,
                MODEL=model, num_warps=BWD_WARPS or max(1, sub // 32),
                **_max_registers(BWD_MAXNREG_HARD if model == 0 else BWD_MAXNREG))
            parts = torch.autograd.grad([t for t, _ in outs], [leaves[i] for i in wanted], [g for _, g in outs],
                                        allow_unused=True)
            for i, g in zip(wanted, parts):
                if g is None:
                    continue
                if i == 2 and inputs[i].ndim == 2:  # shared colours: summed over the chunks
                    grads[i] += g
                else:
                    grads[i][sl] += g
        return (*grads, None, None, None, None, None, None, None, None)


def rasterize_fused(verts: torch.Tensor, normals: torch.Tensor | None, colors: torch.Tensor, camera: Camera,
                    faces: torch.Tensor, settings: RasterSettings, *, tile: int | None = None,
                    face_block: int | None = None) -> torch.Tensor:
    """Render (B, 3, H, W) with the fused Triton kernels (see :func:`diffrender.render` for the arguments;
    every ``settings.raster_model``). ``tile`` (pixels per tile side) and ``face_block`` (faces
    per block) are powers of two; None reads the module's ``TILE`` and ``FACE_BLOCK``."""
    tile = TILE if tile is None else tile
    face_block = FACE_BLOCK if face_block is None else face_block
    if triton is None:
        raise RuntimeError("the fused backend needs triton (it ships with CUDA builds of PyTorch)")
    if not available(verts.device):
        raise ValueError(f"the fused backend runs on CUDA tensors (or on the CPU under TRITON_INTERPRET=1), "
                         f"got {verts.device}")
    for name, n in (("tile", tile), ("face_block", face_block)):
        if n < 1 or n & (n - 1):
            raise ValueError(f"{name} must be a power of two, got {n}")
    st = Static.make(settings, focal=camera.focal, height=camera.height, width=camera.width, tile_h=tile,
                     tile_w=tile)
    nfp = max(1, -(-faces.shape[0] // face_block)) * face_block
    chunk = max(1, COEF_ELEMS // (NUM_COEFFS * nfp))
    return _FusedRasterize.apply(verts, normals, colors, camera.rotation, camera.eye, faces, st, tile,
                                 face_block, chunk, settings.compile, settings.save_blend_state,
                                 backward_tile(faces.shape[0], camera.height, camera.width))

