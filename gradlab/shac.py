"""SHAC with one switch between full analytic policy gradients through pixels and decoupled D.Va.

One iteration, top to bottom (docs/design.md, "A SHAC window"):

1. Rollout window: cut the graph at the window start (task state and frame buffer: SHAC's truncation), then
   roll out ``horizon`` steps: actor(images, a constant blank image, or state) -> tanh action ->
   differentiable simulator -> reward; render the new state into the frame stack.
2. Actor loss: SHAC's ``-(sum_t gamma^t r_t + gamma^T V_target(s_T)) / (T*B)``, episodes cut at resets and the
   terminal value zero after an early termination.
3. Backward: the mode decides what the actor sees and whether its gradient runs through the images
   (``ModePlan``, decided once from the config: docs/design.md, "Where the mode acts"). On probe iterations
   (every ``cosine_every``) the images are rendered WITH grad behind an ``ImageGate`` and the loss is
   differentiated twice over the same graph, gate open and closed: the full and the decoupled gradient of the
   SAME rollout; the training mode's gradient is the one applied. The probe also splits their difference by
   the actor's parameter groups and measures the policy's sensitivity to each frame of its stack.
4. Clip, Adam step with a linear LR decay.
5. Critic fit on TD(lambda) targets of the window; Polyak-update the target critic. The fit is independent of
   the actor's gradient, so with CUDA graphs it runs alongside the backward of step 3 (``overlap_critic``).

With ``--compile`` the parts in :meth:`SHAC.compile_table` run through ``torch.compile``, and on a CUDA device the
window (steps 1-3) and the critic fit are CUDA graphs replayed every iteration; ``gradlab.graphs`` holds that
machinery, and this module calls it the same way either way.

Every iteration reports CUDA-synchronised forward / backward / critic times, peak allocated and reserved memory
(CUDA), bytes saved for backward, pre- and post-clip gradient norms; a NaN/inf anywhere stops the run with the
iteration, the horizon step and the tensor named.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from collections import deque
from collections.abc import Callable, Collection
from typing import ClassVar

import numpy as np
import torch
from torch import nn

import tasks
from gradlab.config import ModePlan, SHACConfig, resolve_config
from gradlab.critic import fit_critic, polyak_update, td_lambda_targets
from gradlab.graphs import WARMUP_ITERS, GraphedCriticPhase, LiveState, WindowGraphs, zero_grads_
from gradlab.networks import Critic, StateActor, VisualActor
from gradlab.normalizer import RunningMeanStd
from gradlab.probes import FiniteFlags, ImageGate, NonFiniteError, cosine, flat_grad, group_norms, image_sensitivity
from gradlab.seeding import resolve_device, rng_state, seed_everything, set_rng_state
from gradlab.timing import RegionTimer
from tasks.vision import FrameStack, TaskRenderer

__all__ = ["COMPILE_PARTS", "SHAC", "NonFiniteError"]

#: What ``--compile`` compiles (:meth:`SHAC.compile_table`), in parts that are each their own graphs and compile
#: work, so that separate processes can compile them at the same time into one cache: the physics' own parts
#: (tasks.PHYSICS_PARTS), the renderer's PyTorch work, and the actor with the critic.
COMPILE_PARTS = (*tasks.PHYSICS_PARTS, "renderer", "networks")

_FLAG_NAMES = ["state_obs", "reward", "terminal_value", "image", "action", "qpos", "qvel"]


class SHAC:
    """The SHAC / D.Va trainer.

    Args:
        cfg: the configuration; None fields are resolved to the task's reference values.
        device: "auto" | "cpu" | "cuda[:N]".

    With ``cfg.compile`` the trainer compiles every part of :meth:`compile_table` at its first iteration, unless
    :meth:`compile` named the parts before (a process that compiles only some of them).
    """

    #: Where the trainer calls what it compiles, by the name a progress display gives the compilations made
    #: there: attribute paths from the trainer, each holding the callable that is called.
    COMPILE_SITES: ClassVar[dict[str, str]] = {
        "physics step": "task.step", "renderer": "_render", "actor": "_actor_mean", "critic": "_target_value",
        "backward pass": "window.backward"}

    def __init__(self, cfg: SHACConfig, *, device: str | torch.device = "auto"):
        self.cfg = resolve_config(cfg)
        cfg = self.cfg
        self.plan = ModePlan.of(cfg.mode)
        self.device = device if isinstance(device, torch.device) else resolve_device(device)
        seed_everything(cfg.seed)

        overrides = {} if cfg.episode_length is None else {"episode_length": cfg.episode_length}
        self.task = tasks.make(cfg.task, cfg.num_envs, device=self.device, seed=cfg.seed, **overrides)
        self.renderer = None
        if self.plan.renders:
            self.renderer = TaskRenderer(self.task, height=cfg.image_size, width=cfg.image_size,
                                         **self._render_options())
        if self.plan.actor_input == "state":
            self.actor = StateActor(self.task.num_obs, self.task.num_act, cfg.actor_hidden, init=cfg.actor_init)
        else:
            self.actor = VisualActor(3 * cfg.frames, cfg.image_size, cfg.image_size, self.task.num_act,
                                     cfg.trunk_dim, cfg.actor_hidden, init=cfg.actor_init)
        self.critic = Critic(self.task.num_obs, cfg.critic_hidden)
        self.actor.to(self.device)
        self.critic.to(self.device)
        self.target_critic = copy.deepcopy(self.critic)
        for p in self.target_critic.parameters():
            p.requires_grad_(False)
        # What the rollout calls every step (both differentiated through); compiled in place (compile_table).
        self._actor_mean, self._target_value = self.actor.mean, self.target_critic
        self.compiled: tuple[str, ...] | None = None  # the parts of COMPILE_PARTS compiled (compile)
        # Told a short text before an iteration spends seconds capturing CUDA graphs (a progress display).
        self.on_status: Callable[[str], None] | None = None
        # CUDA graphs (compile on a CUDA device) capture the critic fit too, so its Adam must be capturable
        # and read its learning rate from a tensor that the decay updates in place.
        self.graphs = cfg.compile and self.device.type == "cuda"
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=cfg.actor_lr, betas=cfg.betas)
        critic_lr = torch.tensor(cfg.critic_lr, device=self.device) if self.graphs else cfg.critic_lr
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=critic_lr, betas=cfg.betas,
                                           capturable=self.graphs)
        self.obs_rms = RunningMeanStd(self.task.num_obs, device=self.device)

        self.frames = FrameStack(cfg.frames)
        # A blind actor's input: one fixed tensor (a captured window reads it at a fixed address).
        self.blank_images = self._blank_images(cfg.num_envs) if self.plan.actor_input == "blank" else None
        self.gate = ImageGate()
        self.flags = FiniteFlags(cfg.horizon, _FLAG_NAMES, self.device)
        self.timer = RegionTimer(self.device)

        self.iteration = 0
        self.wall_s = 0.0
        self.episode_return = torch.zeros(cfg.num_envs, device=self.device)
        self.episode_length = torch.zeros(cfg.num_envs, device=self.device, dtype=torch.long)
        self.recent_returns: deque[float] = deque(maxlen=100)
        self.recent_lengths: deque[int] = deque(maxlen=100)
        self._started = False
        self.start_s: float | None = None  # seconds of the first reset and render (the first render compiles)
        self.live = LiveState()
        self.critic_fit = (GraphedCriticPhase(self._fit_critic, self.critic, self.device) if self.graphs
                           else self._fit_critic)
        self.window = WindowGraphs(forward=self._window_forward, backward=self._backward, commit=self._commit_state,
                                   params=list(self.actor.parameters()), timer=self.timer, device=self.device,
                                   capture=self.graphs,
                                   critic=self.critic_fit if self.graphs and cfg.overlap_critic else None)

    def _render_options(self) -> dict:
        cfg = self.cfg
        # save_blend_state: a full-mode window keeps 7 numbers per pixel per frame (flat in faces) so that each
        # render backward skips a second forward pass (fused backend)
        options = dict(detail=cfg.render_detail, extra_meshes=cfg.extra_meshes, extra_mesh_verts=cfg.extra_mesh_verts,
                       sigma=cfg.sigma, gamma=cfg.render_gamma, raster_model=cfg.raster_model,
                       renderer=cfg.renderer, save_blend_state=True)
        if cfg.raster_model == "alpha":
            options["cull_backfaces"] = False  # alpha coverage sums over all faces, hidden ones included
        return options

    def _blank_images(self, n: int) -> torch.Tensor:
        """A blind actor's input for ``n`` environments: an all-black stack, zeros (n, 3 * frames, H, W)."""
        cfg = self.cfg
        return torch.zeros(n, 3 * cfg.frames, cfg.image_size, cfg.image_size, device=self.device)

    # ------------------------------------------------------------------ compiling
    def compile_table(self) -> dict[str, tuple]:
        """What ``--compile`` compiles, by part (:data:`COMPILE_PARTS`), each entry something with a ``compile()``:
        the task's physics parts (``Task.compile_table``: the callable, where the step calls it, torch.compile's
        options); the renderer (``TaskRenderer.compile``: forward kinematics, vertices, camera and the fused
        rasterizer's per-face setup, hundreds of small kernels per frame eagerly, in forward and again in
        backward; nothing where the trainer does not render); and the actor's mean and the target critic, which
        the rollout calls every step: compiled, their small layers (bias, ReLU, LayerNorm, ELU and their backward)
        fuse, while the convolutions and GEMMs stay cuDNN/cuBLAS calls and the action noise stays eager (same
        draws)."""
        physics = self.task.compile_table()
        return {**{part: (physics[part],) for part in tasks.PHYSICS_PARTS},
                "renderer": () if self.renderer is None else (self.renderer,),
                "networks": (tasks.CompiledCall(self, "_actor_mean", self.actor.mean),
                             tasks.CompiledCall(self, "_target_value", self.target_critic))}

    def compile(self, parts: Collection[str] = COMPILE_PARTS) -> None:
        """Compile ``parts`` (of :data:`COMPILE_PARTS`) where the trainer calls them, each at its first call; the
        other parts run eagerly. Once per trainer, before its first iteration."""
        if isinstance(parts, str) or not set(parts) <= set(COMPILE_PARTS):
            raise ValueError(f"compile parts are some of {COMPILE_PARTS}, got {parts!r}")
        if self.compiled is not None:
            raise RuntimeError(f"this trainer compiled {self.compiled} already")
        import torch._functorch.config as functorch_config

        # Probe iterations differentiate one graph twice (retain_graph=True), which AOTAutograd's donated buffers
        # forbid in compiled backward functions.
        functorch_config.donated_buffer = False
        table = self.compile_table()
        for part in parts:
            for entry in table[part]:
                entry.compile()
        self.compiled = tuple(parts)

    # ------------------------------------------------------------------ state the windows hand on
    def _render(self, *, grad: bool) -> torch.Tensor:
        """Images of the task's current state: (B, 3, H, W) in [0, 1]; differentiable in qpos if ``grad``
        (always the rasterizer: the ray tracer of ``--renderer warp`` has no gradient)."""
        if grad:
            return self.renderer.soft(self.task.qpos)
        with torch.no_grad():
            return self.renderer(self.task.qpos)

    def _start(self) -> None:
        """First reset: state, frame stack tiled with the first image, running stats seeded."""
        obs = self.task.reset()
        self.obs_rms.update(obs)
        if self.plan.renders:
            if self.graphs:
                # A captured render cannot measure or grow its bins (no host sync): fix a generous capacity
                # now, before the warm-up iterations compile the kernels for it.
                self.renderer.freeze_capacity(self.task.qpos, headroom=2.0)
            self.frames.reset(self._render(grad=False))
        self._started = True
        self._commit_state()

    def _commit_state(self) -> None:
        """The window's end state into the fixed tensors the next window starts from (``LiveState``)."""
        self.live.commit(self.task, self.frames if self.plan.renders else None)

    # ------------------------------------------------------------------ rollout window and actor loss
    def _window_forward(self, probe: bool) -> tuple[torch.Tensor, dict]:
        # A probe renders with grad whatever the mode: both gradients need the render graph.
        return self._rollout(render_grad=self.plan.grad_through_images or probe)

    def _ends_without_value(self, info: dict) -> torch.Tensor:
        """(B,) bool: the step ended the episode with a zero terminal value. An early termination does; with
        ``bootstrap_last_step`` a failure on the episode's last step does not (the reference bootstraps every
        episode that reached its length), but a non-finite or runaway state always does."""
        if self.cfg.bootstrap_last_step:
            return info["invalid"] | (info["terminated"] & ~info["time_limit"])
        return info["terminated"]

    def _rollout(self, *, render_grad: bool) -> tuple[torch.Tensor, dict]:
        """One SHAC window. Returns the actor loss (0-d, differentiable) and the window's (T, B) buffers."""
        cfg, task = self.cfg, self.task
        T, B = cfg.horizon, cfg.num_envs
        stats = self.obs_rms.snapshot()
        # SHAC's truncation. Compiled, the cut state requires grad (a leaf): the window's first step then shares
        # the later steps' compiled graphs instead of compiling its own (Task.detach).
        task.detach(requires_grad=cfg.compile)
        self.frames.detach()
        obs = task.state_obs().detach()

        critic_obs = torch.empty(T, B, task.num_obs, device=self.device)
        raw_obs = torch.empty(T, B, task.num_obs, device=self.device)
        rewards = torch.empty(T, B, device=self.device)
        next_values = torch.empty(T, B, device=self.device)
        dones = torch.empty(T, B, device=self.device, dtype=torch.bool)
        episode_ends = torch.empty(T, B, device=self.device, dtype=torch.bool)
        ep_returns = torch.empty(T, B, device=self.device)
        ep_lengths = torch.empty(T, B, device=self.device, dtype=torch.long)

        rew_acc = torch.zeros(B, device=self.device)
        discount = torch.ones(B, device=self.device)
        loss = torch.zeros((), device=self.device)
        self.flags.reset()
        for t in range(T):
            with torch.no_grad():
                critic_obs[t] = RunningMeanStd.apply(obs, stats, cfg.obs_clip)
            if self.plan.actor_input == "images":
                actor_in = self.frames.stacked()
                if render_grad:
                    actor_in = self.gate(actor_in)
                    self.flags.watch_grad(t, "image", actor_in)
            elif self.plan.actor_input == "blank":
                actor_in = self.blank_images
            else:
                actor_in = RunningMeanStd.apply(obs, stats, cfg.obs_clip)
            action = self.actor.sample(self._actor_mean(actor_in))
            self.flags.watch_grad(t, "action", action)

            obs, reward, done, info = task.step(action)
            self.flags.watch_grad(t, "qpos", task.qpos)
            self.flags.watch_grad(t, "qvel", task.qvel)
            self.flags.check(t, "state_obs", info["obs_before_reset"])
            self.flags.check(t, "reward", reward)

            # Value of the state reached by this step (before any reset); zero after an early termination.
            v_next = self._target_value(RunningMeanStd.apply(info["obs_before_reset"], stats, cfg.obs_clip))
            v_next = torch.where(self._ends_without_value(info), torch.zeros_like(v_next), v_next)
            self.flags.check(t, "terminal_value", v_next)

            rew_acc = rew_acc + discount * reward
            ends = done if t < T - 1 else torch.ones_like(done)
            loss = loss - torch.where(ends, rew_acc + cfg.gamma * discount * v_next, torch.zeros_like(v_next)).sum()
            discount = torch.where(done, torch.ones_like(discount), discount * cfg.gamma)
            rew_acc = torch.where(done, torch.zeros_like(rew_acc), rew_acc)

            if self.plan.renders:
                self.frames.push(self._render(grad=render_grad), reset=done)

            with torch.no_grad():
                raw_obs[t] = obs
                rewards[t] = reward
                next_values[t] = v_next
                dones[t] = ends
                episode_ends[t] = done
                self.episode_return += reward
                self.episode_length += 1
                ep_returns[t] = self.episode_return
                ep_lengths[t] = self.episode_length
                self.episode_return.masked_fill_(done, 0.0)
                self.episode_length.masked_fill_(done, 0)
        loss = loss / (T * B)
        buffers = dict(critic_obs=critic_obs, raw_obs=raw_obs, rewards=rewards, next_values=next_values,
                       dones=dones, episode_ends=episode_ends, ep_returns=ep_returns, ep_lengths=ep_lengths)
        return loss, buffers

    # ------------------------------------------------------------------ backward
    def _backward(self, loss: torch.Tensor, probe: bool) -> dict:
        """Actor gradients into ``.grad`` for the training mode; on probes, both estimators of one rollout.

        Returns the probe's metrics as 0-d tensors (empty on plain iterations; keys in ``SHACConfig.cosine_every``):
        computed here, they are part of a captured backward graph and rewritten by every replay.
        """
        params = list(self.actor.parameters())
        zero_grads_(params)
        train_open = self.plan.grad_through_images
        if not probe:
            self.gate.open = train_open
            loss.backward()
            return {}
        # The estimator we do NOT train with goes first (graph retained); the training mode's gradient is
        # computed last, so it is what stays in .grad.
        self.gate.open = not train_open
        loss.backward(retain_graph=True)
        g_other = flat_grad(params)
        zero_grads_(params)
        self.gate.open = train_open
        loss.backward()
        g_train = flat_grad(params)
        g_full, g_dec = (g_train, g_other) if train_open else (g_other, g_train)
        # The image path's contribution alone (the control-regularisation term of D.Va's eq. 5), in total and
        # by the part of the actor it reaches.
        render_term = g_full - g_dec
        by_group = group_norms(render_term, params, self.actor.param_groups())
        # The policy's own sensitivity to each frame, on the stack the window ended in (the parameters are
        # still those of the rollout).
        sensitivity = image_sensitivity(self.actor.mean, self.frames.stacked(), frames=self.cfg.frames)
        return {
            "grad_norm_full": g_full.norm(),
            "grad_norm_decoupled": g_dec.norm(),
            "cos_full_decoupled": cosine(g_full, g_dec),
            "grad_norm_render_term": render_term.norm(),
            **{f"grad_norm_render_term_{name}": norm for name, norm in by_group.items()},
            **{f"image_sensitivity_f{i}": s for i, s in enumerate(sensitivity.unbind(0))},
        }

    # ------------------------------------------------------------------ critic fit
    def _fit_critic(self, buf: dict) -> torch.Tensor:
        """TD(lambda) targets of the window and the critic fit on them; returns the critic loss. It reads only
        the window's buffers and writes only the critic and its optimiser, so it may run alongside the actor's
        backward (``SHACConfig.overlap_critic``); the target critic's update waits for both. Overlapped, a window
        whose actor step then aborts (non-finite or runaway gradient) has fitted the critic already; the run
        stops there either way and keeps no checkpoint of it."""
        cfg = self.cfg
        targets = td_lambda_targets(buf["rewards"], buf["next_values"], buf["dones"], gamma=cfg.gamma, lam=cfg.lam)
        return fit_critic(self.critic, self.critic_opt, buf["critic_obs"].flatten(0, 1), targets.flatten(),
                          iterations=cfg.critic_iterations, batches=cfg.critic_batches, grad_clip=cfg.grad_clip)

    # ------------------------------------------------------------------ one training iteration
    def _lr(self, base: float) -> float:
        """Linear decay from ``base`` to 1e-5 over ``lr_decay_iters`` (the reference's schedule over its
        ``max_epochs``), held at 1e-5 after."""
        frac = min(self.iteration / self.cfg.lr_decay_iters, 1.0)
        return base + (1e-5 - base) * frac

    def _set_learning_rates(self) -> None:
        for group in self.actor_opt.param_groups:
            group["lr"] = self._lr(self.cfg.actor_lr)
        for group in self.critic_opt.param_groups:
            if isinstance(group["lr"], torch.Tensor):
                group["lr"].fill_(self._lr(self.cfg.critic_lr))  # in place: the captured Adam reads it
            else:
                group["lr"] = self._lr(self.cfg.critic_lr)

    def _announce_capture(self, probe: bool) -> None:
        """Say so when this iteration's window will be captured as CUDA graphs (a first capture takes seconds).

        Each kind of window (plain, probe) has run eagerly by the time ``WARMUP_ITERS`` have passed: the first
        iteration is a probe and the second a plain one whenever both kinds occur."""
        if not self.graphs or self.iteration < WARMUP_ITERS or probe in self.window.captured:
            return
        probing = self.plan.probes and self.cfg.cosine_every > 0
        kinds = 2 if probing and self.cfg.cosine_every > 1 else 1
        self._status(f"capturing CUDA graphs (window {len(self.window.captured) + 1}/{kinds})")

    def _status(self, text: str) -> None:
        if self.on_status is not None:
            self.on_status(text)

    def train_iteration(self) -> dict:
        """Run one iteration; returns its metrics (Python scalars)."""
        cfg = self.cfg
        if cfg.compile and self.compiled is None:
            self.compile()
        if not self._started:
            t_start = time.perf_counter()
            self._start()
            self.start_s = time.perf_counter() - t_start
        t_wall = time.perf_counter()
        probe = self.plan.probes and cfg.cosine_every > 0 and self.iteration % cfg.cosine_every == 0
        self.timer.reset()
        self._set_learning_rates()

        # Actor: rollout window, loss and backward, timed ("fwd", "bwd") and memory-probed as one region; with
        # overlap_critic a replayed window also fits the critic ("critic") alongside its backward.
        self._announce_capture(probe)
        if self.graphs and self.critic_fit.graph is None:
            self._status("capturing CUDA graph (critic fit)")
        window = self.window.run(iteration=self.iteration, probe=probe)
        loss, buf = window.loss, window.buffers
        params = list(self.actor.parameters())
        gn = nn.utils.clip_grad_norm_(params, cfg.grad_clip)
        gn_clipped = flat_grad(params).norm()
        self.flags.raise_if_bad(self.iteration, {"actor loss": loss.detach(), "actor gradient norm": gn})
        gn_value = float(gn)
        if gn_value > cfg.abort_grad_norm:
            raise NonFiniteError(
                f"iteration {self.iteration}: actor gradient norm {gn_value:.3g} exceeds abort_grad_norm "
                f"{cfg.abort_grad_norm:.3g} (the reference stops here too)")
        self.actor_opt.step()

        # Critic on TD(lambda) targets of the window (unless it ran alongside the backward), then the target
        # network (after the backward, which differentiated through it).
        if window.overlapped:
            critic_loss = window.critic_loss
        else:
            with self.timer("critic"):
                critic_loss = self.critic_fit(buf)
        polyak_update(self.target_critic, self.critic, cfg.target_alpha)
        self.obs_rms.update(buf["raw_obs"])

        # Episode statistics: one host transfer per iteration.
        ends = buf["episode_ends"].cpu().numpy()
        if ends.any():
            self.recent_returns.extend(buf["ep_returns"].cpu().numpy()[ends].tolist())
            self.recent_lengths.extend(buf["ep_lengths"].cpu().numpy()[ends].tolist())

        self.iteration += 1
        iter_wall = time.perf_counter() - t_wall
        self.wall_s += iter_wall
        ms = self.timer.ms
        metrics = {
            "iter": self.iteration,
            "env_steps": self.iteration * cfg.horizon * cfg.num_envs,
            "wall_s": self.wall_s,
            "return_mean": float(np.mean(self.recent_returns)) if self.recent_returns else None,
            "episode_length_mean": float(np.mean(self.recent_lengths)) if self.recent_lengths else None,
            "episodes": len(self.recent_returns),
            "actor_loss": float(loss.detach()),
            "critic_loss": float(critic_loss),
            "grad_norm": gn_value,
            "grad_norm_clipped": float(gn_clipped),
            "fwd_ms": ms["fwd"],
            "bwd_ms": ms["bwd"],
            "critic_ms": ms["critic"],
            "critic_overlapped": window.overlapped,
            "iter_ms": iter_wall * 1e3,
            "peak_alloc_mb": window.memory.peak_alloc_mb,
            "peak_reserved_mb": window.memory.peak_reserved_mb,
            "saved_mb": window.saved_bytes / 2**20,
            "actor_lr": self.actor_opt.param_groups[0]["lr"],
            "probed": probe,
            "graph": window.replayed,
        }
        metrics.update({k: float(v) for k, v in window.probe_metrics.items()})
        return metrics

    # ------------------------------------------------------------------ evaluation and video
    @torch.no_grad()
    def evaluate(self, *, steps: int | None = None, num_envs: int = 4, video_size: int = 256,
                 record: bool = False) -> tuple[float, list[np.ndarray]]:
        """Deterministic policy on a separate task instance (the training state and RNG are untouched).

        Returns the mean undiscounted return over ``num_envs`` episodes of up to ``steps`` steps, and, if
        ``record``, RGB uint8 frames (H, W, 3) of env 0 from the task camera at ``video_size`` pixels.
        """
        cfg = self.cfg
        steps = steps or self.task.episode_length
        overrides = {} if cfg.episode_length is None else {"episode_length": cfg.episode_length}
        task = tasks.make(cfg.task, num_envs, device=self.device, seed=cfg.seed + 10_007, **overrides)
        if cfg.compile:
            task.compile()  # an eager episode is episode_length x substeps unfused substeps
        obs = task.reset()
        stats = self.obs_rms.snapshot()
        renderer = video = None
        frames = FrameStack(cfg.frames)
        blank = self._blank_images(num_envs) if self.plan.actor_input == "blank" else None
        if self.plan.renders:
            renderer = TaskRenderer(task, height=cfg.image_size, width=cfg.image_size, **self._render_options())
            frames.reset(renderer(task.qpos))
        if record:
            video = TaskRenderer(task, height=video_size, width=video_size, detail=max(cfg.render_detail, 2),
                                 sigma=None, gamma=None, renderer=cfg.renderer)
        total = torch.zeros(num_envs, device=self.device)
        alive = torch.ones(num_envs, device=self.device, dtype=torch.bool)
        out_frames: list[np.ndarray] = []
        for _ in range(steps):
            if record:
                img = video(task.qpos[:1])[0].clamp(0, 1).mul(255).byte().permute(1, 2, 0).cpu().numpy()
                out_frames.append(img)
            if self.plan.actor_input == "images":
                actor_in = frames.stacked()
            elif self.plan.actor_input == "blank":
                actor_in = blank
            else:
                actor_in = RunningMeanStd.apply(obs, stats, cfg.obs_clip)
            action = self.actor(actor_in, deterministic=True)
            obs, reward, done, _ = task.step(action)
            total += reward * alive
            alive &= ~done
            if self.plan.renders:
                frames.push(renderer(task.qpos), reset=done)
            if not bool(alive.any()):
                break
        return float(total.mean()), out_frames

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """Everything that determines the future of the run (resume == uninterrupted on the CPU)."""
        return {
            "config": dataclasses.asdict(self.cfg),
            "iteration": self.iteration,
            "wall_s": self.wall_s,
            "started": self._started,
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "target_critic": self.target_critic.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "obs_rms": self.obs_rms.state_dict(),
            "task": self.task.get_state(),
            "frames": self.frames.state_dict(),
            "episode_return": self.episode_return.clone(),
            "episode_length": self.episode_length.clone(),
            "recent_returns": list(self.recent_returns),
            "recent_lengths": list(self.recent_lengths),
            "rng": rng_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.iteration = state["iteration"]
        self.wall_s = state["wall_s"]
        self._started = state["started"]
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.target_critic.load_state_dict(state["target_critic"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.obs_rms.load_state_dict(state["obs_rms"])
        self.task.set_state(state["task"])
        self.frames.load_state_dict(state["frames"], device=self.device)
        self.episode_return.copy_(state["episode_return"])  # in place: graphs read these tensors
        self.episode_length.copy_(state["episode_length"])
        self.recent_returns = deque(state["recent_returns"], maxlen=100)
        self.recent_lengths = deque(state["recent_lengths"], maxlen=100)
        set_rng_state(state["rng"])
        if self._started:
            self._commit_state()
