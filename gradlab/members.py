"""The members of a trainer: the runs it trains as one batch. A single run is a population of one member.

Member ``m`` owns rows ``m * E .. (m + 1) * E`` of every batch tensor (E environments per member: ``num_envs``
in training, ``eval_envs`` in evaluation) and its own networks, optimisers, observation statistics, noise and
abort guard (docs/design.md, "Populations"). This module holds what the training window and the evaluation both
do with the members' rows, so that the two share it: the task of E environments per member, the renderers and
the images (one renderer call per run of adjacent members of one raster model), the actor's input, the members'
observation statistics and action noise laid out on their rows, the per-member sums of a loss; what the
population must agree on (:func:`check_population`) and the order its members train in (:func:`render_order`;
``gradlab.roster`` applies both, once); the routes of the image gradients; and a member's checkpoint, a single
run's format holding the member's rows of the trainer's state, matched to its member on resume.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import os
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

import tasks
from gradlab.config import ModePlan, SHACConfig
from gradlab.networks import Critic, StateActor, VisualActor
from gradlab.normalizer import RunningMeanStd
from gradlab.presets import SILHOUETTE_RASTER_MODEL
from gradlab.seeding import rng_state, seed_everything
from tasks.vision import FrameStack, TaskRenderer
from vocabulary import MEMBER_FIELDS

__all__ = ["MEMBER_FIELDS", "Member", "actor_input", "alt_raster", "blank_images", "build_member", "check_memory",
           "check_population", "images", "input_kind", "joined_state", "make_renderers", "make_task", "match_states",
           "member_state", "member_sums", "probe_routes", "render_order", "restore_member", "sample",
           "stacked_stats", "why_all_stopped", "window_bytes"]

def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def check_population(cfgs: Sequence[SHACConfig]) -> None:
    """Raise ValueError, naming the flag, unless the resolved configs can train as one population: the same value
    of every setting outside :data:`MEMBER_FIELDS`, all of them on the state vector or none (a state actor has
    no encoder to batch with a visual one), and no member twice."""
    if not cfgs:
        raise ValueError("a population needs at least one member")
    first = dataclasses.asdict(cfgs[0])
    for cfg in cfgs[1:]:
        for name, value in dataclasses.asdict(cfg).items():
            if name not in MEMBER_FIELDS and value != first[name]:
                raise ValueError(f"the members of one population share {_flag(name)}, got {first[name]!r} and "
                                 f"{value!r}")
    on_state = {ModePlan.of(c.mode).actor_input == "state" for c in cfgs}
    if len(on_state) > 1:
        raise ValueError("--mode state trains on the state vector and cannot share a population with the pixel "
                         "modes (full, decoupled, blind): train it as a population of its own")
    distill = {c.mode == "distill" for c in cfgs}
    if len(distill) > 1:
        raise ValueError("--mode distill trains in a trainer of its own (gradlab.Distill) and cannot share a "
                         "population with the other modes: train its members as a population of their own")
    seen = set()
    for cfg in cfgs:
        key = tuple(getattr(cfg, name) for name in MEMBER_FIELDS)
        if key in seen:
            raise ValueError(f"member --mode {cfg.mode} --seed {cfg.seed} --raster-model {cfg.raster_model} "
                             f"--preset {cfg.preset} appears twice in the population")
        seen.add(key)


def window_bytes(cfgs: Sequence[SHACConfig]) -> int:
    """An estimate of what one window of these members keeps for its backward [bytes]: the bulk of a visual
    run's memory, its frame stacks and encoder activations at every step (each convolution's output and its
    ReLU's) and, for full members, the rasterizer's per-pixel state. State runs keep little."""
    total = 0
    for cfg in cfgs:
        plan = ModePlan.of(cfg.mode)
        if plan.actor_input == "state":
            continue
        h = w = cfg.image_size
        per_step = cfg.num_envs * 3 * cfg.frames * h * w  # the frame stack the first convolution keeps
        h, w = (h - 3) // 2 + 1, (w - 3) // 2 + 1
        for _ in range(4):
            per_step += 2 * cfg.num_envs * 32 * h * w
            h, w = h - 2, w - 2
        if plan.grad_through_images:
            per_step += 2 * cfg.num_envs * cfg.image_size**2 * (7 + 3)  # blend state and image, two raster models
        total += 4 * per_step * cfg.horizon
    return total


def _memory_of(device: torch.device) -> int:
    """The device's memory [bytes]: a GPU's, or the machine's for the CPU."""
    if device.type == "cuda":
        return torch.cuda.mem_get_info(device)[1]
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def check_memory(cfgs: Sequence[SHACConfig], device: torch.device) -> None:
    """Refuse, before any work, members whose window would not fit the device together while each would alone:
    the estimate is there to pack runs into processes, and what fewer members per process cannot mend (a run
    alone, or a member that would not fit alone either) is left to the device to tell."""
    need, have = window_bytes(cfgs), _memory_of(device)
    if need > have and all(window_bytes([c]) <= have for c in cfgs):
        raise ValueError(f"a population of {len(cfgs)} members keeps about {need / 2**30:.1f} GiB for one window's "
                         f"backward (estimated), more than the {have / 2**30:.1f} GiB of {device}: "
                         "train fewer members per process (fewer --seed/--mode values, or --pack)")


