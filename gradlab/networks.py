"""Actor and critic networks of SHAC / D.Va (docs/design.md, "A SHAC window").

The visual actor is the DrQ-v2 encoder (4 convolutions, ReLU) followed by a trunk (Linear -> LayerNorm -> Tanh)
and an MLP head (Linear -> ELU -> LayerNorm per hidden layer). The policy is a tanh-squashed Gaussian with a
state-independent log-std initialised at -1; actions are drawn with the reparameterisation trick so that the
analytic policy gradient flows through them into the simulator.

A population (several runs trained in one process) keeps one ordinary module per member, so that each member's
initialisation, optimiser, gradient clipping and checkpoint are those of a run of its own. :class:`MemberStack`
evaluates N members of one architecture on their N batches at once: their parameters stacked along a leading
member axis (differentiably, once per window), linear layers as batched matrix products, convolutions as one
grouped convolution (or one per member), LayerNorm with per-member affine parameters; or each member's own module
on its rows.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from gradlab import precision as _precision

__all__ = ["MLP", "PixelEncoder", "StateActor", "VisualActor", "Critic", "MemberStack", "orthogonal_init"]


def orthogonal_init(module: nn.Module, gain: float = 1.0) -> None:
    """Orthogonal weights, zero biases for every Linear / Conv2d in ``module`` (DrQ-v2, SHAC)."""
    for m in module.modules():
        if isinstance(m, (nn.Linear, nn.Conv2d)):
            nn.init.orthogonal_(m.weight, gain=gain)
            if m.bias is not None:
                nn.init.zeros_(m.bias)


class MLP(nn.Sequential):
    """Linear -> ELU -> LayerNorm per hidden layer, then a plain Linear output layer.

    Args:
        in_dim: input features.
        hidden: widths of the hidden layers.
        out_dim: output features.
    """

    def __init__(self, in_dim: int, hidden: Sequence[int], out_dim: int):
        layers: list[nn.Module] = []
        d = in_dim
        for h in hidden:
            layers += [nn.Linear(d, h), nn.ELU(), nn.LayerNorm(h)]
            d = h
        layers.append(nn.Linear(d, out_dim))
        super().__init__(*layers)


class PixelEncoder(nn.Module):
    """DrQ-v2 encoder: pixels in [0, 1] -> trunk features.

    ``obs - 0.5`` (the reference's ``obs/255 - 0.5`` on images in [0, 1]); conv 3x3 stride 2, three conv 3x3
    stride 1, 32 channels, ReLU; flatten; Linear -> LayerNorm -> Tanh.

    Args:
        in_channels: stacked channels (3 frames x RGB = 9).
        height, width: image size in pixels.
        trunk_dim: output features.
        precision: what the convolutions run in (:mod:`gradlab.precision`): ``"bf16"`` runs them under bfloat16
            autocast and casts their output back to float32 before the trunk; None: the process's
            (``gradlab.precision.current()``, which ``gradlab.precision.use`` sets before the trainer is built).
    """

    def __init__(self, in_channels: int, height: int, width: int, trunk_dim: int, *, precision: str | None = None):
        super().__init__()
        self.precision = _precision.check(_precision.current() if precision is None else precision)
        self.convs = nn.Sequential(
            nn.Conv2d(in_channels, 32, 3, stride=2), nn.ReLU(),
            nn.Conv2d(32, 32, 3, stride=1), nn.ReLU(),
            nn.Conv2d(32, 32, 3, stride=1), nn.ReLU(),
            nn.Conv2d(32, 32, 3, stride=1), nn.ReLU(),
        )
        # Four 3x3 convolutions (one of stride 2) need at least 9x9 pixels.
        if min(height, width) < 9:
            raise ValueError(f"image {height}x{width} is too small for the encoder (needs >= 9x9)")
        with torch.no_grad():
            flat = self.convs(torch.zeros(1, in_channels, height, width)).numel()
        self.trunk = nn.Sequential(nn.Linear(flat, trunk_dim), nn.LayerNorm(trunk_dim), nn.Tanh())
        orthogonal_init(self.convs, gain=nn.init.calculate_gain("relu"))
        orthogonal_init(self.trunk)
        # Channels-last (NHWC) weights and activations: cuDNN's tensor-core convolutions work in NHWC and
        # otherwise transpose every input and gradient (BENCHMARKS.md, "1. SHAC iteration"). Same values; only
        # the memory layout differs.
        self.convs.to(memory_format=torch.channels_last)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """images: (B, C, H, W) in [0, 1] (any memory layout) -> (B, trunk_dim)."""
        x = (images - 0.5).contiguous(memory_format=torch.channels_last)
        with _precision.encoder_autocast(x.device.type, self.precision):
            h = self.convs(x)
        if self.precision == "bf16":
            h = h.float()  # the trunk (Linear, LayerNorm) in float32
        return self.trunk(h.flatten(1))  # flatten in (C, H, W) order whatever the layout


class _GaussianTanhPolicy(nn.Module):
    """Shared head: features -> mean; learnable state-independent log-std."""

    def __init__(self, feat_dim: int, hidden: Sequence[int], act_dim: int, *, init: str = "orthogonal",
                 init_log_std: float = -1.0):
        super().__init__()
        self.mu = MLP(feat_dim, hidden, act_dim)
        if init == "orthogonal":
            orthogonal_init(self.mu, gain=2.0**0.5)
            # The last layer small so initial actions sit near 0 (the tanh's linear region).
            nn.init.orthogonal_(self.mu[-1].weight, gain=0.01)
        elif init != "default":  # "default": nn.Linear's own init, as the reference's ActorStochasticMLP
            raise ValueError(f"unknown actor init {init!r}; valid: default, orthogonal")
        self.log_std = nn.Parameter(torch.full((act_dim,), float(init_log_std)))

    def features(self, obs: torch.Tensor) -> torch.Tensor:
        return obs

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        """The parameters by part of the policy, every parameter in exactly one group: "mlp" (the head that
        maps features to the mean action) and "log_std" (the exploration noise)."""
        return {"mlp": list(self.mu.parameters()), "log_std": [self.log_std]}

    def mean(self, obs: torch.Tensor) -> torch.Tensor:
        """obs -> the action distribution's pre-tanh mean ``mu`` (B, act_dim): deterministic (no sampling),
        which is what gradlab compiles (the noise stays on PyTorch's generator, so compiled and eager runs
        draw the same actions)."""
        return self.mu(self.features(obs))

    def sample(self, mu: torch.Tensor) -> torch.Tensor:
        """mu (B, act_dim) -> ``tanh(mu + std * eps)`` in [-1, 1], reparameterised (rsample)."""
        return torch.tanh(mu + self.log_std.exp() * torch.randn_like(mu))

    def forward(self, obs: torch.Tensor, *, deterministic: bool = False) -> torch.Tensor:
        """obs -> action in [-1, 1]: ``tanh(mu + std * eps)`` (rsample), or ``tanh(mu)`` if deterministic."""
        mu = self.mean(obs)
        return torch.tanh(mu) if deterministic else self.sample(mu)


class StateActor(_GaussianTanhPolicy):
    """Actor on the (normalised) state vector: the reference upper bound ("state" mode).

    obs: (B, obs_dim) -> action (B, act_dim) in [-1, 1].
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden: Sequence[int], *, init: str = "orthogonal"):
        super().__init__(obs_dim, hidden, act_dim, init=init)


