"""Renderer settings (frozen, keyword-only dataclasses: hashable, so they can key compiled kernels)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from vocabulary import RASTER_MODELS

__all__ = ["RASTER_MODELS", "FloorSettings", "RasterModel", "RasterSettings"]

#: the image models of :class:`RasterSettings` (``raster_model``), named in vocabulary.RASTER_MODELS
RasterModel = Literal[RASTER_MODELS]

_RGB = tuple[float, float, float]


def _check_rgb(name: str, c) -> None:
    if len(c) != 3 or not all(0.0 <= float(x) <= 1.0 for x in c):
        raise ValueError(f"{name} must be three floats in [0, 1], got {c!r}")


@dataclass(frozen=True, kw_only=True)
class FloorSettings:
    """The analytic floor: the plane z = 0 with a smooth checker texture.

    The checker is ``mix(color_a, color_b, 0.5 + 0.5 tanh(k sin(pi x / s) sin(pi y / s)))`` with the
    sharpness ``k`` chosen per pixel so an edge between squares spans about ``edge_px`` pixels; far away,
    where squares shrink below a pixel, ``k`` falls and the texture fades smoothly to the mean colour
    instead of aliasing. The texture is what makes a tracking camera's image depend on the camera position
    (an untextured floor gives exactly zero gradient w.r.t. the base position).

    Attributes:
        square_size: side of one checker square [m].
        color_a, color_b: the two square colours (albedo, lit like the robot with normal +z).
        edge_px: edge softness [px].
    """

    square_size: float = 0.5
    color_a: _RGB = (0.82, 0.82, 0.78)
    color_b: _RGB = (0.42, 0.45, 0.48)
    edge_px: float = 0.75

    def __post_init__(self) -> None:
        if not self.square_size > 0:
            raise ValueError(f"square_size must be > 0, got {self.square_size}")
        if not self.edge_px > 0:
            raise ValueError(f"edge_px must be > 0, got {self.edge_px}")
        _check_rgb("color_a", self.color_a)
        _check_rgb("color_b", self.color_b)


@dataclass(frozen=True, kw_only=True)
class RasterSettings:
    """Rasterizer settings.

    ``raster_model`` picks the image model, and with it the gradient estimator (docs/design.md,
    "Image model"). Shared by all three: per pixel centre, a face is a candidate with exact signed Euclidean
    distance ``sd`` [px] to its screen triangle (positive inside) and normalised depth
    ``z_n = (zfar - z) / (zfar - znear)`` (``z`` from perspective-correct barycentrics, which also interpolate
    vertex normals and albedos); colours are Lambert-shaded, ``albedo (ambient + diffuse max(0, n . l))``.
    Behind every face lies the analytic floor where the pixel's ray hits it, else the background (normalised
    depth 0, the far plane).

    * ``"hard"``: a z-buffer. The pixel shows the nearest face whose closed screen triangle contains its
      centre (one face per pixel; the lowest face index among exact depth ties), else the floor, else the
      background; coverage is a step. Gradients reach vertices, normals, colours and the camera only through
      the perspective-correct interpolation and shading of that face (and the floor texture), never through
      which face or surface is seen: silhouettes and occlusion boundaries carry none. This is the estimator of
      D.Va's "SHAC with differentiable rendering" baseline (PyTorch3D ``MeshRasterizer`` with
      ``blur_radius=0, faces_per_pixel=1``, then ``SoftPhongShader``). ``sigma``, ``gamma`` and
      ``coverage_cutoff`` do not act.
    * ``"softmax"``: SoftRas aggregation (Liu et al. 2019, "Soft Rasterizer"). Each face within the
      coverage cut-off has coverage ``D = sigmoid(sd / sigma)`` and weight ``w = D exp((z_n - m) / gamma)``
      (``m``: the pixel's largest candidate ``z_n``, detached; it cancels and only prevents overflow); the
      floor (``D = 1``) and the background (``exp((0 - m) / gamma)``) are candidates of the same softmax, so
      the floor hides what lies below it. The silhouettes against floor and sky follow the faces' joint
      coverage ``A = min(1, sum D)``: with ``W`` the faces' weight sum, ``num / den`` the softmax over faces,
      floor and background, and ``C_b`` the floor/background colour behind the faces,
      ``colour = (A num + (1 - A) W C_b) / (A den + (1 - A) W)``. Where the faces cover the pixel
      (``A = 1``) this is the plain softmax; at a silhouette in front of the floor or sky (``den ~ W``) it
      is ``A softmax + (1 - A) C_b``, so the robot's share fades with its coverage and is one half on the
      true edge: the silhouette is not dilated, and it carries gradient through the sigmoid. (In the plain
      SoftRas softmax a face in front of a surface ``dz_n`` behind it weighs ``D exp(dz_n / gamma)`` against
      it, so it owns every pixel out to the coverage cut-off: silhouettes dilated by ``cutoff_radius`` and
      ending in a jump.) Between faces the softmax acts unchanged.
    * ``"alpha"``: coverage compositing (the silhouette aggregation of Soft Rasterizer and the over
      operator of Porter and Duff 1984): the depth softmax runs over the faces only and is composited over
      the floor/background colour with ``A = min(1, sum D)``: ``colour = A num_f / W + (1 - A) C_b``.
      The floor never occludes faces (parts below z = 0 stay visible). The same formula as ``"softmax"``
      with the floor and background left out of ``num`` and ``den``.

    For both soft models ``A`` sums the coverage of every kept face, hidden ones included: with
    ``cull_backfaces=True`` a face that turns away at a silhouette leaves the sum at once (a jump of up to
    its coverage there); ``cull_backfaces=False`` avoids that at twice the work. As sigma, gamma -> 0 both
    soft images converge to the hard one (``tests/diffrender/test_raster.py``).

    Attributes:
        raster_model: ``"hard"``, ``"softmax"`` (default) or ``"alpha"``, see above.
        sigma: coverage softness [px] (soft models).
        gamma: depth-blend temperature in units of ``z_n`` (``gamma * (zfar - znear)`` metres of depth
            separate two surfaces by a factor e in weight) (soft models).
        znear, zfar: clipping depths [m]. Faces with a vertex closer than ``znear`` are dropped (no
            clipping); the floor is kept beyond ``zfar`` (so it reaches the horizon), faces are not.
        background: colour where no ray hits the floor or a face.
        floor: :class:`FloorSettings`, or None for no floor.
        light_dir: direction towards a directional light, world frame (normalised internally).
        ambient, diffuse: Lambert coefficients, ``ambient + diffuse <= 1`` keeps colours in [0, 1].
        cull_backfaces: drop faces whose projected winding shows their back. Halves the work on closed
            meshes; see above for what it does to the soft models' silhouettes.
        coverage_cutoff: soft models: pairs with ``D`` below this are dropped exactly (binning radius
            ``sigma * ln(1 / cutoff - 1)``); every backend drops the same pairs. With ``A`` the dropped pair
            changes the colour by at most about ``coverage_cutoff``.
        backend: ``"fused"`` (two Triton kernels, forward and a recomputing backward; CUDA only; the
            fastest), ``"tiled"`` (binned PyTorch kernel with a memory-bounded custom backward; any device),
            ``"dense"`` (every face at every pixel, plain autograd; tiny scenes and tests only) or
            ``"auto"``: fused for CUDA tensors when Triton is installed, else tiled. All implement every
            ``raster_model``.
        tile_size: tile side [px] for the tiled backend's binning (the fused backend has its own tiles).
        bin_capacity: (tile, face) pairs per environment the tiled backend can hold (its work is
            proportional to it). None (default): measured the first time a scene layout (faces, image and
            tile size, cut-off radius) is rendered, plus 25 % headroom, then fixed; if a later frame needs
            more, the capacity grows and that frame is rendered again (with a warning). An int is a hard
            limit: overflow raises a RuntimeError with the numbers. Never an incomplete image.
        chunk_elems: pixel-face evaluations per chunk (bounds transient memory); environments are
            processed ``max(1, chunk_elems // (bin_capacity * tile_size**2))`` at a time.
        compile: run the PyTorch parts of the rasterizer through ``torch.compile`` (the first call per shape
            compiles; forward and the recompute-backward compile separately): the tiled backend's binning
            and per-chunk kernel, the fused backend's per-face setup (coefficients, floor planes). Eager,
            they launch several hundred small kernels per render.
        save_blend_state: fused backend: keep the image and four numbers of each pixel's blend for the
            backward (7 numbers per pixel, 12.6 MB for 64 images of 84 x 84 at float32) instead of
            recomputing them with a second forward pass at backward time (cost in BENCHMARKS.md). Off by
            default so a render keeps only its inputs (0.7 MB).
        sync_checks: check bin overflow, face indices and finiteness with one host synchronisation per
            render and raise errors. When False (needed inside CUDA-graph capture) nothing syncs and an
            environment whose bins overflow renders as NaN instead, which downstream NaN guards catch.
    """

    sigma: float = 0.1
    gamma: float = 2e-4
    znear: float = 0.05
    zfar: float = 25.0
    background: _RGB = (0.62, 0.74, 0.86)
    floor: FloorSettings | None = field(default_factory=FloorSettings)
    light_dir: tuple[float, float, float] = (0.35, -0.5, 1.0)
    ambient: float = 0.4
    diffuse: float = 0.6
    cull_backfaces: bool = True
    raster_model: RasterModel = "softmax"
    coverage_cutoff: float = 1e-4
    backend: str = "auto"
    tile_size: int = 2
    bin_capacity: int | None = None
    chunk_elems: int = 1 << 23
    compile: bool = False
    save_blend_state: bool = False
    sync_checks: bool = True

    def __post_init__(self) -> None:
        if not (self.sigma > 0 and math.isfinite(self.sigma)):
            raise ValueError(f"sigma must be > 0 [px], got {self.sigma}")
        if not (self.gamma > 0 and math.isfinite(self.gamma)):
            raise ValueError(f"gamma must be > 0, got {self.gamma}")
        if not 0 < self.znear < self.zfar < math.inf:
            raise ValueError(f"need 0 < znear < zfar < inf, got znear={self.znear}, zfar={self.zfar}")
        _check_rgb("background", self.background)
        if self.floor is not None and not isinstance(self.floor, FloorSettings):
            raise ValueError(f"floor must be a FloorSettings or None, got {type(self.floor).__name__}")
        if len(self.light_dir) != 3 or math.hypot(*self.light_dir) == 0:
            raise ValueError(f"light_dir must be a non-zero 3-vector, got {self.light_dir!r}")
        if self.ambient < 0 or self.diffuse < 0:
            raise ValueError(f"ambient and diffuse must be >= 0, got {self.ambient}, {self.diffuse}")
        if not 0 < self.coverage_cutoff < 0.5:
            raise ValueError(f"coverage_cutoff must be in (0, 0.5), got {self.coverage_cutoff}")
        if self.raster_model not in RASTER_MODELS:
            raise ValueError(f"raster_model must be one of {', '.join(map(repr, RASTER_MODELS))}, "
                             f"got {self.raster_model!r}")
        if self.backend not in ("auto", "dense", "tiled", "fused"):
            raise ValueError(f"backend must be 'auto', 'fused', 'tiled' or 'dense', got {self.backend!r}")
        if not (isinstance(self.tile_size, int) and 1 <= self.tile_size <= 64):
            raise ValueError(f"tile_size must be an int in [1, 64], got {self.tile_size!r}")
        if self.bin_capacity is not None and not (isinstance(self.bin_capacity, int) and self.bin_capacity > 0):
            raise ValueError(f"bin_capacity must be a positive int or None, got {self.bin_capacity!r}")
        if not (isinstance(self.chunk_elems, int) and self.chunk_elems > 0):
            raise ValueError(f"chunk_elems must be a positive int, got {self.chunk_elems!r}")

    @property
    def cutoff_radius(self) -> float:
        """Distance [px] outside a triangle beyond which its coverage is below ``coverage_cutoff``; 0 for
        the hard model (only pixel centres inside a triangle count)."""
        if self.raster_model == "hard":
            return 0.0
        return self.sigma * math.log(1.0 / self.coverage_cutoff - 1.0)

