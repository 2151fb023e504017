"""Small batched rotation and spatial-vector helpers (pure torch, any leading batch shape).

Spatial vectors are 6-vectors (angular part first): a motion ``(w, v)`` is the angular velocity and the
velocity of the body point that coincides with the reference point; a force ``(n, f)`` is the moment about
the reference point and the force. All functions are differentiable and free of host synchronisation.
"""

from __future__ import annotations

import torch

__all__ = [
    "cross",
    "cross_force",
    "cross_motion",
    "quat_mul",
    "quat_to_mat",
    "skew",
]


def cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross product over the last axis with broadcasting. (..., 3) x (..., 3) -> (..., 3).

    Written out instead of ``torch.linalg.cross`` so that it broadcasts freely and compiles to plain
    pointwise kernels.
    """
    ax, ay, az = a.unbind(-1)
    bx, by, bz = b.unbind(-1)
    return torch.stack((ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx), dim=-1)


def skew(a: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrix ``[a]x`` with ``[a]x b = a x b``. (..., 3) -> (..., 3, 3)."""
    x, y, z = a.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack((o, -z, y, z, o, -x, -y, x, o), dim=-1).reshape(*a.shape[:-1], 3, 3)


def quat_to_mat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of a quaternion (w, x, y, z), normalised first as MuJoCo does. (..., 4) -> (..., 3, 3)."""
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    m = torch.stack(
        (
            1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
            2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
            2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
        ),
        dim=-1,
    )  # fmt: skip
    return m.reshape(*q.shape[:-1], 3, 3)


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of quaternions (w, x, y, z). (..., 4) x (..., 4) -> (..., 4)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def cross_motion(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Spatial motion cross product ``a x b``. (..., 6) x (..., 6) -> (..., 6)."""
    aw, av = a[..., :3], a[..., 3:]
    bw, bv = b[..., :3], b[..., 3:]
    return torch.cat((cross(aw, bw), cross(aw, bv) + cross(av, bw)), dim=-1)


def cross_force(a: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """Spatial force cross product ``a x* f`` (motion ``a`` acting on force ``f``). (..., 6) -> (..., 6)."""
    aw, av = a[..., :3], a[..., 3:]
    fn, ff = f[..., :3], f[..., 3:]
    return torch.cat((cross(aw, fn) + cross(av, ff), cross(aw, ff)), dim=-1)