def render_order(cfg: SHACConfig) -> tuple:
    """Members sorted by this key render in as few calls as possible: one per raster model (and gradient)."""
    plan = ModePlan.of(cfg.mode)
    return plan.actor_input == "blank", cfg.raster_model or "", not plan.grad_through_images


def alt_raster(raster_model: str) -> str:
    """The other image model whose gradient a full run's probe also takes: the hard one for a soft model (the
    paper's baseline estimator), the default soft one for the hard model."""
    return SILHOUETTE_RASTER_MODEL if raster_model == "hard" else "hard"


@dataclass(eq=False)
class Member:
    """One run of a trainer: what it owns alone. ``rows``: its environments in the training batch; ``generator``:
    its action noise (None: torch's default generator, a run alone); ``failed``: why it stopped, where it did (it
    then trains no more and its environments only keep the batch's shape)."""

    index: int
    cfg: SHACConfig
    plan: ModePlan
    rows: slice
    actor: nn.Module
    critic: Critic
    target_critic: Critic
    actor_opt: torch.optim.Optimizer
    critic_opt: torch.optim.Optimizer
    obs_rms: RunningMeanStd
    generator: torch.Generator | None
    recent_returns: deque = field(default_factory=lambda: deque(maxlen=100))
    recent_lengths: deque = field(default_factory=lambda: deque(maxlen=100))
    failed: str | None = None

    @property
    def params(self) -> list[nn.Parameter]:
        return list(self.actor.parameters())


def build_member(index: int, cfg: SHACConfig, task: tasks.Task, device: torch.device, *, own_generator: bool,
                 capturable: bool) -> Member:
    """A member's own parts, built as a run of its own builds them: its seed, then its networks (whose
    initialisation draws from torch's generator), then, with ``own_generator`` (several members), its noise
    generator from where that left off; one member draws from torch's default generator, as a run alone does
    (its checkpoint's ``rng`` holds it). ``capturable``: the critic's Adam is captured in a CUDA graph, so it
    must be capturable and read its learning rate from a tensor that the decay updates in place."""
    plan = ModePlan.of(cfg.mode)
    seed_everything(cfg.seed)
    if plan.actor_input == "state":
        actor = StateActor(task.num_obs, task.num_act, cfg.actor_hidden, init=cfg.actor_init)
    else:
        actor = VisualActor(3 * cfg.frames, cfg.image_size, cfg.image_size, task.num_act, cfg.trunk_dim,
                            cfg.actor_hidden, init=cfg.actor_init, precision=cfg.precision)
    critic = Critic(task.num_obs, cfg.critic_hidden)
    actor.to(device)
    critic.to(device)
    target_critic = copy.deepcopy(critic)
    for p in target_critic.parameters():
        p.requires_grad_(False)
    generator = None
    if own_generator:
        generator = torch.Generator(device=device)
        generator.set_state(torch.cuda.get_rng_state(device) if device.type == "cuda" else torch.get_rng_state())
    if cfg.encoder_lr_scale != 1.0 and isinstance(actor, VisualActor):
        encoder = list(actor.encoder.parameters())
        rest = [p for p in actor.parameters() if all(p is not q for q in encoder)]
        groups = [{"params": encoder, "lr_scale": cfg.encoder_lr_scale}, {"params": rest, "lr_scale": 1.0}]
    else:
        groups = [{"params": list(actor.parameters()), "lr_scale": 1.0}]
    actor_opt = torch.optim.Adam(groups, lr=cfg.actor_lr, betas=cfg.betas)
    critic_lr = torch.tensor(cfg.critic_lr, device=device) if capturable else cfg.critic_lr
    critic_opt = torch.optim.Adam(critic.parameters(), lr=critic_lr, betas=cfg.betas, capturable=capturable)
    per_member = cfg.num_envs
    return Member(index, cfg, plan, slice(index * per_member, (index + 1) * per_member), actor, critic,
                  target_critic, actor_opt, critic_opt, RunningMeanStd(task.num_obs, device=device), generator)


