"""Rasterization with three image models (``RasterSettings.raster_model``): a shared per-pair kernel, a dense
reference backend and the tiled backend (the fused Triton backend is :mod:`.fused`, imported when used)."""

from .binning import Bins, bin_faces, count_pairs
from .dense import rasterize_dense
from .kernel import Static, face_validity, project, render_pairs, vertex_normals
from .tiled import chunk_of, measure_capacity, rasterize_tiled, tiled_static

__all__ = [
    "Bins",
    "Static",
    "bin_faces",
    "count_pairs",
    "chunk_of",
    "face_validity",
    "measure_capacity",
    "project",
    "rasterize_dense",
    "rasterize_tiled",
    "render_pairs",
    "tiled_static",
    "vertex_normals",
]
