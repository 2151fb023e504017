"""SHAC / D.Va configuration: one dataclass, field docstrings become the CLI's ``--help`` (tyro).

Fields left at ``None`` take the task's reference value (docs/design.md, "A SHAC window";
notes/dva-reference.md) when the trainer is built; ``config.json`` of a run stores the resolved values.
``ModePlan`` is everything the ``mode`` switch decides, in one place.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

__all__ = ["SHACConfig", "TASK_DEFAULTS", "MODES", "ModePlan", "resolve_config"]

#: Per-task reference hyperparameters (D.Va / SHAC configs).
TASK_DEFAULTS: dict[str, dict] = {
    "cartpole": dict(critic_lr=2e-4, target_alpha=0.2, trunk_dim=64, actor_hidden=(64, 64),
                     critic_hidden=(64, 64)),
    "hopper": dict(critic_lr=2e-4, target_alpha=0.2, trunk_dim=128, actor_hidden=(128, 64, 32),
                   critic_hidden=(64, 64)),
    "ant": dict(critic_lr=2e-3, target_alpha=0.2, trunk_dim=128, actor_hidden=(128, 64, 32),
                critic_hidden=(64, 64)),
    "humanoid": dict(critic_lr=5e-4, target_alpha=0.995, trunk_dim=256, actor_hidden=(256, 128),
                     critic_hidden=(128, 128)),
}


@dataclass(frozen=True)
class ModePlan:
    """What the training mode decides, decided once; the trainer reads this and never the mode's name
    (docs/design.md, "Where the mode acts").

    Attributes:
        actor_input: what the actor sees: "images" (the rendered frame stack), "blank" (a constant all-black
            stack of the same shape, zeros (B, 3 * frames, H, W): the visual actor, blind) or "state" (the
            normalised state vector).
        grad_through_images: the training gradient flows through the images into the renderer (full APG).
            Plain iterations then render with grad and train with the image gate open; otherwise they render
            without grad and the gate stays closed.

    The image gradient is cut in three places, each for its own reason:

    * a decoupled plain iteration renders under ``no_grad``: no render graph is built at all, which is
      what makes D.Va cheap (the image is a constant to the actor);
    * the ``ImageGate`` at the actor's input exists for probe iterations only: they render with grad and
      differentiate ONE graph twice, gate open (full) and closed (decoupled), so the two gradients come from
      the same rollout;
    * the frame buffer is detached at the window start together with the task state: that is SHAC's
      truncation of the whole state between windows (like ``task.detach()``), not an image-gradient switch.
    """

    actor_input: Literal["images", "blank", "state"]
    grad_through_images: bool

    @property
    def renders(self) -> bool:
        """The trainer renders the task during training (the actor's images, the probes' render path); a blind
        actor's input is a constant, so nothing is rendered for it."""
        return self.actor_input == "images"

    @property
    def probes(self) -> bool:
        """Probe iterations (both gradients of one rollout) apply: they need images rendered with grad that the
        actor sees. Not in state mode (no images) nor blind mode (its image does not depend on the state, so its
        full and decoupled gradients are the same)."""
        return self.renders

    @staticmethod
    def of(mode: str) -> ModePlan:
        try:
            return _MODE_PLANS[mode]
        except KeyError:
            raise ValueError(f"unknown mode {mode!r}; valid modes: {', '.join(MODES)}") from None


_MODE_PLANS = {
    "full": ModePlan(actor_input="images", grad_through_images=True),
    "decoupled": ModePlan(actor_input="images", grad_through_images=False),
    "state": ModePlan(actor_input="state", grad_through_images=False),
    "blind": ModePlan(actor_input="blank", grad_through_images=False),
}
MODES = tuple(_MODE_PLANS)


