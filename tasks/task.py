"""The batched task interface shared by cartpole, hopper, ant, humanoid and cheetah.

A :class:`Task` owns ``num_envs`` copies of one robot: the state tensors (``qpos``, ``qvel``, ``progress``,
``prev_actions``), a :class:`~tasks.dynamics.Simulator`, a counter-based reset RNG and the task's reward,
termination and observation. :meth:`Task.step` is differentiable w.r.t. the action and the previous state,
has static shapes and never synchronises with the host (unless ``validate=True``), and resets finished
environments in place with ``torch.where`` (the new state enters without gradient), so a step can be
compiled and captured in a CUDA graph.

Subclasses set the class attributes (``name``, ``asset``, ``camera``, ``Config``, ``num_obs``) and implement
``initial_state``, ``observe``, ``compute_reward`` and ``compute_terminated``.
"""

from __future__ import annotations

import abc
import dataclasses
import functools
import math
import os
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import torch

from vocabulary import SIM_BACKENDS

from . import _pdl
from .dynamics import ContactParams, LimitParams, Simulator
from .model import ArticulatedModel, load_model
from .rng import CounterRNG

__all__ = ["ASSETS", "DEFAULT_INDUCTOR_OPTIONS", "PHYSICS_PARTS", "CameraSpec", "CompiledCall", "Task", "TaskConfig"]

#: The separately compiled pieces of a control step (:meth:`Task.compile_table`): the physics substep, the
#: mass-matrix factorisation and the per-step reward/observation/reset. Each is its own graph, and with its backward
#: its own compile work, so separate processes can compile them at the same time.
PHYSICS_PARTS = ("substep", "factorize", "finish")

ASSETS = Path(__file__).resolve().parent / "assets"
#: inductor options of the physics parts (:meth:`Task.compile_table` says why each one is there)
DEFAULT_INDUCTOR_OPTIONS = {"combo_kernels": True, "unroll_reductions_threshold": 32, "triton.enable_pdl": True}


