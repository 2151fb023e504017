"""Critic targets and updates of SHAC: TD(lambda) over one window, minibatch regression, Polyak target."""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["td_lambda_targets", "fit_critic", "polyak_update"]


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


@torch.no_grad()
def polyak_update(target: nn.Module, source: nn.Module, alpha: float) -> None:
    """target = alpha * target + (1 - alpha) * source, parameter by parameter (two multi-tensor launches: on a
    GPU it runs between graph replays, where every launch is waited for)."""
    targets, sources = list(target.parameters()), list(source.parameters())
    torch._foreach_mul_(targets, alpha)
    torch._foreach_add_(targets, sources, alpha=1.0 - alpha)
