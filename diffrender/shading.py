"""Lambertian shading under one directional light.

``color = albedo * (ambient + diffuse * max(0, n . l))`` with ``l`` the unit direction towards the light and
``n`` the unit surface normal. The rasterizer interpolates per-vertex normals with perspective-correct
barycentrics and shades every pixel-face pair before the depth blend (so each candidate carries its own lit
colour) with :func:`lambert_shade`.
"""

from __future__ import annotations

import math

import torch

__all__ = ["lambert", "lambert_shade", "unit_light"]


def unit_light(light_dir: tuple[float, float, float]) -> tuple[float, float, float]:
    """Normalise a light direction given as three floats."""
    n = math.sqrt(sum(float(c) * float(c) for c in light_dir))
    return (float(light_dir[0]) / n, float(light_dir[1]) / n, float(light_dir[2]) / n)


def lambert(albedo: torch.Tensor, normal: torch.Tensor, light: tuple[float, float, float], *,
            ambient: float, diffuse: float) -> torch.Tensor:
    """Shade ``albedo: (..., 3)`` with (not necessarily unit) normals ``normal: (..., 3)``; returns (..., 3)."""
    return albedo * lambert_shade(normal, light, ambient=ambient, diffuse=diffuse)[..., None]


def lambert_shade(normal: torch.Tensor, light: tuple[float, float, float], *, ambient: float,
                  diffuse: float) -> torch.Tensor:
    """Light factor ``ambient + diffuse * max(0, n . l / |n|)`` of (not necessarily unit) normals
    ``normal: (..., 3)`` and a unit light direction ``light`` (three floats); returns (...)."""
    n_dot_l = normal[..., 0] * light[0] + normal[..., 1] * light[1] + normal[..., 2] * light[2]
    inv_len = torch.rsqrt((normal * normal).sum(-1) + 1e-20)
    return ambient + diffuse * (n_dot_l * inv_len).clamp(min=0.0)
