"""Shared helpers of the task tests: rollouts from a given state and central finite differences."""

from __future__ import annotations

import torch

from tasks import Task


def rollout_return(task: Task, qpos: torch.Tensor, qvel: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """Sum of rewards over ``actions (T, B, A)`` starting from (qpos, qvel); fails if any env resets."""
    task.qpos, task.qvel = qpos, qvel
    task.progress = torch.zeros_like(task.progress)
    task.prev_actions = torch.zeros_like(task.prev_actions)
    total = qpos.new_zeros(())
    for a in actions:
        _, r, done, _ = task.step(a)
        assert not bool(done.any()), "an environment reset during a gradient-check rollout"
        total = total + r.sum()
    return total


def directional_fd_check(
    f, xs: list[torch.Tensor], *, n_dirs: int, eps: float, rtol: float, seed: int = 0
) -> list[tuple[float, float]]:
    """Compare autograd directional derivatives of scalar ``f(*xs)`` with central differences along random
    unit directions (one input at a time). Returns (autograd, fd) pairs; asserts |ad - fd| <= rtol * scale
    where scale is the larger of |fd| and 1e-3 * |grad| |dir|."""
    xs = [x.detach().clone().requires_grad_(True) for x in xs]
    grads = torch.autograd.grad(f(*xs), xs)
    gen = torch.Generator().manual_seed(seed)
    pairs = []
    for i, (x, g) in enumerate(zip(xs, grads)):
        assert torch.isfinite(g).all(), f"non-finite gradient for input {i}"
        for _ in range(n_dirs):
            d = torch.randn(x.shape, generator=gen, dtype=x.dtype)
            d = d / d.norm()
            ad = (g * d).sum().item()
            with torch.no_grad():
                plus = [y.detach() + eps * d if j == i else y.detach() for j, y in enumerate(xs)]
                minus = [y.detach() - eps * d if j == i else y.detach() for j, y in enumerate(xs)]
                fd = ((f(*plus) - f(*minus)) / (2 * eps)).item()
            scale = max(abs(fd), 1e-3 * g.norm().item())
            assert abs(ad - fd) <= rtol * scale, f"input {i}: autograd {ad:.10g} vs finite difference {fd:.10g}"
            pairs.append((ad, fd))
    return pairs
