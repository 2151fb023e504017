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
    def forward(ctx, x: torch.Tensor, alt: torch.Tensor | None, gate: ImageGate) -> torch.Tensor:
        ctx.gate, ctx.has_alt = gate, alt is not None
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        to_image, to_alt = ctx.gate.route_gradient(grad)
        return to_image, (to_alt if ctx.has_alt else None), None


class ImageGate:
    """Identity on the image with a backward-time switch, per member of a population.

    ``gate(images)`` inserts the gate; ``gate.open = True`` lets gradients into the renderer (full),
    ``False`` cuts them (decoupled). Decoupled training without probes should not render with grad at all;
    the gate is for iterations that measure both gradients of the same rollout.

    A population's members are consecutive blocks of ``rows`` environments; :meth:`set_route` then decides per
    member where the image gradient goes: nowhere (None), into the images (``"image"``), or into ``alt``, a
    second rendering of the same states by another image model (``"alt"``: the forward value stays the first
    image's, so both gradients are of the same rollout). A cut member's rows get exact zeros (``torch.where``:
    a non-finite gradient of one member reaches no other). A route sends None, not zeros, where no member takes
    a path: autograd then skips that renderer's backward entirely.
    """

    def __init__(self, open: bool = True, *, members: int = 1, rows: int | None = None,
                 device: torch.device | None = None):
        self.members, self.rows, self.device = members, rows, device
        self._route: tuple[str | None, ...] = ("image" if open else None,) * members
        self._masks: dict[tuple[str | None, ...], dict[str, torch.Tensor]] = {}

    @property
    def open(self) -> bool:
        """Every member's gradient goes into the images."""
        return all(r == "image" for r in self._route)

    @open.setter
    def open(self, value: bool) -> None:
        self._route = ("image" if value else None,) * self.members

    def set_route(self, route: tuple[str | None, ...]) -> None:
        """Per member: None, "image" or "alt". Mixed routes need the gate's ``rows`` and ``device``: the masks
        are made here (a CUDA graph capture cannot create them), once per route."""
        if len(route) != self.members or not set(route) <= {None, "image", "alt"}:
            raise ValueError(f"ImageGate: a route names None, 'image' or 'alt' for each of {self.members} members")
        self._route = tuple(route)
        if route not in self._masks and len(set(route)) > 1:
            if self.rows is None or self.device is None:
                raise ValueError("ImageGate: mixed routes need rows per member and a device")
            flags = {path: torch.tensor([r == path for r in route], device=self.device).repeat_interleave(self.rows)
                     for path in ("image", "alt")}
            self._masks[route] = {path: f.view(-1, 1, 1, 1) for path, f in flags.items()}

    def route_gradient(self, grad: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """The gradient at the gate -> (its share for the images, for ``alt``)."""
        out = []
        for path in ("image", "alt"):
            takers = [r == path for r in self._route]
            if not any(takers):
                out.append(None)
            elif all(takers):
                out.append(grad)
            else:
                out.append(torch.where(self._masks[self._route][path], grad, torch.zeros_like(grad)))
        return out[0], out[1]

    def __call__(self, images: torch.Tensor, alt: torch.Tensor | None = None) -> torch.Tensor:
        """images: (B, C, H, W), differentiable; alt: the same states by another image model, or None."""
        if not images.requires_grad:
            return images
        return _GateFn.apply(images, alt, self)


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
    to hook the tensor's gradient. Nothing is read on the host until ``raise_if_bad`` (or ``failures``) at the
    end of the iteration, one sync. In forward time a NaN first appears at the SMALLEST bad step; in backward it
    is born at the LARGEST bad step and flows to all earlier ones — the report names the origin.

    With ``members`` > 1 (a population) a tensor's leading dimension holds the members' equal blocks of rows, and
    each member is recorded on its own.
    """

    def __init__(self, horizon: int, names: list[str], device: torch.device, *, members: int = 1):
        # Fixed names and a fixed table: hooks registered during the rollout keep a reference to this
        # tensor, so it must never be reallocated while an iteration is in flight.
        self.horizon = horizon
        self.names = list(names)
        self.device = device
        self.members = members
        self.fwd = torch.zeros(members, horizon, len(self.names), dtype=torch.bool, device=device)
        self.bwd = torch.zeros_like(self.fwd)

    def _index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"FiniteFlags: {name!r} is not one of {self.names}") from None

    def _bad(self, t: torch.Tensor) -> torch.Tensor:
        """(members,) bool: a member's block of ``t`` holds a non-finite value."""
        return ~torch.isfinite(t.reshape(self.members, -1)).all(1)

    def reset(self) -> None:
        self.fwd.zero_()
        self.bwd.zero_()

    def check(self, step: int, name: str, t: torch.Tensor) -> None:
        j = self._index(name)
        self.fwd[:, step, j] |= self._bad(t.detach())

    def watch_grad(self, step: int, name: str, t: torch.Tensor) -> None:
        if not t.requires_grad:
            return
        j = self._index(name)
        flags = self.bwd

        def hook(g: torch.Tensor | None):
            if g is not None:  # compiled graphs may pass an undefined (all-zero) gradient as None
                flags[:, step, j] |= self._bad(g)

        t.register_hook(hook)

    def failures(self, iteration: int, extra: dict[str, torch.Tensor] | None = None) -> dict[int, str]:
        """One host sync. Per member whose rollout, gradient or ``extra`` value (one entry per member) was
        non-finite, the message: the first bad (step, tensor) forward, the step a bad gradient was born at, the
        non-finite extras."""
        extra = {k: v.reshape(self.members, -1) for k, v in (extra or {}).items()}
        bad_extra = {k: ~torch.isfinite(v).all(1) for k, v in extra.items()}
        summary = torch.stack([self.fwd.flatten(1).any(1), self.bwd.flatten(1).any(1), *bad_extra.values()])
        if not bool(summary.any()):
            return {}
        out = {}
        fwd, bwd = self.fwd.cpu(), self.bwd.cpu()
        bad_extra = {k: v.cpu() for k, v in bad_extra.items()}
        for m in range(self.members):
            msgs = []
            if fwd[m].any():
                steps, cols = torch.nonzero(fwd[m], as_tuple=True)
                first = int(steps.min())
                names = [self.names[int(c)] for s, c in zip(steps.tolist(), cols.tolist()) if s == first]
                msgs.append(f"non-finite forward value at horizon step {first} in {', '.join(names)}")
            if bwd[m].any():
                steps, cols = torch.nonzero(bwd[m], as_tuple=True)
                last = int(steps.max())
                names = [self.names[int(c)] for s, c in zip(steps.tolist(), cols.tolist()) if s == last]
                msgs.append(f"non-finite gradient born at horizon step {last} in d(loss)/d({', '.join(names)})")
            named = [k for k, v in bad_extra.items() if bool(v[m])]
            if named:
                msgs.append(f"non-finite {', '.join(named)}")
            if msgs:
                out[m] = f"iteration {iteration}: " + "; ".join(msgs)
        return out

    def raise_if_bad(self, iteration: int, extra: dict[str, torch.Tensor] | None = None) -> None:
        """One host sync. Raises NonFiniteError naming the first bad (step, tensor) in the rollout, or its
        gradient, or a non-finite scalar in ``extra`` (e.g. the loss or the parameter-gradient norm), of the first
        member that has one."""
        bad = self.failures(iteration, extra)
        if bad:
            raise NonFiniteError(bad[min(bad)])
