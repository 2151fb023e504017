"""The analytic floor: ray / plane z = 0 intersection per pixel, with a smooth checker texture.

The floor is not a mesh: every pixel casts its own ray, so the floor is exact at any resolution, costs
O(pixels), and its colour is a smooth function of the camera pose. The texture matters for gradients: with a
tracking camera, an untextured floor looks identical wherever the robot is, so the image carries no
information (and exactly zero gradient) about the base position; the checker does.
"""

from __future__ import annotations

import math

import torch

from .settings import FloorSettings

__all__ = ["floor_candidate"]

# Far floor (beyond zfar) keeps this normalised depth in units of gamma above the background's (0), so the
# floor reaches the horizon instead of ending in a visible line at zfar.
_FAR_FLOOR_MARGIN = 20.0
# Checker sharpness cap: tanh(50 sin sin) is a hard edge at any practical resolution.
_MAX_SHARPNESS = 50.0


def floor_candidate(
    rotation: torch.Tensor,
    eye: torch.Tensor,
    px: torch.Tensor,
    py: torch.Tensor,
    *,
    focal: float,
    cx: float,
    cy: float,
    znear: float,
    zfar: float,
    gamma: float,
    floor: FloorSettings,
    light_factor: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The floor as a depth-blend candidate at pixel centres.

    Args:
        rotation: (B, 3, 3) world -> camera; eye: (B, 3) [m].
        px, py: pixel-centre coordinates [px], any shape S (broadcast together).
        focal, cx, cy: intrinsics [px]; znear, zfar [m]; gamma: depth-blend temperature.
        floor: texture settings; light_factor: ``ambient + diffuse * max(0, l_z)`` (normal +z).
    Returns:
        z_n: (B, *S) normalised depth ``(zfar - z) / (zfar - znear)`` (z: camera depth of the hit point);
        color: (B, *S, 3) lit floor colour in [0, 1];
        hit: (B, *S) bool, the ray hits the plane in front of ``znear``.
    """
    s = floor.square_size
    dxc = (px - cx) / focal
    dyc = (py - cy) / focal
    r = rotation.reshape(rotation.shape[0], *([1] * dxc.ndim), 3, 3)
    # world ray direction R^T (dxc, dyc, 1); its camera z is 1, so the hit parameter t is the hit's depth
    d = r[..., 0, :] * dxc[..., None] + r[..., 1, :] * dyc[..., None] + r[..., 2, :]
    dx, dy, dz = d.unbind(-1)
    ez = eye[:, 2].reshape(-1, *([1] * dxc.ndim))
    ok = dz.abs() > 1e-12
    dz_safe = torch.where(ok, dz, torch.ones_like(dz))
    t = -ez / dz_safe
    hit = ok & (t > znear)
    t = torch.where(hit, t, torch.full_like(t, znear))  # finite stand-in where there is no hit
    x = eye[:, 0].reshape(ez.shape) + t * dx
    y = eye[:, 1].reshape(ez.shape) + t * dy
    # pixel footprint on the floor [m]: depth / focal, stretched by the grazing angle
    footprint = t / (focal * dz_safe.abs())
    sharpness = (s / (math.pi * floor.edge_px * footprint)).clamp(max=_MAX_SHARPNESS)
    mix = 0.5 + 0.5 * torch.tanh(sharpness * torch.sin(math.pi * x / s) * torch.sin(math.pi * y / s))
    ca, cb = floor.color_a, floor.color_b  # floats: no host-to-device copies
    color = torch.stack([(cb[k] + (ca[k] - cb[k]) * mix) * light_factor for k in range(3)], dim=-1)
    z_n = ((zfar - t) / (zfar - znear)).clamp(min=_FAR_FLOOR_MARGIN * gamma)
    return z_n, color, hit
