"""The fused rasterizer's forward kernels: :func:`_fused_forward` (one program per tile, environment and split
of the faces' super-blocks; :func:`_binned_forward` the same reading per-tile face lists, which :func:`_bin_faces`
makes) and :func:`_merge_forward` (the parts of a split walk combined), with the device
functions they share with the backward kernels (:mod:`.backward` recomputes the forward's per-pair quantities).

The arguments are laid out as :mod:`.rasterize` launches them: per-face coefficients (B, 45, Fp), face boxes
(B, 4, Fp), block and super-block boxes, the floor planes (B, 5, H, W) and the float constants ``prm`` of
``rasterize._params``. Imports Triton: import this module only where Triton is installed.
"""

import triton
import triton.language as tl


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
    """Whether face block ``blk``'s box touches the tile (a scalar; for a vector of indices, each one's: the
    faces' own boxes, ``bbox_ptr`` a face-box array with NB = Fp and env 0)."""
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
def _touching_faces(fbox, Fp, blk, x_lo, x_hi, y_lo, y_hi, FB: tl.constexpr):
    """Which of block ``blk``'s faces have boxes that reach the tile's pixel centres (FB,), each one's rank
    among those (in face order) and how many there are."""
    near = _block_touches_tile(fbox, 0, Fp, blk * FB + tl.arange(0, FB), x_lo, x_hi, y_lo, y_hi)  # (FB,)
    rank = tl.cumsum(near.to(tl.int32), axis=0) - 1
    return near, rank, tl.sum(near.to(tl.int32), axis=0)


@triton.jit
def _compacted(blk, near, rank, count, c, FB: tl.constexpr, FS: tl.constexpr):
    """Slots ``c .. c + FS - 1`` of block ``blk``'s faces that reach the tile, in face order: their indices (FS,)
    and which slots hold one (slots past ``count`` hold the block's first face, masked out)."""
    slot = c + tl.arange(0, FS)
    pick = near[:, None] & (rank[:, None] == slot[None, :])
    return blk * FB + tl.sum(tl.where(pick, tl.arange(0, FB)[:, None], 0), axis=0), slot < count


@triton.jit
def _block_chunk(cbase, fbox, fo, Fp, blk, h, near, rank, count, xc, yc, zfar, znear, lx, ly, lz, ambient, diffuse,
                 FB: tl.constexpr, FS: tl.constexpr, COMPACT: tl.constexpr):
    """Chunk ``h`` of the ``FS`` faces of block ``blk`` at the tile's pixels, as both forward passes walk
    them: their indices (FS,), whether each pixel centre lies in each face's box, and each pair's signed
    distance, normalised depth and colour (``_candidate``), each (FS, P). COMPACT: the chunk is slots
    ``h * FS ...`` of the block's faces that reach the tile (:func:`_touching_faces`: ``near, rank, count``),
    so no face far from the tile is evaluated; else the block's faces ``h * FS ...``."""
    if COMPACT:
        f, filled = _compacted(blk, near, rank, count, h * FS, FB, FS)
    else:
        f = blk * FB + h * FS + fo
    inbox = _in_face_box(fbox, f, Fp, xc, yc)
    if COMPACT:
        inbox = inbox & filled[:, None]
    sd, zn, cr, cg, cb = _candidate(cbase + f[:, None], Fp, xc[None, :], yc[None, :], zfar, znear, lx, ly, lz,
                                    ambient, diffuse)
    return f, inbox, sd, zn, cr, cg, cb


@triton.jit
def _chunks(fbox, Fp, blk, x_lo, x_hi, y_lo, y_hi, FB: tl.constexpr, FS: tl.constexpr, COMPACT: tl.constexpr):
    """How the passes walk block ``blk``: the chunks to evaluate and, with COMPACT, the block's faces that
    reach the tile (:func:`_touching_faces`); without, every chunk of the block (placeholders for the rest)."""
    if COMPACT:
        near, rank, count = _touching_faces(fbox, Fp, blk, x_lo, x_hi, y_lo, y_hi, FB)
        return (count + FS - 1) // FS, near, rank, count
    else:
        zero = tl.zeros([FB], dtype=tl.int32)
        return FB // FS, zero > 0, zero, 0


