"""Lambertian shading under one directional light.

``color = albedo * (ambient + diffuse * max(0, n . l))`` with ``l`` the unit direction towards the light and
``n`` the unit surface normal. The rasterizer interpolates per-vertex normals with perspective-correct
barycentrics and shades every pixel-face pair before the depth blend (so each candidate carries its own lit
colour); :func:`lambert_from_dots` is that per-pair form, written on precomputed dot products so that the
inner loop touches scalars only.
"""

from __future__ import annotations

import math

import torch

__all__ = ["lambert", "lambert_from_dots", "unit_light"]


def unit_light(light_dir: tuple[float, float, float]) -> tuple[float, float, float]:
    """Normalise a light direction given as three floats."""
    n = math.sqrt(sum(float(c) * float(c) for c in light_dir))
    return (float(light_dir[0]) / n, float(light_dir[1]) / n, float(light_dir[2]) / n)


def lambert(albedo: torch.Tensor, normal: torch.Tensor, light: tuple[float, float, float], *,
            ambient: float, diffuse: float) -> torch.Tensor:
    """Shade ``albedo: (..., 3)`` with (not necessarily unit) normals ``normal: (..., 3)``; returns (..., 3)."""
    l_vec = normal.new_tensor(light)
    n_dot_l = (normal * l_vec).sum(-1) * torch.rsqrt((normal * normal).sum(-1) + 1e-20)
    return albedo * (ambient + diffuse * n_dot_l.clamp(min=0.0))[..., None]


def lambert_from_dots(b: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
                      n_dot_l: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
                      n_dot_n: tuple[torch.Tensor, torch.Tensor, torch.Tensor], *,
                      ambient: float, diffuse: float) -> torch.Tensor:
    """Light factor ``ambient + diffuse * max(0, n . l)`` of the normalised interpolated normal
    ``n = sum_k b_k n_k`` of unit vertex normals ``n_k``, from per-face dot products.

    Args:
        b: three barycentric weights, each (N, P).
        n_dot_l: ``n_k . l`` per face vertex, each (N, 1).
        n_dot_n: ``(n_1 . n_2, n_2 . n_0, n_0 . n_1)``, each (N, 1).
    Returns:
        (N, P) light factor.
    """
    b0, b1, b2 = b
    num = b0 * n_dot_l[0] + b1 * n_dot_l[1] + b2 * n_dot_l[2]
    # |sum b_k n_k|^2 for unit n_k
    sq = b0 * b0 + b1 * b1 + b2 * b2 + 2.0 * (b1 * b2 * n_dot_n[0] + b2 * b0 * n_dot_n[1] + b0 * b1 * n_dot_n[2])
    return ambient + diffuse * (num * torch.rsqrt(sq.clamp(min=0.0) + 1e-20)).clamp(min=0.0)
