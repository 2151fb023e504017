"""State-to-visual distillation (``--mode distill``): a visual student imitates a frozen state expert, as D.Va's
DAgger baseline does it (``algorithms/dagger.py``, ``examples/train_state2visDAgger.py``; docs/distill.md).

One iteration (the reference's epoch), top to bottom:

1. Rollout segment: ``horizon`` (32) steps that resume from where the previous segment ended (no reset between
   segments; environments reset only at their episodes' ends), driven by the **student's own** deterministic
   actions ``tanh(student(frames))``: no expert actions are mixed in and there is no exploration noise. Every
   step stores the frame stack (uint8) and the state observation. No gradient anywhere.
2. Labels: every stored state gets the expert's deterministic pre-tanh action ``expert.mean(normalise(state))``
   (the expert's frozen observation statistics), and the (frames, label) pairs go into the member's FIFO
   :class:`ReplayBuffer` on the device.
3. Updates, once the buffer holds ``distill_starts`` samples: up to ``distill_updates`` Adam steps, each on
   ``distill_batch`` samples drawn without replacement from the whole buffer, loss the MSE of the student's
   pre-tanh output against the label, the learning rate decaying linearly to 1e-5 over ``lr_decay_iters x
   distill_updates`` steps; the iteration's updates stop at the first minibatch loss below
   ``distill_loss_threshold``.

The student (:class:`Student`) is D.Va's ``ActorDeterministicMLP`` on the visual encoder: ``PixelEncoder``
(its trunk the first MLP width, as the presets set ``trunk_dim``), then Linear -> ELU -> LayerNorm per hidden
width and a last Linear, every Linear orthogonal with gain sqrt(2) and zero bias. The expert is a state run of
this toolkit (``--expert``), loaded from its checkpoint; its training time (the trainer's wall-clock, which excludes
evaluation: the reference's algorithm timer minus its evaluation timer) and environment steps are charged to the
student's ``wall_s`` and ``env_steps``.

Members: ``Distill([cfg, ...])`` trains several students in one process over one batched simulation, member m on
environments ``m * B .. (m + 1) * B``, each with its own expert, student, optimiser, buffer and sampling
generator; ``Distill([cfg])`` is a run alone. The trainer has :class:`gradlab.SHAC`'s list interface
(``train_iteration``, ``evaluate``, ``state_dict``, ``load_state_dict``, ``members``), so that code driving a run
trains either the same way. Metrics keys follow SHAC's: ``actor_loss`` is the distillation
loss of the iteration's last update (None before the updates start), ``fwd_ms`` the rollout and labelling,
``bwd_ms`` the updates, ``critic_loss`` None (there is no critic).

A checkpoint holds no buffer (6.35 GB a member at the reference's sizes): a resumed run refills it from its own
rollouts, and its updates wait until it holds ``distill_starts`` samples again (metrics ``buffer_size``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import nn

import tasks
from gradlab import members
from gradlab.checkpoint import load_checkpoint, load_newest_readable
from gradlab.config import ModePlan, SHACConfig
from gradlab.evaluation import Evaluator
from gradlab.networks import MLP, MemberStack, PixelEncoder, StateActor, orthogonal_init
from gradlab.normalizer import RunningMeanStd
from gradlab.probes import NonFiniteError
from gradlab.roster import Roster
from gradlab.seeding import resolve_device, rng_state, seed_everything, set_rng_state
from tasks.vision import FrameStack

__all__ = ["Distill", "Expert", "ReplayBuffer", "Student", "load_expert", "to_uint8"]

#: The learning rate's end value (the reference's linear schedule ends at 1e-5, as SHAC's does).
_LR_END = 1e-5


def to_uint8(images: torch.Tensor) -> torch.Tensor:
    """Images in [0, 1] -> uint8 in [0, 255] (rounded), as the buffer stores them and the student reads them."""
    return images.clamp(0, 1).mul(255).round().to(torch.uint8)


class Student(nn.Module):
    """D.Va's ``ActorDeterministicMLP`` on pixels: frames (B, 3 * frames, H, W) in [0, 1] -> pre-tanh actions
    (B, act_dim). ``PixelEncoder`` to ``trunk_dim`` features (the reference's: ``hidden[0]``, as the presets set
    it), then Linear -> ELU -> LayerNorm per width of ``hidden`` and a last Linear, every Linear orthogonal (gain
    sqrt 2, zero bias; ``models/actor.py``)."""

    def __init__(self, in_channels: int, height: int, width: int, act_dim: int, trunk_dim: int,
                 hidden: Sequence[int], *, precision: str | None = None):
        super().__init__()
        self.encoder = PixelEncoder(in_channels, height, width, trunk_dim, precision=precision)
        self.mu = MLP(trunk_dim, hidden, act_dim)
        orthogonal_init(self.mu, gain=2.0**0.5)

    def mean(self, obs: torch.Tensor) -> torch.Tensor:
        """The deterministic pre-tanh action (B, act_dim); the action taken is its tanh."""
        return self.mu(self.encoder(obs))

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"encoder": list(self.encoder.parameters()), "mlp": list(self.mu.parameters())}


@dataclass(eq=False)
class Expert:
    """A frozen state policy: ``actor`` with its observation statistics ``obs_rms`` and clip; ``wall_s`` and
    ``env_steps``: what training it cost (charged to the student), ``source``: the checkpoint it came from."""

    actor: StateActor
    obs_rms: RunningMeanStd
    obs_clip: float
    wall_s: float
    env_steps: int
    iterations: int
    source: str

    @torch.no_grad()
    def __call__(self, state_obs: torch.Tensor) -> torch.Tensor:
        """Raw state observations (B, obs) -> the expert's deterministic pre-tanh actions (B, act)."""
        return self.actor.mean(RunningMeanStd.apply(state_obs, self.obs_rms.snapshot(), self.obs_clip))