@triton.jit
def _blend_chunk(inbox, sd, zn, cr, cg, cb, inb, num_r, num_g, num_b, den, w_sum, cov_sum, m, sigma, gamma, cutoff,
                 cap):
    """Soft models: one chunk of faces (each (FS, P): box test, signed distance, depth, colour) added to the
    online depth softmax and the weight and coverage sums."""
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
    return num_r, num_g, num_b, den, w_sum, cov_sum, m_new


@triton.jit
def _list_chunk(cbase, fbox, bins_ptr, lbase, cnt, h, fo, Fp, xc, yc, zfar, znear, lx, ly, lz, ambient, diffuse,
                FS: tl.constexpr):
    """Chunk ``h`` of a tile's face list (:func:`_bin_faces`), slots ``h * FS ...``, at the tile's pixels, as
    :func:`_block_chunk` gives a block's: the faces' indices (FS,; past ``cnt`` the slots hold face 0, masked out
    of the box test), whether each pixel centre lies in each face's box, and each pair's signed distance,
    normalised depth and colour (``_candidate``), each (FS, P)."""
    slot = h * FS + fo
    filled = slot < cnt
    f = tl.load(bins_ptr + lbase + slot, mask=filled, other=0)
    inbox = _in_face_box(fbox, f, Fp, xc, yc) & filled[:, None]
    sd, zn, cr, cg, cb = _candidate(cbase + f[:, None], Fp, xc[None, :], yc[None, :], zfar, znear, lx, ly, lz,
                                    ambient, diffuse)
    return f, inbox, sd, zn, cr, cg, cb


@triton.jit
def _blend_walk(coef_ptr, box_ptr, bbox_ptr, sbox_ptr, num_r, num_g, num_b, den, w_sum, cov_sum, m, env, Fp,
                NB, NSB, sb0, NSPLIT,
                xc, yc, inb, x_lo, x_hi, y_lo, y_hi,
                sigma, gamma, znear, zfar, cutoff, cap, ambient, diffuse, lx, ly, lz,
                FB: tl.constexpr, SB: tl.constexpr, FS: tl.constexpr, COMPACT: tl.constexpr):
    """Soft models: online depth softmax over the faces of super-blocks sb0, sb0 + NSPLIT, ..., starting
    from the given sums (floor and background for "softmax", zero for "alpha" and for a split's part);
    also the faces' weight sum and coverage sum. COMPACT: see :func:`_block_chunk`."""
    fo = tl.arange(0, FS)
    cbase = coef_ptr + env * 45 * Fp
    fbox = box_ptr + env * 4 * Fp
    for sb in range(sb0, NSB, NSPLIT):  # coarse: a super-block's box, then its blocks' boxes
        if _block_touches_tile(sbox_ptr, env, NSB, sb, x_lo, x_hi, y_lo, y_hi):
            for j in range(0, SB):
                blk = sb * SB + j
                if _block_touches_tile(bbox_ptr, env, NB, blk, x_lo, x_hi, y_lo, y_hi):
                    n, near, rank, count = _chunks(fbox, Fp, blk, x_lo, x_hi, y_lo, y_hi, FB, FS, COMPACT)
                    for h in range(0, n):  # FS faces at a time: fewer registers per thread
                        _, inbox, sd, zn, cr, cg, cb = _block_chunk(cbase, fbox, fo, Fp, blk, h, near, rank, count,
                                                                    xc, yc, zfar, znear, lx, ly, lz, ambient,
                                                                    diffuse, FB, FS, COMPACT)
                        num_r, num_g, num_b, den, w_sum, cov_sum, m = _blend_chunk(
                            inbox, sd, zn, cr, cg, cb, inb, num_r, num_g, num_b, den, w_sum, cov_sum, m, sigma,
                            gamma, cutoff, cap)
    return num_r, num_g, num_b, den, w_sum, cov_sum, m


