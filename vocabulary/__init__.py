"""The toolkit's vocabulary: the names every layer and command shares, and the arms built from them.

Tasks, training modes, renderers, raster models, presets, the settings a population member may hold of its own,
and the arms (a name for a mode, raster model, preset and the flags that set them) are named here once. The
torch-bound code takes its lists from here (``tasks.TASKS``, ``gradlab.config.MODES``, ``diffrender.settings
.RASTER_MODELS``, ``gradlab.presets.PRESETS``, ...), and the reports, ``ablate-paper``, the benchmarks and the
tests read them here, so a list cannot drift from its twin. This package imports nothing of the toolkit and no
torch: it sits beneath every other package of the toolkit (docs/design.md, "Data flow").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType

__all__ = ["TASKS", "MODES", "IMAGELESS_MODES", "STATE_INPUT_MODES", "RENDERERS", "RASTER_MODELS", "PRESETS",
           "SILHOUETTE_RASTER_MODEL", "PRESET_RASTER_MODEL", "PRESET_FIELDS", "MEMBER_FIELDS", "MEMBER_DEFAULTS",
           "NOT_ARM_SETTINGS",
           "Arm", "ARMS", "DEFAULT_ARMS", "ARM_ORDER", "POPULATION_BENCHMARK_ARMS",
           "REFERENCE_ARM", "CONTROL_ARM", "arm_of", "SIM_BACKENDS"]

#: The tasks, in the order tables list them (``tasks.make`` builds each; ``tasks/registry.py`` holds the classes).
TASKS: tuple[str, ...] = ("cartpole", "cartpole-swingup", "hopper", "ant", "humanoid", "cheetah")
#: The training modes (``gradlab.config.ModePlan`` says what each decides; docs/design.md, "Where the mode acts").
MODES: tuple[str, ...] = ("full", "decoupled", "state", "blind", "distill")
#: Modes that render nothing while training: their raster model names no difference.
IMAGELESS_MODES: tuple[str, ...] = ("state", "blind")
#: Modes whose actor reads the state vector: a reference beside the pixel arms, so its cheap iterations never set
#: a comparison's wall-clock budget (``ablations.reports.stats.common_wall_s``).
STATE_INPUT_MODES: tuple[str, ...] = ("state",)
#: What renders the actor's images: the differentiable rasterizer, or the forward-only Warp ray tracer.
RENDERERS: tuple[str, ...] = ("soft", "warp")
#: What runs the simulator (``tasks.TaskConfig.sim_backend``): the PyTorch reference (``tasks.dynamics``) or the
#: same model as Warp kernels (``tasks.warp_sim``).
SIM_BACKENDS: tuple[str, ...] = ("torch", "warp")
#: The image models of ``diffrender.RasterSettings`` (docs/design.md, "Image model").
RASTER_MODELS: tuple[str, ...] = ("hard", "softmax", "alpha")
#: The trainer's presets (``gradlab/presets.py`` holds their values and sources).
PRESETS: tuple[str, ...] = ("dva", "shac-diffrender", "teacher")
#: The soft raster model whose silhouettes carry gradient: what ``--mode full`` uses unless told otherwise.
#: softmax and alpha pass the same share of the image's change at silhouettes to the gradient (BENCHMARKS.md,
#: renderer); softmax also lets the floor hide parts below it and keeps back-face culling (half the work).
SILHOUETTE_RASTER_MODEL = "softmax"
#: The raster model each preset trains with (shac-diffrender: the paper's baseline, the hard rasterizer).
#: (teacher: the state experts of --mode distill, which render nothing while training.)
PRESET_RASTER_MODEL = MappingProxyType({"dva": SILHOUETTE_RASTER_MODEL, "shac-diffrender": "hard",
                                      "teacher": SILHOUETTE_RASTER_MODEL})
#: Config fields a preset sets (every one of them defaults to None in ``gradlab.SHACConfig``).
PRESET_FIELDS = ("num_envs", "actor_lr", "critic_lr", "target_alpha", "trunk_dim", "actor_hidden", "critic_hidden",
                 "lr_decay_iters", "actor_init", "obs_clip", "bootstrap_last_step", "raster_model")
#: Settings the members of one population may differ in: what they train with and how (mode, seed, image
#: model, preset and the learning-rate schedule, initialisation and update settings the preset fills). Every
#: other setting is the population's: one task, batch, horizon, image and network shape, one probe schedule.
MEMBER_FIELDS = ("mode", "seed", "raster_model", "preset", "actor_lr", "critic_lr", "lr_decay_iters",
                 "target_alpha", "actor_init", "betas", "grad_clip", "critic_iterations", "critic_batches",
                 "abort_grad_norm", "encoder_lr_scale", "lr_warmup_iters", "expert")
#: The trainer's defaults of the member settings no preset supplies (``gradlab.SHACConfig`` takes them from here):
#: a run at its default is named without it.
MEMBER_DEFAULTS = MappingProxyType({"betas": (0.7, 0.95), "grad_clip": 1.0, "critic_iterations": 16,
                                    "critic_batches": 4, "abort_grad_norm": 1e8, "encoder_lr_scale": 1.0,
                                    "lr_warmup_iters": 0, "expert": None})
#: config.json settings that do not change what a run trains (where it writes, how often it measures, how long
#: it may run, how it is compiled and on what), besides those an arm is named by (mode, raster_model, preset)
#: and the seed: runs that differ only in these are one arm.
NOT_ARM_SETTINGS = frozenset({
    "task", "seed", "mode", "raster_model", "preset", "name", "out", "resume", "progress", "tensorboard",
    "checkpoint_every", "keep_checkpoints", "video_every", "video_steps", "compile", "compile_cache",
    "compile_helper", "threads", "device", "time_limit_min", "iters", "cosine_every", "eval_every", "eval_envs",
    "warmup_iters", "overlap_critic", "expert", "sim_backend"})


@dataclass(frozen=True)
class Arm:
    """A named way to train: a mode, a preset and, where the preset's is not wanted, a raster model; ``paper``:
    the D.Va paper's method it reproduces (a key of the paper-numbers table the reports read), ``about``: what it
    stands for."""

    name: str
    mode: str
    about: str
    preset: str = "dva"
    #: ``--raster-model`` where the arm sets it; None: the preset's.
    raster_flag: str | None = None
    paper: str | None = None
    flags: dict = field(init=False, compare=False)

    def __post_init__(self):
        flags = {"preset": self.preset} if self.preset != "dva" else {}
        if self.raster_flag is not None:
            flags["raster-model"] = self.raster_flag
        object.__setattr__(self, "flags", flags)  # the ablate flags that make a run of this arm

    @property
    def raster_model(self) -> str | None:
        """The raster model its runs train with; None for a mode that renders nothing."""
        if self.mode in IMAGELESS_MODES:
            return None
        return self.raster_flag or PRESET_RASTER_MODEL[self.preset]

    @property
    def key(self) -> tuple[str, str | None, str]:
        """(mode, raster model, preset): what a run folder's config.json says of its arm."""
        return self.mode, self.raster_model, self.preset