@dataclass
class SHACConfig:
    """SHAC with one switch between full APG through pixels and decoupled D.Va."""

    task: str = "cartpole"
    """Task: cartpole, hopper, ant or humanoid."""
    mode: Literal["full", "decoupled", "state", "blind"] = "decoupled"
    """full: gradients flow through the rendered images into the robot state; decoupled (D.Va): the image
    stack is detached at the actor's input; state: the actor sees the state vector (upper bound); blind: the
    decoupled visual actor, critic and rewards, but the actor sees a constant all-black image stack, so it
    learns one open-loop action distribution for every state: the floor any result from pixels must beat.
    Blind runs render nothing during training and run no probes."""
    iters: int = 500
    """Training iterations (one iteration = num_envs x horizon env steps). Also the length of the linear
    learning-rate decay."""
    num_envs: int = 64
    """Parallel environments."""
    horizon: int = 32
    """Steps per SHAC window (the backpropagation horizon)."""
    seed: int = 0
    """One seed for everything (networks, noise, resets). Same seed on the CPU gives identical metrics."""
    gamma: float = 0.99
    """Discount."""
    lam: float = 0.95
    """TD(lambda) for the critic targets."""
    actor_lr: float = 2e-3
    """Actor learning rate (decays linearly to 1e-5)."""
    critic_lr: float | None = None
    """Critic learning rate; None: the task's reference value (2e-4 cartpole/hopper, 2e-3 ant, 5e-4
    humanoid)."""
    betas: tuple[float, float] = (0.7, 0.95)
    """Adam betas (actor and critic)."""
    grad_clip: float = 1.0
    """Gradient-norm clipping for actor and critic."""
    critic_iterations: int = 16
    """Critic passes over each window's data."""
    critic_batches: int = 4
    """Minibatches per critic pass."""
    target_alpha: float | None = None
    """Target critic Polyak factor (target = a*target + (1-a)*critic); None: 0.2, humanoid 0.995."""
    trunk_dim: int | None = None
    """Visual encoder trunk width; None: 64 cartpole, 128 hopper/ant, 256 humanoid."""
    actor_hidden: tuple[int, ...] | None = None
    """Actor MLP widths; None: task reference ([64,64], [128,64,32], [256,128])."""
    critic_hidden: tuple[int, ...] | None = None
    """Critic MLP widths; None: [64,64] ([128,128] humanoid)."""
    image_size: int = 84
    """Rendered image height and width in pixels."""
    frames: int = 3
    """Stacked frames at the actor's input."""
    render_detail: int = 1
    """Mesh tessellation level of the robot's primitives (higher: more vertices per mesh)."""
    extra_meshes: int = 0
    """Extra meshes attached to robot links (their vertices move with qpos): scene complexity for the
    memory sweep."""
    extra_mesh_verts: int = 64
    """Vertices per extra mesh."""
    sigma: float | None = None
    """Soft-rasterizer edge softness in pixels; None: the renderer's default."""
    render_gamma: float | None = None
    """Soft-rasterizer depth-blend temperature; None: the renderer's default."""
    render_blend: Literal["softmax", "alpha"] = "softmax"
    """How faces meet the floor: softmax (the depth softmax of docs/design.md, "Image model", with the floor
    as one more candidate) or alpha (faces softmax-blended among themselves, then composited over floor and sky
    by coverage). alpha passes 2-3x more of the image's change at silhouettes to the gradient
    (benchmarks/render.py --jump-share) and renders without back-face culling."""
    episode_length: int | None = None
    """Override the task's episode length (None: 240 cartpole, 1000 others)."""
    cosine_every: int = 10
    """Every K-th iteration, compute both gradients (full and decoupled) of the SAME rollout and log their
    norms and cosine; 0 disables. full and decoupled modes only. Keys: grad_norm_full, grad_norm_decoupled,
    cos_full_decoupled; grad_norm_render_term (the norm of full minus decoupled: the path through the
    renderer) and its split by the actor's parameter groups, grad_norm_render_term_encoder / _mlp / _log_std
    (their squares sum to its square); image_sensitivity_f0 .. f{frames-1}, how much the policy looks at
    each frame of its stack, oldest first: the norm of d(sum of the mean action)/d(frame), averaged over the
    environments, on the frame stack the window ended in (gradlab.probes.image_sensitivity)."""
    compile: bool = False
    """torch.compile the physics substep, the per-step reward/reset and the renderer's PyTorch work (forward
    kinematics, camera, the fused rasterizer's per-face setup) and, on a CUDA device, capture the window
    (forward and backward; plain and probe iterations separately) and the critic phase as CUDA graphs
    replayed every iteration. The first iterations pay the compilation; worth it on a GPU."""
    abort_grad_norm: float = 1e8
    """Stop (as D.Va does) when the actor's pre-clip gradient norm exceeds this."""

    def validate(self) -> None:
        """Clear errors for bad values, before any work."""
        from tasks import TASKS

        if self.task not in TASKS:
            raise ValueError(f"unknown task {self.task!r}; valid tasks: {', '.join(TASKS)}")
        ModePlan.of(self.mode)  # raises for an unknown mode, naming the valid ones
        for name in ("iters", "num_envs", "horizon", "critic_iterations", "critic_batches", "image_size",
                     "frames", "render_detail"):
            v = getattr(self, name)
            if not isinstance(v, int) or v <= 0:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        for name in ("extra_meshes", "cosine_every"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 0:
                raise ValueError(f"{name} must be a non-negative integer, got {v!r}")
        if self.extra_meshes and self.extra_mesh_verts < 6:
            # The renderer's extra meshes are spheres; the smallest closed one it builds has 6 vertices.
            raise ValueError(f"extra_mesh_verts must be >= 6, got {self.extra_mesh_verts}")
        if not 0 < self.gamma <= 1 or not 0 <= self.lam <= 1:
            raise ValueError(f"gamma must be in (0, 1] and lam in [0, 1], got {self.gamma}, {self.lam}")
        if self.actor_lr <= 0 or (self.critic_lr is not None and self.critic_lr <= 0):
            raise ValueError("learning rates must be positive")
        if self.grad_clip <= 0:
            raise ValueError(f"grad_clip must be positive, got {self.grad_clip}")
        if self.critic_batches > self.num_envs * self.horizon:
            raise ValueError("critic_batches cannot exceed num_envs * horizon")
        if self.episode_length is not None and self.episode_length <= 0:
            raise ValueError(f"episode_length must be positive, got {self.episode_length}")
        if self.image_size < 16:
            raise ValueError(f"image_size must be >= 16 pixels for the encoder, got {self.image_size}")


def resolve_config(cfg: SHACConfig) -> SHACConfig:
    """A copy with every None field replaced by the task's reference value (validated first)."""
    cfg.validate()
    defaults = TASK_DEFAULTS[cfg.task]
    updates = {k: v for k, v in defaults.items() if getattr(cfg, k) is None}
    out = dataclasses.replace(cfg, **updates)
    out.actor_hidden = tuple(out.actor_hidden)
    out.critic_hidden = tuple(out.critic_hidden)
    return out