class VisualActor(_GaussianTanhPolicy):
    """Actor on stacked frames: DrQ-v2 encoder + MLP head.

    obs: (B, 3 * frames, H, W) in [0, 1] -> action (B, act_dim) in [-1, 1]. ``precision``: the encoder's
    (:class:`PixelEncoder`).
    """

    def __init__(self, in_channels: int, height: int, width: int, act_dim: int, trunk_dim: int,
                 hidden: Sequence[int], *, init: str = "orthogonal", precision: str | None = None):
        super().__init__(trunk_dim, hidden, act_dim, init=init)
        self.encoder = PixelEncoder(in_channels, height, width, trunk_dim, precision=precision)

    def features(self, obs: torch.Tensor) -> torch.Tensor:
        return self.encoder(obs)

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        """"encoder" (convolutions and trunk: pixels to features), then the head's "mlp" and "log_std"."""
        return {"encoder": list(self.encoder.parameters()), **super().param_groups()}


class Critic(nn.Module):
    """Value function on the normalised privileged state: (B, obs_dim) -> (B,)."""

    def __init__(self, obs_dim: int, hidden: Sequence[int]):
        super().__init__()
        self.net = MLP(obs_dim, hidden, 1)
        orthogonal_init(self.net, gain=2.0**0.5)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs).squeeze(-1)


