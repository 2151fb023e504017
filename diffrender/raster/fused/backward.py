"""The fused rasterizer's backward kernels: :func:`_pixel_backward` (what every pair's gradient at a pixel
shares, and the floor's gradients) and :func:`_fused_backward` (each face's 45 coefficient gradients, summed
over a tile's pixels in registers, then one atomic add per face, coefficient and tile). Both recompute the
forward's quantities with :mod:`.forward`'s device functions.

Imports Triton: import this module only where Triton is installed.
"""

import triton
import triton.language as tl

from .forward import (
    _block_touches_tile,
    _chunks,
    _compacted,
    _cover_coefficients,
    _floor_start,
    _load_params,
    _tile_pixels,
)


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
                    MODEL: tl.constexpr, COMPACT: tl.constexpr):
    """One program per (tile, environment, split): split s walks super-blocks s, s + NSPLIT, ... (each
    face's gradient is a sum over tiles, so it may come from any program). Per sub-block of SUB faces (one
    face per lane), a loop over the tile's pixels inside the faces' boxes accumulates every kept pair's
    gradient in registers from the pair's recomputed forward and the pixel's part
    (``_pixel_backward``), then one atomic add per face and coefficient (no cross-lane reductions).
    MODEL: 0 hard (only the chosen face's colour has a gradient), 1 softmax, 2 alpha. COMPACT: a block's lanes
    hold only its faces whose boxes reach the tile, packed in face order (``forward._compacted``), so that no lane
    walks the tile's pixels for a face far from it; each face's gradient is the same sum over the same pixels."""
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
    fbox = box_ptr + env * 4 * Fp
    inv_zr = 1.0 / (zfar - znear)
    for sb in range(split, NSB, NSPLIT):  # coarse: a super-block's box, then its blocks' boxes
        if _block_touches_tile(sbox_ptr, env, NSB, sb, x_lo, x_hi, y_lo, y_hi):
            for j in range(0, SB):
                blk = sb * SB + j
                if _block_touches_tile(bbox_ptr, env, NB, blk, x_lo, x_hi, y_lo, y_hi):
                    n, near, rank, count = _chunks(fbox, Fp, blk, x_lo, x_hi, y_lo, y_hi, FB, SUB, COMPACT)
                    for sub in range(0, n):
                        if COMPACT:
                            f, filled = _compacted(blk, near, rank, count, sub * SUB, FB, SUB)
                        else:
                            f = blk * FB + sub * SUB + fo
                        bx0 = tl.load(fbox + f)
                        bx1 = tl.load(fbox + Fp + f)
                        by0 = tl.load(fbox + 2 * Fp + f)
                        by1 = tl.load(fbox + 3 * Fp + f)
                        if COMPACT:  # the packed faces reach the tile; an empty slot repeats an index: no lane
                            fm = filled
                        else:
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
