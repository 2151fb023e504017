"""Actor and critic networks of SHAC / D.Va (docs/design.md, "A SHAC window").

The visual actor is the DrQ-v2 encoder (4 convolutions, ReLU) followed by a trunk (Linear -> LayerNorm -> Tanh)
and an MLP head (Linear -> ELU -> LayerNorm per hidden layer). The policy is a tanh-squashed Gaussian with a
state-independent log-std initialised at -1; actions are drawn with the reparameterisation trick so that the
analytic policy gradient flows through them into the simulator.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

__all__ = ["MLP", "PixelEncoder", "StateActor", "VisualActor", "Critic", "orthogonal_init"]


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
    """

    def __init__(self, in_channels: int, height: int, width: int, trunk_dim: int):
        super().__init__()
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
        h = self.convs((images - 0.5).contiguous(memory_format=torch.channels_last))
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

    obs: (B, 3 * frames, H, W) in [0, 1] -> action (B, act_dim) in [-1, 1].
    """

    def __init__(self, in_channels: int, height: int, width: int, act_dim: int, trunk_dim: int,
                 hidden: Sequence[int], *, init: str = "orthogonal"):
        super().__init__(trunk_dim, hidden, act_dim, init=init)
        self.encoder = PixelEncoder(in_channels, height, width, trunk_dim)

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
