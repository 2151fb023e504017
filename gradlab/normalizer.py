"""Running mean / variance of observations (parallel Welford merge), on the device, checkpointable."""

from __future__ import annotations

import torch

__all__ = ["RunningMeanStd"]


class RunningMeanStd:
    """Running statistics of vectors of size ``dim``.

    ``normalize`` uses the statistics as they are; SHAC freezes a copy at each window start (``snapshot``) so
    that one window's observations are all normalised the same way, and merges the window's data afterwards.
    """

    def __init__(self, dim: int, *, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
                 epsilon: float = 1e-4):
        self.mean = torch.zeros(dim, device=device, dtype=dtype)
        self.var = torch.ones(dim, device=device, dtype=dtype)
        # A small prior count keeps the first merge from dividing by zero (as SHAC's RunningMeanStd).
        self.count = torch.tensor(epsilon, device=device, dtype=torch.float64)

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Merge a batch x: (..., dim)."""
        x = x.reshape(-1, self.mean.shape[0]).to(self.mean.dtype)
        b_mean = x.mean(0)
        b_var = x.var(0, unbiased=False)
        b_count = torch.tensor(float(x.shape[0]), device=self.count.device, dtype=torch.float64)
        delta = b_mean - self.mean
        tot = self.count + b_count
        w = (b_count / tot).to(self.mean.dtype)
        w_old = (self.count / tot).to(self.mean.dtype)
        # In place: a captured CUDA graph reads these tensors' memory, so they must never be rebound.
        self.var.copy_(self.var * w_old + b_var * w + delta.square() * w * w_old)
        self.mean.add_(delta * w)
        self.count.copy_(tot)

    def snapshot(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, std) frozen copies for one window (new tensors: later updates do not change them)."""
        return self.mean.clone(), torch.sqrt(self.var + 1e-5)

    @staticmethod
    def apply(x: torch.Tensor, stats: tuple[torch.Tensor, torch.Tensor], clip: float | None = None) -> torch.Tensor:
        """Normalise x with (mean, std) from ``snapshot``, clipped to +-clip unless ``clip`` is None or 0."""
        mean, std = stats
        y = (x - mean) / std
        return torch.clamp(y, -clip, clip) if clip else y

    def state_dict(self) -> dict:
        return {"mean": self.mean.clone(), "var": self.var.clone(), "count": self.count.clone()}

    def load_state_dict(self, state: dict) -> None:
        self.mean.copy_(state["mean"])
        self.var.copy_(state["var"])
        self.count.copy_(state["count"])
