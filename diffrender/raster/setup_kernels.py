"""The fused backend's per-face setup as two Triton kernels, with a hand-written backward.

:func:`face_setup` takes the projected vertices and the vertex normals and colours, and writes what the
raster kernels of :mod:`.fused` read: each face's 45 coefficients in the (B, 45, Fp) layout documented in
:func:`.fused.face_coefficients` (the slow PyTorch reference it matches), each face's screen box, each face
block's box (padded with empty boxes to whole super-blocks) and each super-block's box. One program per
(block of ``face_block`` faces, environment) gathers its faces' corners, applies
:func:`.kernel.face_validity`'s rule (a dropped face becomes the unit triangle, as in the reference), writes
the block's 45 rows with coalesced stores and reduces the block's box in registers; a second, tiny kernel
reduces each super-block's box.

The backward recomputes each face's intermediates from the same inputs (a few dozen flops per face, cheaper
than saving them) and adds each face's gradient into its corners' vertices with atomic adds: into the
projected vertices (only for kept faces: a dropped face's corners are a constant triangle), the normals and
the colours (for every real face, as autograd differentiates the reference; a zero gradient issues no atomic).
Its time follows the memory traffic: the coefficient gradients read once, three gathers per face.

:func:`floor_planes` is the analytic floor of :func:`diffrender.floor.floor_candidate` at every pixel centre
(its reference) as one kernel, and its backward one more: per-pixel gradients summed over each program's
pixels, then twelve atomic adds per program into the camera's rotation and eye.
"""

from __future__ import annotations

import functools
import math

import torch

from ..floor import _FAR_FLOOR_MARGIN, _MAX_SHARPNESS
from .common import AREA_EPS, BBOX_MARGIN
from .kernel import Static

try:  # Triton ships with CUDA builds of PyTorch; CPU-only installs usually lack it
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - exercised on machines without triton
    triton = None

__all__ = ["EMPTY_EXTENT", "NUM_COEFFS", "face_setup", "floor_planes"]

NUM_COEFFS = 45
#: [px] the corners of an empty box (x_min = y_min = EMPTY_EXTENT, x_max = y_max = -EMPTY_EXTENT): it
#: touches no pixel, and a union with it changes nothing
EMPTY_EXTENT = 1e30


@functools.cache
def _setup_params(st: Static, dtype, device) -> torch.Tensor:
    """(znear [m], box growth [px], AREA_EPS [px^2]) in the vertices' dtype, so the kernels compare and round
    as the reference does (a Python float reaches a Triton kernel as float32). Cached: made once, outside
    any CUDA graph capture, and only read afterwards."""
    return torch.tensor([st.znear, st.cutoff_radius + BBOX_MARGIN, AREA_EPS], dtype=dtype, device=device)


#: pixels per program of the floor kernels
FLOOR_BLOCK = 256
_FLOOR_PARAMS = 17


@functools.cache
def _floor_params(st: Static, dtype, device) -> torch.Tensor:
    """The floor's constants in the images' dtype, each rounded as :func:`diffrender.floor.floor_candidate`
    rounds it (a Python float meets a tensor in the tensor's dtype): cx, cy, focal [px], znear, zfar,
    zfar - znear [m], the normalised depth's floor, square size [m], pi * edge_px, pi, light factor, colour b
    (3) and colour a - b (3). Cached as :func:`_setup_params`."""
    fl = st.floor
    light = st.ambient + st.diffuse * max(0.0, st.light[2])
    vals = [st.cx, st.cy, st.focal, st.znear, st.zfar, st.zfar - st.znear, _FAR_FLOOR_MARGIN * st.gamma,
            fl.square_size, math.pi * fl.edge_px, math.pi, light, *fl.color_b,
            *(a - b for a, b in zip(fl.color_a, fl.color_b))]
    return torch.tensor(vals, dtype=dtype, device=device)


