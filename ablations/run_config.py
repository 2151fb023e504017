"""``ablate``'s settings: a run's (:class:`RunConfig`: the trainer's settings and the run options) and the command
line's (:class:`AblateConfig`: the same with several values of a member's own axes, or members listed one by one),
and the one reading of the words that name members (``--member k=v,...`` and the several-valued flags).

A single run is a population of one: :meth:`AblateConfig.members` gives the runs a command line stands for, one
or many, each a :class:`RunConfig`.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import typing
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

from gradlab.config import ModePlan, SHACConfig, check_as_given
from gradlab.config_checks import check_integers, check_number
from vocabulary import MEMBER_FIELDS

__all__ = ["RunConfig", "AblateConfig", "shac_part", "check_shared", "default_threads", "RESUMABLE", "AXES",
           "check_given_flags", "SWEEP_WIDE"]

#: Settings a resume may change (where it runs, how long it goes on); config.json wins for every other one.
RESUMABLE = ("device", "iters", "time_limit_min", "compile_cache", "threads", "compile_helper")
#: The member settings ``ablate`` takes several values of (a population of every combination), in product order.
AXES = ("mode", "raster_model", "preset", "seed")
#: Most CPU threads a run takes by default: the simulator's and networks' tensors are small, so more threads add
#: synchronisation more than speed.
MAX_DEFAULT_THREADS = 8


@dataclass
class RunConfig(SHACConfig):
    """Train SHAC on a task with full, decoupled (D.Va) or state policy gradients, and measure them."""

    device: str = "auto"
    """auto (CUDA when present, else CPU), cpu, or cuda[:N]."""
    threads: int | None = None
    """CPU threads of torch in this process (and OMP_NUM_THREADS / MKL_NUM_THREADS of the processes it starts);
    recorded in config.json. None: $OMP_NUM_THREADS where set, else half the cores this process may use, at least
    1 and at most 8, so that a run leaves room on a shared machine (two runs each taking every core are many
    times slower than both with half). On the CPU the thread count changes the metrics' last bits."""
    out: Path = Path("runs")
    """Parent folder of the run folder."""
    name: str | None = None
    """Run folder name; None: <task>_<mode>_seed<seed>_<date>-<time>."""
    resume: Path | None = None
    """Continue the run in this folder from its newest readable checkpoint. Its config.json wins over other flags
    except --device, --iters, --time-limit-min, --compile-cache and --threads, which a resume may change (e.g. to
    train the same run longer). metrics.jsonl keeps every readable line up to the checkpoint's iteration; lines
    after it (iterations the resume trains again) and damaged lines are moved to metrics.jsonl.redone-<time> and
    metrics.jsonl.damaged-<time> beside it, each named in one line (a last line cut off mid-write is dropped).
    A folder without a checkpoint is refused unless --restart is given."""
    restart: bool = False
    """With --resume of a folder that holds no checkpoint (the run stopped before its first one): train it again
    from iteration 1 in that folder, its old metrics.jsonl, summary.json and videos/ kept beside under the suffix
    .before-restart-<time>. A folder with a checkpoint resumes from it either way."""
    checkpoint_every: int = 50
    """Iterations between checkpoints (and always at the end, and when a signal or an error stops the run: the
    last finished iteration is checkpointed then, from a copy the run holds in memory)."""
    keep_checkpoints: int = 2
    """Checkpoints kept on disk (oldest deleted); more than one lets a resume survive a damaged newest one."""
    video_every: int = 100
    """Iterations between evaluation videos (MP4 of the deterministic policy; also at the end); 0 disables."""
    video_steps: int | None = 300
    """Steps per evaluation video (at most one episode; 300 steps = 5 s at 60 fps); None: one episode."""
    time_limit_min: float | None = None
    """Stop cleanly (final checkpoint, video and summary) once the run's training wall-clock (the sum of its
    iterations' times, compilation included, carried across --resume) reaches this many minutes; None: run all
    iterations."""
    warmup_iters: int = 2
    """Iterations excluded from the timing medians in summary.json (allocator and kernel warm-up)."""
    tensorboard: bool = False
    """Also log the metrics to TensorBoard (needs the tensorboard package) in <run>/tb."""
    progress: bool = True
    """Show a progress bar: ret= the training return (mean of the last 100 finished training episodes of the
    exploring policy; - before the first ends), eval= the last deterministic evaluation return, ms= the
    iteration's wall-clock milliseconds, gn= the actor's gradient norm before clipping."""
    compile_cache: str | None = None
    """With --compile: the root folder of torch.compile's caches (a subfolder per torch/Triton/device version;
    delete it to start cold); None: $PIXELGRAD_COMPILE_CACHE, else ~/.cache/pixelgrad/compile; 'off': torch's
    own cache locations and no artifact file."""
    compile_helper: bool = True
    """With --compile on a GPU and nothing compiled for these settings yet: helper processes compile the rest of
    the physics, the renderer and the networks while this one compiles the physics substep, into the same cache
    (ablations/startup/helpers.py); --no-compile-helper compiles everything in this process."""

    eval_final_every: int = 0
    """With --eval-final-from: evaluate also every this many iterations from that iteration on (a denser schedule
    in the window a final return averages), beside every --eval-every-th; 0: no denser window."""
    eval_final_from: int | None = None
    """The first iteration of the denser evaluation window (--eval-final-every): evaluations at this iteration,
    then every --eval-final-every iterations after it; None: none."""

    def evaluates_at(self, iteration: int, ended: bool = False) -> bool:
        """Whether iteration ``iteration`` (iterations done, 1-based) is followed by an evaluation: every
        --eval-every-th, every --eval-final-every-th from --eval-final-from on, and the last (``ended``) where
        either schedule is on."""
        every, dense, start = self.eval_every, self.eval_final_every, self.eval_final_from
        if ended and (every or (dense and start is not None)):
            return True
        if every and iteration % every == 0:
            return True
        return bool(dense) and start is not None and iteration >= start and (iteration - start) % dense == 0

    def validate(self) -> None:
        """SHACConfig's checks plus the run options'; every error names its flag."""
        super().validate()
        self.check_run_options()

    def check_run_options(self) -> None:
        """The run options' checks alone (the trainer's settings are checked where they are resolved:
        ``gradlab.roster.Roster``); every error names its flag."""
        check_integers(self, ("eval_final_every",), minimum=0)
        check_integers(self, ("eval_final_from",), minimum=1, optional=True)
        if bool(self.eval_final_every) != (self.eval_final_from is not None):
            raise ValueError("--eval-final-every and --eval-final-from go together: give both (a denser "
                             f"evaluation window from an iteration on) or neither, got --eval-final-every "
                             f"{self.eval_final_every} and --eval-final-from {self.eval_final_from}")
        check_integers(self, ("checkpoint_every", "keep_checkpoints"), minimum=1)
        check_integers(self, ("threads", "video_steps"), minimum=1, optional=True)
        check_integers(self, ("video_every", "warmup_iters"), minimum=0)
        if self.time_limit_min is not None:
            check_number("time_limit_min", self.time_limit_min, "(0, inf)")
        if self.compile_cache is not None and not self.compile_cache.strip():
            raise ValueError("--compile-cache is empty: give a folder, or 'off' for torch's own cache locations")


