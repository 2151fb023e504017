"""Dense reference backend: every face at every pixel, plain autograd.

Memory is O(B * F * H * W) in the forward and everything is kept for the backward, so this is for tests and
tiny scenes only. It shares the per-pair mathematics with the tiled backend (:mod:`.kernel`) and differs in
everything the tiled backend adds: no binning, no chunking, no custom autograd function, no recompute.
"""

from __future__ import annotations

import torch

from ..camera import Camera
from ..settings import RasterSettings
from .kernel import Static, face_validity, project, render_pairs

__all__ = ["rasterize_dense"]


def rasterize_dense(verts: torch.Tensor, normals: torch.Tensor | None, colors: torch.Tensor, camera: Camera,
                    faces: torch.Tensor, settings: RasterSettings) -> torch.Tensor:
    """Render (B, 3, H, W) with one tile covering the whole image and every face as a pair (see
    :func:`diffrender.render` for the arguments)."""
    st = Static.make(settings, focal=camera.focal, height=camera.height, width=camera.width,
                     tile_h=camera.height, tile_w=camera.width)
    b, nf = verts.shape[0], faces.shape[0]
    with torch.no_grad():
        valid = face_validity(project(verts, camera.rotation, camera.eye, st)[:, faces], st)
    dev = verts.device
    pair_env = torch.arange(b, device=dev).repeat_interleave(nf)
    pair_face = torch.arange(nf, device=dev).repeat(b)
    return render_pairs(verts, normals, colors, camera.rotation, camera.eye, faces, pair_env, pair_face,
                        torch.zeros_like(pair_face), valid.reshape(-1), st)
