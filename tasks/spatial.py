"""Small batched linear-algebra helpers with two lowerings: eager and compiled.

The simulator works on many tiny matrices (3x3, 4x4, 6x6) and contracts with constant 0/1 tree masks. In
eager mode the fastest form is a single ``matmul`` per product (few kernel launches). Under ``torch.compile``
a ``matmul`` becomes an opaque library call (cuBLAS) that Inductor cannot fuse with its neighbours, whereas a
broadcast multiply-and-sum is fused into the surrounding pointwise kernels. Every helper therefore checks
``torch.compiler.is_compiling()`` (a constant while Dynamo traces) and emits the form that suits the mode;
both compute the same numbers.

Spatial vectors are 6-vectors, angular part first: a motion ``(w, v)`` is the angular velocity and the
velocity of the body point at the reference point; a force ``(n, f)`` is the moment about the reference point
and the force. All functions take any leading batch shape, are differentiable and never synchronise.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = [
    "RowGather",
    "bmm",
    "bmv",
    "contract",
    "cross",
    "cross_force",
    "cross_motion",
    "quat_mul",
    "quat_to_mat",
    "skew",
]

_compiling = torch.compiler.is_compiling


def bmm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Batched matrix product with broadcasting. (..., m, n) x (..., n, p) -> (..., m, p)."""
    if _compiling():
        return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
    return a @ b