def probe_routes(members: Sequence[Member]) -> dict[str, tuple[str | None, ...]]:
    """Where each backward pass sends each member's image gradient (``ImageGate.set_route``): ``train``, the
    gradient every member trains with (last, so it stays in ``.grad``); on probe iterations first ``other``, the
    estimator it does not train with, and, where a member trains full, ``alt``, its full gradient through the
    other raster model's image of the same states."""
    full = [m.plan.grad_through_images for m in members]
    sees = [m.plan.renders for m in members]
    routes = {"train": tuple("image" if f else None for f in full),
              "other": tuple("image" if s and not f else None for s, f in zip(sees, full))}
    if any(full):
        routes["alt"] = tuple("alt" if f else None for f in full)
    return routes


def why_all_stopped(members: Sequence[Member]) -> str:
    """Why the training ended once every member stopped: each member's reason; a run alone's as it is, without
    a member's number (the closing lines and summary.json of a run alone name no members)."""
    if len(members) == 1:
        return members[0].failed
    return "every member of the population stopped: " + "; ".join(f"member {m.index}: {m.failed}" for m in members)


# ---------------------------------------------------------------------- the members' rows of one batch
def make_task(cfg: SHACConfig, seeds: Sequence[int], per_member: int, device: torch.device) -> tasks.Task:
    """The population's task: ``per_member`` environments for each reset seed, member m's resets those a task of
    its own with seed ``seeds[m]`` draws (``tasks.rng.CounterRNG`` groups)."""
    overrides = {} if cfg.episode_length is None else {"episode_length": cfg.episode_length}
    if cfg.sim_backend != "torch":
        overrides["sim_backend"] = cfg.sim_backend
    return tasks.make(cfg.task, len(seeds) * per_member, device=device, seed=list(seeds), **overrides)


def _render_options(cfg: SHACConfig, raster_model: str) -> dict:
    # save_blend_state: a full-mode window keeps 7 numbers per pixel per frame (flat in faces) so that each
    # render backward skips a second forward pass (fused backend)
    options = dict(detail=cfg.render_detail, extra_meshes=cfg.extra_meshes, extra_mesh_verts=cfg.extra_mesh_verts,
                   sigma=cfg.sigma, gamma=cfg.render_gamma, raster_model=raster_model,
                   renderer=cfg.renderer, save_blend_state=True)
    if raster_model == "alpha":
        options["cull_backfaces"] = False  # alpha coverage sums over all faces, hidden ones included
    return options


def make_renderers(task: tasks.Task, cfg: SHACConfig, rasters: Sequence[str]) -> dict[str, TaskRenderer]:
    """One renderer of ``task`` per raster model in ``rasters`` (repeats ignored), at the population's image size."""
    return {r: TaskRenderer(task, height=cfg.image_size, width=cfg.image_size, **_render_options(cfg, r))
            for r in dict.fromkeys(rasters)}


def _render_key(member: Member, grad: Sequence[bool] | None, alt: bool) -> tuple[str | None, bool]:
    if alt:
        return (alt_raster(member.cfg.raster_model), True) if member.plan.grad_through_images else (None, False)
    if not member.plan.renders:
        return None, False
    return member.cfg.raster_model, bool(grad is not None and grad[member.index])


