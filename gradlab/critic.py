"""Critic targets and updates of SHAC: TD(lambda) over one window, minibatch regression, Polyak target; a
population's members' critics fitted in groups (:func:`critic_groups`, :func:`fit_member_critics`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import nn
from torch.optim.adam import adam as adam_step

from gradlab.networks import MemberStack

if TYPE_CHECKING:
    from gradlab.members import Member

__all__ = ["td_lambda_targets", "fit_critic", "fit_critics", "polyak_update", "CriticGroup", "critic_groups",
           "fit_member_critics"]


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
                targets: torch.Tensor, *, iterations: int, batches: int, grad_clip: float | torch.Tensor,
                adam_groups: Sequence[Sequence[int]] | None = None) -> torch.Tensor:
    """:func:`fit_critic` for N members at once: ``iterations`` passes of ``batches`` minibatch steps, each step
    covering every member with one stacked forward and backward.

    Member m gets exactly what :func:`fit_critic` does alone on ``obs[m], targets[m]`` with its own critic
    (``critics.members[m]``) and optimiser (``optimizers[m]``): its minibatch k is the same contiguous slice of its
    own rows, its loss the mean squared error over them, its non-finite gradients zeroed, its gradient clipped by
    its own total norm (``clip_grad_norm_``'s formula), its own optimiser stepped. Only the rounding of the
    batched kernels differs. The gradients are taken with respect to the stacked parameters and gathered into one
    (N, P) tensor, so that zeroing, norms and clipping run once for all members; then each member's ``.grad`` is
    written in place and its optimiser steps. No host syncs and no tensors kept between calls: the fit may be
    captured as a CUDA graph (``gradlab.graphs.GraphedCriticPhase``).

    Args:
        critics: the members' critics, stacked (``"grouped"`` or ``"loop"`` batching, two or more members).
        optimizers: (N,) each member's optimiser over its critic's parameters.
        obs: (N, R, obs_dim) each member's normalised states. targets: (N, R) its value targets.
        iterations, batches: passes over the rows and minibatches per pass (as :func:`fit_critic`).
        grad_clip: the gradient-norm bound, one for all members or an (N,) tensor of one per member.
        adam_groups: members (indices into ``optimizers``, each member in one group) whose optimisers, each a
            ``torch.optim.Adam`` of one parameter group, step together in one call of torch's Adam
            (``torch.optim.adam.adam``, its multi-tensor kernels on a GPU: the same arithmetic as each step on
            its own, in a few launches instead of a few per member). The caller vouches that their learning rates
            are equal at every call: a tensor learning rate (a captured fit's) is read from the group's first
            member and not compared, which would need a host sync; the other settings are checked. None: each
            optimiser steps on its own.
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
    flat_params = [p for params in member_params for p in params]
    member_grads = [p.grad for p in flat_params]
    sizes = [p.numel() for p in member_params[0]]
    adam_groups = [[optimizers[m] for m in group] for group in _checked_adam_groups(optimizers, adam_groups)]
    with torch.no_grad():
        stacked = critics.stack()  # (N, ...) copies of the parameters, refreshed after every step
        stacked_slices = [t[m] for m in range(n) for t in stacked.values()]
    leaves = [t.requires_grad_() for t in stacked.values()]
    last = []
    for it in range(iterations):
        losses = []
        for o, y in minibatches:
            with torch.enable_grad():
                loss = (critics.value(stacked, o).unflatten(0, (n, -1)) - y).square().mean(dim=1)  # (N,)
                # a member's loss reaches only its own slice of each stacked parameter
                grads = torch.autograd.grad(loss.sum(), leaves)
            with torch.no_grad():
                # one (N, P) row of every member's gradient: zeroing, norms and clipping in one kernel each
                flat = torch.cat([g.flatten(1) for g in grads], dim=1)
                _clip_members_(flat, grad_clip)
                torch._foreach_copy_(member_grads, [part.view_as(p) for m in range(n)
                                                    for part, p in zip(flat[m].split(sizes), member_params[m])])
            for group in adam_groups:
                _adam_step(group)
            with torch.no_grad():
                torch._foreach_copy_(stacked_slices, flat_params)
            losses.append(loss.detach())
        if it == iterations - 1:
            last = losses
    return torch.stack(last).mean(dim=0)


@torch.no_grad()
def _clip_members_(grads: torch.Tensor, max_norm: float | torch.Tensor) -> None:
    """Zero the non-finite entries of ``grads`` (N, P), each row one member's whole gradient, and clip row m by its
    norm as ``clip_grad_norm_`` does: coef = max_norm / (norm + 1e-6), at most 1. max_norm: a float or (N,)."""
    torch.nan_to_num_(grads, nan=0.0, posinf=0.0, neginf=0.0)
    total = torch.linalg.vector_norm(grads, dim=1)  # (N,)
    grads.mul_(torch.clamp(max_norm / (total + 1e-6), max=1.0).unsqueeze(1))


def _checked_adam_groups(optimizers: Sequence[torch.optim.Optimizer],
                         groups: Sequence[Sequence[int]] | None) -> list[list[int]]:
    """``groups`` (None: every optimiser alone) after checking that each optimiser is in exactly one and that the
    optimisers of a group can step as one: Adam with one parameter group each, equal settings, equal learning
    rates where they are floats, tensors in all or none."""
    if groups is None:
        return [[m] for m in range(len(optimizers))]
    groups = [list(g) for g in groups]
    if sorted(m for g in groups for m in g) != list(range(len(optimizers))):
        raise ValueError(f"adam_groups must hold each of the {len(optimizers)} members once, got {groups}")
    for group in groups:
        if len(group) == 1:
            continue
        opts = [optimizers[m] for m in group]
        if any(type(o) is not torch.optim.Adam or len(o.param_groups) != 1 for o in opts):
            raise ValueError("adam_groups: only torch.optim.Adam optimisers of one parameter group step together")
        settings = [{k: v for k, v in o.param_groups[0].items() if k not in ("params", "lr")} for o in opts]
        lrs = [o.param_groups[0]["lr"] for o in opts]
        tensor_lr = {isinstance(lr, torch.Tensor) for lr in lrs}
        if any(s != settings[0] for s in settings) or len(tensor_lr) > 1 or (
                tensor_lr == {False} and len(set(lrs)) > 1):
            raise ValueError(f"adam_groups: members {group} differ in their Adam settings or learning rates")
    return groups


@torch.no_grad()
def _adam_step(optimizers: Sequence[torch.optim.Adam]) -> None:
    """Step Adam optimisers of equal settings (one parameter group each, every parameter with a gradient) in one
    call of torch's Adam; an optimiser whose state is not yet made (its first step) steps on its own first."""
    if len(optimizers) == 1 or any(len(o.state) < len(o.param_groups[0]["params"]) for o in optimizers):
        for optimizer in optimizers:
            optimizer.step()
        return
    group = optimizers[0].param_groups[0]
    params = [p for o in optimizers for p in o.param_groups[0]["params"]]
    states = [o.state[p] for o in optimizers for p in o.param_groups[0]["params"]]
    beta1, beta2 = group["betas"]
    adam_step(
        params, [p.grad for p in params], [s["exp_avg"] for s in states], [s["exp_avg_sq"] for s in states],
        [s["max_exp_avg_sq"] for s in states] if group["amsgrad"] else [], [s["step"] for s in states],
        foreach=group["foreach"], capturable=group["capturable"], differentiable=group["differentiable"],
        fused=group["fused"], decoupled_weight_decay=group["decoupled_weight_decay"], amsgrad=group["amsgrad"],
        beta1=beta1, beta2=beta2, lr=group["lr"], weight_decay=group["weight_decay"], eps=group["eps"],
        maximize=group["maximize"])


@torch.no_grad()
def polyak_update(target: nn.Module, source: nn.Module, alpha: float) -> None:
    """target = alpha * target + (1 - alpha) * source, parameter by parameter (two multi-tensor launches: on a
    GPU it runs between graph replays, where every launch is waited for)."""
    targets, sources = list(target.parameters()), list(source.parameters())
    torch._foreach_mul_(targets, alpha)
    torch._foreach_add_(targets, sources, alpha=1.0 - alpha)


@dataclass(eq=False)
class CriticGroup:
    """Members whose critics fit in one pass: their critics stacked (None: a member alone, fitted by
    :func:`fit_critic`), their indices as a tensor (None: every member, in order), their gradient bound (a float,
    or an (N,) tensor where they differ) and which of them step their Adam together (``fit_critics``'
    adam_groups, indices into ``members``)."""

    members: list[Member]
    stack: MemberStack | None
    index: torch.Tensor | None
    grad_clip: float | torch.Tensor
    adam_groups: list[list[int]] | None = None


def critic_groups(members: Sequence[Member], batching: str, device: torch.device) -> list[CriticGroup]:
    """The members whose critics fit together: with batched kernels, those of equal ``critic_iterations`` and
    ``critic_batches`` (one pass of minibatch steps), each group with its critics stacked and its members'
    gradient bounds (one float where they agree, else a tensor, made here: a captured fit cannot copy from the
    host); members of one critic learning rate, decay and betas step their Adam together (the trainer gives them
    the same rate at every iteration). With ``"modules"`` batching, and for a member alone in its group, each
    member fits alone (a run's exact arithmetic)."""
    by_shape: dict[tuple, list[Member]] = {}
    for m in members:
        key = (m.index,) if batching == "modules" else (m.cfg.critic_iterations, m.cfg.critic_batches)
        by_shape.setdefault(key, []).append(m)
    groups = []
    for group in by_shape.values():
        if len(group) == 1:
            groups.append(CriticGroup(group, None, None, group[0].cfg.grad_clip))
            continue
        index = None if len(group) == len(members) else torch.tensor([m.index for m in group], device=device)
        clips = [m.cfg.grad_clip for m in group]
        grad_clip = clips[0] if len(set(clips)) == 1 else torch.tensor(clips, device=device)
        by_schedule: dict[tuple, list[int]] = {}
        for i, m in enumerate(group):
            by_schedule.setdefault((m.cfg.critic_lr, m.cfg.lr_decay_iters, tuple(m.cfg.betas)), []).append(i)
        groups.append(CriticGroup(group, MemberStack([m.critic for m in group], batching=batching), index,
                                  grad_clip, list(by_schedule.values())))
    return groups


def fit_member_critics(groups: Sequence[CriticGroup], buf: dict, *, gamma: float, lam: float) -> torch.Tensor:
    """TD(lambda) targets of one window's (T, N * B) buffers and each member's critic fitted on its own rows, group
    by group; returns (N,) each member's critic loss. The targets' recursion is elementwise over the columns, so
    one recursion over every member's columns gives each member its own targets."""
    n = sum(len(g.members) for g in groups)
    targets = td_lambda_targets(buf["rewards"], buf["next_values"], buf["dones"], gamma=gamma, lam=lam)
    # member-major rows, each member's in the order fit_critic reads them alone (step, then environment)
    obs = buf["critic_obs"].unflatten(1, (n, -1)).movedim(1, 0).flatten(1, 2)  # (N, T * B, obs_dim)
    targets = targets.unflatten(1, (n, -1)).movedim(1, 0).flatten(1, 2)  # (N, T * B)
    losses = [None] * n
    for group in groups:
        c = group.members[0].cfg
        if group.stack is None:
            m = group.members[0]
            losses[m.index] = fit_critic(m.critic, m.critic_opt, obs[m.index], targets[m.index],
                                         iterations=c.critic_iterations, batches=c.critic_batches,
                                         grad_clip=c.grad_clip)
            continue
        rows = slice(None) if group.index is None else group.index
        fitted = fit_critics(group.stack, [m.critic_opt for m in group.members], obs[rows], targets[rows],
                             iterations=c.critic_iterations, batches=c.critic_batches, grad_clip=group.grad_clip,
                             adam_groups=group.adam_groups)
        for m, loss in zip(group.members, fitted.unbind(0)):
            losses[m.index] = loss
    return torch.stack(losses)
