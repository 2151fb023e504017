"""Fused backend: the rasterizer as two Triton kernels (forward, and a recomputing backward).

Same image model and the same per-pixel arithmetic as :mod:`..kernel` (the dense reference and the tiled
backend), organised for the GPU:

* **Per-face coefficients** (O(B * F)): the projected triangles become the constants of every per-pixel
  quantity, each affine in the pixel centre ``(x, y)`` [px]: screen barycentrics
  ``lambda_k = LA_k + LX_k x + LY_k y``, the position along each edge ``s_k = PA_k + PX_k x + PY_k y``, edge
  heights ``H_k``, squared edge lengths, inverse corner depths and the corners' normals and albedos: ``C = 45``
  numbers per face, laid out (B, C, F) so a kernel reads one coefficient of a block of consecutive faces with
  one coalesced load. Projection and vertex normals are PyTorch (a few ops, differentiated by autograd); the
  rest is two Triton kernels with a hand-written backward (:func:`..setup_kernels.face_setup`: coefficients,
  face boxes, block and super-block boxes); :func:`face_coefficients` is its PyTorch reference. The floor's
  per-pixel depth and colour are one more kernel (:func:`..setup_kernels.floor_planes`).
* **Forward kernel**: one program per (tile of TILE x TILE pixels, environment; 4 x 4 by default). It walks
  the faces in blocks of ``FACE_BLOCK`` on two levels (a super-block of ``SUPER_BLOCK`` blocks, then its blocks),
  skips a super-block or block whose screen bounding box misses the tile, evaluates
  the block's faces at all the tile's pixels as one (FACE_BLOCK, TILE^2) array, and blends with an online
  softmax (a running per-pixel maximum, rescaling the sums when it grows; as in flash attention). It writes
  the image and, when asked, each pixel's blend state (final maximum, denominator, the faces' weight and
  coverage sums): by default no pair lists, no bins, no capacity to overflow (``tuning.FWD_BIN`` bins the
  faces into fixed-capacity per-tile lists first, read by every forward walk; a tile whose list overflows walks
  the blocks, and :func:`bin_overflows` reads the count outside any CUDA graph). Where the faces make many super-blocks
  (:func:`forward_splits`), each tile's walk is split between several programs, each blending its share of
  the super-blocks from an empty start, and a merge kernel combines their parts with the floor and background
  (online softmaxes merge exactly; the hard model keeps the nearest part, ties to the lowest face index).
* **Backward kernel**: one program per (tile of BWD_TILE x BWD_TILE pixels, environment; BWD_TILE_DENSE where
  faces crowd, :func:`backward_tile`) and per split of the super-blocks (:func:`backward_splits`: one split
  per 2k faces, up to 16), walking its faces as the forward does. From each pixel's
  blend state and colour (kept by the forward, or from a second forward pass), it forms the gradient of
  every pixel-face pair in closed form. Faces are taken in sub-blocks of ``BWD_SUB_BLOCK``, one face per lane,
  of each block only the faces whose own boxes reach the tile, packed in face order (``BWD_COMPACT``):
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
instead (coverage a step, no sums; ``FWD_DEFER_SHADING``: the walk compares depths only and shades the chosen
face once at the end), and its backward differentiates only the chosen face's colour.

Saved for backward: the inputs (O(B * V)); with ``RasterSettings.save_blend_state`` also the image and four
numbers of each pixel's blend (7 numbers, O(B * H * W)), which spares the backward a second forward pass.
Flat in the number of faces either way. Requires CUDA tensors, or, for testing on a CPU,
``TRITON_INTERPRET=1`` in the environment before this package is imported (Triton's interpreter).

Modules: :mod:`.tuning` (the constants above: tile sides, blocks, splits, warps, register caps, memory bounds;
set them there between renders), :mod:`.forward` and :mod:`.backward` (the Triton kernels), :mod:`.rasterize`
(:func:`rasterize_fused`, the autograd Function and the launch heuristics) and :mod:`.reference` (the
setup kernels' PyTorch references). Without Triton the package imports, and rendering raises.
"""

from ..setup_kernels import NUM_COEFFS, face_setup
from . import tuning
from .rasterize import (
    BinOverflowWarning,
    available,
    backward_splits,
    backward_tile,
    bin_capacity_needed,
    bin_overflows,
    forward_splits,
    rasterize_fused,
)
from .reference import face_coefficients, super_block_boxes

__all__ = ["NUM_COEFFS", "BinOverflowWarning", "available", "backward_splits", "backward_tile", "bin_capacity_needed",
           "bin_overflows", "face_coefficients", "face_setup", "forward_splits", "rasterize_fused", "super_block_boxes",
           "tuning"]
