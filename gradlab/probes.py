"""Gradient probes: the full / decoupled switch, both gradients of ONE rollout, their norms, cosine and split, the
policy's image sensitivity, the NaN guard.

The two estimators differ by one detach at the actor's image input. ``ImageGate`` sits exactly there. Its
forward is the identity; its backward passes the image gradient (full APG through the renderer) or drops it
(D.Va's decoupled gradient) depending on a switch read AT BACKWARD TIME. That makes the probe exact: one
forward rollout (same noise, same states), two backward passes over the same graph, and the two gradients
differ only by the path through the renderer — the control-regularisation term of the D.Va paper's eq. (5).

Two probes explain that term: ``group_norms`` splits it by the actor's parameter groups (encoder, MLP head,
log-std: which part of the policy the image path reaches), and ``image_sensitivity`` measures how much the
policy looks at each frame of its stack at all. Everything here returns tensors without a host sync, so a
captured CUDA graph can compute them (docs/design.md, "Adding a probe").
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import torch

__all__ = [
    "ImageGate",
    "flat_grad",
    "group_norms",
    "image_sensitivity",
    "cosine",
    "NonFiniteError",
    "FiniteFlags",
]


class _GateFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, gate: ImageGate) -> torch.Tensor:
        ctx.gate = gate
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        # None (not zeros): autograd then skips the renderer's backward entirely when the gate is closed.
        return (grad if ctx.gate.open else None), None


class ImageGate:
    """Identity on the image with a backward-time switch.

    ``gate(images)`` inserts the gate; ``gate.open = True`` lets gradients into the renderer (full),
    ``False`` cuts them (decoupled). Decoupled training without probes should not render with grad at all;
    the gate is for iterations that measure both gradients of the same rollout.
    """

    def __init__(self, open: bool = True):
        self.open = open

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        if not images.requires_grad:
            return images
        return _GateFn.apply(images, self)


def flat_grad(params: Iterable[torch.nn.Parameter]) -> torch.Tensor:
    """Concatenated gradients (zeros where a parameter has none), float64 for exact norms and cosines."""
    parts = []
    for p in params:
        g = p.grad
        parts.append(torch.zeros(p.numel(), dtype=torch.float64, device=p.device) if g is None
                     else g.detach().reshape(-1).to(torch.float64))
    return torch.cat(parts) if parts else torch.zeros(0, dtype=torch.float64)


def group_norms(vec: torch.Tensor, params: Sequence[torch.nn.Parameter],
                groups: dict[str, Sequence[torch.nn.Parameter]]) -> dict[str, torch.Tensor]:
    """The norm of ``vec`` restricted to each group of parameters (0-d tensors, no host sync).

    vec: a ``flat_grad(params)``-shaped vector (sum of ``p.numel()``,), in ``params`` order; groups: name ->
    parameters, each one of ``params``. When the groups partition ``params`` the squares of the group norms
    sum to ``vec.norm()**2``.
    """
    spans, start = {}, 0
    for p in params:
        spans[id(p)] = (start, start + p.numel())
        start += p.numel()
    if start != vec.numel():
        raise ValueError(f"group_norms: vec has {vec.numel()} entries, the parameters {start}")
    out = {}
    for name, ps in groups.items():
        parts = [vec[slice(*spans[id(p)])] for p in ps]
        out[name] = torch.cat(parts).norm() if parts else vec.new_zeros(())
    return out


def image_sensitivity(mean: Callable[[torch.Tensor], torch.Tensor], images: torch.Tensor, *,
                      frames: int) -> torch.Tensor:
    """How much a policy looks at each frame of its input stack: (frames,), oldest frame first.

    Entry i is ``mean_b || d(sum_a mu_a(x_b)) / d(frame i of x_b) ||_2``: the gradient of the mean action
    summed over its dimensions (one backward pass, not the full Jacobian), with respect to the pixels of
    frame i, its norm per environment b, averaged over the environments. Zero means the policy ignores the
    frame; a blind policy gives zeros. ``images`` is detached first, so no gradient reaches its producer and
    nothing is accumulated in the parameters' ``.grad``.

    Args:
        mean: the actor's mean, (B, 3 * frames, H, W) -> (B, act_dim).
        images: (B, 3 * frames, H, W) in [0, 1].
        frames: frames in the stack.
    """
    x = images.detach().requires_grad_(True)
    with torch.enable_grad():
        (g,) = torch.autograd.grad(mean(x).sum(), x)
    return g.unflatten(1, (frames, -1)).flatten(2).norm(dim=2).mean(0)


def cosine(a: torch.Tensor, b: torch.Tensor, eps: float = 1e-30) -> torch.Tensor:
    """Cosine similarity of two flat vectors (0-d tensor); 0 when either is zero."""
    na, nb = a.norm(), b.norm()
    return torch.where((na > eps) & (nb > eps), (a @ b) / (na * nb).clamp_min(eps), torch.zeros_like(na))


class NonFiniteError(FloatingPointError):
    """A NaN/inf in the rollout or its gradients; the message names iteration, horizon step and tensor."""


class FiniteFlags:
    """Device-side record of which (step, tensor) pairs were non-finite, without host synchronisation.

    The rollout calls ``check(step, name, tensor)`` on forward values and ``watch_grad(step, name, tensor)``
    to hook the tensor's gradient. Nothing is read on the host until ``raise_if_bad`` at the end of the
    iteration, one sync. In forward time a NaN first appears at the SMALLEST bad step; in backward it is born
    at the LARGEST bad step and flows to all earlier ones — the report names the origin.
    """

    def __init__(self, horizon: int, names: list[str], device: torch.device):
        # Fixed names and a fixed table: hooks registered during the rollout keep a reference to this
        # tensor, so it must never be reallocated while an iteration is in flight.
        self.horizon = horizon
        self.names = list(names)
        self.device = device
        self.fwd = torch.zeros(horizon, len(self.names), dtype=torch.bool, device=device)
        self.bwd = torch.zeros_like(self.fwd)

    def _index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"FiniteFlags: {name!r} is not one of {self.names}") from None

    def reset(self) -> None:
        self.fwd.zero_()
        self.bwd.zero_()

    def check(self, step: int, name: str, t: torch.Tensor) -> None:
        j = self._index(name)
        self.fwd[step, j] |= ~torch.isfinite(t.detach()).all()

    def watch_grad(self, step: int, name: str, t: torch.Tensor) -> None:
        if not t.requires_grad:
            return
        j = self._index(name)
        flags = self.bwd

        def hook(g: torch.Tensor | None):
            if g is not None:  # compiled graphs may pass an undefined (all-zero) gradient as None
                flags[step, j] |= ~torch.isfinite(g).all()

        t.register_hook(hook)

    def raise_if_bad(self, iteration: int, extra: dict[str, torch.Tensor] | None = None) -> None:
        """One host sync. Raises NonFiniteError naming the first bad (step, tensor) in the rollout, or its
        gradient, or a non-finite scalar in ``extra`` (e.g. the loss or the parameter-gradient norm)."""
        extra = extra or {}
        bad_extra = [k for k, v in extra.items() if not bool(torch.isfinite(v).all())]
        fwd_bad = bool(self.fwd.any())
        bwd_bad = bool(self.bwd.any())
        if not (bad_extra or fwd_bad or bwd_bad):
            return
        msgs = []
        if fwd_bad:
            steps, cols = torch.nonzero(self.fwd, as_tuple=True)
            first = int(steps.min())
            names = [self.names[int(c)] for s, c in zip(steps.tolist(), cols.tolist()) if s == first]
            msgs.append(f"non-finite forward value at horizon step {first} in {', '.join(names)}")
        if bwd_bad:
            steps, cols = torch.nonzero(self.bwd, as_tuple=True)
            last = int(steps.max())
            names = [self.names[int(c)] for s, c in zip(steps.tolist(), cols.tolist()) if s == last]
            msgs.append(f"non-finite gradient born at horizon step {last} in d(loss)/d({', '.join(names)})")
        if bad_extra:
            msgs.append(f"non-finite {', '.join(bad_extra)}")
        raise NonFiniteError(f"iteration {iteration}: " + "; ".join(msgs))
