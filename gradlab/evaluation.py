"""Evaluation of a trainer's members: the deterministic policy on a task of its own (docs/design.md, "Evaluation").

Every member's deterministic policy (``tanh`` of its mean action) plays one whole episode in each of its
``eval_envs`` environments of a separate task, reset from the fixed seed :data:`EVAL_SEED` (every evaluation of
every run starts from the same states); the training state and random streams are untouched. A step is the
training window's step without noise or gradient, built from the same pieces (``gradlab.members``: the task, the
renderers and their one call per raster model, the actors' input, the members' statistics on their rows). Where
the trainer captures (``--compile`` on a GPU), the evaluation's state lives in fixed tensors (``LiveState``) and,
after ``WARMUP_ITERS`` eager steps, one CUDA graph of a step replays for every later step of this and every later
evaluation.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

import tasks
from gradlab import members
from gradlab.config import SHACConfig
from gradlab.graphs import WARMUP_ITERS, LiveState
from gradlab.networks import MemberStack
from tasks.vision import FrameStack, TaskRenderer

__all__ = ["EVAL_SEED", "EvaluationState", "Evaluator"]

#: The reset seed of every evaluation: each evaluation of every run starts its episodes from the same states.
EVAL_SEED = 1_000_003


@dataclass(eq=False)
class EvaluationState:
    """The evaluation task, its renderers and its state in tensors that every evaluation reuses, in place: what a
    captured evaluation step reads and writes (``obs``, ``stats``, ``params`` are made at the first evaluation).
    ``rng``: the task's reset-noise state after it was made, restored before every evaluation."""

    task: tasks.Task
    renderers: dict
    rng: torch.Tensor
    live: LiveState
    frames: FrameStack
    blank: torch.Tensor | None
    total: torch.Tensor
    length: torch.Tensor
    alive: torch.Tensor
    obs: torch.Tensor | None = None
    stats: tuple = ()
    params: dict = field(default_factory=dict)
    graph: Any = None
    warm: int = 0