_ARMS = (
    Arm("decoupled", "decoupled", "D.Va: the actor's image input is detached; the dva preset", paper="dva"),
    Arm("full-hard", "full", "the paper's full-APG baseline: gradients through the hard rasterizer (silhouettes "
        "carry none), the baseline's learning-rate decay length", preset="shac-diffrender",
        paper="shac-diffrender"),
    Arm("full-hard-dva", "full", "full-hard's estimator (the hard rasterizer) on the dva preset's learning-rate "
        "schedule (decoupled's): beside full-hard only the schedule differs, beside decoupled only the gradient "
        "estimator", raster_flag="hard"),
    Arm("full-soft", "full", "full APG through this toolkit's default soft raster model (silhouettes carry "
        "gradient); the dva preset"),
    Arm("full-alpha", "full", "full APG through coverage compositing over floor and sky (the other raster model "
        "whose silhouettes carry gradient); the dva preset", raster_flag="alpha"),
    Arm("state", "state", "the actor sees the state vector: the upper bound of learning from pixels"),
    Arm("blind", "blind", "the actor sees a constant black image: the floor of a policy that cannot see"),
    Arm("expert", "state", "a state expert for distill, trained as D.Va's teacher (teacher_student/teacher/<task>"
        ".yaml)", preset="teacher"),
    Arm("distill", "distill", "state-to-visual distillation (D.Va's DAgger baseline): a deterministic visual student "
        "imitates a frozen state expert on its own rollouts (gradlab/distill.py)"),
)
#: The arms, by name (``ablate-paper --arms`` lists them in this order).
ARMS: MappingProxyType[str, Arm] = MappingProxyType({a.name: a for a in _ARMS})
#: The arms ablate-paper runs unless --arms names others: one full arm per kind of image gradient (none at
#: silhouettes, the default soft model's), the hard one also on D.Va's schedule (estimator and schedule apart),
#: the two controls and D.Va.
DEFAULT_ARMS = ("decoupled", "full-hard", "full-hard-dva", "full-soft", "state", "blind")
#: The order reports list the arms in (other arms follow by mode: decoupled, full, state, blind).
ARM_ORDER = ("decoupled", "full-soft", "full-hard", "full-hard-dva", "full-alpha", "state", "blind", "expert",
             "distill")
#: The arms the population and evaluation benchmarks cycle their members through, in that order (a benchmark row's
#: ``arm`` is an index into it).
POPULATION_BENCHMARK_ARMS = ("decoupled", "full-soft", "full-hard-dva", "blind")
#: The arm every other is held against (D.Va), and the control it must beat before any arm is ranked: the
#: visual actor fed a constant black image.
REFERENCE_ARM, CONTROL_ARM = "decoupled", "blind"

_BY_KEY = {a.key: a.name for a in _ARMS}


def arm_of(mode: str, raster_model: str | None, preset: str | None) -> str | None:
    """The name of the arm that trains in ``mode`` with ``raster_model`` (ignored for IMAGELESS_MODES) and
    ``preset``, or None where no arm does."""
    return _BY_KEY.get((mode, None if mode in IMAGELESS_MODES else raster_model, preset))