@dataclass(frozen=True)
class CameraSpec:
    """Where the task's camera looks from (docs/design.md, "Image model"). ``eye`` and ``target`` [m] are
    offsets from the tracked root position (``root_body``'s origin) on the tracked axes (``track``: "none"
    fixed, "xz" or "xyz"); with ``track="none"`` they are world coordinates. Images are ``height x width``
    RGB."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    fov_deg: float
    track: Literal["none", "xz", "xyz"]
    root_body: str
    height: int = 84
    width: int = 84


def _env_flag(name: str) -> bool:
    return os.environ.get(name, "").strip().lower() not in ("", "0", "false", "no")


@dataclass(frozen=True)
class TaskConfig:
    """Task settings; any field can be overridden by keyword in :func:`tasks.make`.

    episode_length: control steps before truncation. substeps: semi-implicit Euler substeps per control step
    (dt = 1/60 s per control step). early_termination: end episodes on the task's failure condition (an
    invalid state - NaN/inf or |value| > 1e6 - always ends the episode). contact: ground contact on/off.
    contact_ke [N/m], contact_kd [N s/m^2], contact_kf [N s/m], contact_mu: dflex contact parameters.
    limit_ke [N m/rad], limit_kd [N m s/rad], limit_damping: joint-limit penalty (see
    :class:`tasks.dynamics.LimitParams`; "always" is dflex's behaviour). action_scale: torque = clip(a, -1, 1)
    * gear * action_scale. mass_matrix_every: recompute the mass matrix and its inverse every this many substeps
    and reuse it in between (dflex's "MM caching", which SHAC used once per control step; None = substeps,
    1 = every substep). linalg: how the mass matrix is inverted ("library": cuSOLVER/LAPACK; "torch": the same
    Cholesky in plain tensor ops, e.g. where a solver library cannot be captured in a CUDA graph).
    reset_noise: randomise reset states (False: the nominal start state).
    sim_backend: what runs the substeps of :meth:`Task.step`: "torch" (:class:`~tasks.dynamics.Simulator`, the
    reference) or "warp" (:class:`~tasks.warp_sim.WarpSimulator`, the same model as Warp kernels, a launch a
    substep; ``sim`` stays the torch simulator for everything else a task computes). ``linalg`` and
    ``compile``'s substep and factorize parts act on the torch backend only.
    validate: check actions for NaN/inf on every step (a host sync; default from env var TASKS_VALIDATE).
    """

    episode_length: int = 1000
    substeps: int = 16
    early_termination: bool = True
    contact: bool = True
    contact_ke: float = 0.0
    contact_kd: float = 0.0
    contact_kf: float = 0.0
    contact_mu: float = 0.0
    limit_ke: float = 1.0e3
    limit_kd: float = 1.0e1
    limit_damping: Literal["always", "violated"] = "always"
    action_scale: float = 1.0
    mass_matrix_every: int | None = None
    linalg: Literal["library", "torch"] = "library"
    reset_noise: bool = True
    sim_backend: Literal["torch", "warp"] = "torch"
    validate: bool = field(default_factory=lambda: _env_flag("TASKS_VALIDATE"))

    def __post_init__(self) -> None:
        if not (isinstance(self.episode_length, int) and self.episode_length >= 1):
            raise ValueError(f"episode_length must be a positive int, got {self.episode_length!r}")
        if not (isinstance(self.substeps, int) and self.substeps >= 1):
            raise ValueError(f"substeps must be a positive int, got {self.substeps!r}")
        if self.mass_matrix_every is not None and not (
            isinstance(self.mass_matrix_every, int) and self.mass_matrix_every >= 1
        ):
            raise ValueError(f"mass_matrix_every must be None or a positive int, got {self.mass_matrix_every!r}")
        if self.linalg not in ("library", "torch"):
            raise ValueError(f"linalg must be 'library' or 'torch', got {self.linalg!r}")
        if self.sim_backend not in SIM_BACKENDS:
            raise ValueError(f"sim_backend must be one of {', '.join(SIM_BACKENDS)}, got {self.sim_backend!r}")
        if self.limit_damping not in ("always", "violated"):
            raise ValueError(f"limit_damping must be 'always' or 'violated', got {self.limit_damping!r}")
        for name in ("contact_ke", "contact_kd", "contact_kf", "contact_mu", "limit_ke", "limit_kd"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v >= 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")


@dataclass(frozen=True)
class CompiledCall:
    """A callable that ``--compile`` runs through ``torch.compile``, and where it is called from:
    ``owner.<attr>``. :meth:`compile` puts ``torch.compile(fn, **options)`` there (which compiles at its first
    call), :meth:`run_eagerly` puts ``eager`` back (``fn`` where None).

    ``options`` are torch.compile's keyword arguments; their inductor ``options`` are merged under a caller's, and
    dropped for a caller's ``mode`` or another backend (torch.compile takes a mode or options, not both);
    programmatic dependent launch in them is made race-free (``tasks._pdl``)."""

    owner: Any
    attr: str
    fn: Callable
    options: dict[str, Any] = field(default_factory=lambda: {"dynamic": False})
    eager: Callable | None = None

    def compile(self, **overrides: Any) -> None:
        import torch._dynamo.config as dynamo_config

        # Dynamo keeps one guard set per batch size, dtype, device and grad pattern of a compiled function's
        # inputs, shared by every object whose method it compiled (every Task shares the compiled substep's code).
        # Past its default limit of 8 it quietly runs the function eagerly for the rest of the process.
        dynamo_config.recompile_limit = max(getattr(dynamo_config, "recompile_limit", 8), 64)
        kw = {**{k: v for k, v in self.options.items() if k != "options"}, **overrides}
        inductor = {**self.options.get("options", {}), **(overrides.get("options") or {})}
        if inductor and "mode" not in kw and kw.get("backend", "inductor") == "inductor":
            kw["options"] = _pdl.options(inductor)
        setattr(self.owner, self.attr, torch.compile(self.fn, **kw))

    def run_eagerly(self) -> None:
        setattr(self.owner, self.attr, self.fn if self.eager is None else self.eager)


@functools.cache
def _cached_model(path: str) -> ArticulatedModel:
    return load_model(path)


def _resolve_device(device: torch.device | str) -> torch.device:
    d = torch.device(device)
    if d.type == "cuda" and d.index is None:
        d = torch.device("cuda", torch.cuda.current_device())
    return d


class Task(abc.ABC):
    """``num_envs`` environments of one task; see the module docstring and docs/design.md, "Simulator model".

    Attributes: name, num_envs, num_obs, num_act, episode_length, dt [s] (control step, 1/60), substeps,
    device, dtype, mjcf_path (str), sim (:class:`~tasks.dynamics.Simulator`), qpos (B, nq), qvel (B, nv),
    progress (B,) long (control steps since the last reset), prev_actions (B, num_act) (the last clipped
    action; zero after a reset), camera (:class:`CameraSpec`), config (:class:`TaskConfig`).
    """

    name: ClassVar[str]
    asset: ClassVar[str]
    camera: ClassVar[CameraSpec]
    Config: ClassVar[type[TaskConfig]] = TaskConfig
    num_obs: ClassVar[int]
    noise_dim: ClassVar[int]  # uniforms per environment consumed by one reset draw
    dt: ClassVar[float] = 1.0 / 60.0
    #: The attributes that are the environments' state: what one control step hands to the next, and so what a
    #: snapshot (:meth:`get_state`), a checkpoint and the CUDA graphs' fixed tensors (gradlab.graphs.LiveState)
    #: hold. The reset RNG's counter is state too; it keeps its own (``rng.get_state``).
    STATE_TENSORS: ClassVar[tuple[str, ...]] = ("qpos", "qvel", "progress", "prev_actions")

    def __init__(
        self,
        num_envs: int,
        *,
        device: torch.device | str = "cpu",
        seed: int | Sequence[int] = 0,
        dtype: torch.dtype = torch.float32,
        config: TaskConfig | None = None,
    ) -> None:
        if not (isinstance(num_envs, int) and num_envs >= 1):
            raise ValueError(f"num_envs must be a positive int, got {num_envs!r}")
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        self.config = config if config is not None else self.Config()
        cfg = self.config
        self.num_envs = num_envs
        self.device = _resolve_device(device)
        self.dtype = dtype
        # One seed, or one per equal group of environments (a population of runs simulated as one batch: each
        # group's resets are those its run would draw alone, tasks.rng)
        self.seed = int(seed) if isinstance(seed, int) else tuple(int(s) for s in seed)
        self.mjcf_path = str(ASSETS / self.asset)
        self.model = _cached_model(self.mjcf_path)
        contact = None
        if cfg.contact and cfg.contact_ke > 0:
            contact = ContactParams(cfg.contact_ke, cfg.contact_kd, cfg.contact_kf, cfg.contact_mu)
        limits = LimitParams(cfg.limit_ke, cfg.limit_kd, cfg.limit_damping)
        self.sim = Simulator(
            self.model, device=self.device, dtype=dtype, contact=contact, limits=limits, linalg=cfg.linalg
        )
        self.warp_sim = None
        if cfg.sim_backend == "warp":
            from .warp_sim import WarpSimulator

            self.warp_sim = WarpSimulator(self.model, device=self.device, dtype=dtype, contact=contact, limits=limits)
        self.num_act = self.model.nu
        self.episode_length = cfg.episode_length
        self.substeps = cfg.substeps
        self.rng = CounterRNG(num_envs, self.noise_dim, seed=self.seed, device=self.device)
        self._substep: Callable = self._chained_substep
        self._factorize: Callable = self.sim.factorize
        self.mass_matrix_every = cfg.mass_matrix_every or cfg.substeps
        self._finish: Callable = self._finish_impl
        qpos, qvel = self.initial_state(None)
        self.qpos, self.qvel = qpos, qvel
        self.progress = torch.zeros(num_envs, dtype=torch.long, device=self.device)
        self.prev_actions = torch.zeros(num_envs, self.num_act, dtype=dtype, device=self.device)

    # ------------------------------------------------------------------------------------------------------
    # task-specific hooks
    @abc.abstractmethod
    def initial_state(self, u: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Reset states from uniforms ``u (B, noise_dim)`` in [0, 1) (None: the nominal start state)."""

    @abc.abstractmethod
    def observe(self, qpos: torch.Tensor, qvel: torch.Tensor, prev_actions: torch.Tensor) -> torch.Tensor:
        """State observation (B, num_obs)."""

    @abc.abstractmethod
    def compute_reward(self, qpos: torch.Tensor, qvel: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Reward (B,) of reaching (qpos, qvel) with the clipped ``action``."""

    @abc.abstractmethod
    def compute_terminated(self, qpos: torch.Tensor, qvel: torch.Tensor) -> torch.Tensor:
        """Task failure condition (B,) bool (applied when ``early_termination``)."""

    # ------------------------------------------------------------------------------------------------------
    # helpers for subclasses
    def _const(self, values) -> torch.Tensor:
        return torch.as_tensor(values, dtype=self.dtype, device=self.device)

    def _noise(self, u: torch.Tensor | None, n: int, start: int, scale: float) -> torch.Tensor | float:
        """Uniform noise in [-scale, scale) from columns [start, start + n) of ``u`` (0 when u is None)."""
        if u is None or not self.config.reset_noise:
            return 0.0
        return (2.0 * u[:, start : start + n] - 1.0) * scale

    # ------------------------------------------------------------------------------------------------------
    # public API
    def reset(self) -> torch.Tensor:
        """Reset every environment (a fresh seeded draw); returns the observation (B, num_obs)."""
        with torch.no_grad():
            qpos, qvel = self.initial_state(self.rng.uniform(self.dtype))
        self.qpos, self.qvel = qpos, qvel
        self.progress = torch.zeros_like(self.progress)
        self.prev_actions = torch.zeros_like(self.prev_actions)
        return self.state_obs()

    def state_obs(self) -> torch.Tensor:
        """Observation of the current state (B, num_obs), differentiable w.r.t. the state."""
        return self.observe(self.qpos, self.qvel, self.prev_actions)

    def step(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        """Advance every environment by one control step (``substeps`` physics substeps).

        action: (B, num_act) in [-1, 1] (clipped; torque = action * gear * action_scale).
        Returns ``obs (B, num_obs)`` (after resets), ``reward (B,)``, ``done (B,) bool`` (terminated or
        truncated) and ``info`` with ``obs_before_reset``, ``qpos_before_reset``, ``qvel_before_reset``
        (differentiable; the state this step reached), ``terminated`` and ``truncated`` (B,) bool, and
        ``invalid`` (a non-finite or runaway state, a kind of termination) and ``time_limit`` (the episode
        reached its length, whether or not it also terminated), (B,) bool. Finished environments are reset in
        place (new state without gradient; ``progress`` and ``prev_actions`` zeroed).
        """
        self._check_action(action)
        a = torch.clamp(action, -1.0, 1.0)
        tau = self.sim.actuator_force(a * self.config.action_scale)
        h = self.dt / self.substeps
        qpos, qvel = self.qpos, self.qvel
        if self.warp_sim is not None:
            qpos, qvel = self.warp_sim.step(qpos, qvel, tau, h, self.substeps, self.mass_matrix_every)
        else:
            M = Minv = None
            for i in range(self.substeps):
                if i % self.mass_matrix_every == 0:
                    M, Minv = self._factorize(qpos)
                qpos, qvel, tau, M = self._substep(qpos, qvel, tau, h, M, Minv)
        (self.qpos, self.qvel, self.progress, self.prev_actions, obs, reward, done, info) = self._finish(
            qpos, qvel, a, self.progress
        )
        return obs, reward, done, info

    def _chained_substep(self, qpos, qvel, tau, h, M, Minv, copy: bool = False):
        """One physics substep that also hands the applied force ``tau`` and the cached mass matrix ``M`` on to
        the next substep; with ``copy`` (the compiled path) as new tensors of the same values. Every substep of
        a control step reads the same ``tau`` and ``M``: passed along a chain instead of fanned out, their
        gradients add up inside each substep's compiled backward rather than in one more autograd
        accumulation kernel per substep and tensor."""
        qpos, qvel = self.sim.substep(qpos, qvel, tau, h, (M, Minv))
        if copy:
            tau, M = tau.clone(), M.clone()
        return qpos, qvel, tau, M

    def _finish_impl(self, qpos, qvel, a, progress):
        """Reward, termination, truncation and the in-place reset of finished environments."""
        obs_before = self.observe(qpos, qvel, a)
        reward = self.compute_reward(qpos, qvel, a)
        invalid = ~(torch.isfinite(qpos).all(-1) & torch.isfinite(qvel).all(-1))
        invalid = invalid | (qpos.abs() > 1e6).any(-1) | (qvel.abs() > 1e6).any(-1)
        terminated = invalid
        if self.config.early_termination:
            terminated = terminated | self.compute_terminated(qpos, qvel)
        progress = progress + 1
        truncated = (progress >= self.episode_length) & ~terminated
        done = terminated | truncated
        with torch.no_grad():  # fresh noise for every env every step: no data-dependent shapes
            q0, v0 = self.initial_state(self.rng.uniform(self.dtype))
        d = done[:, None]
        new_qpos = torch.where(d, q0, qpos)
        new_qvel = torch.where(d, v0, qvel)
        new_prev = torch.where(d, torch.zeros_like(a), a)
        new_progress = torch.where(done, torch.zeros_like(progress), progress)
        obs = self.observe(new_qpos, new_qvel, new_prev)
        info = {
            "obs_before_reset": obs_before,
            "qpos_before_reset": qpos,
            "qvel_before_reset": qvel,
            "terminated": terminated,
            "truncated": truncated,
            "invalid": invalid,
            "time_limit": progress >= self.episode_length,
        }
        return new_qpos, new_qvel, new_progress, new_prev, obs, reward, done, info

    def detach(self, *, requires_grad: bool = False) -> None:
        """Cut the autograd graph at the current state (call at every SHAC window start).

        With ``requires_grad`` the cut state (``qpos``, ``qvel``) is a fresh leaf that requires grad, so that the
        first control step sees the same grad pattern as every later one: a compiled step then has one guard
        set (one compilation) instead of one per pattern (three for the substep: the start state, the first
        step's later substeps, the later steps' mass matrices). Gradients into the parameters are unchanged
        (eagerly to the bit; compiled, to float rounding, as the first step then runs the later steps' graphs);
        the leaf's own gradient is computed and dropped, a few more backward kernels per window (their cost:
        BENCHMARKS.md, section 1).
        """
        self.qpos = self.qpos.detach()
        self.qvel = self.qvel.detach()
        if requires_grad:
            self.qpos.requires_grad_(True)
            self.qvel.requires_grad_(True)
        self.prev_actions = self.prev_actions.detach()

    def state_tensors(self) -> dict[str, torch.Tensor]:
        """The state (:data:`STATE_TENSORS`) by name: the task's own tensors, not copies."""
        return {k: getattr(self, k) for k in self.STATE_TENSORS}

    def use_state_tensors(self, tensors: Mapping[str, torch.Tensor]) -> None:
        """Point the task at these tensors (every :data:`STATE_TENSORS` name, taken as they are: no copy)."""
        for k in self.STATE_TENSORS:
            setattr(self, k, tensors[k])

    def get_state(self) -> dict[str, torch.Tensor]:
        """Copies of the state tensors (:data:`STATE_TENSORS`) and the reset RNG state (``rng``)."""
        return {**{k: v.detach().clone() for k, v in self.state_tensors().items()}, "rng": self.rng.get_state()}

    def set_state(self, state: dict[str, torch.Tensor]) -> None:
        """Restore a :meth:`get_state` dict (tensors are copied to this task's device, each state tensor taking the
        dtype of the one it replaces)."""
        current = self.state_tensors()
        expected = {**{k: tuple(v.shape) for k, v in current.items()}, "rng": (self.rng.groups + 1,)}
        missing = set(expected) - set(state)
        if missing:
            raise KeyError(f"set_state: missing keys {sorted(missing)}")
        for k, shape in expected.items():
            if tuple(state[k].shape) != shape:
                raise ValueError(f"set_state: {k} has shape {tuple(state[k].shape)}, expected {shape}")
        self.use_state_tensors({k: state[k].to(self.device, v.dtype).clone() for k, v in current.items()})
        self.rng.set_state(state["rng"])

    def compile_table(self) -> dict[str, CompiledCall]:
        """What ``--compile`` compiles of a control step, by part (:data:`PHYSICS_PARTS`): each part where
        :meth:`step` calls it, with static shapes and :data:`DEFAULT_INDUCTOR_OPTIONS`. The substep is compiled on
        its own (not the whole control step) so that compile time does not grow with ``substeps``; compiled, it
        hands ``tau`` and the mass matrix on as new tensors (:meth:`_chained_substep`).

        A substep is many tiny kernels whose launch latency, not their work, is its time (BENCHMARKS.md section
        3), so each inductor option removes launches or hides their latency, with the same losses: combo kernels
        launch independent small kernels as one; reductions over up to 32 elements (the simulator's 3-, 6- and
        joint-sized sums) are unrolled into the pointwise code around them instead of launching their own
        kernels; programmatic dependent launch (Hopper and newer; a no-op elsewhere) lets each kernel be scheduled
        while the one before it drains, with every kernel waiting before its first access (``tasks._pdl`` says
        which race that avoids)."""
        options = {"dynamic": False, "options": DEFAULT_INDUCTOR_OPTIONS}
        return {
            "substep": CompiledCall(self, "_substep", functools.partial(self._chained_substep, copy=True), options,
                                    eager=self._chained_substep),
            "factorize": CompiledCall(self, "_factorize", self.sim.factorize, options),
            "finish": CompiledCall(self, "_finish", self._finish_impl, options),
        }

    def compile(self, *, parts: Collection[str] = PHYSICS_PARTS, **compile_kwargs: Any) -> Task:
        """Compile the physics substep, the mass-matrix factorisation and the per-step reward/reset with
        ``torch.compile`` (:meth:`compile_table`); ``parts`` names which of them (:data:`PHYSICS_PARTS`), the
        others stay as they are. Keyword arguments go to ``torch.compile`` (inductor ``options`` are merged over
        :data:`DEFAULT_INDUCTOR_OPTIONS` unless a ``mode`` is given). Returns self."""
        table = self.compile_table()
        for part in _check_parts(parts):
            table[part].compile(**compile_kwargs)
        return self

    @contextmanager
    def running_eagerly(self, parts: Collection[str]) -> Iterator[None]:
        """Within the block the named physics parts (:data:`PHYSICS_PARTS`) run eagerly, compiled or not; after
        it, as before. A process that compiles only some parts ahead steps with the others eager, so that it
        does not compile them too (same values: the compiled parts are the same functions)."""
        parts = _check_parts(parts)
        table = self.compile_table()
        kept = {part: getattr(self, table[part].attr) for part in parts}
        for part in parts:
            table[part].run_eagerly()
        try:
            yield
        finally:
            for part, fn in kept.items():
                setattr(self, table[part].attr, fn)

    def _check_action(self, action: torch.Tensor) -> None:
        if not isinstance(action, torch.Tensor):
            raise TypeError(f"{self.name}: action must be a torch.Tensor, got {type(action).__name__}")
        if tuple(action.shape) != (self.num_envs, self.num_act):
            raise ValueError(
                f"{self.name}: action has shape {tuple(action.shape)}, expected (num_envs, num_act) = "
                f"({self.num_envs}, {self.num_act})"
            )
        if action.dtype != self.dtype:
            raise TypeError(f"{self.name}: action dtype is {action.dtype}, the task runs in {self.dtype}")
        if action.device != self.device:
            raise ValueError(f"{self.name}: action is on {action.device}, the task is on {self.device}")
        if self.config.validate and not bool(torch.isfinite(action).all()):
            bad = (~torch.isfinite(action)).any(-1).nonzero().flatten().tolist()
            raise ValueError(f"{self.name}: action has NaN/inf in environments {bad[:10]}")

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(name={self.name!r}, num_envs={self.num_envs}, device={self.device}, "
            f"dtype={self.dtype}, num_obs={self.num_obs}, num_act={self.num_act})"
        )


def _check_parts(parts: Collection[str]) -> tuple[str, ...]:
    if isinstance(parts, str) or not set(parts) <= set(PHYSICS_PARTS):
        raise ValueError(f"physics parts are some of {PHYSICS_PARTS}, got {parts!r}")
    return tuple(parts)


def config_fields(cls: type[TaskConfig]) -> tuple[str, ...]:
    """Names of the overridable fields of a config class."""
    return tuple(f.name for f in dataclasses.fields(cls))
