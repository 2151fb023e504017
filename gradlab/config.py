"""SHAC / D.Va configuration: one dataclass, field docstrings become the CLI's ``--help`` (tyro).

Fields left at ``None`` take the value of the chosen preset (:mod:`gradlab.presets`: the reference code's
per-task hyperparameters, with their sources) when the trainer is built; ``config.json`` of a run stores the
resolved values and which of them the preset supplied. ``ModePlan`` is everything the ``mode`` switch
decides, in one place.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

from gradlab.config_checks import check_integers, check_number, flag
from gradlab.precision import PRECISIONS
from gradlab.presets import preset_values
from vocabulary import MEMBER_DEFAULTS, MODES, PRESET_FIELDS, PRESETS, RASTER_MODELS, RENDERERS, SIM_BACKENDS, TASKS

__all__ = ["SHACConfig", "MODES", "ModePlan", "resolve_config", "check_as_given"]

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
    # a student sees rendered images, without their gradient (it learns by regression: gradlab/distill.py)
    "distill": ModePlan(actor_input="images", grad_through_images=False),
}
if tuple(_MODE_PLANS) != MODES:  # the names are vocabulary's: a mode without its plan is refused here
    raise ImportError(f"gradlab.config plans the modes {tuple(_MODE_PLANS)}, vocabulary.MODES names {MODES}")


@dataclass
class SHACConfig:
    """SHAC with one switch between full APG through pixels and decoupled D.Va."""

    task: str = "cartpole"
    """Task: cartpole (D.Va's, with joint springs), cartpole-swingup (SHAC's spring-free swing-up), hopper,
    ant, humanoid or cheetah (docs/tasks.md lists every constant and its source)."""
    preset: Literal[PRESETS] = "dva"
    """Hyperparameters every field left unset takes (gradlab/presets.py, with sources): dva, D.Va's per-task
    configs (SHAC's state-based ones for --mode state where they differ); shac-diffrender, the paper's
    full-APG baseline (its decay length, the hard rasterizer). Explicit flags override the preset; config.json
    records both."""
    mode: Literal[MODES] = "decoupled"
    """full: gradients flow through the rendered images into the robot state; decoupled (D.Va): the image
    stack is detached at the actor's input; state: the actor sees the state vector (upper bound); blind: the
    decoupled visual actor, critic and rewards, but the actor sees a constant all-black image stack, so it
    learns one open-loop action distribution for every state: the floor any result from pixels must beat.
    Blind runs render nothing during training and run no probes."""
    iters: int = 500
    """Training iterations (one iteration = num_envs x horizon env steps)."""
    lr_decay_iters: int | None = None
    """Iterations over which both learning rates decay linearly to 1e-5 (the reference's max_epochs:
    D.Va 4000 cartpole, 30000 hopper/ant/cheetah, 60000 humanoid); None: the preset's."""
    num_envs: int | None = None
    """Parallel environments; None: the preset's (64; SHAC's state-based hopper 256)."""
    horizon: int = 32
    """Steps per SHAC window (the backpropagation horizon)."""
    seed: int = 0
    """One seed for everything (networks, noise, resets), an integer in [-2**63, 2**63 - 1]. Same seed on the CPU
    gives identical metrics."""
    gamma: float = 0.99
    """Discount."""
    lam: float = 0.95
    """TD(lambda) for the critic targets."""
    actor_lr: float | None = None
    """Actor learning rate (decays linearly to 1e-5); None: the preset's (2e-3; SHAC's state cartpole 1e-2)."""
    critic_lr: float | None = None
    """Critic learning rate; None: the preset's (2e-4 cartpole/hopper, 2e-3 ant/cheetah, 5e-4 humanoid)."""
    betas: tuple[float, float] = MEMBER_DEFAULTS["betas"]
    """Adam betas (actor and critic)."""
    grad_clip: float = MEMBER_DEFAULTS["grad_clip"]
    """Gradient-norm clipping for actor and critic."""
    critic_iterations: int = MEMBER_DEFAULTS["critic_iterations"]
    """Critic passes over each window's data."""
    critic_batches: int = MEMBER_DEFAULTS["critic_batches"]
    """Minibatches per critic pass."""
    target_alpha: float | None = None
    """Target critic Polyak factor (target = a*target + (1-a)*critic); None: 0.2, humanoid 0.995."""
    trunk_dim: int | None = None
    """Visual encoder trunk width; None: 64 cartpole, 128 hopper/ant/cheetah, 256 humanoid."""
    actor_hidden: tuple[int, ...] | None = None
    """Actor MLP widths; None: task reference ([64,64], [128,64,32], [256,128])."""
    critic_hidden: tuple[int, ...] | None = None
    """Critic MLP widths; None: [64,64] ([128,128] humanoid)."""
    actor_init: Literal["default", "orthogonal"] | None = None
    """Initialisation of the actor's MLP: default (PyTorch's nn.Linear init, as the reference's actor:
    initial mean actions of order 0.5 before the tanh) or orthogonal (gain sqrt(2), last layer 0.01: mean
    actions near 0); None: the preset's (default)."""
    obs_clip: float | None = None
    """Clip normalised state observations to +-obs_clip; 0 disables (the reference does not clip); None: the
    preset's (0)."""
    bootstrap_last_step: bool | None = None
    """An episode that fails exactly on its last step is bootstrapped with the target critic (the reference
    counts only episodes shorter than the episode length as early terminations) instead of ending with a zero
    value; None: the preset's (true)."""
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
    raster_model: Literal[RASTER_MODELS] | None = None
    """The rasterizer's image model, and so the gradient estimator of --mode full (docs/design.md, "Image
    model"): hard, a z-buffer whose gradients flow only through interpolation and shading (the paper's
    full-APG baseline, PyTorch3D at blur 0); softmax, SoftRas aggregation with the floor and sky as
    candidates; alpha, faces composited over floor and sky by coverage. The soft models' silhouettes carry
    gradient. None: the preset's (shac-diffrender: hard; else the soft default, gradlab.presets)."""
    renderer: Literal[RENDERERS] = "soft"
    """Where the images the actor trains on come from: soft, the differentiable rasterizer; warp, the
    forward-only Warp ray tracer (the rasterizer's sharp limit, cost nearly flat in mesh faces) for modes
    whose images need no gradient (decoupled, blind, state's videos). Probe iterations render with the
    rasterizer so that both gradients are taken through one differentiable image. Evaluation videos use it
    too."""
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
    (forward and backward; plain and probe iterations separately) and the critic fit as CUDA graphs
    replayed every iteration. The first iterations pay the compilation; worth it on a GPU."""
    precision: Literal[PRECISIONS] = "fp32"
    """Numeric precision on a CUDA device (gradlab/precision.py): fp32, float32 with PyTorch's defaults (matmuls
    in full float32; cuDNN may run the encoder's float32 convolutions in TF32, its default); tf32, TF32 tensor
    cores for every float32 matmul and convolution, a process-wide switch that also reaches the simulator, the
    renderer and the critic; bf16, the encoder's convolutions under bfloat16 autocast, their output cast back to
    float32 for the trunk, everything else exactly as fp32. One value for a whole population (the TF32 switches
    are the process's). The CPU trains in fp32 only: tf32 and bf16 are refused there."""
    overlap_critic: bool = True
    """With CUDA graphs (--compile on a GPU), fit the critic on a second stream while the actor's backward
    replays: the fit reads only the window's buffers and the backward never reads the critic, so the numbers
    are the same and the fit's time hides behind the backward's. critic_ms is then the fit's own time, not
    added to the iteration's. False: fit after the backward (the phases' times add up)."""
    abort_grad_norm: float = MEMBER_DEFAULTS["abort_grad_norm"]
    """Stop (as D.Va does) when the actor's pre-clip gradient norm exceeds this."""
    eval_every: int = 250
    """Every K-th iteration (and at the last), evaluate the deterministic policy (its mean action) on eval_envs
    environments started from fixed evaluation seeds (the same initial states at every evaluation, for every
    run), for one whole episode each; logs eval_return_mean, eval_return_std, eval_length_mean and its cost
    eval_s. 0 disables. Cost (BENCHMARKS.md, section 7): with --compile on a GPU about 1 s for a hopper run's 16
    whole episodes, 4-5 % of 250 iterations, plus about 40 s compiling at the first evaluation."""
    eval_envs: int = 16
    """Environments (whole episodes) per evaluation."""
    encoder_lr_scale: float = MEMBER_DEFAULTS["encoder_lr_scale"]
    """Scale of the visual encoder's learning rate against the actor's (an ablation of the early blind phase,
    where the first Adam steps on the large trunk layer saturate it; the reference: 1)."""
    lr_warmup_iters: int = MEMBER_DEFAULTS["lr_warmup_iters"]
    """Iterations over which the actor's learning rate ramps linearly from 0 to its schedule (an ablation of
    the early blind phase; the reference: 0, none)."""
    expert: str | None = MEMBER_DEFAULTS["expert"]
    """--mode distill: the frozen state expert the student imitates, a state run's folder (its newest readable
    checkpoint) or one of its checkpoint files; its training time and steps are charged to the student
    (docs/distill.md). A member's own setting: distill members with one expert each form a population."""
    distill_buffer: int = 100_000
    """--mode distill: samples the replay buffer holds (FIFO, on the device, frames as uint8; D.Va's
    max_replay_buffer_size)."""
    distill_starts: int = 32_000
    """--mode distill: samples the buffer must hold before the student's updates start (D.Va's learning_starts)."""
    distill_updates: int = 2000
    """--mode distill: most Adam steps an iteration (D.Va's num_update_per_epoch)."""
    distill_batch: int = 128
    """--mode distill: samples per Adam step, drawn without replacement from the whole buffer (D.Va's
    batch_size)."""
    distill_loss_threshold: float = 0.1
    """--mode distill: an iteration's updates stop at the first minibatch whose loss is below this (D.Va's
    supervised_loss_threshold)."""
    sim_backend: Literal[SIM_BACKENDS] = "torch"
    """What runs the physics substeps (tasks.TaskConfig.sim_backend): torch, the PyTorch simulator (the
    reference); warp, the same model as Warp kernels (tasks/warp_sim.py), a kernel launch a substep. Not part
    of a run's arm. One value for a whole population (its environments are one batch)."""

    def validate(self) -> None:
        """Clear errors for bad values, before any work: each names its flag as typed (``--num-envs``), NaN and
        infinities included."""
        if self.task not in TASKS:
            raise ValueError(f"--task: unknown task {self.task!r}; valid tasks: {', '.join(TASKS)}")
        try:
            plan = ModePlan.of(self.mode)
        except ValueError as e:
            raise ValueError(f"--mode: {e}") from None
        if self.preset not in PRESETS:
            raise ValueError(f"--preset: unknown preset {self.preset!r}; valid presets: {', '.join(PRESETS)}")
        if self.raster_model is not None and self.raster_model not in RASTER_MODELS:
            raise ValueError(f"--raster-model: unknown raster model {self.raster_model!r}; valid: "
                             f"{', '.join(RASTER_MODELS)}")
        if self.renderer not in RENDERERS:
            raise ValueError(f"--renderer: unknown renderer {self.renderer!r}; valid renderers: "
                             f"{', '.join(RENDERERS)}")
        if self.renderer == "warp" and plan.grad_through_images:
            raise ValueError(f"--renderer warp renders without gradient, but --mode {self.mode} backpropagates "
                             "through the images: use --renderer soft (the differentiable rasterizer)")
        if self.sim_backend not in SIM_BACKENDS:
            raise ValueError(f"--sim-backend: unknown simulator backend {self.sim_backend!r}; valid: "
                             f"{', '.join(SIM_BACKENDS)}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"--precision: unknown precision {self.precision!r}; valid: {', '.join(PRECISIONS)}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or not -2**63 <= self.seed < 2**63:
            raise ValueError(f"--seed must be an integer in [-2**63, 2**63 - 1] (torch's 64-bit seed), got "
                             f"{self.seed!r}")
        check_integers(self, ("iters", "horizon", "critic_iterations", "critic_batches", "image_size", "frames",
                              "render_detail", "eval_envs"), minimum=1)
        check_integers(self, ("num_envs", "lr_decay_iters", "trunk_dim", "episode_length"), minimum=1,
                       optional=True)
        check_integers(self, ("extra_meshes", "cosine_every", "eval_every", "lr_warmup_iters"), minimum=0)
        # The renderer's extra meshes are spheres; the smallest closed one it builds has 6 vertices.
        check_integers(self, ("extra_mesh_verts",), minimum=6 if self.extra_meshes else 1)
        if self.image_size < 16:
            raise ValueError(f"--image-size must be >= 16 pixels for the encoder, got {self.image_size}")
        for name in ("actor_hidden", "critic_hidden"):
            widths = getattr(self, name)
            if widths is not None and (not widths or not all(isinstance(w, int) and w > 0 for w in widths)):
                raise ValueError(f"{flag(name)} must be one or more positive layer widths, got {widths!r}")
        check_number("gamma", self.gamma, "(0, 1]")
        check_number("lam", self.lam, "[0, 1]")
        for i, beta in enumerate(self.betas):
            check_number("betas", beta, "[0, 1)", what=f"--betas (value {i + 1})")
        for name, interval in (("actor_lr", "(0, inf)"), ("critic_lr", "(0, inf)"), ("target_alpha", "[0, 1]"),
                               ("obs_clip", "[0, inf)"), ("sigma", "(0, inf)"), ("render_gamma", "(0, inf)")):
            if getattr(self, name) is not None:
                check_number(name, getattr(self, name), interval)
        check_number("grad_clip", self.grad_clip, "(0, inf)")
        check_number("encoder_lr_scale", self.encoder_lr_scale, "(0, inf)")
        check_number("abort_grad_norm", self.abort_grad_norm, "(0, inf]")
        check_integers(self, ("distill_buffer", "distill_starts", "distill_updates", "distill_batch"), minimum=1)
        check_number("distill_loss_threshold", self.distill_loss_threshold, "[0, inf)")
        if self.mode == "distill":
            if not self.distill_batch <= self.distill_starts <= self.distill_buffer:
                raise ValueError(f"--distill-starts {self.distill_starts} must lie between --distill-batch "
                                 f"{self.distill_batch} and --distill-buffer {self.distill_buffer}")
        if self.num_envs is not None and self.critic_batches > self.num_envs * self.horizon:
            raise ValueError(f"--critic-batches {self.critic_batches} cannot exceed --num-envs x --horizon "
                             f"({self.num_envs * self.horizon})")


def check_as_given(cfg: SHACConfig) -> None:
    """Checks of the settings as given, before the preset fills in the unset ones (a preset's table holds values
    for every mode, so a resolved config.json may hold them where they do not act): a setting given for a mode in
    which it means nothing is refused, rather than recorded in config.json as if it had acted. ValueError naming
    the flags."""
    plan = ModePlan.of(cfg.mode)
    if cfg.raster_model is not None and not plan.renders:
        raise ValueError(f"--raster-model {cfg.raster_model} means nothing with --mode {cfg.mode}: the raster model "
                         "is the image model of the images the actor trains on, and this actor sees none")
    if cfg.mode == "distill" and not cfg.expert:
        raise ValueError("--expert: --mode distill needs a state expert, a state run's folder or checkpoint (train "
                         "one with --mode state --preset teacher)")
    if cfg.expert and cfg.mode != "distill":
        raise ValueError(f"--expert means nothing with --mode {cfg.mode}: only a distill student has an expert")
    if cfg.preset == "teacher" and cfg.mode != "state":
        raise ValueError(f"--preset teacher trains the state experts of --mode distill: use it with --mode state, "
                         f"not --mode {cfg.mode}")


def resolve_config(cfg: SHACConfig) -> SHACConfig:
    """A copy with every None field the preset sets replaced by the preset's value for the task and mode
    (validated before and after)."""
    cfg.validate()
    table = preset_values(cfg.preset, cfg.task, cfg.mode)
    out = dataclasses.replace(cfg, **{k: table[k] for k in PRESET_FIELDS if getattr(cfg, k) is None})
    out.actor_hidden = tuple(out.actor_hidden)
    out.critic_hidden = tuple(out.critic_hidden)
    out.validate()
    return out
