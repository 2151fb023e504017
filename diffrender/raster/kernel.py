"""The per-chunk rasterization kernel shared by the dense and tiled backends (every image model).

Both backends call :func:`render_pairs` with a list of (face, tile) pairs per environment; the kernel
evaluates every pair at every pixel of its tile and blends. The dense backend passes every face once with a
single tile covering the whole image; the tiled backend passes binned pairs over small tiles. Given the same
pair semantics (a pixel-face pair counts iff the face is valid and ``sd > -cutoff_radius``) both compute the
same image, bit for bit up to summation order.

Everything here is plain batched tensor code with static shapes (no data-dependent Python control flow,
no host synchronisation) so ``torch.compile`` can fuse it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..floor import floor_candidate
from ..settings import FloorSettings, RasterSettings
from ..shading import lambert_shade, unit_light
from .common import AREA_EPS

__all__ = ["Static", "face_validity", "project", "render_pairs", "vertex_normals"]



@dataclass(frozen=True)
class Static:
    """Everything the kernel needs that is not a tensor (hashable: part of compiled-kernel guards)."""

    height: int
    width: int
    tile_h: int
    tile_w: int
    focal: float
    cx: float
    cy: float
    sigma: float
    gamma: float
    znear: float
    zfar: float
    cutoff_radius: float
    background: tuple[float, float, float]
    floor: FloorSettings | None
    light: tuple[float, float, float]
    ambient: float
    diffuse: float
    cull_backfaces: bool
    raster_model: str = "softmax"

    @property
    def tiles_x(self) -> int:
        return -(-self.width // self.tile_w)

    @property
    def tiles_y(self) -> int:
        return -(-self.height // self.tile_h)

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    @property
    def tile_pixels(self) -> int:
        return self.tile_h * self.tile_w

    @classmethod
    def make(cls, settings: RasterSettings, *, focal: float, height: int, width: int,
             tile_h: int, tile_w: int) -> Static:
        return cls(height=height, width=width, tile_h=tile_h, tile_w=tile_w, focal=float(focal),
                   cx=0.5 * width, cy=0.5 * height, sigma=float(settings.sigma), gamma=float(settings.gamma),
                   znear=float(settings.znear), zfar=float(settings.zfar),
                   cutoff_radius=float(settings.cutoff_radius),
                   background=tuple(float(c) for c in settings.background), floor=settings.floor,
                   light=unit_light(settings.light_dir), ambient=float(settings.ambient),
                   diffuse=float(settings.diffuse), cull_backfaces=bool(settings.cull_backfaces),
                   raster_model=settings.raster_model)


def project(verts: torch.Tensor, rotation: torch.Tensor, eye: torch.Tensor, st: Static) -> torch.Tensor:
    """World vertices (B, V, 3) [m] -> (B, V, 3) ``(u [px], v [px], z [m])``.

    Depths are clamped to ``znear`` before the division so that vertices behind the camera give finite
    (meaningless) pixel coordinates; every face using such a vertex is dropped by :func:`face_validity`,
    and the clamp has zero gradient there, so no NaN or inf reaches the backward pass.
    """
    cam = torch.einsum("bij,bnj->bni", rotation, verts - eye[:, None, :])
    z = cam[..., 2]
    zs = z.clamp(min=st.znear)
    return torch.stack([st.focal * cam[..., 0] / zs + st.cx, st.focal * cam[..., 1] / zs + st.cy, z], dim=-1)


def face_validity(face_uvz: torch.Tensor, st: Static) -> torch.Tensor:
    """(B, F, 3, 3) per-face ``(u, v, z)`` -> (B, F) bool: in front of znear, non-degenerate and, with
    back-face culling, front-facing (negative signed area in y-down pixel coordinates)."""
    u, v, z = face_uvz.unbind(-1)
    area2 = (u[..., 1] - u[..., 0]) * (v[..., 2] - v[..., 0]) - (v[..., 1] - v[..., 0]) * (u[..., 2] - u[..., 0])
    ok = (z > st.znear).all(-1) & torch.isfinite(area2)
    if st.cull_backfaces:
        return ok & (area2 < -AREA_EPS)
    return ok & (area2.abs() > AREA_EPS)


def vertex_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals of a mesh: verts (B, V, 3), faces (F, 3) -> (B, V, 3)."""
    # (B, F, 3, 3) corners by index_select, whose backward is an index_add (one atomic add per corner): the
    # backward of verts[:, faces] (index_put with accumulate) sorts all B x F x 3 indices first, every backward
    fv = verts.index_select(1, faces.reshape(-1)).unflatten(1, (faces.shape[0], 3))
    fn = torch.linalg.cross(fv[:, :, 1] - fv[:, :, 0], fv[:, :, 2] - fv[:, :, 0])  # |fn| = 2 area
    acc = verts.new_zeros(verts.shape).index_add_(1, faces.reshape(-1), fn.repeat_interleave(3, dim=1))
    return acc * torch.rsqrt((acc * acc).sum(-1, keepdim=True) + 1e-30)