def shac_part(cfg: RunConfig) -> SHACConfig:
    """The SHACConfig fields of a RunConfig."""
    names = {f.name for f in dataclasses.fields(SHACConfig)}
    return SHACConfig(**{k: v for k, v in dataclasses.asdict(cfg).items() if k in names})


def default_threads() -> int:
    """$OMP_NUM_THREADS where it is a positive integer, else half the cores this process may use (its CPU
    affinity), at least 1 and at most ``MAX_DEFAULT_THREADS``."""
    env = os.environ.get("OMP_NUM_THREADS", "")
    if env.isdigit() and int(env) > 0:
        return int(env)
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity outside Linux
        cores = os.cpu_count() or 1
    return max(1, min(MAX_DEFAULT_THREADS, cores // 2))


def check_shared(members: list[RunConfig]) -> None:
    """Run options (not trainer settings) that a population's members must share, named as flags."""
    trainer_fields = {f.name for f in dataclasses.fields(SHACConfig)}
    for name in (f.name for f in dataclasses.fields(RunConfig)):
        if name in trainer_fields or name in ("resume", "name", "restart"):
            continue
        values = {repr(getattr(m, name)) for m in members}
        if len(values) > 1:
            raise ValueError(f"the members of one population share --{name.replace('_', '-')}, got "
                             f"{' and '.join(sorted(values))}")


#: The environment variable a sweep's worker sets for the ``ablate`` it starts: its flags are sweep-wide (``--set``
#: of ``ablate-sweep`` or ``ablate-paper``), given for every run of a grid, so :func:`check_given_flags` exempts them.
SWEEP_WIDE = "PIXELGRAD_SWEEP_WIDE"


def check_given_flags(members: list[RunConfig], given: Collection[str]) -> None:
    """The project's rule (``gradlab.config.check_as_given``) for settings whose being given, not their value,
    is what a run's options cannot show: a flag in ``given`` (the fields set on the command line) that means
    nothing for the run, or for every member of a population (a population-wide flag that acts for some member
    is kept), is refused; ValueError naming the flags."""
    first = members[0]

    def none(means) -> bool:
        return not any(means(m) for m in members)

    if "video_steps" in given and none(lambda m: m.video_every > 0):
        raise ValueError(f"--video-steps {first.video_steps} means nothing with --video-every 0: no video is "
                         f"recorded; drop it, or give --video-every N")
    if "eval_envs" in given and none(lambda m: m.video_every > 0 or m.eval_every > 0):
        raise ValueError(f"--eval-envs {first.eval_envs} means nothing with --eval-every 0 --video-every 0: "
                         f"nothing is evaluated; drop it, or give --eval-every N")
    if "cosine_every" in given and first.cosine_every and none(lambda m: ModePlan.of(m.mode).probes):
        modes = " ".join(dict.fromkeys(m.mode for m in members))
        raise ValueError(f"--cosine-every {first.cosine_every} means nothing with --mode {modes}: probe iterations "
                         f"compare the gradients through the images, and this actor's do not depend on them")
    for name in ("sigma", "render_gamma"):
        if name in given and none(lambda m: ModePlan.of(m.mode).actor_input != "state"):
            raise ValueError(f"--{name.replace('_', '-')} {getattr(first, name)} means nothing with --mode state: "
                             f"it shapes the rendered images, and a state actor sees none")


# ---------------------------------------------------------------------------------------------- the command line
@dataclass
class _Ablate(RunConfig):
    """Train SHAC on a task with full, decoupled (D.Va), blind or state policy gradients, and measure them.
    Several values of --mode, --seed, --raster-model or --preset train every combination as one population in
    this process (one batched simulation; each member a run of its own, in its own run folder)."""

    member: tuple[str, ...] = ()
    """Population members one by one instead of a product: each 'mode=full,seed=0[,raster_model=hard][,preset=P]
    [,other=V]' with settings a member may have of its own (vocabulary.MEMBER_FIELDS); the other flags are the
    population's. Not with several values of --mode, --seed, --raster-model or --preset."""

    def members(self) -> list[RunConfig]:
        """The runs these options stand for: one (a single run), or a population's members; ValueError naming the
        flag for options that do not make one."""
        return [member for member, _ in self._members()]

    def checked_members(self) -> list[RunConfig]:
        """:meth:`members`, each validated as given (before a preset fills in); ValueError naming the flag, or the
        ``--member`` entry and its words for a listed member's own settings."""
        out = []
        for member, entry in self._members():
            try:
                member.validate()
                check_as_given(member)
            except ValueError as e:
                if entry is None:
                    raise
                spec, words = entry
                message = str(e)
                for key, raw in words:
                    flag = "--" + key.replace("_", "-")
                    message = message.replace(f"{flag} {raw}", f"{key}={raw}").replace(flag, key)
                raise ValueError(f"--member {spec!r}: {message}") from None
            out.append(member)
        return out

    def _members(self) -> list[tuple[RunConfig, tuple[str, list[tuple[str, str]]] | None]]:
        """(run, its --member entry and that entry's (key, raw value) words, or None for a product's run)."""
        base = {f.name: getattr(self, f.name) for f in dataclasses.fields(RunConfig) if f.name not in AXES}
        values = {name: (None,) if getattr(self, name) is None else getattr(self, name) for name in AXES}
        for name, vals in values.items():
            if len(set(vals)) != len(vals):
                raise ValueError(f"--{name.replace('_', '-')} lists a value twice: {' '.join(map(str, vals))}")
        if self.member:
            several = [f"--{k.replace('_', '-')}" for k, v in values.items() if len(v) > 1]
            if several:
                raise ValueError(f"--member lists the members one by one: give {' and '.join(several)} one value")
            one = {k: v[0] for k, v in values.items()}
            out = []
            for spec in self.member:
                words = _member_words(spec)
                try:
                    own = {key: _typed(key, raw) for key, raw in words}
                except ValueError as e:
                    raise ValueError(f"--member {spec!r}: {e}") from None
                out.append((RunConfig(**{**base, **one, **own}), (spec, words)))
            return out
        return [(RunConfig(**base, **dict(zip(AXES, combo))), None)
                for combo in itertools.product(*values.values())]


def _member_words(spec: str) -> list[tuple[str, str]]:
    """'mode=full,seed=0,...' -> [("mode", "full"), ("seed", "0"), ...]: a member's own settings as given;
    ValueError naming the entry for a word that is not one."""
    words = []
    for part in filter(None, (p.strip() for p in spec.split(","))):
        key, sep, raw = part.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or key not in MEMBER_FIELDS:
            raise ValueError(f"--member {spec!r}: {part!r} is not a member's own setting (one of "
                             f"{', '.join(MEMBER_FIELDS)}, as key=value)")
        if key in (k for k, _ in words):  # the last would win without a word
            raise ValueError(f"--member {spec!r}: {key} is given twice: give it once")
        words.append((key, raw.strip()))
    if "mode" not in dict(words):
        raise ValueError(f"--member {spec!r}: every member names its mode (mode=...)")
    return words


def _typed(key: str, raw: str):
    """A member word's value typed as its setting's annotation says; ValueError naming the key (as the entry gives
    it) for a value that is not of that type: a seed that is no integer, a wrong number of betas."""
    hint = typing.get_type_hints(RunConfig)[key]
    args = typing.get_args(hint)
    optional = type(None) in args
    kind = next(a for a in args if a is not type(None)) if optional else hint
    if raw.lower() == "none":
        if optional:
            return None
        raise ValueError(f"{key}=none: {key} takes a value")
    if typing.get_origin(kind) is typing.Literal:
        return raw  # validate() names the choices
    if kind is bool:
        if raw.lower() not in ("1", "true", "yes", "0", "false", "no"):
            raise ValueError(f"{key} must be true or false, got {raw!r}")
        return raw.lower() in ("1", "true", "yes")
    if typing.get_origin(kind) is tuple:  # e.g. betas=0.7/0.95
        parts, kinds = raw.split("/"), typing.get_args(kind)
        if Ellipsis not in kinds and len(parts) != len(kinds):
            raise ValueError(f"{key} takes {len(kinds)} values separated by '/', got {len(parts)}: {raw}")
        return tuple(_number(key, x, kinds[0]) for x in parts)
    if kind in (int, float):
        return _number(key, raw, kind)
    return raw


def _number(key: str, raw: str, kind: type):
    try:
        return kind(raw)
    except ValueError:
        raise ValueError(f"{key} must be {'an integer' if kind is int else 'a number'}, got {raw!r}") from None


def _several_valued(cls: type, names: tuple[str, ...]) -> type:
    """``cls`` with each of ``names`` taking one or more values: ``tuple[T, ...]`` of its type ``T`` (None stays
    a possible value of the whole), its default the one value. The fields keep their help (tyro reads it from the
    classes they are declared in)."""
    hints = typing.get_type_hints(cls)
    fields = []
    for f in dataclasses.fields(cls):
        if f.name not in names:
            continue
        args = typing.get_args(hints[f.name])
        optional = type(None) in args
        one = next(a for a in args if a is not type(None)) if optional else hints[f.name]  # T | None: T
        several = tuple[one, ...] | None if optional else tuple[one, ...]
        default = None if f.default is None else (f.default,)
        fields.append((f.name, several, dataclasses.field(default=default)))
    derived = dataclasses.make_dataclass("AblateConfig", fields, bases=(cls,), namespace={"__doc__": cls.__doc__})
    derived.__module__, derived.__qualname__ = cls.__module__, "AblateConfig"
    return derived


#: ``ablate``'s options: a run's settings with several values of :data:`AXES`, and ``--member``.
AblateConfig = _several_valued(_Ablate, AXES)