class MemberStack:
    """N modules of one architecture (a population's actors or critics), evaluated together.

    Each member keeps its own parameters (its optimiser and checkpoint stay a run's own). :meth:`stack` stacks
    them along a leading member axis, differentiably: gradients of the stacked tensors flow back to each member's
    own parameters, and a member's loss reaches no other member's parameters. Call it once per window and pass
    the result to every step. With one member nothing is stacked and the member module itself runs, so a
    population of one computes exactly what a single run computes.

    Inputs and outputs are member-major: rows ``m * B .. (m + 1) * B`` belong to member ``m``.

    Args:
        members: modules of identical structure: :class:`StateActor`, :class:`VisualActor` or :class:`Critic`.
        batching: ``"grouped"``, the stacked parameters in batched matrix products and a visual encoder's
            convolutions as one convolution with ``groups = N`` over the members' images side by side on the
            channel axis; ``"loop"``, the same with one convolution per member; ``"modules"``, each member's own
            module on its rows, one after the other (exactly a run alone's arithmetic, and its kernel launches).
    """

    BATCHINGS = ("grouped", "loop", "modules")

    def __init__(self, members: Sequence[nn.Module], *, batching: Literal["grouped", "loop", "modules"] = "grouped"):
        if not members:
            raise ValueError("MemberStack needs at least one member")
        kinds = {type(m) for m in members}
        if len(kinds) > 1:
            raise ValueError(f"MemberStack: members of one kind only, got {sorted(k.__name__ for k in kinds)}")
        shapes = {tuple((n, tuple(p.shape)) for n, p in m.named_parameters()) for m in members}
        if len(shapes) > 1:
            raise ValueError("MemberStack: the members' parameter shapes differ")
        if batching not in self.BATCHINGS:
            raise ValueError(f"unknown member batching {batching!r}; valid: {', '.join(self.BATCHINGS)}")
        precisions = {m.encoder.precision for m in members if isinstance(m, VisualActor)}
        if len(precisions) > 1:  # one batched convolution runs in one precision
            raise ValueError(f"MemberStack: the members' encoders differ in precision: {sorted(precisions)}")
        self.members = list(members)
        self.n = len(self.members)
        self.batching = batching
        self._template = self.members[0]

    def stack(self) -> dict[str, torch.Tensor]:
        """Every parameter of the members as one (N, ...) tensor, by name; empty for a single member or
        ``"modules"`` batching."""
        if self.n == 1 or self.batching == "modules":
            return {}
        per_member = [dict(m.named_parameters()) for m in self.members]
        return {name: torch.stack([p[name] for p in per_member]) for name in per_member[0]}

    # ------------------------------------------------------------------ the members' forward passes
    def mean(self, params: dict[str, torch.Tensor], obs: torch.Tensor) -> torch.Tensor:
        """Policies: obs (N * B, ...) -> pre-tanh mean actions (N * B, act_dim)."""
        if self.n == 1:
            return self._template.mean(obs)
        if self.batching == "modules":
            return torch.cat([m.mean(x) for m, x in zip(self.members, obs.chunk(self.n))])
        if isinstance(self._template, VisualActor):
            features = self._encoder(params, obs)
        else:
            features = obs.unflatten(0, (self.n, -1))
        return self._sequential(self._template.mu, "mu.", params, features).flatten(0, 1)

    def value(self, params: dict[str, torch.Tensor], obs: torch.Tensor) -> torch.Tensor:
        """Critics: obs (N * B, obs_dim) -> values (N * B,)."""
        if self.n == 1:
            return self._template(obs)
        if self.batching == "modules":
            return torch.cat([m(x) for m, x in zip(self.members, obs.chunk(self.n))])
        out = self._sequential(self._template.net, "net.", params, obs.unflatten(0, (self.n, -1)))
        return out.squeeze(-1).flatten(0, 1)

    def _encoder(self, params: dict[str, torch.Tensor], images: torch.Tensor) -> torch.Tensor:
        """(N * B, C, H, W) in [0, 1] -> (N, B, trunk_dim), as :class:`PixelEncoder` per member."""
        n = self.n
        x = (images - 0.5).unflatten(0, (n, -1))  # (N, B, C, H, W)
        encoder = self._template.encoder
        with _precision.encoder_autocast(x.device.type, encoder.precision):
            flat = self._convolutions(params, x, encoder.convs)
        if encoder.precision == "bf16":
            flat = flat.float()  # the trunk (Linear, LayerNorm) in float32, as PixelEncoder.forward
        return self._sequential(encoder.trunk, "encoder.trunk.", params, flat)

    def _convolutions(self, params: dict[str, torch.Tensor], x: torch.Tensor, convs: nn.Sequential) -> torch.Tensor:
        """The encoder's convolutions per member: x (N, B, C, H, W) -> (N, B, C' H' W'), each member's features in
        (C, H, W) order."""
        n = self.n
        b, c, h, w = x.shape[1:]
        if self.batching == "grouped":
            # the members side by side on the channel axis: group m of every convolution sees member m alone
            y = x.transpose(0, 1).reshape(b, n * c, h, w).contiguous(memory_format=torch.channels_last)
            for i, layer in enumerate(convs):
                if isinstance(layer, nn.Conv2d):
                    weight, bias = params[f"encoder.convs.{i}.weight"], params[f"encoder.convs.{i}.bias"]
                    y = F.conv2d(y, weight.flatten(0, 1), bias.flatten(), stride=layer.stride,
                                 padding=layer.padding, groups=n)
                else:
                    y = layer(y)
            return y.reshape(b, n, -1).transpose(0, 1)  # (N, B, C' H' W'), each member's (C, H, W) order
        outs = []
        for m in range(n):
            y = x[m].contiguous(memory_format=torch.channels_last)
            for i, layer in enumerate(convs):
                if isinstance(layer, nn.Conv2d):
                    y = F.conv2d(y, params[f"encoder.convs.{i}.weight"][m], params[f"encoder.convs.{i}.bias"][m],
                                 stride=layer.stride, padding=layer.padding)
                else:
                    y = layer(y)
            outs.append(y.flatten(1))
        return torch.stack(outs)

    def _sequential(self, seq: nn.Sequential, prefix: str, params: dict[str, torch.Tensor],
                    x: torch.Tensor) -> torch.Tensor:
        """``seq`` (Linear, LayerNorm and parameter-free layers) applied per member: x (N, B, in) -> (N, B, out)."""
        for i, layer in enumerate(seq):
            name = f"{prefix}{i}"
            if isinstance(layer, nn.Linear):
                # W x^T rather than x W^T: the weight's gradient then comes out in the weight's own layout
                weight, bias = params[f"{name}.weight"], params[f"{name}.bias"]
                x = torch.bmm(weight, x.transpose(1, 2)).transpose(1, 2) + bias.unsqueeze(1)
            elif isinstance(layer, nn.LayerNorm):
                x = F.layer_norm(x, layer.normalized_shape, eps=layer.eps)
                x = torch.addcmul(params[f"{name}.bias"].unsqueeze(1), x, params[f"{name}.weight"].unsqueeze(1))
            elif any(True for _ in layer.parameters()):
                raise TypeError(f"MemberStack cannot batch {type(layer).__name__} ({name})")
            else:
                x = layer(x)
        return x