def _times_rgb(x: torch.Tensor, rgb: tuple[float, float, float]) -> torch.Tensor:
    """x (...) times a constant colour -> (..., 3), without a host-to-device copy of the colour."""
    return torch.stack([x * rgb[0], x * rgb[1], x * rgb[2]], dim=-1)


def _tile_pixel_centres(tile: torch.Tensor, st: Static, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel centres of tiles: tile (...,) long -> px, py (..., tile_h * tile_w)."""
    k = torch.arange(st.tile_pixels, device=tile.device)
    lx = (k % st.tile_w).to(dtype) + 0.5
    ly = (k // st.tile_w).to(dtype) + 0.5
    x0 = ((tile % st.tiles_x) * st.tile_w).to(dtype)[..., None]
    y0 = ((tile // st.tiles_x) * st.tile_h).to(dtype)[..., None]
    return x0 + lx, y0 + ly


def render_pairs(
    verts: torch.Tensor,
    normals: torch.Tensor | None,
    colors: torch.Tensor,
    rotation: torch.Tensor,
    eye: torch.Tensor,
    faces: torch.Tensor,
    pair_env: torch.Tensor,
    pair_face: torch.Tensor,
    pair_tile: torch.Tensor,
    pair_valid: torch.Tensor,
    st: Static,
) -> torch.Tensor:
    """Render B environments from a pooled list of (environment, face, tile) pairs.

    Args:
        verts: (B, V, 3) [m] world vertices.
        normals: (B, V, 3) unit world vertex normals, or None to use area-weighted mesh normals.
        colors: (V, 3) or (B, V, 3) albedo in [0, 1].
        rotation: (B, 3, 3), eye: (B, 3) [m]: camera extrinsics (see :class:`diffrender.Camera`).
        faces: (F, 3) long.
        pair_env, pair_face, pair_tile: (N,) long; pair_valid: (N,) bool (invalid slots are padding).
        st: static settings.
    Returns:
        (B, 3, H, W) image.
    """
    b, nv, _ = verts.shape
    n = pair_face.shape[0]
    dt = verts.dtype
    uvz = project(verts, rotation, eye, st)
    if normals is None:
        normals = vertex_normals(verts, faces)
    if colors.ndim == 2:
        colors = colors.expand(b, nv, 3)
    # one gather of everything a face needs: (u, v, z, pad, n (3), albedo (3)) per corner
    vdata = torch.cat([uvz, torch.zeros_like(uvz[..., :1]), normals, colors], dim=-1)  # (B, V, 10)
    vidx = faces[pair_face] + (pair_env * nv)[:, None]  # (N, 3)
    fd = vdata.reshape(b * nv, 10).index_select(0, vidx.reshape(-1)).view(n, 3, 10)
    valid = pair_valid
    # padding slots get a harmless unit triangle so no inf/NaN is ever formed (their weight is zero)
    # (constants are built on the device, never copied from host lists: no H2D copy, CUDA-graph capturable)
    eye3 = torch.eye(3, dtype=dt, device=verts.device)
    dummy = torch.cat([eye3[:, 1:3], eye3.new_ones(3, 1), eye3.new_zeros(3, 7)], dim=1)
    fd = torch.where(valid[:, None, None], fd, dummy)

    # ---- per-pair constants. Index k runs over the three edges, edge k being the one opposite vertex k
    # (from vertex k+1 to vertex k+2); everything that does not depend on the pixel is computed here, and
    # the pixel-dependent quantities are affine in the tile-local pixel offsets (lx, ly). The three edges
    # are stacked on dim 1 so each step below is one tensor operation for all of them (fewer kernels).
    u, v = fd[:, :, 0], fd[:, :, 1]  # (N, 3)
    iz = 1.0 / fd[:, :, 2:3]  # (N, 3, 1)
    ua, va = u.roll(-1, 1), v.roll(-1, 1)  # edge start (vertex k+1)
    ex, ey = u.roll(-2, 1) - ua, v.roll(-2, 1) - va  # edge vector (to vertex k+2)
    area2 = ex[:, :1] * (v[:, :1] - va[:, :1]) - ey[:, :1] * (u[:, :1] - ua[:, :1])  # (N, 1), cross(e0, p0 - a0)
    area2 = torch.where(area2 == 0, torch.ones_like(area2), area2)  # only padding/dropped faces
    inv_area = 1.0 / area2
    len2 = ex * ex + ey * ey
    inv_len2 = 1.0 / len2
    tile = pair_tile
    ox = ((tile % st.tiles_x) * st.tile_w).to(dt)[:, None] - ua  # tile origin relative to the edge start
    oy = ((tile // st.tiles_x) * st.tile_h).to(dt)[:, None] - va
    k_pix = torch.arange(st.tile_pixels, device=verts.device)
    lx = ((k_pix % st.tile_w).to(dt) + 0.5).view(1, 1, -1)  # (1, 1, T) pixel-centre offsets in the tile
    ly = ((k_pix // st.tile_w).to(dt) + 0.5).view(1, 1, -1)
    # screen-space barycentrics lambda_k = cross(e_k, p - a_k) / area2 and the position along each edge
    # (0 at its start, 1 at its end), as c0 + cx * lx + cy * ly
    lam_c = torch.stack([(ex * oy - ey * ox) * inv_area, -ey * inv_area, ex * inv_area], -1)  # (N, 3, 3)
    par_c = torch.stack([(ex * ox + ey * oy) * inv_len2, ex * inv_len2, ey * inv_len2], -1)
    height = (area2.abs() * torch.sqrt(inv_len2))[..., None]  # (N, 3, 1): |area2| / |e_k|

    # ---- per pixel of the pair's tile: (N, 3, T) per edge, (N, T) per pixel
    lam = lam_c[..., 0:1] + lam_c[..., 1:2] * lx + lam_c[..., 2:3] * ly
    dline = lam * height  # signed distance to each edge's line (inside positive)
    s_par = par_c[..., 0:1] + par_c[..., 1:2] * lx + par_c[..., 2:3] * ly
    overshoot = s_par - s_par.clamp(0.0, 1.0)  # beyond the ends the nearest point is an end point
    dseg2 = dline * dline + len2[..., None] * (overshoot * overshoot)  # squared distance to each segment
    # pairwise minimum, not amin: amin's backward divides by the number of entries equal to the minimum,
    # which is 0 (NaN) when a fused compiled kernel recomputes the entries with different rounding
    dmin = torch.minimum(torch.minimum(dline[:, 0], dline[:, 1]), dline[:, 2])
    dsmin = torch.minimum(torch.minimum(dseg2[:, 0], dseg2[:, 1]), dseg2[:, 2])
    # exact signed Euclidean distance to the triangle (linear in the pixel offset at an edge):
    # inside, the nearest edge line; outside, the nearest point of the boundary
    sd = torch.where(dmin >= 0, dmin, -torch.sqrt(dsmin + 1e-20))
    # perspective-correct barycentrics from clamped screen barycentrics (1/z is affine in screen space)
    lc = lam.clamp(min=0.0)
    q = lc * iz
    inv_q = 1.0 / q.sum(1, keepdim=True)
    depth = lc.sum(1) * inv_q[:, 0]
    bary = q * inv_q  # (N, 3, T)
    z_n = (st.zfar - depth) * (1.0 / (st.zfar - st.znear))
    # interpolate normal and albedo in one batched matmul: (N, T, 3) x (N, 3, 6)
    attr = torch.bmm(bary.transpose(1, 2), fd[:, :, 4:10])
    normal, albedo = attr[..., :3], attr[..., 3:]
    color = albedo * lambert_shade(normal, st.light, ambient=st.ambient, diffuse=st.diffuse)[..., None]  # (N, T, 3)
    # ---- blend. Per-pixel buffers are laid out (B * tiles, T): a pair's pixels are one contiguous row.
    ntile = st.num_tiles
    rows = pair_env * ntile + pair_tile
    idx = rows[:, None].expand(n, st.tile_pixels)
    all_tiles = torch.arange(ntile, device=verts.device)
    fpx, fpy = _tile_pixel_centres(all_tiles, st, dt)  # (tiles, T)
    # behind every face: the floor where the pixel's ray hits it, else the background (normalised depth 0)
    bg_zn = 0.0
    if st.floor is not None:
        light_factor = st.ambient + st.diffuse * max(0.0, st.light[2])
        f_zn, f_col, f_hit = floor_candidate(rotation, eye, fpx, fpy, focal=st.focal, cx=st.cx, cy=st.cy,
                                             znear=st.znear, zfar=st.zfar, gamma=st.gamma, floor=st.floor,
                                             light_factor=light_factor)
        f_zn = f_zn.reshape(b * ntile, -1)
        f_col = f_col.reshape(b * ntile, -1, 3)
        f_hit = f_hit.reshape(b * ntile, -1)
        m0 = torch.where(f_hit, f_zn.detach(), torch.full_like(f_zn, bg_zn))
    else:
        m0 = verts.new_full((b * ntile, st.tile_pixels), bg_zn)
    if st.raster_model == "hard":
        out = _hard_blend(z_n, color, valid[:, None] & (sd >= 0), pair_face, faces.shape[0], idx, rows, m0,
                          f_col if st.floor is not None else None, f_hit if st.floor is not None else None, st)
    else:
        keep = valid[:, None] & (sd > -st.cutoff_radius)
        coverage = torch.sigmoid(sd * (1.0 / st.sigma))
        # the floor / background colour behind the faces, C_b: relative weights floor : background =
        # exp(z_f / gamma) : 1 (m-independent, so it never over- or underflows)
        behind = _times_rgb(torch.ones_like(m0), st.background)
        if st.floor is not None:
            # no-hit pixels carry a stand-in depth; mask before exp so no inf is formed (inf * 0 = NaN in
            # backward)
            f_expo = torch.where(f_hit, (f_zn - m0) / st.gamma, torch.full_like(f_zn, -math.inf))
            r_floor = torch.where(f_hit, torch.sigmoid(f_zn / st.gamma), torch.zeros_like(f_zn))
            behind = behind + r_floor[..., None] * (f_col - behind)
        # Kept faces have (z_n - m) / gamma <= 0 up to rounding. The cap guards against the keep mask being
        # re-evaluated with different rounding (a fused compiled backward recomputes sd): a pair dropped when m
        # was formed, re-kept later, could otherwise have exp(+hundreds) = inf. Capped, it weighs at most its
        # coverage (~ the cut-off), the same as the cut-off's own discontinuity; legitimate pairs never reach it.
        cap = max(0.02, 100.0 * torch.finfo(dt).eps / st.gamma)
        # Detached per-pixel max of the candidates' normalised depth: it cancels in the blend and only keeps
        # exp() <= 1; it must include every kept face so no weight overflows. "softmax": the floor and the
        # background are candidates like the faces; "alpha": the faces only (0 where there are none).
        with torch.no_grad():
            cand = torch.where(keep, z_n, torch.full_like(z_n, -math.inf))
            start = m0 if st.raster_model == "softmax" else torch.full_like(m0, -math.inf)
            m = start.scatter_reduce(0, idx, cand, reduce="amax", include_self=True)
            m = torch.where(torch.isfinite(m), m, torch.zeros_like(m))
        expo = torch.where(keep, ((z_n - m[rows]) * (1.0 / st.gamma)).clamp(max=cap),
                           torch.full_like(z_n, -math.inf))
        w = coverage * torch.exp(expo)  # exactly 0 for dropped pairs (also in the backward)
        cov = torch.where(keep, coverage, torch.zeros_like(coverage))
        zero = torch.zeros_like(m0)
        # the faces' coverage sum and weight sum per pixel. (A = min(1, sum D), not 1 - prod(1 - D): two
        # triangles sharing an edge have complementary sigmoids there, D1 + D2 = 1, so the sum is exactly 1
        # across a mesh's internal edges, while the product form leaves A = 0.75 seams all over a surface.)
        cov_sum = zero.index_add(0, rows, cov)
        w_faces = zero.index_add(0, rows, w)
        if st.raster_model == "softmax":
            # the floor and background start the per-pixel sums; the faces are scattered onto them (scattering
            # into fresh zero buffers and adding the floor afterwards was mis-compiled by inductor 2.13 on the
            # CPU: the scattered part went missing; test_raster.py::test_compiled_kernel_matches_eager)
            shift = torch.exp((m0 - m) / st.gamma)  # rescale floor/background weights from m0 to m
            den = shift * torch.exp((bg_zn - m0) / st.gamma)
            num = _times_rgb(den, st.background)
            if st.floor is not None:
                w_floor = shift * torch.exp(f_expo)
                num = num + w_floor[..., None] * f_col
                den = den + w_floor
            num = num.index_add(0, rows, color * w[..., None])
            den = den.index_add(0, rows, w)
        else:
            # a buffer of its own: scattering into an expanded view of ``zero`` fails in inductor 2.13's CPU
            # code generation (test_raster.py::test_compiled_kernel_matches_eager)
            num = m0.new_zeros((*m0.shape, 3)).index_add(0, rows, color * w[..., None])
            den = w_faces
        out = _cover(num, den, w_faces, cov_sum, behind)
    img = out.view(b, st.tiles_y, st.tiles_x, st.tile_h, st.tile_w, 3).permute(0, 5, 1, 3, 2, 4)
    img = img.reshape(b, 3, st.tiles_y * st.tile_h, st.tiles_x * st.tile_w)
    return img[:, :, : st.height, : st.width]


def _cover(num: torch.Tensor, den: torch.Tensor, w_faces: torch.Tensor, cov_sum: torch.Tensor,
           behind: torch.Tensor) -> torch.Tensor:
    """The soft models' colour ``(A num + (1 - A) W C_b) / (A den + (1 - A) W)`` with ``A = min(1, sum D)``:
    num (P, 3) and den (P,) the depth softmax's sums, w_faces (P,) the faces' part ``W`` of den, cov_sum (P,)
    ``sum D``, behind (P, 3) the floor/background colour ``C_b``. Pixels without faces show ``C_b``."""
    a = cov_sum.clamp(max=1.0)
    has = cov_sum > 0
    uncovered = (1.0 - a) * w_faces
    q = torch.where(has, a * den + uncovered, torch.ones_like(den))  # > 0 where there are faces
    mixed = (a[..., None] * num + uncovered[..., None] * behind) / q[..., None]
    return torch.where(has[..., None], mixed, behind)


def _hard_blend(z_n, color, inside, pair_face, num_faces: int, idx, rows, m0, f_col, f_hit, st: Static):
    """The hard model: per pixel the nearest face containing the centre (lowest face index among exact
    depth ties), strictly nearer than the floor / background (``m0``); else the floor or background. The
    choice is made without gradient; the chosen face's colour keeps its gradient. Returns (P, 3)."""
    with torch.no_grad():
        cand = torch.where(inside, z_n, torch.full_like(z_n, -math.inf))
        m = m0.scatter_reduce(0, idx, cand, reduce="amax", include_self=True)
        wins = inside & (z_n == m[rows]) & (z_n > m0[rows])
        face_id = torch.where(wins, pair_face[:, None], torch.full_like(idx, num_faces))
        chosen = torch.full_like(m0, num_faces, dtype=torch.long).scatter_reduce(0, idx, face_id, reduce="amin",
                                                                                include_self=True)
        selected = wins & (pair_face[:, None] == chosen[rows])
    faces_color = torch.zeros((*m0.shape, 3), dtype=color.dtype, device=color.device)
    faces_color = faces_color.index_add(0, rows, color * selected[..., None].to(color.dtype))
    behind = _times_rgb(torch.ones_like(m0), st.background)
    if f_col is not None:
        behind = torch.where(f_hit[..., None], f_col, behind)
    return torch.where((chosen < num_faces)[..., None], faces_color, behind)