class Evaluator:
    """Evaluates a trainer's members ``population`` (their actors run as ``actors``, a ``MemberStack`` of them)
    with the population's settings ``cfg`` on ``device``; the task and its tensors are made at the first
    evaluation and kept."""

    def __init__(self, population: Sequence[members.Member], actors: MemberStack, cfg: SHACConfig,
                 device: torch.device):
        self.members, self.actors, self.cfg, self.device = list(population), actors, cfg, device
        self.kind = members.input_kind(self.members)
        self.state: EvaluationState | None = None

    def build(self) -> EvaluationState:
        """The evaluation task (``eval_envs`` environments per member, reset seed :data:`EVAL_SEED`), its
        renderers by raster model and its tensors, made once: kept between evaluations, a compiled one compiles
        once."""
        if self.state is None:
            cfg, n = self.cfg, len(self.members)
            task = members.make_task(cfg, [EVAL_SEED] * n, cfg.eval_envs, self.device)
            renderers = members.make_renderers(task, cfg,
                                               [m.cfg.raster_model for m in self.members if m.plan.renders])
            if cfg.compile:
                # an eager episode is episode_length x substeps unfused substeps, and every frame hundreds of small
                # rendering kernels: compiled for the evaluation's own shapes once, at the first evaluation
                task.compile()
                for renderer in renderers.values():
                    renderer.compile()
            rows = n * cfg.eval_envs
            self.state = EvaluationState(
                task=task, renderers=renderers, rng=task.rng.get_state(), live=LiveState(),
                frames=FrameStack(cfg.frames),
                blank=members.blank_images(cfg, rows, self.device) if self.kind == "blank" else None,
                total=torch.zeros(rows, device=self.device), length=torch.zeros(rows, device=self.device),
                alive=torch.ones(rows, device=self.device, dtype=torch.bool))
        return self.state

    def images(self, task: tasks.Task, renderers: dict[str, TaskRenderer]) -> torch.Tensor:
        """The evaluation task's images, (N * E, 3, H, W), rendered as the training window renders them."""
        return members.images(self.members, renderers, task.qpos, self.cfg.eval_envs, self.cfg.image_size)

    @torch.no_grad()
    def __call__(self, *, capture: bool, video_steps: int = 0, video_size: int = 256) -> list[dict | None]:
        """Per member (None for a member that has stopped) ``eval_return_mean``, ``eval_return_std`` (undiscounted
        return over the episodes), ``eval_length_mean`` (steps), ``eval_steps`` and ``frames``: with
        ``video_steps``, RGB uint8 frames (H, W, 3) of the member's first environment from the task camera at
        ``video_size`` pixels, for its first ``video_steps`` steps (else empty). ``capture``: replay the steps
        from a CUDA graph (the trainer's own setting)."""
        cfg, n, E = self.cfg, len(self.members), self.cfg.eval_envs
        sees = self.kind == "images"
        ev = self.build()
        task, renderers = ev.task, ev.renderers
        task.rng.set_state(ev.rng)  # every evaluation from the same initial states
        obs = task.reset()
        if sees:
            ev.frames.reset(self.images(task, renderers))
        ev.live.commit(task, ev.frames if sees else None)
        stats = members.stacked_stats(self.members, E)
        params = self.actors.stack()
        if ev.obs is None:  # the first evaluation makes the tensors every later one (and a captured step) reuses
            ev.obs, ev.stats = obs, tuple(t.clone() for t in stats)
            ev.params = {k: v.detach() for k, v in params.items()}
        else:
            ev.obs.copy_(obs)
            for fixed, now in [*zip(ev.stats, stats), *((ev.params[k], params[k]) for k in ev.params)]:
                fixed.copy_(now)
        ev.total.zero_()
        ev.length.zero_()
        ev.alive.fill_(True)
        video = None
        if video_steps:
            video = renderers.get(("video", video_size))
            if video is None:
                video = renderers[("video", video_size)] = TaskRenderer(
                    task, height=video_size, width=video_size, detail=max(cfg.render_detail, 2), sigma=None,
                    gamma=None, renderer=cfg.renderer)
        recorded: list[list[np.ndarray]] = [[] for _ in range(n)]
        steps = 0
        for step in range(task.episode_length):
            if video is not None and step < video_steps:
                first = torch.arange(n, device=self.device) * E
                shots = video(task.qpos[first]).clamp(0, 1).mul(255).byte().permute(0, 2, 3, 1).cpu().numpy()
                for i in range(n):
                    recorded[i].append(shots[i])
                self.step(ev)
            elif capture:
                self.step_captured(ev)
            else:
                self.step(ev)
            steps = step + 1
            # one host sync every few steps: the episodes' ends (and videos') are read in batches
            if step % 16 == 15 and not bool(ev.alive.any()) and (video is None or step + 1 >= video_steps):
                break
        out: list[dict | None] = []
        for m in self.members:
            if m.failed is not None:
                out.append(None)
                continue
            rows = slice(m.index * E, (m.index + 1) * E)
            returns = ev.total[rows].double()
            out.append({"eval_return_mean": float(returns.mean()),
                        "eval_return_std": float(returns.std(unbiased=False)),
                        "eval_length_mean": float(ev.length[rows].mean()),
                        "eval_steps": steps,
                        "frames": recorded[m.index]})
        return out

    def step(self, ev: EvaluationState) -> None:
        """One step of every evaluation environment, in place on ``ev``'s tensors (what a captured graph of it
        replays): the deterministic action, the step, the returns of the episodes still running, the frames."""
        task, sees = ev.task, self.kind == "images"
        actor_in = members.actor_input(self.kind, frames=ev.frames, obs=ev.obs, stats=ev.stats, blank=ev.blank,
                                       clip=self.cfg.obs_clip)
        action = torch.tanh(self.actors.mean(ev.params, actor_in))
        obs, reward, done, _ = task.step(action)
        ev.total.add_(reward * ev.alive)
        ev.length.add_(ev.alive.to(ev.length.dtype))
        ev.alive.logical_and_(~done)
        if sees:
            ev.frames.push(self.images(task, ev.renderers), reset=done)
        ev.live.commit(task, ev.frames if sees else None)
        ev.obs.copy_(obs)

    def step_captured(self, ev: EvaluationState) -> None:
        """:meth:`step` replayed from a CUDA graph: an evaluation step runs as one launch instead of the hundreds
        of kernels of the physics, the renderer and the actors. Its first ``WARMUP_ITERS`` calls run eagerly
        (compiling, library warm-up), then one is captured and every call replays it (capturing records without
        running: the captured step is replayed at once, so it counts)."""
        if ev.graph is None:
            if ev.warm < WARMUP_ITERS:
                ev.warm += 1
                self.step(ev)
                return
            ev.graph = torch.cuda.CUDAGraph()
            torch.cuda.synchronize(self.device)
            with torch.cuda.graph(ev.graph, stream=torch.cuda.Stream(self.device)):
                self.step(ev)
        ev.graph.replay()