def _warps(face_block: int) -> int:
    return max(1, min(8, face_block // 32))


if triton is not None:
    # a jitted function reads module globals only as constexpr
    _EMPTY = tl.constexpr(EMPTY_EXTENT)
    _MAX_SHARP = tl.constexpr(_MAX_SHARPNESS)

    @triton.jit
    def _corners(uvz_ptr, faces_ptr, f, real, env_v):
        """The vertex indices and projected corners ``(u, v, z)`` of faces ``f`` (zeros where not ``real``)."""
        fi = faces_ptr + f * 3
        i0 = tl.load(fi, mask=real, other=0)
        i1 = tl.load(fi + 1, mask=real, other=0)
        i2 = tl.load(fi + 2, mask=real, other=0)
        p0 = uvz_ptr + env_v + i0 * 3
        p1 = uvz_ptr + env_v + i1 * 3
        p2 = uvz_ptr + env_v + i2 * 3
        u0 = tl.load(p0, mask=real, other=0.0)
        v0 = tl.load(p0 + 1, mask=real, other=0.0)
        z0 = tl.load(p0 + 2, mask=real, other=0.0)
        u1 = tl.load(p1, mask=real, other=0.0)
        v1 = tl.load(p1 + 1, mask=real, other=0.0)
        z1 = tl.load(p1 + 2, mask=real, other=0.0)
        u2 = tl.load(p2, mask=real, other=0.0)
        v2 = tl.load(p2 + 1, mask=real, other=0.0)
        z2 = tl.load(p2 + 2, mask=real, other=0.0)
        return i0, i1, i2, u0, v0, z0, u1, v1, z1, u2, v2, z2

    @triton.jit
    def _kept(u0, v0, z0, u1, v1, z1, u2, v2, z2, real, znear, area_eps, CULL: tl.constexpr):
        """:func:`.kernel.face_validity`: in front of znear, a finite and large enough signed area (negative,
        i.e. front-facing, with back-face culling)."""
        av = (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0)
        ok = real & (z0 > znear) & (z1 > znear) & (z2 > znear) & (tl.abs(av) < float("inf"))
        if CULL:
            ok = ok & (av < -area_eps)
        else:
            ok = ok & (tl.abs(av) > area_eps)
        return ok

    @triton.jit
    def _kept_corners(u0, v0, z0, u1, v1, z1, u2, v2, z2, real, znear, area_eps, CULL: tl.constexpr):
        """:func:`_kept`, and the corners with a dropped face's replaced by the triangle (0, 0), (1, 0), (0, 1)
        at depth 1, as the reference does: no inf/NaN is ever formed from a dropped face."""
        ok = _kept(u0, v0, z0, u1, v1, z1, u2, v2, z2, real, znear, area_eps, CULL)
        return (ok, tl.where(ok, u0, 0.0), tl.where(ok, v0, 0.0), tl.where(ok, z0, 1.0),
                tl.where(ok, u1, 1.0), tl.where(ok, v1, 0.0), tl.where(ok, z1, 1.0),
                tl.where(ok, u2, 0.0), tl.where(ok, v2, 1.0), tl.where(ok, z2, 1.0))

    @triton.jit
    def _edge_rows(ex, ey, ua, va, inv_area, abs_area):
        """Edge k's rows: barycentric lambda_k (LA, LX, LY), position along the edge (PA, PX, PY), height
        H_k, squared length."""
        len2 = ex * ex + ey * ey
        inv_len2 = 1.0 / len2
        return ((ey * ua - ex * va) * inv_area, -ey * inv_area, ex * inv_area,
                -(ex * ua + ey * va) * inv_len2, ex * inv_len2, ey * inv_len2,
                abs_area * tl.sqrt(inv_len2), len2)

    @triton.jit
    def _store_edge_rows(cp, k, Fp, stored, ex, ey, ua, va, inv_area, abs_area):
        """Edge k's eight rows (:func:`_edge_rows`) into rows k, k + 3, ..., k + 21 of the block's coefficients."""
        la, lx, ly, pa, px, py, h, l2 = _edge_rows(ex, ey, ua, va, inv_area, abs_area)
        tl.store(cp + k * Fp, la, mask=stored)
        tl.store(cp + (k + 3) * Fp, lx, mask=stored)
        tl.store(cp + (k + 6) * Fp, ly, mask=stored)
        tl.store(cp + (k + 9) * Fp, pa, mask=stored)
        tl.store(cp + (k + 12) * Fp, px, mask=stored)
        tl.store(cp + (k + 15) * Fp, py, mask=stored)
        tl.store(cp + (k + 18) * Fp, h, mask=stored)
        tl.store(cp + (k + 21) * Fp, l2, mask=stored)

    @triton.jit
    def _edge_grads_at(gp, k, Fp, ex, ey, ua, va, inv_area, abs_area):
        """:func:`_edge_grads` of edge k, its eight rows' gradients read from rows k, k + 3, ..., k + 21."""
        return _edge_grads(ex, ey, ua, va, inv_area, abs_area, tl.load(gp + k * Fp), tl.load(gp + (k + 3) * Fp),
                           tl.load(gp + (k + 6) * Fp), tl.load(gp + (k + 9) * Fp), tl.load(gp + (k + 12) * Fp),
                           tl.load(gp + (k + 15) * Fp), tl.load(gp + (k + 18) * Fp), tl.load(gp + (k + 21) * Fp))

    @triton.jit
    def _edge_grads(ex, ey, ua, va, inv_area, abs_area, gla, glx, gly, gpa, gpx, gpy, gh, gl2):
        """Reverse of :func:`_edge_rows`: the gradients of edge k's vector (ex, ey), start (ua, va), of
        1 / area and of |area|, given those of its eight rows."""
        len2 = ex * ex + ey * ey
        inv_len2 = 1.0 / len2
        sq = tl.sqrt(inv_len2)
        # lambda rows: (ey ua - ex va, -ey, ex) / area
        gn = gla * inv_area
        g_inv_area = gla * (ey * ua - ex * va) - glx * ey + gly * ex
        g_ex = gly * inv_area - gn * va
        g_ey = gn * ua - glx * inv_area
        g_ua = gn * ey
        g_va = -gn * ex
        # position rows: (-(ex ua + ey va), ex, ey) / len2, and H = |area| sqrt(1 / len2)
        gp = -gpa * inv_len2
        g_inv_len2 = -gpa * (ex * ua + ey * va) + gpx * ex + gpy * ey + gh * abs_area * 0.5 / sq
        g_len2 = gl2 - g_inv_len2 * inv_len2 * inv_len2
        g_ex += gp * ua + gpx * inv_len2 + 2.0 * ex * g_len2
        g_ey += gp * va + gpy * inv_len2 + 2.0 * ey * g_len2
        g_ua += gp * ex
        g_va += gp * ey
        return g_ex, g_ey, g_ua, g_va, g_inv_area, gh * sq

    @triton.jit
    def _setup_forward(uvz_ptr, normals_ptr, colors_ptr, faces_ptr, prm, coef_ptr, box_ptr, bbox_ptr, NF, V, Fp,
                       NBP, COLOR_ENV_STRIDE, FB: tl.constexpr, CULL: tl.constexpr):
        """One program per (block of FB faces, environment). Writes the block's coefficients (45, FB) and face
        boxes (4, FB) (faces NF .. Fp are padding: dropped, zero normals and colours) and the block's box;
        a block past the faces (the padding of the last super-block) writes only its empty box."""
        blk = tl.program_id(0)
        env = tl.program_id(1).to(tl.int64)
        znear = tl.load(prm)
        grow = tl.load(prm + 1)
        area_eps = tl.load(prm + 2)
        f = blk * FB + tl.arange(0, FB)
        real = f < NF
        stored = f < Fp
        env_v = env * V * 3
        i0, i1, i2, u0, v0, z0, u1, v1, z1, u2, v2, z2 = _corners(uvz_ptr, faces_ptr, f, real, env_v)
        ok, u0, v0, z0, u1, v1, z1, u2, v2, z2 = _kept_corners(u0, v0, z0, u1, v1, z1, u2, v2, z2, real, znear,
                                                               area_eps, CULL)
        # edge k runs from corner k+1 to corner k+2
        ex0 = u2 - u1
        ey0 = v2 - v1
        area = ex0 * (v0 - v1) - ey0 * (u0 - u1)
        area = tl.where(area == 0, 1.0, area)
        inv_area = 1.0 / area
        abs_area = tl.abs(area)
        cp = coef_ptr + env * 45 * Fp + f
        _store_edge_rows(cp, 0, Fp, stored, ex0, ey0, u1, v1, inv_area, abs_area)
        _store_edge_rows(cp, 1, Fp, stored, u0 - u2, v0 - v2, u2, v2, inv_area, abs_area)
        _store_edge_rows(cp, 2, Fp, stored, u1 - u0, v1 - v0, u0, v0, inv_area, abs_area)
        tl.store(cp + 24 * Fp, 1.0 / z0, mask=stored)
        tl.store(cp + 25 * Fp, 1.0 / z1, mask=stored)
        tl.store(cp + 26 * Fp, 1.0 / z2, mask=stored)
        # corners' normals (rows 27 + 3 c + j) and colours (36 + 3 c + j), whether or not the face is kept
        for c in tl.static_range(3):
            idx = i0 if c == 0 else (i1 if c == 1 else i2)
            npt = normals_ptr + env_v + idx * 3
            apt = colors_ptr + env * COLOR_ENV_STRIDE + idx * 3
            for j in tl.static_range(3):
                tl.store(cp + (27 + 3 * c + j) * Fp, tl.load(npt + j, mask=real, other=0.0), mask=stored)
                tl.store(cp + (36 + 3 * c + j) * Fp, tl.load(apt + j, mask=real, other=0.0), mask=stored)
        # the pixel centres a kept face can touch: its box grown by the coverage cut-off; dropped: empty
        x_min = tl.where(ok, tl.minimum(tl.minimum(u0, u1), u2) - grow, _EMPTY)
        x_max = tl.where(ok, tl.maximum(tl.maximum(u0, u1), u2) + grow, -_EMPTY)
        y_min = tl.where(ok, tl.minimum(tl.minimum(v0, v1), v2) - grow, _EMPTY)
        y_max = tl.where(ok, tl.maximum(tl.maximum(v0, v1), v2) + grow, -_EMPTY)
        bp = box_ptr + env * 4 * Fp + f
        tl.store(bp, x_min, mask=stored)
        tl.store(bp + Fp, x_max, mask=stored)
        tl.store(bp + 2 * Fp, y_min, mask=stored)
        tl.store(bp + 3 * Fp, y_max, mask=stored)
        bb = bbox_ptr + env * 4 * NBP + blk
        tl.store(bb, tl.min(x_min, axis=0))
        tl.store(bb + NBP, tl.max(x_max, axis=0))
        tl.store(bb + 2 * NBP, tl.min(y_min, axis=0))
        tl.store(bb + 3 * NBP, tl.max(y_max, axis=0))

    @triton.jit
    def _super_boxes(bbox_ptr, sbox_ptr, NBP, NSB, SB: tl.constexpr, SBP: tl.constexpr):
        """One program per (super-block, environment): the union of its SB block boxes (SBP: SB rounded up
        to a power of two)."""
        sb = tl.program_id(0)
        env = tl.program_id(1).to(tl.int64)
        j = tl.arange(0, SBP)
        m = j < SB
        bp = bbox_ptr + env * 4 * NBP + sb * SB + j
        sp = sbox_ptr + env * 4 * NSB + sb
        tl.store(sp, tl.min(tl.load(bp, mask=m, other=_EMPTY), axis=0))
        tl.store(sp + NSB, tl.max(tl.load(bp + NBP, mask=m, other=-_EMPTY), axis=0))
        tl.store(sp + 2 * NSB, tl.min(tl.load(bp + 2 * NBP, mask=m, other=_EMPTY), axis=0))
        tl.store(sp + 3 * NSB, tl.max(tl.load(bp + 3 * NBP, mask=m, other=-_EMPTY), axis=0))

    @triton.jit
    def _add_nonzero(ptr, g, mask):
        """Atomic add where the gradient is not exactly zero (adding zero changes nothing and costs an atomic)."""
        tl.atomic_add(ptr, g, mask=mask & (g != 0.0))

    @triton.jit
    def _add_corner(q, gu, gv, gz, mask):
        """:func:`_add_nonzero` of one corner's (u, v, z) gradient into its projected vertex at ``q``."""
        _add_nonzero(q, gu, mask)
        _add_nonzero(q + 1, gv, mask)
        _add_nonzero(q + 2, gz, mask)

    @triton.jit
    def _setup_backward(uvz_ptr, faces_ptr, prm, gcoef_ptr, guvz_ptr, gnormals_ptr, gcolors_ptr, NF, V, Fp,
                        COLOR_ENV_STRIDE, FB: tl.constexpr, CULL: tl.constexpr, NEED_UVZ: tl.constexpr,
                        NEED_NORMALS: tl.constexpr, NEED_COLORS: tl.constexpr):
        """One program per (block of FB faces, environment): the gradients of the block's coefficients
        (45, FB) added into the corners' projected vertices, normals and colours."""
        blk = tl.program_id(0)
        env = tl.program_id(1).to(tl.int64)
        f = blk * FB + tl.arange(0, FB)
        real = f < NF
        env_v = env * V * 3
        gp = gcoef_ptr + env * 45 * Fp + f
        i0, i1, i2, u0, v0, z0, u1, v1, z1, u2, v2, z2 = _corners(uvz_ptr, faces_ptr, f, real, env_v)
        if NEED_UVZ:
            # dropped faces: the constant triangle, no gradient (their lanes are masked off below)
            ok, u0, v0, z0, u1, v1, z1, u2, v2, z2 = _kept_corners(u0, v0, z0, u1, v1, z1, u2, v2, z2, real,
                                                                   tl.load(prm), tl.load(prm + 2), CULL)
            ex0 = u2 - u1
            ey0 = v2 - v1
            ex1 = u0 - u2
            ey1 = v0 - v2
            ex2 = u1 - u0
            ey2 = v1 - v0
            raw = ex0 * (v0 - v1) - ey0 * (u0 - u1)
            area = tl.where(raw == 0, 1.0, raw)
            inv_area = 1.0 / area
            abs_area = tl.abs(area)
            gx0, gy0, gua0, gva0, gia0, gaa0 = _edge_grads_at(gp, 0, Fp, ex0, ey0, u1, v1, inv_area, abs_area)
            gx1, gy1, gua1, gva1, gia1, gaa1 = _edge_grads_at(gp, 1, Fp, ex1, ey1, u2, v2, inv_area, abs_area)
            gx2, gy2, gua2, gva2, gia2, gaa2 = _edge_grads_at(gp, 2, Fp, ex2, ey2, u0, v0, inv_area, abs_area)
            # area (1 where its formula gives exactly 0: a constant, no gradient) through 1 / area and |area|
            g_area = -(gia0 + gia1 + gia2) * inv_area * inv_area + (gaa0 + gaa1 + gaa2) * tl.where(area > 0, 1.0,
                                                                                                     -1.0)
            g_area = tl.where(raw == 0, 0.0, g_area)
            # area = ex0 (v0 - v1) - ey0 (u0 - u1)
            gx0 += g_area * (v0 - v1)
            gy0 -= g_area * (u0 - u1)
            gu0 = gua2 - g_area * ey0 + gx1 - gx2
            gu1 = gua0 + g_area * ey0 - gx0 + gx2
            gu2 = gua1 + gx0 - gx1
            gv0 = gva2 + g_area * ex0 + gy1 - gy2
            gv1 = gva0 - g_area * ex0 - gy0 + gy2
            gv2 = gva1 + gy0 - gy1
            gz0 = -tl.load(gp + 24 * Fp) / (z0 * z0)
            gz1 = -tl.load(gp + 25 * Fp) / (z1 * z1)
            gz2 = -tl.load(gp + 26 * Fp) / (z2 * z2)
            _add_corner(guvz_ptr + env_v + i0 * 3, gu0, gv0, gz0, ok)
            _add_corner(guvz_ptr + env_v + i1 * 3, gu1, gv1, gz1, ok)
            _add_corner(guvz_ptr + env_v + i2 * 3, gu2, gv2, gz2, ok)
        for c in tl.static_range(3):
            idx = i0 if c == 0 else (i1 if c == 1 else i2)
            for j in tl.static_range(3):
                if NEED_NORMALS:
                    _add_nonzero(gnormals_ptr + env_v + idx * 3 + j, tl.load(gp + (27 + 3 * c + j) * Fp, mask=real,
                                                                              other=0.0), real)
                if NEED_COLORS:
                    _add_nonzero(gcolors_ptr + env * COLOR_ENV_STRIDE + idx * 3 + j,
                                 tl.load(gp + (36 + 3 * c + j) * Fp, mask=real, other=0.0), real)


    @triton.jit
    def _floor_rays(rot_ptr, eye_ptr, prm, HW, W, BLOCK: tl.constexpr):
        """What both floor kernels start from, for the program's environment ``env`` and BLOCK pixels ``pix``
        (``m``: those inside the image), and per pixel centre the camera-space ray (dxc, dyc, 1), the world
        ray's (dx, dy), the eye's height, whether dz is usable (ok) and dz (1 where not), the hit flag, the
        hit's depth t (znear where there is no hit), the focal length [px] and the floor point (xw, yw) [m] at
        depth t."""
        env = tl.program_id(1).to(tl.int64)
        pix = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        m = pix < HW
        rot = rot_ptr + env * 9
        eye = eye_ptr + env * 3
        cx = tl.load(prm)
        cy = tl.load(prm + 1)
        focal = tl.load(prm + 2)
        znear = tl.load(prm + 3)
        x = (pix % W).to(cx.dtype) + 0.5
        y = (pix // W).to(cx.dtype) + 0.5
        dxc = (x - cx) / focal
        dyc = (y - cy) / focal
        # world ray direction R^T (dxc, dyc, 1): its camera z is 1, so the hit parameter t is the hit's depth
        dx = tl.load(rot) * dxc + tl.load(rot + 3) * dyc + tl.load(rot + 6)
        dy = tl.load(rot + 1) * dxc + tl.load(rot + 4) * dyc + tl.load(rot + 7)
        dz = tl.load(rot + 2) * dxc + tl.load(rot + 5) * dyc + tl.load(rot + 8)
        ez = tl.load(eye + 2)
        ok = tl.abs(dz) > 1e-12
        dzs = tl.where(ok, dz, 1.0)
        t0 = -ez / dzs
        hit = ok & (t0 > znear)
        t = tl.where(hit, t0, znear)
        xw = tl.load(eye) + t * dx
        yw = tl.load(eye + 1) + t * dy
        return env, pix, m, dxc, dyc, dx, dy, ez, ok, dzs, hit, t, focal, xw, yw

    @triton.jit
    def _tanh(a):
        """tanh from one exp (no tanh in Triton's core language); exact at +-inf."""
        e = tl.exp(-2.0 * tl.abs(a))
        th = (1.0 - e) / (1.0 + e)
        return tl.where(a < 0, -th, th)

    @triton.jit
    def _floor_forward(rot_ptr, eye_ptr, prm, out_ptr, HW, W, BLOCK: tl.constexpr):
        """One program per (BLOCK pixels, environment): the floor's normalised depth, lit colour and hit flag
        (1.0 / 0.0) into out (B, 5, H, W)."""
        env, pix, m, _, _, _, _, _, _, dzs, hit, t, focal, xw, yw = _floor_rays(rot_ptr, eye_ptr, prm, HW, W, BLOCK)
        zfar = tl.load(prm + 4)
        s = tl.load(prm + 7)
        pi = tl.load(prm + 9)
        light = tl.load(prm + 10)
        # pixel footprint on the floor [m]: depth / focal, stretched by the grazing angle
        footprint = t / (focal * tl.abs(dzs))
        sharp = tl.minimum(s / (tl.load(prm + 8) * footprint), _MAX_SHARP)
        mix = 0.5 + 0.5 * _tanh(sharp * tl.sin(pi * xw / s) * tl.sin(pi * yw / s))
        zn = tl.maximum((zfar - t) / tl.load(prm + 5), tl.load(prm + 6))
        op = out_ptr + env * 5 * HW + pix
        tl.store(op, zn, mask=m)
        tl.store(op + HW, (tl.load(prm + 11) + tl.load(prm + 14) * mix) * light, mask=m)
        tl.store(op + 2 * HW, (tl.load(prm + 12) + tl.load(prm + 15) * mix) * light, mask=m)
        tl.store(op + 3 * HW, (tl.load(prm + 13) + tl.load(prm + 16) * mix) * light, mask=m)
        tl.store(op + 4 * HW, tl.where(hit, 1.0, 0.0), mask=m)

    @triton.jit
    def _floor_backward(rot_ptr, eye_ptr, prm, g_ptr, G_ENV_STRIDE, grot_ptr, geye_ptr, HW, W,
                        BLOCK: tl.constexpr):
        """One program per (BLOCK pixels, environment): the gradients of its pixels' depth and colour planes
        (g: (B, >= 4, H, W), rows 0-3 read) mapped to the camera's rotation (3, 3) and eye (3), summed over
        the pixels, then added atomically."""
        env, pix, m, dxc, dyc, dx, dy, ez, ok, dzs, hit, t, focal, xw, yw = _floor_rays(rot_ptr, eye_ptr, prm, HW,
                                                                                        W, BLOCK)
        zfar = tl.load(prm + 4)
        s = tl.load(prm + 7)
        pi = tl.load(prm + 9)
        light = tl.load(prm + 10)
        adz = tl.abs(dzs)
        footprint = t / (focal * adz)
        sharp_raw = s / (tl.load(prm + 8) * footprint)
        sharp = tl.minimum(sharp_raw, _MAX_SHARP)
        ux = pi * xw / s
        uy = pi * yw / s
        sx = tl.sin(ux)
        sy = tl.sin(uy)
        th = _tanh(sharp * sx * sy)
        gp = g_ptr + env * G_ENV_STRIDE + pix
        g_zn = tl.load(gp, mask=m, other=0.0)
        g_mix = light * (tl.load(prm + 14) * tl.load(gp + HW, mask=m, other=0.0)
                         + tl.load(prm + 15) * tl.load(gp + 2 * HW, mask=m, other=0.0)
                         + tl.load(prm + 16) * tl.load(gp + 3 * HW, mask=m, other=0.0))
        g_a = g_mix * 0.5 * (1.0 - th * th)
        g_sharp = tl.where(sharp_raw <= _MAX_SHARP, g_a * sx * sy, 0.0)
        g_x = g_a * sharp * sy * tl.cos(ux) * pi / s
        g_y = g_a * sharp * sx * tl.cos(uy) * pi / s
        g_fp = -g_sharp * sharp_raw / footprint
        g_t = g_fp / (focal * adz) + g_x * dx + g_y * dy
        g_t += tl.where((zfar - t) / tl.load(prm + 5) >= tl.load(prm + 6), -g_zn / tl.load(prm + 5), 0.0)
        g_dzs = -g_fp * footprint / adz * tl.where(dzs < 0, -1.0, 1.0)
        g_t0 = tl.where(hit, g_t, 0.0)  # no hit: t is the constant znear
        g_dzs += g_t0 * ez / (dzs * dzs)
        g_dx = tl.where(m, g_x * t, 0.0)
        g_dy = tl.where(m, g_y * t, 0.0)
        g_dz = tl.where(m & ok, g_dzs, 0.0)
        ge = geye_ptr + env * 3
        tl.atomic_add(ge, tl.sum(tl.where(m, g_x, 0.0), axis=0))
        tl.atomic_add(ge + 1, tl.sum(tl.where(m, g_y, 0.0), axis=0))
        tl.atomic_add(ge + 2, tl.sum(tl.where(m, -g_t0 / dzs, 0.0), axis=0))
        gr = grot_ptr + env * 9
        tl.atomic_add(gr, tl.sum(g_dx * dxc, axis=0))
        tl.atomic_add(gr + 1, tl.sum(g_dy * dxc, axis=0))
        tl.atomic_add(gr + 2, tl.sum(g_dz * dxc, axis=0))
        tl.atomic_add(gr + 3, tl.sum(g_dx * dyc, axis=0))
        tl.atomic_add(gr + 4, tl.sum(g_dy * dyc, axis=0))
        tl.atomic_add(gr + 5, tl.sum(g_dz * dyc, axis=0))
        tl.atomic_add(gr + 6, tl.sum(g_dx, axis=0))
        tl.atomic_add(gr + 7, tl.sum(g_dy, axis=0))
        tl.atomic_add(gr + 8, tl.sum(g_dz, axis=0))


class _FaceSetup(torch.autograd.Function):
    """:func:`face_setup` with its hand-written backward (see the module's docstring)."""

    @staticmethod
    def forward(ctx, uvz, normals, colors, faces, st: Static, face_block: int, super_block: int):
        b, nv, _ = uvz.shape
        nf = faces.shape[0]
        nb = max(1, -(-nf // face_block))
        nsb = -(-nb // super_block)
        nbp = nsb * super_block
        fp = nb * face_block
        dt, dev = uvz.dtype, uvz.device
        coef = torch.empty(b, NUM_COEFFS, fp, dtype=dt, device=dev)
        box = torch.empty(b, 4, fp, dtype=dt, device=dev)
        bbox = torch.empty(b, 4, nbp, dtype=dt, device=dev)
        sbox = torch.empty(b, 4, nsb, dtype=dt, device=dev)
        if nf == 0:  # one block of padding faces (and no mesh to point a kernel at: empty tensors)
            coef.zero_()
            for t in (box, bbox, sbox):
                t[:, 0::2].fill_(EMPTY_EXTENT)
                t[:, 1::2].fill_(-EMPTY_EXTENT)
        else:
            _setup_forward[(nbp, b)](uvz, normals, colors, faces, _setup_params(st, dt, dev), coef, box, bbox, nf,
                                     nv, fp, nbp, 0 if colors.ndim == 2 else nv * 3, FB=face_block,
                                     CULL=st.cull_backfaces, num_warps=_warps(face_block))
            _super_boxes[(nsb, b)](bbox, sbox, nbp, nsb, SB=super_block, SBP=triton.next_power_of_2(super_block))
        ctx.save_for_backward(uvz, normals, colors, faces)
        ctx.cfg = (st, face_block, nb)
        ctx.mark_non_differentiable(box, bbox, sbox)
        ctx.set_materialize_grads(False)
        return coef, box, bbox, sbox

    @staticmethod
    def backward(ctx, gcoef, _gbox, _gbbox, _gsbox):
        need_uvz, need_normals, need_colors = ctx.needs_input_grad[:3]
        if gcoef is None or not (need_uvz or need_normals or need_colors):
            return (None,) * 7
        st, face_block, nb = ctx.cfg
        uvz, normals, colors, faces = ctx.saved_tensors
        b, nv, _ = uvz.shape
        g_uvz = torch.zeros_like(uvz) if need_uvz else None
        g_normals = torch.zeros_like(normals) if need_normals else None
        g_colors = torch.zeros_like(colors) if need_colors else None
        if faces.shape[0] > 0:
            _setup_backward[(nb, b)](
                uvz, faces, _setup_params(st, uvz.dtype, uvz.device), gcoef.contiguous(),
                uvz if g_uvz is None else g_uvz, uvz if g_normals is None else g_normals,
                uvz if g_colors is None else g_colors, faces.shape[0], nv, gcoef.shape[2],
                0 if colors.ndim == 2 else nv * 3, FB=face_block, CULL=st.cull_backfaces, NEED_UVZ=need_uvz,
                NEED_NORMALS=need_normals, NEED_COLORS=need_colors, num_warps=_warps(face_block))
        return g_uvz, g_normals, g_colors, None, None, None, None


def face_setup(uvz: torch.Tensor, normals: torch.Tensor, colors: torch.Tensor, faces: torch.Tensor, st: Static,
               *, face_block: int, super_block: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Everything the fused raster kernels read of the faces, from the projected vertices (Triton; CUDA, or
    the CPU under ``TRITON_INTERPRET=1``). Differentiable in ``uvz``, ``normals`` and ``colors``.

    Args:
        uvz: (B, V, 3) projected vertices ``(u [px], v [px], z [m])`` (:func:`.kernel.project`).
        normals: (B, V, 3) vertex normals (unit length not required; the raster kernels normalise).
        colors: (V, 3) shared or (B, V, 3) per-environment albedos.
        faces: (F, 3) long vertex indices; st: static settings (znear, cut-off radius, back-face culling).
        face_block: faces per block (a power of two); super_block: blocks per super-block.
    Returns:
        coef: (B, 45, Fp), Fp = max(1, ceil(F / face_block)) * face_block, rows as
            :func:`.fused.face_coefficients` (faces F .. Fp are padding: dropped, zero normals and colours);
        face_box: (B, 4, Fp) (x_min, x_max, y_min, y_max) [px] of the pixel centres a face can touch (empty
            for dropped faces); block_box: (B, 4, NSB * super_block) each block's union of face boxes,
            padded with empty boxes; super_box: (B, 4, NSB) the union of each run of ``super_block`` blocks.
            The boxes carry no gradient.
    """
    if face_block < 1 or face_block & (face_block - 1):
        raise ValueError(f"face_block must be a power of two, got {face_block}")
    if super_block < 1:
        raise ValueError(f"super_block must be at least 1, got {super_block}")
    if colors.ndim == 3 and colors.shape[0] != uvz.shape[0]:
        raise ValueError(f"colors: (V, 3) or (B, V, 3) with B = {uvz.shape[0]}, got {tuple(colors.shape)}")
    return _FaceSetup.apply(uvz.contiguous(), normals.contiguous(), colors.contiguous(), faces.contiguous(), st,
                            face_block, super_block)


class _FloorPlanes(torch.autograd.Function):
    """:func:`floor_planes` with its hand-written backward."""

    @staticmethod
    def forward(ctx, rotation, eye, st: Static):
        b = rotation.shape[0]
        hw = st.height * st.width
        out = torch.empty(b, 5, st.height, st.width, dtype=rotation.dtype, device=rotation.device)
        _floor_forward[(triton.cdiv(hw, FLOOR_BLOCK), b)](rotation, eye, _floor_params(st, out.dtype, out.device),
                                                          out, hw, st.width, BLOCK=FLOOR_BLOCK)
        ctx.save_for_backward(rotation, eye)
        ctx.st = st
        ctx.set_materialize_grads(False)
        return out

    @staticmethod
    def backward(ctx, g):
        if g is None or not any(ctx.needs_input_grad[:2]):
            return None, None, None
        rotation, eye = ctx.saved_tensors
        st = ctx.st
        hw = st.height * st.width
        if g.stride(3) != 1 or g.stride(2) != st.width or g.stride(1) != hw:
            g = g.contiguous()
        g_rot, g_eye = torch.zeros_like(rotation), torch.zeros_like(eye)
        _floor_backward[(triton.cdiv(hw, FLOOR_BLOCK), rotation.shape[0])](
            rotation, eye, _floor_params(st, g.dtype, g.device), g, g.stride(0), g_rot, g_eye, hw, st.width,
            BLOCK=FLOOR_BLOCK)
        return (g_rot if ctx.needs_input_grad[0] else None), (g_eye if ctx.needs_input_grad[1] else None), None


def floor_planes(rotation: torch.Tensor, eye: torch.Tensor, st: Static) -> torch.Tensor:
    """The analytic floor at every pixel centre (Triton; its PyTorch reference is
    :func:`diffrender.floor.floor_candidate`), differentiable in the camera except the hit flag.

    Args:
        rotation: (B, 3, 3) world -> camera; eye: (B, 3) [m]; st: static settings with ``st.floor`` set.
    Returns:
        (B, 5, H, W): normalised depth, lit colour (3) and hit flag (1.0 / 0.0) per pixel.
    """
    if st.floor is None:
        raise ValueError("floor_planes: st.floor is None (no floor to draw)")
    return _FloorPlanes.apply(rotation.contiguous(), eye.contiguous(), st)