def _expert_checkpoint(path: Path) -> Path:
    """The checkpoint file ``--expert`` names: the file itself, or a run folder's newest readable checkpoint."""
    if not path.exists():
        raise ValueError(f"--expert {path}: no such file or folder")
    if path.is_file():
        return path
    folder = path / "checkpoints" if (path / "checkpoints").is_dir() else path
    try:
        return load_newest_readable(folder).path
    except ValueError:
        raise ValueError(f"--expert {path}: holds no readable checkpoint (a state run's folder, or one of its "
                         "checkpoints/ckpt_<iteration>.pt files)") from None


def load_expert(cfg: SHACConfig, task, device: torch.device) -> Expert:
    """The expert ``cfg.expert`` names, for ``cfg.task``. ValueError naming ``--expert`` where there is none, it is
    not a state run, or it is of another task or size of observation and action."""
    if not cfg.expert:
        raise ValueError("--expert: --mode distill needs a state expert, a state run's folder or checkpoint (train "
                         "one with --mode state --preset teacher)")
    path = _expert_checkpoint(Path(cfg.expert))
    try:
        state = load_checkpoint(path)
    except Exception as e:  # any unreadable file is the flag's fault
        raise ValueError(f"--expert {cfg.expert}: {path} is not a checkpoint ({type(e).__name__})") from None
    config = state.get("config") if isinstance(state, dict) else None
    if not isinstance(config, dict) or "actor" not in state:
        raise ValueError(f"--expert {cfg.expert}: {path} is not a run's checkpoint")
    if config.get("mode") != "state":
        raise ValueError(f"--expert {cfg.expert}: a --mode {config.get('mode')} run, not a state run (the expert "
                         "sees the state vector: train it with --mode state)")
    if config.get("task") != cfg.task:
        raise ValueError(f"--expert {cfg.expert}: an expert of task {config.get('task')}, not --task {cfg.task}")
    actor = StateActor(task.num_obs, task.num_act, tuple(config["actor_hidden"]))
    try:
        actor.load_state_dict(state["actor"])
    except RuntimeError:
        raise ValueError(f"--expert {cfg.expert}: its actor does not fit task {cfg.task}'s observations and "
                         "actions") from None
    actor.to(device).eval().requires_grad_(False)
    obs_rms = RunningMeanStd(task.num_obs, device=device)
    obs_rms.load_state_dict(state["obs_rms"])
    iterations = int(state["iteration"])
    return Expert(actor, obs_rms, float(config.get("obs_clip") or 0.0), float(state["wall_s"]),
                  iterations * int(config["horizon"]) * int(config["num_envs"]), iterations, str(path))


