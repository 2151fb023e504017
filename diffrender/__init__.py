"""diffrender: a differentiable soft rasterizer for articulated MuJoCo robots.

qpos --(RobotModel: pytorch-kinematics FK)--> world vertices --(Camera)--> soft rasterizer --> (B, 3, H, W)

Public API:
    RobotModel.from_mjcf(path, *, detail, dtype, device)  posed meshes of a compiled MuJoCo model
    Camera.look_at(eye, target, up, fov_deg, height, width)  batched pinhole cameras
    tracking_camera(root_pos, *, eye_offset, target_offset, track, ...)  cameras that follow a root
    render(verts, faces, colors, camera, settings, *, normals)  the soft rasterizer
    backend_for(settings, device)  which rasterizer backend render() uses there
    RasterSettings, FloorSettings  keyword-only frozen settings
"""

from .camera import Camera, tracking_camera
from .render import backend_for, render
from .robot import MJCFError, RobotModel
from .settings import FloorSettings, RasterSettings

__all__ = [
    "Camera",
    "FloorSettings",
    "MJCFError",
    "RasterSettings",
    "RobotModel",
    "backend_for",
    "render",
    "tracking_camera",
]
