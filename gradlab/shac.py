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
   differentiated over the same graph with the gate open and closed: the full and the decoupled gradient of the
   SAME rollout (and, for full runs, the full gradient through the other raster model's image of the same
   states); the training mode's gradient is the one applied. The probe also splits the render term by the
   actor's parameter groups and measures the policy's sensitivity to each frame of its stack.
4. Clip, Adam step with a linear LR decay.
5. Critic fit on TD(lambda) targets of the window; Polyak-update the target critic. The fit is independent of
   the actor's gradient, so with CUDA graphs it runs alongside the backward of step 3 (``overlap_critic``).

The trainer always trains **members** (docs/design.md, "Populations"): ``SHAC([cfg, ...])`` several runs in one
process as one batched simulation, ``SHAC([cfg])`` a run alone, a population of one; its answers are lists, one
entry per member. Member ``m`` owns environments ``m * B .. (m + 1) * B`` of one task, and its own actor, critic,
target critic, optimisers, observation statistics, action noise, learning-rate schedule, gradient clipping and
abort guard (``gradlab.members``); the members' networks run as batched kernels (``MemberStack``), their losses
are summed (no member's loss reaches another member's parameters) and each member's metrics are its own. A
population of one computes what a run alone computes, bit for bit, through four arithmetic choices made where
they live: torch's default generator for its noise (``members.build_member``), its own modules in
``MemberStack``, and a critic group of one whose Adam steps alone (``gradlab.critic``). Evaluation
(``gradlab.evaluation``) and the critics' fit in groups live beside.

With ``--compile`` the parts in :meth:`SHAC.compile_table` run through ``torch.compile``, and on a CUDA device the
window (steps 1-3) and the critic fit are CUDA graphs replayed every iteration; ``gradlab.graphs`` holds that
machinery, and this module calls it the same way either way.

Every iteration reports CUDA-synchronised forward / backward / critic times, peak allocated and reserved memory
(CUDA), bytes saved for backward, pre- and post-clip gradient norms; a NaN/inf anywhere stops the run (a
population: the member) with the iteration, the horizon step and the tensor named.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection, Sequence
from typing import ClassVar

import numpy as np
import torch
from torch import nn

import diffrender
import tasks
from gradlab import members
from gradlab.config import ModePlan, SHACConfig
from gradlab.critic import critic_groups, fit_member_critics, polyak_update
from gradlab.evaluation import EVAL_SEED, EvaluationState, Evaluator
from gradlab.graphs import WARMUP_ITERS, GraphedCriticPhase, LiveState, WindowGraphs, zero_grads_
from gradlab.members import MEMBER_FIELDS, Member, check_population, window_bytes
from gradlab.networks import MemberStack
from gradlab.normalizer import RunningMeanStd
from gradlab.probes import FiniteFlags, ImageGate, NonFiniteError, cosine, flat_grad, group_norms, image_sensitivity
from gradlab.roster import Roster
from gradlab.seeding import resolve_device, seed_everything, set_rng_state
from gradlab.timing import RegionTimer
from tasks.vision import FrameStack

__all__ = ["COMPILE_PARTS", "EVAL_SEED", "MEMBER_FIELDS", "SHAC", "Member", "NonFiniteError", "Roster",
           "check_population", "window_bytes"]

#: What ``--compile`` compiles (:meth:`SHAC.compile_table`), in parts that are each their own graphs and compile
#: work, so that separate processes can compile them at the same time into one cache: the physics' own parts
#: (tasks.PHYSICS_PARTS), the renderer's PyTorch work, and the actor with the critic.
COMPILE_PARTS = (*tasks.PHYSICS_PARTS, "renderer", "networks")

_FLAG_NAMES = ["state_obs", "reward", "terminal_value", "image", "action", "qpos", "qvel"]