def bmv(a: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Batched matrix-vector product with broadcasting. (..., m, n) x (..., n) -> (..., m)."""
    if _compiling():
        return (a * x.unsqueeze(-2)).sum(-1)
    return (a @ x.unsqueeze(-1)).squeeze(-1)


def contract(mask: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``out[b, i, k] = sum_j mask[i, j] x[b, j, k]`` for a constant mask. (m, n) x (B, n, k) -> (B, m, k)."""
    if _compiling():
        return (mask[None, :, :, None] * x[:, None, :, :]).sum(2)
    return torch.matmul(mask, x)


class _GatherRows(torch.autograd.Function):
    """``x[:, idx]`` whose backward is a gather-and-sum, not a scatter.

    The gradient of a row gather adds every output row into its source row. PyTorch does that with
    ``index_put(accumulate=True)``, which Inductor lowers to a zero fill plus one atomic add per element: it
    cannot know which outputs share a source. Here the sharing is static, so the backward reads, for every
    source row, the at most ``F`` output rows that came from it (``inv (n, F)``, padded with the index of an
    appended zero row) and sums them: plain loads and one store, fused into the kernels around it.
    """

    @staticmethod
    def forward(x: torch.Tensor, idx: torch.Tensor, inv: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        return x[:, idx]

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(inputs[2])

    @staticmethod
    def backward(ctx, g):  # type: ignore[override]
        (inv,) = ctx.saved_tensors
        g = torch.cat((g, g.new_zeros(g.shape[0], 1, *g.shape[2:])), dim=1)
        return g[:, inv].sum(2), None, None


class RowGather:
    """A constant row selection ``x[:, idx]`` for ``x (B, n, ...)`` -> ``(B, len(idx), ...)``.

    Eager it is plain indexing. Compiled, its backward gathers and sums the output rows of each source row
    (:class:`_GatherRows`) instead of scattering them with atomics. ``no_grad_rows``: source rows whose
    gradient is never needed (constants such as an appended identity); they get none, so a constant row
    that many outputs share does not widen the backward's sum for every row.
    """

    def __init__(self, idx, n: int, *, device: torch.device, no_grad_rows=()) -> None:
        idx = np.asarray(idx, dtype=np.int64).reshape(-1)
        if len(idx) and (idx.min() < 0 or idx.max() >= n):
            raise ValueError(f"RowGather: indices must lie in [0, {n}), got {idx.tolist()}")
        skip = set(int(r) for r in no_grad_rows)
        users = [[] if r in skip else np.flatnonzero(idx == r).tolist() for r in range(n)]
        width = max([1, *map(len, users)])
        inv = np.full((n, width), len(idx), dtype=np.int64)  # len(idx): the appended zero row
        for r, u in enumerate(users):
            inv[r, : len(u)] = u
        self.idx = torch.as_tensor(idx, device=device)
        self.inv = torch.as_tensor(inv, device=device)
        self.width = width

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if _compiling():
            return _GatherRows.apply(x, self.idx, self.inv)
        return x[:, self.idx]


# Levi-Civita tensors as (9, 3) and (36, 6) matrices: cross products become one outer product and one matmul
# in eager mode (2 kernels instead of ~11 for the component formula).
def _levi_civita() -> torch.Tensor:
    e = torch.zeros(3, 3, 3, dtype=torch.float64)
    e[0, 1, 2] = e[1, 2, 0] = e[2, 0, 1] = 1.0
    e[0, 2, 1] = e[2, 1, 0] = e[1, 0, 2] = -1.0
    return e  # e[i, j, k]: (a x b)_i = e[i, j, k] a_j b_k


_E3 = _levi_civita().permute(1, 2, 0).reshape(9, 3)
_EM = torch.zeros(6, 6, 6, dtype=torch.float64)  # (a x b)_i = EM[j, k, i] a_j b_k, motion cross product
_EF = torch.zeros(6, 6, 6, dtype=torch.float64)  # (a x* f)_i = EF[j, k, i] a_j f_k, force cross product
_eps = _levi_civita()
for _i in range(3):
    for _j in range(3):
        for _k in range(3):
            v = _eps[_i, _j, _k]
            _EM[_j, _k, _i] = v  # w x w'
            _EM[_j, 3 + _k, 3 + _i] = v  # w x v'
            _EM[3 + _j, _k, 3 + _i] = v  # v x w'
            _EF[_j, _k, _i] = v  # w x n
            _EF[3 + _j, 3 + _k, _i] = v  # v x f
            _EF[_j, 3 + _k, 3 + _i] = v  # w x f
_EM = _EM.reshape(36, 6)
_EF = _EF.reshape(36, 6)
_cache: dict[tuple, torch.Tensor] = {}


def _table(t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    key = (id(t), like.device, like.dtype)
    out = _cache.get(key)
    if out is None:
        out = _cache[key] = t.to(device=like.device, dtype=like.dtype)
    return out


def _cross3(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    ax, ay, az = a.unbind(-1)
    bx, by, bz = b.unbind(-1)
    return torch.stack((ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx), dim=-1)


def cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross product over the last axis with broadcasting. (..., 3) x (..., 3) -> (..., 3)."""
    if _compiling():
        return _cross3(a, b)
    outer = (a.unsqueeze(-1) * b.unsqueeze(-2)).flatten(-2)
    return outer @ _table(_E3, outer)


def cross_motion(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Spatial motion cross product ``a x b``. (..., 6) x (..., 6) -> (..., 6)."""
    if _compiling():
        aw, av, bw, bv = a[..., :3], a[..., 3:], b[..., :3], b[..., 3:]
        return torch.cat((_cross3(aw, bw), _cross3(aw, bv) + _cross3(av, bw)), dim=-1)
    outer = (a.unsqueeze(-1) * b.unsqueeze(-2)).flatten(-2)
    return outer @ _table(_EM, outer)


def cross_force(a: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """Spatial force cross product ``a x* f`` (motion ``a`` acting on force ``f``). (..., 6) -> (..., 6)."""
    if _compiling():
        aw, av, fn, ff = a[..., :3], a[..., 3:], f[..., :3], f[..., 3:]
        return torch.cat((_cross3(aw, fn) + _cross3(av, ff), _cross3(aw, ff)), dim=-1)
    outer = (a.unsqueeze(-1) * f.unsqueeze(-2)).flatten(-2)
    return outer @ _table(_EF, outer)


def skew(a: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrix ``[a]x`` with ``[a]x b = a x b``. (..., 3) -> (..., 3, 3)."""
    # nested 3-way stacks: Inductor lowers a cat of <= 8 inputs to one pointwise kernel, a wider one to a
    # separate write per input
    x, y, z = a.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack((torch.stack((o, -z, y), -1), torch.stack((z, o, -x), -1), torch.stack((-y, x, o), -1)), -2)


def quat_to_mat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of a quaternion (w, x, y, z), normalised first as MuJoCo does. (..., 4) -> (..., 3, 3)."""
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = (
        torch.stack((1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)), dim=-1),
        torch.stack((2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)), dim=-1),
        torch.stack((2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)), dim=-1),
    )
    return torch.stack(rows, dim=-2)


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
