"""Tiled backend: binned pairs, chunked over environments, with a memory-bounded custom backward.

Forward (no autograd graph inside): for each chunk of environments, bin faces into tiles
(:mod:`.binning`) and run the kernel (:mod:`.kernel`) on the pair lists.

Saved for backward: only the inputs (world vertices, normals if given, colours, camera rotation and eye,
faces), i.e. O(B * V) - no pair lists, no per-pixel-per-face intermediates, no per-pixel statistics. The
backward recomputes, per chunk of environments, the binning and the kernel under autograd and
back-propagates the incoming image gradient through that chunk only, accumulating into the input gradients.
Each chunk's autograd graph is freed before the next one, so transient memory is bounded by the chunk size
and saved memory is independent of the number of faces and of faces per pixel. Since nothing the backward
needs is consumed, ``backward(retain_graph=True)`` can be called any number of times.

Because a chunk holds whole environments, the chunk's image - including the per-pixel max ``m`` and
denominators - is recomputed exactly, so gradients equal those of the dense backend (up to float summation
order).
"""

from __future__ import annotations

import functools
import math

import torch

from ..camera import Camera
from ..settings import RasterSettings
from .binning import Bins, bin_faces, count_pairs
from .common import chunks, rows
from .kernel import Static, render_pairs

__all__ = ["chunk_of", "measure_capacity", "rasterize_tiled", "tiled_static"]


@functools.cache
def _compiled(fn):
    # static shapes (bin capacity, chunk size) by construction: no dynamic-shape tracing
    return torch.compile(fn, dynamic=False)


def _kernel(compile_: bool):
    return _compiled(render_pairs) if compile_ else render_pairs


def _binner(compile_: bool):
    return _compiled(bin_faces) if compile_ else bin_faces


def tiled_static(settings: RasterSettings, camera: Camera) -> Static:
    return Static.make(settings, focal=camera.focal, height=camera.height, width=camera.width,
                       tile_h=settings.tile_size, tile_w=settings.tile_size)


def _chunk_envs(settings: RasterSettings, st: Static, capacity: int) -> int:
    """Environments per chunk: as many as fit ``chunk_elems`` pixel-face evaluations."""
    return max(1, settings.chunk_elems // max(1, capacity * st.tile_pixels))


def _bins(verts, rotation, eye, faces, st: Static, slots: int, compile_: bool = False) -> Bins:
    if faces.shape[0] == 0 or slots == 0:
        b, dev = verts.shape[0], verts.device
        empty = torch.zeros(0, dtype=torch.long, device=dev)
        return Bins(env=empty, face=empty, tile=empty, valid=empty.bool(),
                    count=torch.zeros(b, dtype=torch.long, device=dev))
    return _binner(compile_)(verts, rotation, eye, faces, st, slots)


class _TiledRasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, verts, normals, colors, rotation, eye, faces, st: Static, capacity: int, chunk: int,
                compile_: bool):
        kernel = _kernel(compile_)
        b = verts.shape[0]
        out = verts.new_empty(b, 3, st.height, st.width)
        need = torch.zeros(b, dtype=torch.long, device=verts.device)
        for sl in chunks(b, chunk):
            nb = sl.stop - sl.start
            bins = _bins(verts[sl], rotation[sl], eye[sl], faces, st, capacity * nb, compile_)
            # slots are pooled over the chunk: report the chunk's demand per environment (rounded up)
            need[sl] = -(-bins.count.sum() // nb)
            out[sl] = kernel(verts[sl], rows(normals, sl), rows(colors, sl, shared_ok=True), rotation[sl],
                             eye[sl], faces, bins.env, bins.face, bins.tile, bins.valid, st)
        # environments of an overflowing chunk are NaN, never a silently incomplete image (render() also
        # raises unless host syncs are disabled)
        out.masked_fill_((need > capacity)[:, None, None, None], math.nan)
        ctx.save_for_backward(verts, normals, colors, rotation, eye, faces)
        ctx.cfg = (st, capacity, chunk, compile_)
        ctx.mark_non_differentiable(need)
        # an undefined incoming gradient (e.g. gradlab's closed ImageGate) stays None: no recompute at all
        ctx.set_materialize_grads(False)
        return out, need

    @staticmethod
    def backward(ctx, grad_img, _grad_need):
        verts, normals, colors, rotation, eye, faces = ctx.saved_tensors
        st, capacity, chunk, compile_ = ctx.cfg
        if grad_img is None:
            return (None,) * 10
        kernel = _kernel(compile_)
        need = ctx.needs_input_grad[:5]
        inputs = (verts, normals, colors, rotation, eye)
        grads = [torch.zeros_like(x) if (nd and x is not None) else None for x, nd in zip(inputs, need)]
        for sl in chunks(verts.shape[0], chunk):
            bins = _bins(verts[sl], rotation[sl], eye[sl], faces, st, capacity * (sl.stop - sl.start), compile_)
            with torch.enable_grad():
                leaves = [None if x is None
                          else rows(x, sl, shared_ok=i == 2).detach().requires_grad_(bool(nd))
                          for i, (x, nd) in enumerate(zip(inputs, need))]
                img = kernel(*leaves, faces, bins.env, bins.face, bins.tile, bins.valid, st)
                wanted = [i for i, leaf in enumerate(leaves) if leaf is not None and leaf.requires_grad]
                if not wanted:
                    continue
                parts = torch.autograd.grad(img, [leaves[i] for i in wanted], grad_img[sl], allow_unused=True)
            for i, gpart in zip(wanted, parts):
                if gpart is None:
                    continue
                if i == 2 and inputs[i].ndim == 2:  # shared colours: sum over chunks
                    grads[i] += gpart
                else:
                    grads[i][sl] += gpart
        return (*grads, None, None, None, None, None)


def measure_capacity(verts, rotation, eye, faces, settings: RasterSettings, st: Static) -> tuple[int, int]:
    """Slots per environment the current frame needs under the chunking that capacity implies, and the
    capacity with 25 % headroom (two passes: the chunking depends on the capacity). One host sync."""
    counts = count_pairs(verts, rotation, eye, faces, st).tolist()
    b = len(counts)
    capacity = _with_headroom(sum(counts) / b)
    need = 0
    for _ in range(2):
        chunk = _chunk_envs(settings, st, capacity)
        need = max(-(-sum(counts[sl]) // (sl.stop - sl.start)) for sl in chunks(b, chunk))
        capacity = _with_headroom(need)
    return need, capacity


def chunk_of(env: int, b: int, settings: RasterSettings, st: Static, capacity: int) -> slice:
    """The chunk of environments that ``env`` is rendered with."""
    chunk = _chunk_envs(settings, st, capacity)
    start = env // chunk * chunk
    return slice(start, min(b, start + chunk))


def _with_headroom(need: float) -> int:
    return max(64, -(-int(need * 1.25) // 64) * 64)


def rasterize_tiled(verts: torch.Tensor, normals: torch.Tensor | None, colors: torch.Tensor, camera: Camera,
                    faces: torch.Tensor, settings: RasterSettings, capacity: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Tiled render with ``capacity`` pair slots per environment, pooled over each chunk of environments
    (see :func:`diffrender.render`). Returns the image (B, 3, H, W) (NaN for the environments of a chunk
    that overflowed) and each environment's chunk demand per environment (B,) long (> capacity: overflow)."""
    st = tiled_static(settings, camera)
    capacity = capacity if faces.shape[0] else 0
    return _TiledRasterize.apply(verts, normals, colors, camera.rotation, camera.eye, faces, st, capacity,
                                 _chunk_envs(settings, st, capacity), bool(settings.compile))