class ReplayBuffer:
    """A FIFO of ``capacity`` (frames, label) samples on ``device``: frames uint8 (capacity, C, H, W), labels float32
    (capacity, act). As the reference's ``ExpertReplayBuffer`` (``utils/dataset.py``): samples are written at the
    write position; a batch that would run past the end is cut there (its overflow dropped) and the next batch
    starts again at 0, over the oldest samples."""

    def __init__(self, capacity: int, image_shape: Sequence[int], act_dim: int, device: torch.device):
        self.capacity = capacity
        self.images = torch.zeros(capacity, *image_shape, dtype=torch.uint8, device=device)
        self.actions = torch.zeros(capacity, act_dim, device=device)
        self.size = self.pos = 0

    def __len__(self) -> int:
        return self.size

    def append(self, images: torch.Tensor, actions: torch.Tensor) -> None:
        """images (n, C, H, W) uint8, actions (n, act)."""
        n = min(images.shape[0], self.capacity - self.pos)
        self.images[self.pos:self.pos + n] = images[:n]
        self.actions[self.pos:self.pos + n] = actions[:n]
        self.size = min(self.size + n, self.capacity)
        self.pos = (self.pos + n) % self.capacity

    def sample(self, batch: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """``batch`` samples without replacement: frames as float in [0, 1] (batch, C, H, W), labels (batch, act)."""
        idx = torch.randperm(self.size, device=self.actions.device, generator=generator)[:batch]
        return self.images[idx].float() / 255.0, self.actions[idx]


@dataclass(eq=False)
class DistillMember:
    """One student of a trainer: its rows of the batch, student, optimiser, expert, buffer and sampling generator.
    ``obs_rms`` is never updated (the student sees no state); the shared evaluation code reads it. ``updates``:
    Adam steps taken so far (the learning-rate schedule's clock)."""

    index: int
    cfg: SHACConfig
    plan: ModePlan
    rows: slice
    actor: Student
    actor_opt: torch.optim.Optimizer
    expert: Expert
    buffer: ReplayBuffer
    generator: torch.Generator
    obs_rms: RunningMeanStd
    updates: int = 0
    recent_returns: deque = field(default_factory=lambda: deque(maxlen=100))
    recent_lengths: deque = field(default_factory=lambda: deque(maxlen=100))
    failed: str | None = None

    @property
    def params(self) -> list[nn.Parameter]:
        return list(self.actor.parameters())


class Distill:
    """The distillation trainer of a population of runs (a run alone: one), with :class:`gradlab.SHAC`'s list
    interface (module docstring).

    Args:
        roster: the members (a :class:`gradlab.roster.Roster`), or their ``--mode distill`` configurations, one
            per member (None fields resolved by the preset; they share every setting but
            :data:`vocabulary.MEMBER_FIELDS`: a population's students differ in seed and expert).
        device: "auto" | "cpu" | "cuda[:N]".
    """

    #: What ``--compile`` compiles (:meth:`compile`): the rollouts' physics parts (``tasks.PHYSICS_PARTS``) and the
    #: renderer's PyTorch work. The students' updates stay eager, and nothing is captured as a CUDA graph: a
    #: segment runs without gradient, so its cost is the simulator's and the renderer's small kernels.
    COMPILE_PARTS: ClassVar[tuple[str, ...]] = (*tasks.PHYSICS_PARTS, "renderer")
    #: Where the trainer calls what it compiles, by the name a progress display gives its compilations.
    COMPILE_SITES: ClassVar[dict[str, str]] = {"physics step": "task.step", "renderer": "_render"}

    def __init__(self, roster: Roster | Sequence[SHACConfig], *, device: str | torch.device = "auto"):
        self.roster = roster = roster if isinstance(roster, Roster) else Roster.of(roster)
        cfgs = list(roster.cfgs)
        if cfgs[0].mode != "distill":
            raise ValueError(f"--mode: gradlab.Distill trains --mode distill, got --mode {cfgs[0].mode}")
        self.n = n = len(cfgs)
        self.cfg = cfg = cfgs[0]
        self.device = device if isinstance(device, torch.device) else resolve_device(device)
        B = cfg.num_envs
        seed_everything(cfg.seed)
        self.task = members.make_task(cfg, [c.seed for c in cfgs], B, self.device)
        self.renderers = members.make_renderers(self.task, cfg, [c.raster_model for c in cfgs])
        experts = [load_expert(c, self.task, self.device) for c in cfgs]  # bad input before any work
        image_shape = (3 * cfg.frames, cfg.image_size, cfg.image_size)
        self.members: list[DistillMember] = []
        for i, (c, expert) in enumerate(zip(cfgs, experts)):
            seed_everything(c.seed)  # a member's student is initialised as a run alone's
            student = Student(*image_shape, self.task.num_act, c.trunk_dim, c.actor_hidden,
                              precision=c.precision).to(self.device)
            generator = torch.Generator(device=self.device)
            generator.manual_seed(c.seed)
            self.members.append(DistillMember(
                i, c, ModePlan.of(c.mode), slice(i * B, (i + 1) * B), student,
                torch.optim.Adam(student.parameters(), lr=c.actor_lr, betas=c.betas), expert,
                ReplayBuffer(c.distill_buffer, image_shape, self.task.num_act, self.device), generator,
                RunningMeanStd(self.task.num_obs, device=self.device)))
        self.actors = MemberStack([m.actor for m in self.members], batching="modules")
        self.frames = FrameStack(cfg.frames)
        self.evaluator = Evaluator(self.members, self.actors, cfg, self.device)
        self.graphs = False  # no CUDA graphs: a segment's steps run one by one (compiled with --compile)
        self.compiled: tuple[str, ...] | None = None  # the parts of COMPILE_PARTS compiled (compile)
        self.on_status = None
        self.iteration = 0
        self.wall_s = 0.0  # the students' own training time; each adds its expert's (Expert.wall_s)
        self.start_s: float | None = None
        self._started = False
        self.episode_return = torch.zeros(n * B, device=self.device)
        self.episode_length = torch.zeros(n * B, device=self.device, dtype=torch.long)

    # ------------------------------------------------------------------ compiling
    def compile(self, parts: Sequence[str] = COMPILE_PARTS) -> None:
        """Compile ``parts`` (of :attr:`COMPILE_PARTS`) where the rollouts call them, each at its first call: the
        task's physics parts (``Task.compile_table``) and the renderers (``TaskRenderer.compile``). Once per
        trainer, before its first iteration."""
        if isinstance(parts, str) or not set(parts) <= set(self.COMPILE_PARTS):
            raise ValueError(f"compile parts are some of {self.COMPILE_PARTS}, got {parts!r}")
        if self.compiled is not None:
            raise RuntimeError(f"this trainer compiled {self.compiled} already")
        physics = self.task.compile_table()
        for part in parts:
            for entry in (physics[part],) if part in physics else self.renderers.values():
                entry.compile()
        self.compiled = tuple(parts)

    # ------------------------------------------------------------------ the rollout segment
    def _render(self) -> torch.Tensor:
        return members.images(self.members, self.renderers, self.task.qpos, self.cfg.num_envs, self.cfg.image_size)

    def _start(self) -> None:
        self.task.reset()
        self.frames.reset(self._render())
        self._started = True

    @torch.no_grad()
    def _segment(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``horizon`` steps on from the previous segment's end with the students' own actions. Returns the
        frames the students saw, uint8 (T, N * B, C, H, W), and the states they were in, (T, N * B, obs)."""
        cfg, task = self.cfg, self.task
        T, rows = cfg.horizon, self.n * cfg.num_envs
        images = torch.empty(T, rows, 3 * cfg.frames, cfg.image_size, cfg.image_size, dtype=torch.uint8,
                             device=self.device)
        states = torch.empty(T, rows, task.num_obs, device=self.device)
        ends = torch.empty(T, rows, dtype=torch.bool, device=self.device)
        returns, lengths = torch.empty(T, rows, device=self.device), torch.empty(T, rows, device=self.device)
        for t in range(T):
            states[t] = task.state_obs()
            images[t] = to_uint8(self.frames.stacked())
            # the student reads the frames as the buffer holds them (uint8), in training and in its rollouts
            action = torch.tanh(self.actors.mean({}, images[t].float() / 255.0))
            _, reward, done, _ = task.step(action)
            self.frames.push(self._render(), reset=done)
            self.episode_return += reward
            self.episode_length += 1
            ends[t], returns[t], lengths[t] = done, self.episode_return, self.episode_length
            self.episode_return.masked_fill_(done, 0.0)
            self.episode_length.masked_fill_(done, 0)
        ends = ends.cpu()  # the episodes' ends: one host transfer a segment
        if ends.any():
            returns, lengths = returns.cpu(), lengths.cpu()
            for m in self.members:
                mine = ends[:, m.rows]
                m.recent_returns.extend(returns[:, m.rows][mine].tolist())
                m.recent_lengths.extend(lengths[:, m.rows][mine].long().tolist())
        return images, states

    # ------------------------------------------------------------------ the updates
    def _lr(self, m: DistillMember) -> float:
        """Linear from ``actor_lr`` to 1e-5 over ``lr_decay_iters x distill_updates`` Adam steps (the reference's
        ``max_epochs x num_update_per_epoch``), held after."""
        frac = min(m.updates / (m.cfg.lr_decay_iters * m.cfg.distill_updates), 1.0)
        return m.cfg.actor_lr + (_LR_END - m.cfg.actor_lr) * frac

    def _update(self, m: DistillMember) -> tuple[float | None, float | None, int]:
        """Member m's updates of this iteration: (last loss, last gradient norm, steps); (None, None, 0) while its
        buffer holds fewer than ``distill_starts`` samples."""
        cfg = m.cfg
        if len(m.buffer) < cfg.distill_starts:
            return None, None, 0
        loss_value = grad_norm = None
        steps = 0
        for _ in range(cfg.distill_updates):
            for group in m.actor_opt.param_groups:
                group["lr"] = self._lr(m)
            frames, labels = m.buffer.sample(cfg.distill_batch, m.generator)
            loss = F.mse_loss(m.actor.mean(frames), labels)
            m.actor_opt.zero_grad(set_to_none=True)
            loss.backward()
            grad_norm = torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in m.params]))
            m.actor_opt.step()
            m.updates += 1
            steps += 1
            loss_value = float(loss.detach())  # the early stop reads every loss on the host, as the reference
            if not math.isfinite(loss_value):
                raise NonFiniteError(f"iteration {self.iteration + 1}: member {m.index}'s distillation loss is "
                                     f"{loss_value}")
            if loss_value < cfg.distill_loss_threshold:  # the reference's early stop
                break
        return loss_value, float(grad_norm), steps

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def train_iteration(self) -> list[dict]:
        """One iteration (segment, labels, updates); its metrics, one dict per member."""
        cfg = self.cfg
        if cfg.compile and self.compiled is None:
            self.compile()
        if not self._started:
            t_start = time.perf_counter()
            self._start()
            self.start_s = time.perf_counter() - t_start
        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)
        t_wall = time.perf_counter()
        images, states = self._segment()
        for m in self.members:
            m.buffer.append(images[:, m.rows].flatten(0, 1), m.expert(states[:, m.rows].flatten(0, 1)))
        self._sync()
        t_rollout = time.perf_counter()
        updated = [self._update(m) for m in self.members]
        self._sync()
        t_end = time.perf_counter()
        self.iteration += 1
        self.wall_s += t_end - t_wall
        cuda = self.device.type == "cuda"
        shared = {"fwd_ms": (t_rollout - t_wall) * 1e3, "bwd_ms": (t_end - t_rollout) * 1e3, "critic_ms": None,
                  "iter_ms": (t_end - t_wall) * 1e3,
                  "peak_alloc_mb": torch.cuda.max_memory_allocated(self.device) / 2**20 if cuda else None,
                  "peak_reserved_mb": torch.cuda.max_memory_reserved(self.device) / 2**20 if cuda else None}
        out = []
        for m, (loss, grad_norm, steps) in zip(self.members, updated):
            own_steps = self.iteration * cfg.horizon * cfg.num_envs
            out.append({
                "iter": self.iteration,
                "env_steps": m.expert.env_steps + own_steps,
                "wall_s": m.expert.wall_s + self.wall_s,
                "student_env_steps": own_steps,
                "student_wall_s": self.wall_s,
                "expert_wall_s": m.expert.wall_s,
                "expert_env_steps": m.expert.env_steps,
                "return_mean": sum(m.recent_returns) / len(m.recent_returns) if m.recent_returns else None,
                "episode_length_mean": (sum(m.recent_lengths) / len(m.recent_lengths)
                                        if m.recent_lengths else None),
                "episodes": len(m.recent_returns),
                "actor_loss": loss,
                "critic_loss": None,
                "grad_norm": grad_norm,
                "grad_norm_clipped": grad_norm,  # the reference does not clip the student's gradient
                "updates": steps,
                "updates_total": m.updates,
                "buffer_size": len(m.buffer),
                **shared,
                "actor_lr": m.actor_opt.param_groups[0]["lr"],
                "probed": False,
                "graph": False,
            })
        return out

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, *, video_steps: int = 0, video_size: int = 256) -> list[dict]:
        """Each student's deterministic policy ``tanh(student(frames))`` on the toolkit's evaluation (whole
        episodes of ``eval_envs`` environments from the fixed evaluation seed; ``gradlab.evaluation``), as
        :meth:`gradlab.SHAC.evaluate` returns it."""
        return self.evaluator(capture=False, video_steps=video_steps, video_size=video_size)

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> list[dict]:
        """Per member everything but its buffer (module docstring): the clock, the
        student, its optimiser and generator, its rows of the task, frames and episode counters, where its expert
        came from."""
        task, frames = self.task.get_state(), self.frames.state_dict()
        seeds, counter = task["rng"][:-1], task["rng"][-1:]
        states = []
        for m in self.members:
            own_task = {k: v[m.rows] for k, v in task.items() if k != "rng"}
            own_task["rng"] = torch.cat([seeds[m.index:m.index + 1], counter])
            states.append({
                "config": dataclasses.asdict(m.cfg), "iteration": self.iteration, "wall_s": self.wall_s,
                "started": self._started, "actor": m.actor.state_dict(), "actor_opt": m.actor_opt.state_dict(),
                "updates": m.updates, "generator": m.generator.get_state(), "task": own_task,
                "frames": dict(frames, frames=[f[m.rows] for f in frames["frames"]]),
                "episode_return": self.episode_return[m.rows].clone(),
                "episode_length": self.episode_length[m.rows].clone(),
                "recent_returns": list(m.recent_returns), "recent_lengths": list(m.recent_lengths),
                "expert": {"source": m.expert.source, "wall_s": m.expert.wall_s, "env_steps": m.expert.env_steps,
                           "iterations": m.expert.iterations},
                "rng": rng_state()})
        return states

    def load_state_dict(self, states: Sequence[dict]) -> None:
        """Restore :meth:`state_dict` (one dict per member, in any order: ``members.match_states``); the buffers
        start empty and refill (module docstring)."""
        ordered = members.match_states(self.members, states)
        first = ordered[0]
        self.iteration, self.wall_s, self._started = first["iteration"], first["wall_s"], first["started"]
        for m, s in zip(self.members, ordered):
            m.actor.load_state_dict(s["actor"])
            m.actor_opt.load_state_dict(s["actor_opt"])
            m.updates = s["updates"]
            m.generator.set_state(s["generator"].cpu())
            m.recent_returns = deque(s["recent_returns"], maxlen=100)
            m.recent_lengths = deque(s["recent_lengths"], maxlen=100)
        task, frames, episode_return, episode_length = members.joined_state(ordered)
        self.task.set_state(task)
        self.frames.load_state_dict(frames, device=self.device)
        self.episode_return.copy_(episode_return)
        self.episode_length.copy_(episode_length)
        set_rng_state(first["rng"])

    def expert_record(self) -> list[dict]:
        """Per member: the expert's checkpoint and what training it cost (JSON-ready)."""
        return [{"source": m.expert.source, "wall_s": m.expert.wall_s, "env_steps": m.expert.env_steps,
                 "iterations": m.expert.iterations} for m in self.members]
