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
from .binning import Bins, bin_faces
from .kernel import Static, render_pairs

__all__ = ["rasterize_tiled", "tiled_static"]


@functools.cache
def _compiled_kernel():
    return torch.compile(render_pairs, dynamic=False)


def _kernel(compile_: bool):
    return _compiled_kernel() if compile_ else render_pairs


def tiled_static(settings: RasterSettings, camera: Camera) -> Static:
    return Static.make(settings, focal=camera.focal, height=camera.height, width=camera.width,
                       tile_h=settings.tile_size, tile_w=settings.tile_size)


def _bins(verts, rotation, eye, faces, st: Static, capacity: int) -> Bins:
    if faces.shape[0] == 0 or capacity == 0:
        b = verts.shape[0]
        empty = torch.zeros(b, 0, dtype=torch.long, device=verts.device)
        return Bins(face=empty, tile=empty, valid=empty.bool(), count=torch.zeros(b, dtype=torch.long,
                                                                                    device=verts.device))
    return bin_faces(verts, rotation, eye, faces, st, capacity)


def _rows(x: torch.Tensor | None, sl: slice, *, shared_ok: bool = False) -> torch.Tensor | None:
    """Slice a per-environment tensor; shared (V, 3) colours (``shared_ok``) are used whole."""
    if x is None or (shared_ok and x.ndim == 2):
        return x
    return x[sl]


class _TiledRasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, verts, normals, colors, rotation, eye, faces, st: Static, capacity: int, chunk: int,
                compile_: bool):
        kernel = _kernel(compile_)
        b = verts.shape[0]
        out = verts.new_empty(b, 3, st.height, st.width)
        counts = []
        for b0 in range(0, b, chunk):
            sl = slice(b0, min(b, b0 + chunk))
            bins = _bins(verts[sl], rotation[sl], eye[sl], faces, st, capacity)
            counts.append(bins.count)
            out[sl] = kernel(verts[sl], _rows(normals, sl), _rows(colors, sl, shared_ok=True), rotation[sl],
                             eye[sl], faces, bins.face, bins.tile, bins.valid, st)
        count = torch.cat(counts)
        # an environment whose bins overflowed is NaN, never a silently incomplete image (render() also
        # raises unless host syncs are disabled)
        out.masked_fill_((count > capacity)[:, None, None, None], math.nan)
        ctx.save_for_backward(verts, normals, colors, rotation, eye, faces)
        ctx.cfg = (st, capacity, chunk, compile_)
        ctx.mark_non_differentiable(count)
        return out, count

    @staticmethod
    def backward(ctx, grad_img, _grad_count):
        verts, normals, colors, rotation, eye, faces = ctx.saved_tensors
        st, capacity, chunk, compile_ = ctx.cfg
        kernel = _kernel(compile_)
        need = ctx.needs_input_grad[:5]
        inputs = (verts, normals, colors, rotation, eye)
        grads = [torch.zeros_like(x) if (nd and x is not None) else None for x, nd in zip(inputs, need)]
        b = verts.shape[0]
        for b0 in range(0, b, chunk):
            sl = slice(b0, min(b, b0 + chunk))
            bins = _bins(verts[sl], rotation[sl], eye[sl], faces, st, capacity)
            with torch.enable_grad():
                leaves = [None if x is None
                          else _rows(x, sl, shared_ok=i == 2).detach().requires_grad_(bool(nd))
                          for i, (x, nd) in enumerate(zip(inputs, need))]
                img = kernel(*leaves, faces, bins.face, bins.tile, bins.valid, st)
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


def rasterize_tiled(verts: torch.Tensor, normals: torch.Tensor | None, colors: torch.Tensor, camera: Camera,
                    faces: torch.Tensor, settings: RasterSettings, capacity: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Tiled render with ``capacity`` pair slots per environment (see :func:`diffrender.render`). Returns the
    image (B, 3, H, W) (NaN for environments that overflowed) and the pairs each environment needed (B,)."""
    st = tiled_static(settings, camera)
    capacity = capacity if faces.shape[0] else 0
    chunk = max(1, settings.chunk_elems // max(1, capacity * st.tile_pixels))
    return _TiledRasterize.apply(verts, normals, colors, camera.rotation, camera.eye, faces, st, capacity, chunk,
                                 bool(settings.compile))