def images(members: Sequence[Member], renderers: dict[str, TaskRenderer], qpos: torch.Tensor, per_member: int,
           image_size: int, *, grad: Sequence[bool] | None = None, alt: bool = False) -> torch.Tensor:
    """Images of every member's environments, (N * E, 3, H, W) in [0, 1]: member m's rows from its raster model,
    differentiable in its qpos where ``grad[m]`` (always through the rasterizer: the ray tracer of ``--renderer
    warp`` has no gradient), a blind member's rows zeros (its actor sees no image); ``alt``: the other raster
    model of a full member's probe, the other members' rows zeros. One renderer call for each run of adjacent
    members of one raster model and gradient (the population order keeps them adjacent): a call a member costs
    hundreds of small kernels a member and step (BENCHMARKS.md, section 7)."""
    blocks = []
    for (raster, g), group in itertools.groupby(members, key=lambda m: _render_key(m, grad, alt)):
        group = list(group)
        start, stop = group[0].index * per_member, (group[-1].index + 1) * per_member
        if raster is None:
            blocks.append(torch.zeros(stop - start, 3, image_size, image_size, device=qpos.device))
            continue
        q = qpos if (start, stop) == (0, qpos.shape[0]) else qpos[start:stop]
        if g:
            blocks.append(renderers[raster].soft(q))
        else:
            with torch.no_grad():
                blocks.append(renderers[raster](q))
    return blocks[0] if len(blocks) == 1 else torch.cat(blocks)


def blank_images(cfg: SHACConfig, rows: int, device: torch.device) -> torch.Tensor:
    """A blind actor's input for ``rows`` environments: an all-black stack, zeros (rows, 3 * frames, H, W)."""
    return torch.zeros(rows, 3 * cfg.frames, cfg.image_size, cfg.image_size, device=device)


def input_kind(members: Sequence[Member]) -> str:
    """What the population's actors see (``ModePlan.actor_input``): "images" where any member renders (a blind
    member's rows of the frame stack are then zeros), else "state" or "blank" (members of one kind only)."""
    if any(m.plan.renders for m in members):
        return "images"
    return members[0].plan.actor_input


def actor_input(kind: str, *, frames: FrameStack, obs: torch.Tensor, stats: tuple[torch.Tensor, torch.Tensor],
                blank: torch.Tensor | None, clip: float) -> torch.Tensor:
    """The actors' input of one step, by :func:`input_kind`: the frame stack, the normalised state, or the blind
    actors' constant stack."""
    if kind == "images":
        return frames.stacked()
    if kind == "state":
        return RunningMeanStd.apply(obs, stats, clip)
    return blank


