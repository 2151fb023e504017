"""Critic targets and updates of SHAC: TD(lambda) over one window, minibatch regression, Polyak target."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from gradlab.networks import MemberStack

__all__ = ["td_lambda_targets", "fit_critic", "fit_critics", "polyak_update"]


@torch.no_grad()
def td_lambda_targets(rewards: torch.Tensor, next_values: torch.Tensor, done: torch.Tensor, *, gamma: float,
                      lam: float) -> torch.Tensor:
    """TD(lambda) value targets for one window, computed backwards (SHAC's recursion).

    Args:
        rewards: (T, B) rewards r_t.
        next_values: (T, B) target-critic values of s_{t+1} (0 where the episode terminated early).
        done: (T, B) 1 where the episode ended at step t or the window ends (last row all ones), else 0.
        gamma: discount. lam: lambda in [0, 1).
    Returns:
        (T, B) targets: the lambda-weighted mix of n-step returns, each bootstrapped with next_values and cut
        at episode ends.
    """
    if lam >= 1.0:
        raise ValueError("td_lambda_targets needs lam < 1 (use lam=0.999... for Monte-Carlo-like targets)")
    T = rewards.shape[0]
    done = done.to(rewards.dtype)
    a = torch.zeros_like(rewards[0])
    b = torch.zeros_like(rewards[0])
    lam_acc = torch.ones_like(rewards[0])
    out = torch.empty_like(rewards)
    for t in reversed(range(T)):
        d = done[t]
        lam_acc = lam_acc * lam * (1.0 - d) + d
        a = (1.0 - d) * (lam * gamma * a + gamma * next_values[t] + (1.0 - lam_acc) / (1.0 - lam) * rewards[t])
        b = gamma * (next_values[t] * d + b * (1.0 - d)) + rewards[t]
        out[t] = (1.0 - lam) * a + lam_acc * b
    return out


def fit_critic(critic: nn.Module, optimizer: torch.optim.Optimizer, obs: torch.Tensor, targets: torch.Tensor, *,
               iterations: int, batches: int, grad_clip: float) -> torch.Tensor:
    """Regress ``critic(obs)`` on ``targets`` with ``iterations`` passes of ``batches`` minibatches each.

    obs: (N, obs_dim) normalised states; targets: (N,). Minibatches are contiguous slices (the reference
    does not shuffle). Non-finite critic gradients are zeroed (as the reference) so one bad sample cannot
    poison the critic. Returns the mean loss of the last pass (0-d tensor, no host sync).
    """
    n = obs.shape[0]
    size = (n + batches - 1) // batches
    last = []
    params = [p for p in critic.parameters() if p.requires_grad]
    for it in range(iterations):
        losses = []
        for start in range(0, n, size):
            o, y = obs[start:start + size], targets[start:start + size]
            loss = (critic(o) - y).square().mean()
            optimizer.zero_grad(set_to_none=False)  # in place: the phase may be a captured CUDA graph
            loss.backward()
            for p in params:
                if p.grad is not None:
                    torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
            nn.utils.clip_grad_norm_(params, grad_clip)
            optimizer.step()
            losses.append(loss.detach())
        if it == iterations - 1:
            last = losses
    return torch.stack(last).mean()


def fit_critics(critics: MemberStack, optimizers: Sequence[torch.optim.Optimizer], obs: torch.Tensor,
                targets: torch.Tensor, *, iterations: int, batches: int,
                grad_clip: float | torch.Tensor) -> torch.Tensor:
    """:func:`fit_critic` for N members at once: ``iterations`` passes of ``batches`` minibatch steps, each step
    covering every member with one stacked forward and backward.

    Member m gets exactly what :func:`fit_critic` does alone on ``obs[m], targets[m]`` with its own critic
    (``critics.members[m]``) and optimiser (``optimizers[m]``): its minibatch k is the same contiguous slice of its
    own rows, its loss the mean squared error over them, its non-finite gradients zeroed, its gradient clipped by
    its own total norm (``clip_grad_norm_``'s formula), its own optimiser stepped. Only the rounding of the
    batched kernels differs. The gradients are taken with respect to the stacked parameters, so that zeroing,
    norms and clipping run once per parameter tensor for all members; then each member's ``.grad`` is written in
    place and its optimiser steps. No host syncs and no tensors kept between calls: the fit may be captured as a
    CUDA graph (``gradlab.graphs.GraphedCriticPhase``).

    Args:
        critics: the members' critics, stacked (``"grouped"`` or ``"loop"`` batching, two or more members).
        optimizers: (N,) each member's optimiser over its critic's parameters.
        obs: (N, R, obs_dim) each member's normalised states. targets: (N, R) its value targets.
        iterations, batches: passes over the rows and minibatches per pass (as :func:`fit_critic`).
        grad_clip: the gradient-norm bound, one for all members or an (N,) tensor of one per member.
    Returns:
        (N,) each member's mean loss over the last pass's minibatches.
    """
    if critics.n < 2 or critics.batching == "modules":
        raise ValueError("fit_critics needs two or more members in batched kernels (use fit_critic per member)")
    n, rows = targets.shape
    size = (rows + batches - 1) // batches
    # each minibatch member-major and contiguous once, read by every pass
    minibatches = [(obs[:, start:start + size].flatten(0, 1), targets[:, start:start + size])
                   for start in range(0, rows, size)]
    member_params = [list(m.parameters()) for m in critics.members]
    for params in member_params:  # written in place below (a captured graph writes these very tensors)
        for p in params:
            if p.grad is None:
                p.grad = torch.zeros_like(p)
    member_grads = [p.grad for params in member_params for p in params]
    last = []
    for it in range(iterations):
        losses = []
        for o, y in minibatches:
            with torch.no_grad():
                stacked = critics.stack()  # (N, ...) copies of the parameters as the last step left them
            leaves = [t.requires_grad_() for t in stacked.values()]
            with torch.enable_grad():
                loss = (critics.value(stacked, o).unflatten(0, (n, -1)) - y).square().mean(dim=1)  # (N,)
                # a member's loss reaches only its own slice of each stacked parameter
                grads = torch.autograd.grad(loss.sum(), leaves)
            with torch.no_grad():
                _clip_members_(grads, grad_clip)
                torch._foreach_copy_(member_grads, [g[m] for m in range(n) for g in grads])
            for optimizer in optimizers:
                optimizer.step()
            losses.append(loss.detach())
        if it == iterations - 1:
            last = losses
    return torch.stack(last).mean(dim=0)


@torch.no_grad()
def _clip_members_(grads: Sequence[torch.Tensor], max_norm: float | torch.Tensor) -> None:
    """Zero the non-finite entries of stacked gradients (each (N, ...)) and clip member m's slices by their total
    norm as ``clip_grad_norm_`` does: coef = max_norm / (total + 1e-6), at most 1. max_norm: a float or (N,)."""
    norms = []
    for g in grads:
        torch.nan_to_num_(g, nan=0.0, posinf=0.0, neginf=0.0)
        norms.append(torch.linalg.vector_norm(g, dim=tuple(range(1, g.dim()))))
    total = torch.linalg.vector_norm(torch.stack(norms), dim=0)  # (N,)
    coef = torch.clamp(max_norm / (total + 1e-6), max=1.0)
    for g in grads:
        g.mul_(coef.view(-1, *(1,) * (g.dim() - 1)))


@torch.no_grad()
def polyak_update(target: nn.Module, source: nn.Module, alpha: float) -> None:
    """target = alpha * target + (1 - alpha) * source, parameter by parameter (two multi-tensor launches: on a
    GPU it runs between graph replays, where every launch is waited for)."""
    targets, sources = list(target.parameters()), list(source.parameters())
    torch._foreach_mul_(targets, alpha)
    torch._foreach_add_(targets, sources, alpha=1.0 - alpha)
