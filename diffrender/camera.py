"""Batched pinhole cameras in pixel units.

Conventions (OpenCV): camera frame x right, y down, z forward (depth); pixel ``(row i, column j)`` has its
centre at ``(u, v) = (j + 0.5, i + 0.5)``; a camera-frame point ``(x, y, z)`` projects to
``u = f x / z + W / 2``, ``v = f y / z + H / 2`` with the focal length ``f = (H / 2) / tan(fov / 2)`` [px]
(``fov`` is the vertical field of view). World frame: MuJoCo's, z up.

Camera extrinsics are tensors in the autograd graph, so an image is differentiable with respect to the eye
and target positions (a tracking camera follows the robot's root, so its pose depends on ``qpos``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

__all__ = ["Camera", "focal_length", "tracking_camera"]

_Vec = torch.Tensor | Sequence[float]


@dataclass(frozen=True, eq=False)
class Camera:
    """A batch of B pinhole cameras sharing intrinsics and image size.

    Attributes:
        rotation: (B, 3, 3) world -> camera rotation; its rows are the camera's right, down and forward
            axes expressed in the world frame.
        eye: (B, 3) [m] camera centre in the world frame.
        focal: focal length [px] (same for x and y: square pixels).
        height, width: image size [px].
    """

    rotation: torch.Tensor
    eye: torch.Tensor
    focal: float
    height: int
    width: int

    def __post_init__(self) -> None:
        r, e = self.rotation, self.eye
        if not (isinstance(r, torch.Tensor) and r.ndim == 3 and r.shape[1:] == (3, 3)):
            raise ValueError(f"camera rotation must be a (B, 3, 3) tensor, got {getattr(r, 'shape', type(r))}")
        if not (isinstance(e, torch.Tensor) and e.ndim == 2 and e.shape[1] == 3 and e.shape[0] == r.shape[0]):
            raise ValueError(f"camera eye must be a (B, 3) tensor with B = {r.shape[0]}, "
                             f"got {getattr(e, 'shape', type(e))}")
        if r.dtype != e.dtype or r.device != e.device:
            raise ValueError(f"camera rotation ({r.dtype}, {r.device}) and eye ({e.dtype}, {e.device}) differ")
        if not r.dtype.is_floating_point:
            raise ValueError(f"camera tensors must be floating point, got {r.dtype}")
        if int(self.height) <= 0 or int(self.width) <= 0:
            raise ValueError(f"image size must be positive, got height={self.height}, width={self.width}")
        if not (self.focal > 0 and math.isfinite(self.focal)):
            raise ValueError(f"focal length must be positive and finite, got {self.focal}")

    @property
    def batch_size(self) -> int:
        return int(self.rotation.shape[0])

    @property
    def cx(self) -> float:
        """Principal point x [px] (image centre)."""
        return 0.5 * self.width

    @property
    def cy(self) -> float:
        """Principal point y [px] (image centre)."""
        return 0.5 * self.height

    @property
    def dtype(self) -> torch.dtype:
        return self.rotation.dtype

    @property
    def device(self) -> torch.device:
        return self.rotation.device

    @classmethod
    def look_at(cls, eye: _Vec, target: _Vec, up: _Vec, fov_deg: float, height: int, width: int) -> Camera:
        """Cameras at ``eye`` looking at ``target`` with ``up`` roughly up in the image.

        Args:
            eye: (B, 3) or (3,) [m].
            target: (B, 3) or (3,) [m].
            up: (B, 3) or (3,), need not be unit or orthogonal to the view direction, but not parallel to it.
            fov_deg: vertical field of view [deg], in (0, 180).
            height, width: image size [px].
        Differentiable w.r.t. ``eye``, ``target`` (and ``up``). dtype/device come from the tensor arguments
        (float32 on the CPU if none is a tensor); tensors of different dtypes or devices are an error.
        """
        if not 0.0 < float(fov_deg) < 180.0:
            raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg}")
        tensors = {n: v for n, v in (("eye", eye), ("target", target), ("up", up)) if isinstance(v, torch.Tensor)}
        dtypes = {v.dtype for v in tensors.values()}
        devices = {v.device for v in tensors.values()}
        if len(dtypes) > 1 or len(devices) > 1:
            desc = ", ".join(f"{n}: {v.dtype} on {v.device}" for n, v in tensors.items())
            raise ValueError(f"look_at arguments must share dtype and device ({desc})")
        dtype = dtypes.pop() if dtypes else torch.float32
        device = devices.pop() if devices else torch.device("cpu")
        if not dtype.is_floating_point:
            raise ValueError(f"look_at tensors must be floating point, got {dtype}")

        def vec(name, v):
            if not isinstance(v, torch.Tensor) and len(v) != 3:
                raise ValueError(f"look_at: {name} must have shape (3,) or (B, 3), got {v!r}")
            t = v.to(dtype) if isinstance(v, torch.Tensor) else _const3(v, dtype, device)
            if t.ndim not in (1, 2) or t.shape[-1] != 3:
                raise ValueError(f"look_at: {name} must have shape (3,) or (B, 3), got {tuple(t.shape)}")
            return t.reshape(-1, 3)

        e, t, u = vec("eye", eye), vec("target", target), vec("up", up)
        sizes = {x.shape[0] for x in (e, t, u)} - {1}
        if len(sizes) > 1:
            raise ValueError(f"look_at: batch sizes of eye/target/up disagree: {e.shape[0]}, {t.shape[0]}, "
                             f"{u.shape[0]}")
        b = sizes.pop() if sizes else 1
        e, t, u = e.expand(b, 3), t.expand(b, 3), u.expand(b, 3)
        forward = _normalize(t - e)
        right = _normalize(torch.linalg.cross(forward, u))
        down = torch.linalg.cross(forward, right)
        rotation = torch.stack([right, down, forward], dim=1)
        return cls(rotation=rotation, eye=e, focal=focal_length(fov_deg, height), height=int(height),
                   width=int(width))

    def world_to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """(B, N, 3) world points [m] -> (B, N, 3) camera-frame points [m] (z is depth)."""
        return torch.einsum("bij,bnj->bni", self.rotation, points - self.eye[:, None, :])

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """(B, N, 3) world points [m] -> (B, N, 3) ``(u [px], v [px], z [m])``. Only meaningful for z > 0."""
        p = self.world_to_camera(points)
        z = p[..., 2]
        return torch.stack([self.focal * p[..., 0] / z + self.cx, self.focal * p[..., 1] / z + self.cy, z], -1)

    def expand(self, batch_size: int) -> Camera:
        """Broadcast a single camera (B = 1) to ``batch_size`` cameras (no copy)."""
        if self.batch_size == batch_size:
            return self
        if self.batch_size != 1:
            raise ValueError(f"cannot expand a batch of {self.batch_size} cameras to {batch_size}")
        return Camera(rotation=self.rotation.expand(batch_size, 3, 3), eye=self.eye.expand(batch_size, 3),
                      focal=self.focal, height=self.height, width=self.width)


def focal_length(fov_deg: float, height: int) -> float:
    """Focal length [px] of a pinhole camera with vertical field of view ``fov_deg`` [deg] over ``height`` px."""
    return 0.5 * int(height) / math.tan(math.radians(float(fov_deg)) / 2.0)


def _const3(values, dtype, device) -> torch.Tensor:
    """A (3,) tensor from three numbers, filled on the device (no host-to-device copy)."""
    vals = [float(x) for x in values]
    if len(vals) != 3:
        raise ValueError(f"expected three numbers, got {values!r}")
    return torch.stack([torch.full((), x, dtype=dtype, device=device) for x in vals])


def _normalize(v: torch.Tensor) -> torch.Tensor:
    # no epsilon: a degenerate look-at (eye == target, up parallel to the view) has no meaningful camera
    # and should show up as non-finite values, which render() rejects with a clear error
    return v / v.norm(dim=-1, keepdim=True)


_TRACK_MASKS = {"xyz": (1.0, 1.0, 1.0), "xz": (1.0, 0.0, 1.0), "none": (0.0, 0.0, 0.0)}


def tracking_camera(
    root_pos: torch.Tensor,
    *,
    eye_offset: Sequence[float],
    target_offset: Sequence[float],
    track: str = "xyz",
    up: Sequence[float] = (0.0, 0.0, 1.0),
    fov_deg: float,
    height: int,
    width: int,
) -> Camera:
    """Cameras that follow a robot's root: ``eye = a + eye_offset``, ``target = a + target_offset`` with the
    anchor ``a`` the tracked components of ``root_pos`` (others 0).

    Args:
        root_pos: (B, 3) [m] root position per environment (e.g. ``qpos[:, :3]`` of a free joint).
        eye_offset, target_offset: (3,) [m].
        track: ``"xyz"`` (follow all of the root), ``"xz"`` (only x and z move the camera, as for the
            planar hopper), ``"none"`` (fixed camera at the offsets).
        up, fov_deg, height, width: see :meth:`Camera.look_at`.
    Gradients flow from the image into ``root_pos`` through the camera extrinsics.
    """
    if track not in _TRACK_MASKS:
        raise ValueError(f"track must be one of {sorted(_TRACK_MASKS)}, got {track!r}")
    if not isinstance(root_pos, torch.Tensor) or root_pos.ndim != 2 or root_pos.shape[1] != 3:
        raise ValueError(f"root_pos must be a (B, 3) tensor, got {getattr(root_pos, 'shape', type(root_pos))}")
    # component-wise with Python floats: no host-to-device copies (cheap, CUDA-graph capturable)
    mask = _TRACK_MASKS[track]
    eye = torch.stack([root_pos[:, k] * mask[k] + float(eye_offset[k]) for k in range(3)], dim=-1)
    target = torch.stack([root_pos[:, k] * mask[k] + float(target_offset[k]) for k in range(3)], dim=-1)
    return Camera.look_at(eye, target, _const3(up, root_pos.dtype, root_pos.device), fov_deg, height, width)