def stacked_stats(members: Sequence[Member], per_member: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Frozen observation statistics (``RunningMeanStd.snapshot``) of every member on its rows: (mean, std), each
    (N * E, obs); normalising with them is elementwise, so each row gets exactly its member's own arithmetic."""
    snapshots = [m.obs_rms.snapshot() for m in members]
    return tuple(torch.stack(s).repeat_interleave(per_member, 0) for s in zip(*snapshots))


def sample(members: Sequence[Member], mu: torch.Tensor, per_member: int) -> torch.Tensor:
    """mu (N * B, act) -> ``tanh(mu + std * eps)``, each member's noise from its own generator and std (one
    member: torch's default generator, the draws and arithmetic of its actor's own ``sample``)."""
    eps = torch.cat([torch.randn(per_member, mu.shape[1], device=mu.device, dtype=mu.dtype, generator=m.generator)
                     for m in members])
    std = torch.stack([m.actor.log_std for m in members]).exp().repeat_interleave(per_member, 0)
    return torch.tanh(mu + std * eps)


def member_sums(x: torch.Tensor, n: int) -> torch.Tensor:
    """(N * B,) -> (N,), each member's sum of its rows."""
    return x.view(n, -1).sum(1)


# ---------------------------------------------------------------------- checkpoints: a member's is a run's
def member_state(m: Member, *, iteration: int, wall_s: float, started: bool, task: dict, frames: dict,
                 episode_return: torch.Tensor, episode_length: torch.Tensor) -> dict:
    """Everything that determines the future of member ``m`` (resume == uninterrupted on the CPU), in a single
    run's checkpoint format: the trainer's clock and iteration, the member's own parts and its rows of the
    trainer's task state (``Task.get_state()``: its reset seed with the shared counter), frame stack
    (``FrameStack.state_dict()``) and episode counters; torch's global random state, and the member's noise
    generator where it has its own (``generator``)."""
    seeds, counter = task["rng"][:-1], task["rng"][-1:]
    own_task = {k: v[m.rows] for k, v in task.items() if k != "rng"}
    own_task["rng"] = torch.cat([seeds[m.index:m.index + 1], counter])
    state = {
        "config": dataclasses.asdict(m.cfg),
        "iteration": iteration,
        "wall_s": wall_s,
        "started": started,
        "actor": m.actor.state_dict(),
        "critic": m.critic.state_dict(),
        "target_critic": m.target_critic.state_dict(),
        "actor_opt": m.actor_opt.state_dict(),
        "critic_opt": m.critic_opt.state_dict(),
        "obs_rms": m.obs_rms.state_dict(),
        "task": own_task,
        "frames": dict(frames, frames=[f[m.rows] for f in frames["frames"]]),
        "episode_return": episode_return[m.rows].clone(),
        "episode_length": episode_length[m.rows].clone(),
        "recent_returns": list(m.recent_returns),
        "recent_lengths": list(m.recent_lengths),
        "rng": rng_state(),
    }
    if m.generator is not None:
        state["generator"] = m.generator.get_state()
    if m.failed is not None:
        state["failed"] = m.failed
    return state


def _config_key(config: dict[str, Any]) -> tuple:
    return tuple(repr(config.get(name)) for name in MEMBER_FIELDS)


def match_states(members: Sequence[Member], states: Sequence[dict]) -> list[dict]:
    """Checkpoints of the members, given in any order, in the order of ``members``; ValueError where they are of
    other members, or of a member trained in a population of another size.

    A run alone's checkpoint is its own whatever its config says (a run resumed with other settings, e.g. a
    config.json restored by hand); a population's are matched by their member settings. A member of several
    draws its noise from a generator of its own, which its checkpoint holds; a run alone draws from torch's
    default generator: a checkpoint of the one cannot resume the other exactly, so it is refused."""
    states = list(states)
    if len(states) != len(members):
        raise ValueError(f"{len(states)} member states for a population of {len(members)}")
    if len(members) == 1:
        ordered = states
    else:
        by_config = {_config_key(s["config"]): s for s in states}
        ordered = [by_config.get(_config_key(dataclasses.asdict(m.cfg))) for m in members]
        if any(s is None for s in ordered):
            raise ValueError("the checkpoints are of other members than this population's")
    for m, s in zip(members, ordered):
        if (m.generator is None) != ("generator" not in s):
            trained, here = ("a member of a population", "a run alone") if m.generator is None else \
                ("a run alone", f"a member of a population of {len(members)}")
            raise ValueError(f"the checkpoint of {trained} cannot resume exactly as {here} (its action noise "
                             f"comes from another generator): resume it as it was trained")
    return ordered


def restore_member(m: Member, state: dict) -> None:
    """A member's own parts from its checkpoint (:func:`member_state`)."""
    m.actor.load_state_dict(state["actor"])
    m.critic.load_state_dict(state["critic"])
    m.target_critic.load_state_dict(state["target_critic"])
    m.actor_opt.load_state_dict(state["actor_opt"])
    m.critic_opt.load_state_dict(state["critic_opt"])
    m.obs_rms.load_state_dict(state["obs_rms"])
    m.recent_returns = deque(state["recent_returns"], maxlen=100)
    m.recent_lengths = deque(state["recent_lengths"], maxlen=100)
    if m.generator is not None:
        m.generator.set_state(state["generator"].cpu())  # a host ByteTensor, wherever map_location put it


def joined_state(ordered: Sequence[dict]) -> tuple[dict, dict, torch.Tensor, torch.Tensor]:
    """The trainer's shared state from its members' checkpoints, in member order: the task state (each member's
    rows and reset seed, the one counter they must share), the frame stack and the episode return and length."""
    names = [k for k in ordered[0]["task"] if k != "rng"]  # the task's state tensors, as its get_state gave them
    task = {k: torch.cat([s["task"][k] for s in ordered]) for k in names}
    counters = {int(s["task"]["rng"][-1]) for s in ordered}
    if len(counters) != 1:
        raise ValueError("the members' checkpoints are of different reset counters")
    task["rng"] = torch.cat([s["task"]["rng"][:-1] for s in ordered] + [ordered[0]["task"]["rng"][-1:]])
    frames = dict(ordered[0]["frames"])
    frames["frames"] = [torch.cat(fs) for fs in zip(*(s["frames"]["frames"] for s in ordered))]
    return (task, frames, torch.cat([s["episode_return"] for s in ordered]),
            torch.cat([s["episode_length"] for s in ordered]))