class SHAC:
    """The SHAC / D.Va trainer of a population of runs (a run alone: a population of one).

    Args:
        roster: the members (a :class:`Roster`), or their configurations, one per member (None fields are
            resolved to the task's reference values; :func:`check_population` says which settings they share).
            :meth:`train_iteration`, :meth:`evaluate`, :meth:`state_dict` and :meth:`load_state_dict` take and
            give lists, one entry per member in the order of :attr:`members` (the roster's: members of one image
            model render together; ``member.cfg`` tells which is which).
        device: "auto" | "cpu" | "cuda[:N]".
        batching: how a population's networks run as one batch (``MemberStack``): ``"grouped"`` (batched kernels),
            ``"loop"`` (one convolution per member), ``"modules"`` (each member's own modules, a run alone's exact
            arithmetic).

    With ``cfg.compile`` the trainer compiles every part of :meth:`compile_table` at its first iteration, unless
    :meth:`compile` named the parts before (a process that compiles only some of them).
    """

    #: Where the trainer calls what it compiles, by the name a progress display gives the compilations made
    #: there: attribute paths from the trainer, each holding the callable that is called.
    COMPILE_SITES: ClassVar[dict[str, str]] = {
        "physics step": "task.step", "renderer": "_render", "actor": "_actor_mean", "critic": "_target_value",
        "backward pass": "window.backward"}

    def __init__(self, roster: Roster | Sequence[SHACConfig], *, device: str | torch.device = "auto",
                 batching: str = "grouped"):
        self.roster = roster = roster if isinstance(roster, Roster) else Roster.of(roster)
        cfgs = list(roster.cfgs)
        if roster.shared.mode == "distill":
            raise ValueError("--mode distill is trained by gradlab.Distill, not SHAC")
        self.n = n = len(cfgs)
        self.cfg = cfg = roster.shared  # the settings every member shares (outside MEMBER_FIELDS)
        self.device = device if isinstance(device, torch.device) else resolve_device(device)
        members.check_memory(cfgs, self.device)
        B = cfg.num_envs
        seed_everything(cfg.seed)

        self.task = members.make_task(cfg, [c.seed for c in cfgs], B, self.device)
        # one renderer per image model a member trains on or probes with (the population renders each in one call)
        plans = [ModePlan.of(c.mode) for c in cfgs]
        rasters = [c.raster_model for c, p in zip(cfgs, plans) if p.renders]
        rasters += [members.alt_raster(c.raster_model) for c, p in zip(cfgs, plans) if p.grad_through_images]
        self.renderers = members.make_renderers(self.task, cfg, rasters)

        self.graphs = cfg.compile and self.device.type == "cuda"
        # several members draw their noise from generators of their own; one draws from torch's, as a run alone
        self.members = [members.build_member(i, c, self.task, self.device, own_generator=n > 1,
                                             capturable=self.graphs) for i, c in enumerate(cfgs)]
        self.actors = MemberStack([m.actor for m in self.members], batching=batching)
        self.target_critics = MemberStack([m.target_critic for m in self.members], batching=batching)
        # What the rollout calls every step (both differentiated through); compiled in place (compile_table).
        self._actor_mean, self._target_value = self.actors.mean, self.target_critics.value
        self.compiled: tuple[str, ...] | None = None  # the parts of COMPILE_PARTS compiled (compile)
        # Told a short text before an iteration spends seconds capturing CUDA graphs (a progress display).
        self.on_status: Callable[[str], None] | None = None
        self.alive = torch.ones(n, dtype=torch.bool, device=self.device)  # members still training (graphs read it)

        self.input_kind = members.input_kind(self.members)  # what the actors see: "images", "state" or "blank"
        self.sees = self.input_kind == "images"  # some member's actor sees rendered images
        self.frames = FrameStack(cfg.frames)
        # A blind actor's input: one fixed tensor (a captured window reads it at a fixed address).
        self.blank_images = members.blank_images(cfg, n * B, self.device) if self.input_kind == "blank" else None
        self.gate = ImageGate(members=n, rows=B, device=self.device)
        self._routes = members.probe_routes(self.members)
        for route in self._routes.values():  # each route's masks now, outside any CUDA graph capture
            self.gate.set_route(route)
        self.flags = FiniteFlags(cfg.horizon, _FLAG_NAMES, self.device, members=n)
        self.timer = RegionTimer(self.device)

        self.iteration = 0
        self.wall_s = 0.0
        self.episode_return = torch.zeros(n * B, device=self.device)
        self.episode_length = torch.zeros(n * B, device=self.device, dtype=torch.long)
        self._started = False
        self.start_s: float | None = None  # seconds of the first reset and render (the first render compiles)
        self.evaluator = Evaluator(self.members, self.actors, cfg, self.device)  # its task made at first use
        self.live = LiveState()
        self._critic_groups = critic_groups(self.members, batching, self.device)
        self.critic_fit = (GraphedCriticPhase(self._fit_critic, nn.ModuleList([m.critic for m in self.members]),
                                              self.device) if self.graphs else self._fit_critic)
        self.window = WindowGraphs(forward=self._window_forward, backward=self._backward, commit=self._commit_state,
                                   params=[p for m in self.members for p in m.params], timer=self.timer,
                                   device=self.device, capture=self.graphs,
                                   critic=self.critic_fit if self.graphs and cfg.overlap_critic else None,
                                   generators=[m.generator for m in self.members if m.generator is not None])

    # ------------------------------------------------------------------ compiling
    def compile_table(self) -> dict[str, tuple]:
        """What ``--compile`` compiles, by part (:data:`COMPILE_PARTS`), each entry something with a ``compile()``:
        the task's physics parts (``Task.compile_table``: the callable, where the step calls it, torch.compile's
        options); the renderers (``TaskRenderer.compile``: forward kinematics, vertices, camera and the fused
        rasterizer's per-face setup, hundreds of small kernels per frame eagerly, in forward and again in
        backward; nothing where the trainer does not render); and the actors' mean and the target critics, which
        the rollout calls every step: compiled, their small layers (bias, ReLU, LayerNorm, ELU and their backward)
        fuse, while the convolutions and GEMMs stay cuDNN/cuBLAS calls and the action noise stays eager (same
        draws)."""
        physics = self.task.compile_table()
        return {**{part: (physics[part],) for part in tasks.PHYSICS_PARTS},
                "renderer": tuple(self.renderers.values()),
                "networks": (tasks.CompiledCall(self, "_actor_mean", self.actors.mean),
                             tasks.CompiledCall(self, "_target_value", self.target_critics.value))}

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
    def _render(self, grad: Sequence[bool], *, alt: bool = False) -> torch.Tensor:
        """Images of every member's environments, (N * B, 3, H, W) (``gradlab.members.images``): member m's
        differentiable where ``grad[m]``; ``alt``: the other raster model of a full member's probe."""
        return members.images(self.members, self.renderers, self.task.qpos, self.cfg.num_envs,
                              self.cfg.image_size, grad=grad, alt=alt)

    def _start(self) -> None:
        """First reset: state, frame stack tiled with the first image, running stats seeded."""
        obs = self.task.reset()
        for m in self.members:
            m.obs_rms.update(obs[m.rows])
        if self.sees:
            if self.graphs:
                # A captured render cannot measure or grow its bins (no host sync): fix a generous capacity
                # now, before the warm-up iterations compile the kernels for it.
                for renderer in self.renderers.values():
                    renderer.freeze_capacity(self.task.qpos, headroom=2.0)
            self.frames.reset(self._render([False] * self.n))
        self._started = True
        self._commit_state()

    def _commit_state(self) -> None:
        """The window's end state into the fixed tensors the next window starts from (``LiveState``)."""
        self.live.commit(self.task, self.frames if self.sees else None)

    # ------------------------------------------------------------------ rollout window and actor loss
    def _window_forward(self, probe: bool) -> tuple[torch.Tensor, dict]:
        # A probe renders with grad whatever the mode: both gradients need the render graph.
        return self._rollout(render_grad=[m.plan.grad_through_images or probe for m in self.members],
                             alt=probe and "alt" in self._routes)

    def _ends_without_value(self, info: dict) -> torch.Tensor:
        """(B,) bool: the step ended the episode with a zero terminal value. An early termination does; with
        ``bootstrap_last_step`` a failure on the episode's last step does not (the reference bootstraps every
        episode that reached its length), but a non-finite or runaway state always does."""
        if self.cfg.bootstrap_last_step:
            return info["invalid"] | (info["terminated"] & ~info["time_limit"])
        return info["terminated"]

    def _rollout(self, *, render_grad: Sequence[bool], alt: bool = False) -> tuple[torch.Tensor, dict]:
        """One SHAC window. Returns the actor loss, (N,) one per member (differentiable), and the window's
        (T, N * B) buffers."""
        cfg, task = self.cfg, self.task
        T, B = cfg.horizon, self.n * cfg.num_envs
        stats = members.stacked_stats(self.members, cfg.num_envs)  # every step of a window normalises with these
        # SHAC's truncation. Compiled, the cut state requires grad (a leaf): the window's first step then shares
        # the later steps' compiled graphs instead of compiling its own (Task.detach).
        task.detach(requires_grad=cfg.compile)
        self.frames.detach()
        alt_frames = None
        if alt:  # a full member's probe: the same states through the other raster model, behind the same gate
            alt_frames = FrameStack(cfg.frames)
            alt_frames.frames = list(self.frames.frames)
        obs = task.state_obs().detach()
        actor_params = self.actors.stack()
        with torch.no_grad():
            target_params = self.target_critics.stack()
        gated = self.sees and any(render_grad)

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
        loss = torch.zeros(self.n, device=self.device)
        self.flags.reset()
        for t in range(T):
            with torch.no_grad():
                critic_obs[t] = RunningMeanStd.apply(obs, stats, cfg.obs_clip)
            actor_in = members.actor_input(self.input_kind, frames=self.frames, obs=obs, stats=stats,
                                           blank=self.blank_images, clip=cfg.obs_clip)
            if gated:
                actor_in = self.gate(actor_in, None if alt_frames is None else alt_frames.stacked())
                self.flags.watch_grad(t, "image", actor_in)
            action = members.sample(self.members, self._actor_mean(actor_params, actor_in), cfg.num_envs)
            self.flags.watch_grad(t, "action", action)

            obs, reward, done, info = task.step(action)
            self.flags.watch_grad(t, "qpos", task.qpos)
            self.flags.watch_grad(t, "qvel", task.qvel)
            self.flags.check(t, "state_obs", info["obs_before_reset"])
            self.flags.check(t, "reward", reward)

            # Value of the state reached by this step (before any reset); zero after an early termination.
            v_next = self._target_value(target_params,
                                        RunningMeanStd.apply(info["obs_before_reset"], stats, cfg.obs_clip))
            v_next = torch.where(self._ends_without_value(info), torch.zeros_like(v_next), v_next)
            self.flags.check(t, "terminal_value", v_next)

            rew_acc = rew_acc + discount * reward
            ends = done if t < T - 1 else torch.ones_like(done)
            loss = loss - members.member_sums(
                torch.where(ends, rew_acc + cfg.gamma * discount * v_next, torch.zeros_like(v_next)), self.n)
            discount = torch.where(done, torch.ones_like(discount), discount * cfg.gamma)
            rew_acc = torch.where(done, torch.zeros_like(rew_acc), rew_acc)

            if self.sees:
                self.frames.push(self._render(render_grad), reset=done)
                if alt_frames is not None:
                    alt_frames.push(self._render(render_grad, alt=True), reset=done)

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
        loss = loss / (T * cfg.num_envs)
        buffers = dict(critic_obs=critic_obs, raw_obs=raw_obs, rewards=rewards, next_values=next_values,
                       dones=dones, episode_ends=episode_ends, ep_returns=ep_returns, ep_lengths=ep_lengths)
        return loss, buffers

    # ------------------------------------------------------------------ backward
    def _backward(self, loss: torch.Tensor, probe: bool) -> dict:
        """Actor gradients into ``.grad`` for the training mode; on probes, both estimators of one rollout.

        Returns the probe's metrics as 0-d tensors keyed ``(member index, key)`` (empty on plain iterations; keys
        in ``SHACConfig.cosine_every``): computed here, they are part of a captured backward graph and rewritten
        by every replay.
        """
        params = self.window.params
        zero_grads_(params)
        # a stopped member's loss takes no part (its gradient, possibly non-finite, is never read)
        total = torch.where(self.alive, loss, torch.zeros_like(loss)).sum()
        if not probe:
            self.gate.set_route(self._routes["train"])
            total.backward()
            return {}
        # The estimators we do NOT train with go first (graph retained); the training mode's gradient is
        # computed last, so it is what stays in .grad.
        grads: dict[str, list[torch.Tensor]] = {}
        for name in ("other", "alt", "train"):
            if name not in self._routes:
                continue
            self.gate.set_route(self._routes[name])
            total.backward(retain_graph=name != "train")
            grads[name] = [flat_grad(m.params) for m in self.members]
            if name != "train":
                zero_grads_(params)
        metrics = {}
        for m in self.members:
            if not m.plan.probes:
                continue
            g_train, g_other = grads["train"][m.index], grads["other"][m.index]
            full = m.plan.grad_through_images
            g_full, g_dec = (g_train, g_other) if full else (g_other, g_train)
            out = self._probe_metrics(m, g_full, g_dec)
            if full:
                # the same rollout's full gradient through the other image model: hard against soft
                g_alt = grads["alt"][m.index]
                hard, soft = (g_full, g_alt) if m.cfg.raster_model == "hard" else (g_alt, g_full)
                out.update(grad_norm_full_hard=hard.norm(), grad_norm_full_soft=soft.norm(),
                           cos_hard_soft=cosine(hard, soft), cos_hard_decoupled=cosine(hard, g_dec),
                           cos_soft_decoupled=cosine(soft, g_dec))
            metrics.update({(m.index, k): v for k, v in out.items()})
        return metrics

    def _probe_metrics(self, member: Member, g_full: torch.Tensor, g_dec: torch.Tensor) -> dict:
        # The image path's contribution alone (the control-regularisation term of D.Va's eq. 5), in total and
        # by the part of the actor it reaches.
        render_term = g_full - g_dec
        by_group = group_norms(render_term, member.params, member.actor.param_groups())
        # The policy's own sensitivity to each frame, on the stack the window ended in (the parameters are
        # still those of the rollout).
        sensitivity = image_sensitivity(member.actor.mean, self.frames.stacked()[member.rows], frames=self.cfg.frames)
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
        """TD(lambda) targets of the window and each member's critic fit on its own rows; returns (N,) the
        members' critic losses. It reads only the window's buffers and writes only the critics and their
        optimisers, so it may run alongside the actor's backward (``SHACConfig.overlap_critic``); the target
        critics' update waits for both. Overlapped, a window whose actor step then aborts (non-finite or runaway
        gradient) has fitted the critic already; the run stops there either way and keeps no checkpoint of it.
        Members fit in the groups of ``gradlab.critic.critic_groups``: batched kernels fit those that share
        iterations and minibatches in one pass; a member alone in its group (a run alone) and ``"modules"`` batching fit
        member by member."""
        return fit_member_critics(self._critic_groups, buf, gamma=self.cfg.gamma, lam=self.cfg.lam)

    # ------------------------------------------------------------------ one training iteration
    def _lr(self, cfg: SHACConfig, base: float) -> float:
        """Linear decay from ``base`` to 1e-5 over ``lr_decay_iters`` (the reference's schedule over its
        ``max_epochs``), held at 1e-5 after."""
        frac = min(self.iteration / cfg.lr_decay_iters, 1.0)
        return base + (1e-5 - base) * frac

    def _set_learning_rates(self) -> None:
        for m in self.members:
            cfg = m.cfg
            actor_lr = self._lr(cfg, cfg.actor_lr)
            if cfg.lr_warmup_iters:
                actor_lr *= min(1.0, (self.iteration + 1) / cfg.lr_warmup_iters)
            for group in m.actor_opt.param_groups:
                group["lr"] = actor_lr * group.get("lr_scale", 1.0)
            for group in m.critic_opt.param_groups:
                if isinstance(group["lr"], torch.Tensor):
                    group["lr"].fill_(self._lr(cfg, cfg.critic_lr))  # in place: the captured Adam reads it
                else:
                    group["lr"] = self._lr(cfg, cfg.critic_lr)

    def _announce_capture(self, probe: bool) -> None:
        """Say so when this iteration's window will be captured as CUDA graphs (a first capture takes seconds).

        Each kind of window (plain, probe) has run eagerly by the time ``WARMUP_ITERS`` have passed: the first
        iteration is a probe and the second a plain one whenever both kinds occur."""
        if not self.graphs or self.iteration < WARMUP_ITERS or probe in self.window.captured:
            return
        probing = self._probing and self.cfg.cosine_every > 0
        kinds = 2 if probing and self.cfg.cosine_every > 1 else 1
        self._status(f"capturing CUDA graphs (window {len(self.window.captured) + 1}/{kinds})")

    @property
    def _probing(self) -> bool:
        return any(m.plan.probes for m in self.members)

    def _status(self, text: str) -> None:
        if self.on_status is not None:
            self.on_status(text)

    def train_iteration(self) -> list[dict | None]:
        """Run one iteration; returns its metrics (Python scalars), one dict per member (None for a member that
        has stopped; ``member.failed`` says why). Raises NonFiniteError once every member has stopped."""
        cfg = self.cfg
        if cfg.compile and self.compiled is None:
            self.compile()
        if not self._started:
            t_start = time.perf_counter()
            self._start()
            self.start_s = time.perf_counter() - t_start
        t_wall = time.perf_counter()
        probe = self._probing and cfg.cosine_every > 0 and self.iteration % cfg.cosine_every == 0
        self.timer.reset()
        self._set_learning_rates()

        # Actor: rollout window, loss and backward, timed ("fwd", "bwd") and memory-probed as one region; with
        # overlap_critic a replayed window also fits the critic ("critic") alongside its backward.
        self._announce_capture(probe)
        if self.graphs and self.critic_fit.graph is None:
            self._status("capturing CUDA graph (critic fit)")
        window = self.window.run(iteration=self.iteration, probe=probe)
        loss, buf = window.loss, window.buffers
        live = [m for m in self.members if m.failed is None]
        norms = {m.index: nn.utils.clip_grad_norm_(m.params, m.cfg.grad_clip) for m in live}
        clipped = {m.index: flat_grad(m.params).norm() for m in live}
        gn = torch.stack([norms.get(i, torch.zeros((), device=self.device)) for i in range(self.n)])
        # named as metrics.jsonl and ablate count iterations: from 1 (self.iteration counts those finished)
        failures = self.flags.failures(self.iteration + 1, {"actor loss": loss.detach(), "actor gradient norm": gn})
        for m in live:
            if m.index in failures:
                self._stop(m, failures[m.index])
        values = {i: float(v) for i, v in norms.items() if self.members[i].failed is None}
        for m in live:
            if m.failed is None and values[m.index] > m.cfg.abort_grad_norm:
                self._stop(m, f"iteration {self.iteration + 1}: actor gradient norm {values[m.index]:.3g} exceeds "
                              f"abort_grad_norm {m.cfg.abort_grad_norm:.3g} (the reference stops here too)")
        live = [m for m in live if m.failed is None]
        if not live:
            raise NonFiniteError(members.why_all_stopped(self.members))
        for m in live:
            m.actor_opt.step()

        # Critic on TD(lambda) targets of the window (unless it ran alongside the backward), then the target
        # network (after the backward, which differentiated through it).
        if window.overlapped:
            critic_loss = window.critic_loss
        else:
            with self.timer("critic"):
                critic_loss = self.critic_fit(buf)
        for m in live:
            polyak_update(m.target_critic, m.critic, m.cfg.target_alpha)
            m.obs_rms.update(buf["raw_obs"][:, m.rows])

        # Episode statistics: one host transfer per iteration.
        ends = buf["episode_ends"].cpu().numpy()
        if ends.any():
            ep_returns, ep_lengths = buf["ep_returns"].cpu().numpy(), buf["ep_lengths"].cpu().numpy()
            for m in live:
                mine = ends[:, m.rows]
                m.recent_returns.extend(ep_returns[:, m.rows][mine].tolist())
                m.recent_lengths.extend(ep_lengths[:, m.rows][mine].tolist())

        self.iteration += 1
        iter_wall = time.perf_counter() - t_wall
        self.wall_s += iter_wall
        ms = self.timer.ms
        shared = {
            "fwd_ms": ms["fwd"],
            "bwd_ms": ms["bwd"],
            "critic_ms": ms["critic"],
            "critic_overlapped": window.overlapped,
            "iter_ms": iter_wall * 1e3,
            "peak_alloc_mb": window.memory.peak_alloc_mb,
            "peak_reserved_mb": window.memory.peak_reserved_mb,
            "saved_mb": window.saved_bytes / 2**20,
        }
        if overflows := diffrender.bin_overflows():  # binned renders' overflowing tiles, read after the sync above
            shared["bin_overflows"] = overflows
        losses, critic_losses = loss.detach().cpu().unbind(0), critic_loss.detach().cpu().unbind(0)
        out: list[dict | None] = []
        for m in self.members:
            if m.failed is not None:
                out.append(None)
                continue
            metrics = {
                "iter": self.iteration,
                "env_steps": self.iteration * cfg.horizon * cfg.num_envs,
                "wall_s": self.wall_s,
                "return_mean": float(np.mean(m.recent_returns)) if m.recent_returns else None,
                "episode_length_mean": float(np.mean(m.recent_lengths)) if m.recent_lengths else None,
                "episodes": len(m.recent_returns),
                "actor_loss": float(losses[m.index]),
                "critic_loss": float(critic_losses[m.index]),
                "grad_norm": values[m.index],
                "grad_norm_clipped": float(clipped[m.index]),
                **shared,
                "actor_lr": m.actor_opt.param_groups[-1]["lr"],
                # the exploration noise: where it has collapsed, the policy's gradient has little to act on
                "action_std": float(m.actor.log_std.detach().exp().mean()),
                "probed": probe and m.plan.probes,
                "graph": window.replayed,
            }
            metrics.update({k: float(v) for (i, k), v in window.probe_metrics.items() if i == m.index})
            out.append(metrics)
        return out

    def _stop(self, member: Member, why: str) -> None:
        """A member stops training (the others go on): no more actor steps, no more target-critic updates or
        metrics, its loss out of the backward; its environments keep the batch's shape (CUDA graphs replay fixed
        shapes), and so does the critic fit, which goes on fitting its critic with the others' (one batched,
        possibly captured call): nothing it acts with or reports."""
        member.failed = why
        self.alive[member.index] = False

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, *, video_steps: int = 0, video_size: int = 256) -> list[dict | None]:
        """The deterministic policy (``tanh`` of its mean action) of every member, on a separate task of
        ``eval_envs`` environments per member started from the fixed seed :data:`EVAL_SEED` (the same initial
        states at every evaluation, for every run), each for one whole episode; the training state and random
        streams are untouched (``gradlab.evaluation``).

        Returns per member ``eval_return_mean``, ``eval_return_std`` (undiscounted
        return over the episodes), ``eval_length_mean`` (steps) and ``frames``: with ``video_steps``, RGB uint8
        frames (H, W, 3) of the member's first environment from the task camera at ``video_size`` pixels, for its
        first ``video_steps`` steps (else empty). None for a member that has stopped.
        """
        return self.evaluator(capture=self.graphs, video_steps=video_steps, video_size=video_size)

    @property
    def _evaluation(self) -> EvaluationState | None:
        """The evaluation's task and tensors, once an evaluation made them."""
        return self.evaluator.state

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> list[dict]:
        """Everything that determines the future of the runs (resume == uninterrupted on the CPU): one dict per
        member, each in a run alone's checkpoint format (``members.member_state``)."""
        return [members.member_state(m, iteration=self.iteration, wall_s=self.wall_s, started=self._started,
                                       task=self.task.get_state(), frames=self.frames.state_dict(),
                                       episode_return=self.episode_return, episode_length=self.episode_length)
                for m in self.members]

    def load_state_dict(self, states: Sequence[dict]) -> None:
        """Restore :meth:`state_dict`: one dict per member, in any order (``members.match_states``)."""
        ordered = members.match_states(self.members, states)
        iterations = {s["iteration"] for s in ordered}
        if len(iterations) != 1:
            raise ValueError(f"the members' checkpoints are of different iterations: {sorted(iterations)}")
        first = ordered[0]
        self.iteration, self.wall_s, self._started = first["iteration"], first["wall_s"], first["started"]
        for m, s in zip(self.members, ordered):
            members.restore_member(m, s)
            if s.get("failed"):
                self._stop(m, s["failed"])
        task, frames, episode_return, episode_length = members.joined_state(ordered)
        self.task.set_state(task)
        self.frames.load_state_dict(frames, device=self.device)
        # in place: graphs read these tensors
        self.episode_return.copy_(episode_return)
        self.episode_length.copy_(episode_length)
        set_rng_state(first["rng"])
        if self._started:
            self._commit_state()
