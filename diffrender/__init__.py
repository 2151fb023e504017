"""diffrender: a differentiable soft rasterizer for articulated MuJoCo robots.

qpos --(RobotModel: pytorch-kinematics FK)--> world vertices --(Camera)--> soft rasterizer --> (B, 3, H, W)

Public API:
    RobotModel.from_mjcf(path, *, detail, dtype, device)  posed meshes of a compiled MuJoCo model
    RobotModel.pose(qpos) -> RobotPose  one forward-kinematics pass; links, geoms and meshes read off it
    Camera.look_at(eye, target, up, fov_deg, height, width)  batched pinhole cameras
    tracking_camera(root_pos, *, eye_offset, target_offset, track, ...)  cameras that follow a root
    focal_length(fov_deg, height)  the focal length [px] those cameras use
    render(verts, faces, colors, camera, settings, *, normals)  the soft rasterizer
    backend_for(settings, device)  which rasterizer backend render() uses there
    measure_bin_capacity(verts, faces, camera, settings)  a tiled-backend bin capacity for a frame
    bin_overflows()  the fused backend's binned tile lists that overflowed since the last call (0 unbinned)
    BinCapacityWarning  the tiled backend's automatic bin capacity grew (given once per process)
    RasterSettings, FloorSettings  keyword-only frozen settings
    RayTracer(faces, *, num_envs, num_verts, device, settings, shadows)  forward-only Warp ray tracer of the
        same scene (the rasterizer's sharp limit; no gradient), render_raytraced(...) its functional form
"""

import sys

import torch

from . import raster
from .camera import Camera, focal_length, tracking_camera
from .raytrace import RayTracer, render_raytraced
from .render import BinCapacityWarning, backend_for, render
from .robot import MJCFError, RobotModel, RobotPose
from .settings import FloorSettings, RasterSettings

__all__ = [
    "BinCapacityWarning",
    "Camera",
    "FloorSettings",
    "MJCFError",
    "RasterSettings",
    "RayTracer",
    "RobotModel",
    "RobotPose",
    "backend_for",
    "bin_overflows",
    "focal_length",
    "measure_bin_capacity",
    "render",
    "render_raytraced",
    "tracking_camera",
]


def bin_overflows() -> int:
    """The (tile, environment) face lists of the fused backend's binned forward (``FWD_BIN``) that overflowed
    their capacity since the last call, over every device, and the counters reset
    (:func:`diffrender.raster.fused.bin_overflows`: the first nonzero count warns once). 0 where the fused
    backend has not rendered in this process: it is not imported for the question. Call it outside CUDA graph
    capture, after a synchronisation: one host transfer per device that rendered binned."""
    fused = sys.modules.get(f"{__name__}.raster.fused")
    return 0 if fused is None else fused.bin_overflows()


def measure_bin_capacity(verts: torch.Tensor, faces: torch.Tensor, camera: Camera, settings: RasterSettings) -> int:
    """(tile, face) pairs per environment that the tiled backend needs for this frame, with the headroom the
    automatic capacity uses: a value for ``RasterSettings(bin_capacity=...)``. A fixed capacity is what a
    render inside a captured CUDA graph needs, since there it cannot measure or grow its bins.

    Args:
        verts: (B, V, 3) [m] world vertices.
        faces: (F, 3) long.
        camera: B cameras, or one (broadcast to B).
        settings: the settings the frames will be rendered with (tile size and chunking set the count).
    Returns:
        the capacity, pairs per environment. One host synchronisation.
    """
    if not (isinstance(verts, torch.Tensor) and verts.ndim == 3 and verts.shape[-1] == 3):
        raise ValueError(f"verts must be a (B, V, 3) tensor, got {getattr(verts, 'shape', type(verts))}")
    camera = camera.expand(verts.shape[0])
    static = raster.tiled_static(settings, camera)
    _, capacity = raster.measure_capacity(verts, camera.rotation, camera.eye, faces, settings, static)
    return capacity