@triton.jit
def _blend_list(coef_ptr, box_ptr, bins_ptr, lbase, cnt, num_r, num_g, num_b, den, w_sum, cov_sum, m, env, Fp,
                h0, NSPLIT, xc, yc, inb, sigma, gamma, znear, zfar, cutoff, cap, ambient, diffuse, lx, ly, lz,
                FS: tl.constexpr):
    """Soft models: :func:`_blend_walk` over the tile's face list instead of the blocks, chunks h0, h0 + NSPLIT,
    ... of FS listed faces (the same faces in the same order; the sums regrouped)."""
    fo = tl.arange(0, FS)
    cbase = coef_ptr + env * 45 * Fp
    fbox = box_ptr + env * 4 * Fp
    for h in range(h0, (cnt + FS - 1) // FS, NSPLIT):
        _, inbox, sd, zn, cr, cg, cb = _list_chunk(cbase, fbox, bins_ptr, lbase, cnt, h, fo, Fp, xc, yc, zfar, znear,
                                                   lx, ly, lz, ambient, diffuse, FS)
        num_r, num_g, num_b, den, w_sum, cov_sum, m = _blend_chunk(
            inbox, sd, zn, cr, cg, cb, inb, num_r, num_g, num_b, den, w_sum, cov_sum, m, sigma, gamma, cutoff, cap)
    return num_r, num_g, num_b, den, w_sum, cov_sum, m


@triton.jit
def _blend_pass(coef_ptr, box_ptr, bbox_ptr, sbox_ptr, bins_ptr, lbase, cnt, num_r, num_g, num_b, den, w_sum,
                cov_sum, m, env, Fp, NB, NSB, sb0, NSPLIT,
                xc, yc, inb, x_lo, x_hi, y_lo, y_hi,
                sigma, gamma, znear, zfar, cutoff, cap, ambient, diffuse, lx, ly, lz,
                FB: tl.constexpr, SB: tl.constexpr, FS: tl.constexpr, COMPACT: tl.constexpr, BIN: tl.constexpr,
                CAP: tl.constexpr):
    """Soft models' walk: with BIN and a tile whose list holds all its ``cnt`` faces (``cnt <= CAP``) over the
    list (:func:`_blend_list`; split s takes list chunks s, s + NSPLIT, ...), else, as for an overflowing tile,
    over the blocks (:func:`_blend_walk`; split s takes super-blocks s, s + NSPLIT, ...)."""
    if BIN:
        if cnt <= CAP:
            num_r, num_g, num_b, den, w_sum, cov_sum, m = _blend_list(
                coef_ptr, box_ptr, bins_ptr, lbase, cnt, num_r, num_g, num_b, den, w_sum, cov_sum, m, env, Fp, sb0,
                NSPLIT, xc, yc, inb, sigma, gamma, znear, zfar, cutoff, cap, ambient, diffuse, lx, ly, lz, FS)
        else:
            num_r, num_g, num_b, den, w_sum, cov_sum, m = _blend_walk(
                coef_ptr, box_ptr, bbox_ptr, sbox_ptr, num_r, num_g, num_b, den, w_sum, cov_sum, m, env, Fp, NB,
                NSB, sb0, NSPLIT, xc, yc, inb, x_lo, x_hi, y_lo, y_hi, sigma, gamma, znear, zfar, cutoff, cap,
                ambient, diffuse, lx, ly, lz, FB, SB, FS, COMPACT)
    else:
        num_r, num_g, num_b, den, w_sum, cov_sum, m = _blend_walk(
            coef_ptr, box_ptr, bbox_ptr, sbox_ptr, num_r, num_g, num_b, den, w_sum, cov_sum, m, env, Fp, NB, NSB,
            sb0, NSPLIT, xc, yc, inb, x_lo, x_hi, y_lo, y_hi, sigma, gamma, znear, zfar, cutoff, cap, ambient,
            diffuse, lx, ly, lz, FB, SB, FS, COMPACT)
    return num_r, num_g, num_b, den, w_sum, cov_sum, m


@triton.jit
def _nearest_chunk(f, inbox, sd, zn, cr, cg, cb, inb, col_r, col_g, col_b, nearest, m, REPEATS: tl.constexpr,
                   DEFER: tl.constexpr):
    """Hard model: one chunk of faces (indices (FS,), each other (FS, P)) against the running nearest face:
    the chunk's nearest kept face (lowest index among exact ties) replaces it where strictly nearer.
    REPEATS: the chunk's empty slots repeat a face index (a compacted chunk or a list's tail), so a face's
    colour is taken only where it is kept."""
    keep = inbox & inb[None, :] & (sd >= 0)
    zk = tl.where(keep, zn, -float("inf"))
    best = tl.max(zk, axis=0)
    first = tl.min(tl.where(keep & (zk == best[None, :]), f[:, None], 2147483647), axis=0)
    if not DEFER:
        one = f[:, None] == first[None, :]
        if REPEATS:
            one = one & keep
    upd = best > m
    if not DEFER:
        col_r = tl.where(upd, tl.sum(tl.where(one, cr, 0.0), axis=0), col_r)
        col_g = tl.where(upd, tl.sum(tl.where(one, cg, 0.0), axis=0), col_g)
        col_b = tl.where(upd, tl.sum(tl.where(one, cb, 0.0), axis=0), col_b)
    nearest = tl.where(upd, first.to(nearest.dtype), nearest)
    m = tl.where(upd, best, m)
    return col_r, col_g, col_b, nearest, m


@triton.jit
def _nearest_walk(coef_ptr, box_ptr, bbox_ptr, sbox_ptr, col_r, col_g, col_b, nearest, m, env, Fp, NB,
                  NSB, sb0, NSPLIT,
                  xc, yc, inb, x_lo, x_hi, y_lo, y_hi, znear, zfar, ambient, diffuse, lx, ly, lz,
                  FB: tl.constexpr, SB: tl.constexpr, FS: tl.constexpr, COMPACT: tl.constexpr,
                  DEFER: tl.constexpr):
    """Hard model: among the faces of super-blocks sb0, sb0 + NSPLIT, ..., the nearest face whose
    triangle contains the pixel centre, strictly nearer than ``m`` (the floor or background); the lowest
    face index among exact ties, as the faces come in order. Returns its colour (unshaded with DEFER), its
    index (as a float; -1 for none; ``nearest`` must come in as -1) and its normalised depth. COMPACT: see
    :func:`_block_chunk`."""
    fo = tl.arange(0, FS)
    cbase = coef_ptr + env * 45 * Fp
    fbox = box_ptr + env * 4 * Fp
    for sb in range(sb0, NSB, NSPLIT):  # coarse: a super-block's box, then its blocks' boxes
        if _block_touches_tile(sbox_ptr, env, NSB, sb, x_lo, x_hi, y_lo, y_hi):
            for j in range(0, SB):
                blk = sb * SB + j
                if _block_touches_tile(bbox_ptr, env, NB, blk, x_lo, x_hi, y_lo, y_hi):
                    n, near, rank, count = _chunks(fbox, Fp, blk, x_lo, x_hi, y_lo, y_hi, FB, FS, COMPACT)
                    for h in range(0, n):
                        # with DEFER the colours go unused and are compiled away
                        f, inbox, sd, zn, cr, cg, cb = _block_chunk(cbase, fbox, fo, Fp, blk, h, near, rank, count,
                                                                    xc, yc, zfar, znear, lx, ly, lz, ambient,
                                                                    diffuse, FB, FS, COMPACT)
                        col_r, col_g, col_b, nearest, m = _nearest_chunk(f, inbox, sd, zn, cr, cg, cb, inb, col_r,
                                                                         col_g, col_b, nearest, m, COMPACT, DEFER)
    return col_r, col_g, col_b, nearest, m


@triton.jit
def _nearest_list(coef_ptr, box_ptr, bins_ptr, lbase, cnt, col_r, col_g, col_b, nearest, m, env, Fp, h0, NSPLIT,
                  xc, yc, inb, znear, zfar, ambient, diffuse, lx, ly, lz, FS: tl.constexpr, DEFER: tl.constexpr):
    """Hard model: :func:`_nearest_walk` over the tile's face list, chunks h0, h0 + NSPLIT, ... of FS listed
    faces (the same faces in the same order: the same face at the same depth)."""
    fo = tl.arange(0, FS)
    cbase = coef_ptr + env * 45 * Fp
    fbox = box_ptr + env * 4 * Fp
    for h in range(h0, (cnt + FS - 1) // FS, NSPLIT):
        f, inbox, sd, zn, cr, cg, cb = _list_chunk(cbase, fbox, bins_ptr, lbase, cnt, h, fo, Fp, xc, yc, zfar, znear,
                                                   lx, ly, lz, ambient, diffuse, FS)
        col_r, col_g, col_b, nearest, m = _nearest_chunk(f, inbox, sd, zn, cr, cg, cb, inb, col_r, col_g, col_b,
                                                         nearest, m, True, DEFER)
    return col_r, col_g, col_b, nearest, m


@triton.jit
def _nearest_pass(coef_ptr, box_ptr, bbox_ptr, sbox_ptr, bins_ptr, lbase, cnt, col_r, col_g, col_b, nearest, m, env,
                  Fp, NB, NSB, sb0, NSPLIT,
                  xc, yc, inb, x_lo, x_hi, y_lo, y_hi, znear, zfar, ambient, diffuse, lx, ly, lz,
                  FB: tl.constexpr, SB: tl.constexpr, FS: tl.constexpr, COMPACT: tl.constexpr,
                  DEFER: tl.constexpr, BIN: tl.constexpr, CAP: tl.constexpr):
    """Hard model's walk (:func:`_nearest_walk`; with BIN over the tile's face list where it holds all the
    tile's faces, as :func:`_blend_pass`). DEFER: the walk finds the face by depth alone and shades only the
    chosen face of each pixel at the end (the same arithmetic, so the same colour), instead of shading every
    face-pixel pair it meets."""
    cbase = coef_ptr + env * 45 * Fp
    if BIN:
        if cnt <= CAP:
            col_r, col_g, col_b, nearest, m = _nearest_list(
                coef_ptr, box_ptr, bins_ptr, lbase, cnt, col_r, col_g, col_b, nearest, m, env, Fp, sb0, NSPLIT, xc,
                yc, inb, znear, zfar, ambient, diffuse, lx, ly, lz, FS, DEFER)
        else:
            col_r, col_g, col_b, nearest, m = _nearest_walk(
                coef_ptr, box_ptr, bbox_ptr, sbox_ptr, col_r, col_g, col_b, nearest, m, env, Fp, NB, NSB, sb0,
                NSPLIT, xc, yc, inb, x_lo, x_hi, y_lo, y_hi, znear, zfar, ambient, diffuse, lx, ly, lz, FB, SB, FS,
                COMPACT, DEFER)
    else:
        col_r, col_g, col_b, nearest, m = _nearest_walk(
            coef_ptr, box_ptr, bbox_ptr, sbox_ptr, col_r, col_g, col_b, nearest, m, env, Fp, NB, NSB, sb0, NSPLIT,
            xc, yc, inb, x_lo, x_hi, y_lo, y_hi, znear, zfar, ambient, diffuse, lx, ly, lz, FB, SB, FS, COMPACT,
            DEFER)
    if DEFER:
        won = nearest >= 0
        face = tl.where(won, nearest, 0.0).to(tl.int32)
        _, _, cr, cg, cb = _candidate(cbase + face[None, :], Fp, xc[None, :], yc[None, :], zfar, znear, lx, ly, lz,
                                      ambient, diffuse)
        col_r = tl.where(won, tl.sum(cr, axis=0), col_r)
        col_g = tl.where(won, tl.sum(cg, axis=0), col_g)
        col_b = tl.where(won, tl.sum(cb, axis=0), col_b)
    return col_r, col_g, col_b, nearest, m


@triton.jit
def _bin_faces(box_ptr, bbox_ptr, sbox_ptr, bins_ptr, cnt_ptr, over_ptr, Fp, NB, NSB, H, W, TX,
               TILE_: tl.constexpr, FB: tl.constexpr, SB: tl.constexpr, CAP: tl.constexpr):
    """One program per (tile, environment): the tile's face list, the faces whose boxes (the setup kernel's
    ``face_box``) reach the tile's pixel centres, in face order, found by the forward's walk over super-block
    and block boxes. Writes up to CAP face indices into ``bins_ptr`` (B, T, CAP) int32, the tile's count of such
    faces (all of them, also past CAP) into ``cnt_ptr`` (B, T) int32, and adds 1 to the device counter
    ``over_ptr`` (1,) int32 where the count passes CAP (the walks then take that tile's faces from the blocks)."""
    tile = tl.program_id(0)
    env = tl.program_id(1).to(tl.int64)
    nt = tl.num_programs(0)
    _, _, _, _, x_lo, x_hi, y_lo, y_hi = _tile_pixels(tile, W, H, TX, tl.load(box_ptr), TILE_)
    fbox = box_ptr + env * 4 * Fp
    lbase = (env * nt + tile) * CAP
    c = tl.program_id(0) * 0
    for sb in range(0, NSB):
        if _block_touches_tile(sbox_ptr, env, NSB, sb, x_lo, x_hi, y_lo, y_hi):
            for j in range(0, SB):
                blk = sb * SB + j
                if _block_touches_tile(bbox_ptr, env, NB, blk, x_lo, x_hi, y_lo, y_hi):
                    near, rank, count = _touching_faces(fbox, Fp, blk, x_lo, x_hi, y_lo, y_hi, FB)
                    slot = c + rank
                    tl.store(bins_ptr + lbase + slot, blk * FB + tl.arange(0, FB), mask=near & (slot < CAP))
                    c += count
    tl.store(cnt_ptr + env * nt + tile, c)
    tl.atomic_add(over_ptr, 1, mask=c > CAP)


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
                   FS: tl.constexpr, SAVE: tl.constexpr, SPLIT: tl.constexpr, MODEL: tl.constexpr,
                   COMPACT: tl.constexpr, DEFER: tl.constexpr):
    """The forward without face lists: :func:`_forward_program` (its arguments and grid) with BIN off."""
    _forward_program(coef_ptr, box_ptr, bbox_ptr, sbox_ptr, floor_ptr, prm, out_ptr, state_ptr, part_ptr, box_ptr,
                     box_ptr, Fp, NB, NSB, NSPLIT, H, W, TX, TILE_, FB, SB, FS, SAVE, SPLIT, MODEL, COMPACT, DEFER,
                     False, 1)


@triton.jit
def _binned_forward(coef_ptr, box_ptr, bbox_ptr, sbox_ptr, floor_ptr, prm, out_ptr, state_ptr, part_ptr, bins_ptr,
                    cnt_ptr, Fp, NB, NSB, NSPLIT, H, W, TX, TILE_: tl.constexpr, FB: tl.constexpr, SB: tl.constexpr,
                    FS: tl.constexpr, SAVE: tl.constexpr, SPLIT: tl.constexpr, MODEL: tl.constexpr,
                    COMPACT: tl.constexpr, DEFER: tl.constexpr, CAP: tl.constexpr):
    """The forward reading the tiles' face lists (``tuning.FWD_BIN``): :func:`_forward_program` with BIN on."""
    _forward_program(coef_ptr, box_ptr, bbox_ptr, sbox_ptr, floor_ptr, prm, out_ptr, state_ptr, part_ptr, bins_ptr,
                     cnt_ptr, Fp, NB, NSB, NSPLIT, H, W, TX, TILE_, FB, SB, FS, SAVE, SPLIT, MODEL, COMPACT, DEFER,
                     True, CAP)


@triton.jit
def _forward_program(coef_ptr, box_ptr, bbox_ptr, sbox_ptr, floor_ptr, prm, out_ptr, state_ptr, part_ptr, bins_ptr,
                     cnt_ptr, Fp, NB, NSB, NSPLIT, H, W, TX, TILE_: tl.constexpr, FB: tl.constexpr, SB: tl.constexpr,
                     FS: tl.constexpr, SAVE: tl.constexpr, SPLIT: tl.constexpr, MODEL: tl.constexpr,
                     COMPACT: tl.constexpr, DEFER: tl.constexpr, BIN: tl.constexpr, CAP: tl.constexpr):
    """One program per (tile, environment, split). MODEL: 0 hard, 1 softmax, 2 alpha. State per pixel
    (SAVE): soft models the blend's maximum, its denominator, the faces' weight sum and coverage sum; hard
    the maximum and the chosen face (-1: none).

    Unsplit (``SPLIT`` False, one program per tile): the walk over all faces, the image and the state.
    Split: program s walks super-blocks s, s + NSPLIT, ... from an empty start and stores its part of the
    blend in ``part_ptr`` (NSPLIT, B, PART_PER_PIXEL, H, W): soft models the part's maximum, its colour
    sums (3), weight sum and coverage sum; hard the part's nearest depth, face and colour (3).
    ``_merge_forward`` then combines the parts with the floor and background.

    BIN: the walks read the tile's face list (``bins_ptr`` (B, T, CAP) int32 and its count ``cnt_ptr`` (B, T),
    :func:`_bin_faces`), split s taking its chunks s, s + NSPLIT, ...; a tile whose count passes CAP walks the
    blocks as without BIN."""
    tile = tl.program_id(0)
    env = tl.program_id(1).to(tl.int64)  # offsets below pass 2^31 elements for large batches and images
    split = tl.program_id(2).to(tl.int64)
    sigma, gamma, znear, zfar, cutoff, cap, ambient, diffuse, lx, ly, lz = _load_params(prm)
    xc, yc, pix, inb, x_lo, x_hi, y_lo, y_hi = _tile_pixels(tile, W, H, TX, sigma, TILE_)
    HW = H * W
    if BIN:
        lt = env * tl.num_programs(0) + tile
        cnt = tl.load(cnt_ptr + lt)
        lbase = lt * CAP
    else:  # unused placeholders, of the types above
        cnt = tile * 0
        lbase = env * 0
    if SPLIT:
        zero = tl.zeros_like(xc)
        if MODEL == 0:
            c_r, c_g, c_b, nearest, m = _nearest_pass(
                coef_ptr, box_ptr, bbox_ptr, sbox_ptr, bins_ptr, lbase, cnt, zero, zero, zero, zero - 1.0, zero - 1e4,
                env, Fp, NB, NSB, split, NSPLIT, xc, yc, inb, x_lo, x_hi, y_lo, y_hi, znear, zfar, ambient, diffuse,
                lx, ly, lz, FB, SB, FS, COMPACT, DEFER, BIN, CAP)
            p1, p2, p3, p4, p5 = nearest, c_r, c_g, c_b, zero
        else:
            p1, p2, p3, _den, p4, p5, m = _blend_pass(
                coef_ptr, box_ptr, bbox_ptr, sbox_ptr, bins_ptr, lbase, cnt, zero, zero, zero, zero, zero, zero,
                zero - 1e4, env, Fp, NB, NSB, split, NSPLIT, xc, yc, inb, x_lo, x_hi, y_lo, y_hi, sigma, gamma, znear,
                zfar, cutoff, cap, ambient, diffuse, lx, ly, lz, FB, SB, FS, COMPACT, BIN, CAP)
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
                coef_ptr, box_ptr, bbox_ptr, sbox_ptr, bins_ptr, lbase, cnt, c_r, c_g, c_b, nearest, m, env, Fp, NB,
                NSB, 0, 1, xc, yc, inb, x_lo, x_hi, y_lo, y_hi, znear, zfar, ambient, diffuse, lx, ly, lz, FB, SB, FS,
                COMPACT, DEFER, BIN, CAP)
            s1, s2, s3 = nearest, tl.zeros_like(m), tl.zeros_like(m)
        else:
            zero = tl.zeros_like(fzn)
            num_r, num_g, num_b, den, m = _soft_start(fzn, fr, fg, fb, fhit, bg_r, bg_g, bg_b, gamma, MODEL)
            num_r, num_g, num_b, den, w_sum, cov_sum, m = _blend_pass(
                coef_ptr, box_ptr, bbox_ptr, sbox_ptr, bins_ptr, lbase, cnt, num_r, num_g, num_b, den, zero, zero, m,
                env, Fp, NB, NSB, 0, 1, xc, yc, inb, x_lo, x_hi, y_lo, y_hi, sigma, gamma, znear, zfar, cutoff, cap,
                ambient, diffuse, lx, ly, lz, FB, SB, FS, COMPACT, BIN, CAP)
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
