"""One training run as a folder a researcher can trust, resume and plot.

A run folder holds:
    config.json      the resolved configuration (every flag, preset values filled in), what the preset supplied
                     and which flags overrode it, the start time (UTC) + versions
    git.txt          commit, branch, dirty status and diff stat of the code that ran (git.diff: the full diff)
    metrics.jsonl    one JSON object per iteration (``REQUIRED_KEYS``, plus ``PROBE_KEYS`` on probed iterations)
    summary.json     written at the end (or when the run stops on an error): medians without warm-up, peaks,
                     the seconds from process start to the end of its first iteration (``first_iter_s``) and,
                     with --compile, what was compiled and how much came from the compile cache (``compile``)
    checkpoints/     ckpt_<iter>.pt (the last ``keep_checkpoints``), written atomically; a resume starts from
                     the newest one that loads and renames damaged newer ones to ckpt_<iter>.pt.damaged
    videos/          iter_<iter>.mp4 evaluation rollouts of the deterministic policy
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ablations.startup import Startup
from gradlab.checkpoint import (
    LoadedCheckpoint,
    NoReadableCheckpointError,
    atomic_write_json,
    atomic_write_text,
    checkpoint_path,
    load_newest_readable,
    prune_checkpoints,
    save_checkpoint,
)
from gradlab.config import SHACConfig
from gradlab.presets import PRESET_FIELDS, PRESETS, preset_record
from gradlab.probes import NonFiniteError
from gradlab.seeding import resolve_device
from gradlab.timing import median

__all__ = ["RunConfig", "check_writable", "environment_info", "git_info", "read_metrics", "run", "write_video"]

#: Keys every metrics line has.
REQUIRED_KEYS = ("iter", "env_steps", "wall_s", "return_mean", "actor_loss", "critic_loss", "grad_norm",
                 "grad_norm_clipped", "fwd_ms", "bwd_ms", "peak_alloc_mb", "peak_reserved_mb")
#: Keys added on probed iterations.
PROBE_KEYS = ("cos_full_decoupled", "grad_norm_full", "grad_norm_decoupled", "grad_norm_render_term")
#: Keys that depend on the clock, not on the computation (excluded when comparing runs for determinism).
TIMING_KEYS = ("wall_s", "fwd_ms", "bwd_ms", "critic_ms", "iter_ms", "peak_alloc_mb", "peak_reserved_mb")
_IMPORTED = time.time()  # when no better process start time is known (_process_started)


@dataclass
class RunConfig(SHACConfig):
    """Train SHAC on a task with full, decoupled (D.Va) or state policy gradients, and measure them."""

    device: str = "auto"
    """auto (CUDA when present, else CPU), cpu, or cuda[:N]."""
    out: Path = Path("runs")
    """Parent folder of the run folder."""
    name: str | None = None
    """Run folder name; None: <task>_<mode>_seed<seed>_<date>-<time>."""
    resume: Path | None = None
    """Continue the run in this folder from its last checkpoint. Its config.json wins over other flags except
    --device, --iters, --time-limit-min and --compile-cache, which a resume may change (e.g. to train the same
    run longer)."""
    checkpoint_every: int = 50
    """Iterations between checkpoints (and always at the end)."""
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
    """Show a progress bar."""
    compile_cache: str | None = None
    """With --compile: the root folder of torch.compile's caches (a subfolder per torch/Triton/device version;
    delete it to start cold); None: $PIXELGRAD_COMPILE_CACHE, else ~/.cache/pixelgrad/compile; 'off': torch's
    own cache locations and no artifact file."""
    compile_helper: bool = True
    """With --compile on a GPU and nothing compiled for these settings yet: helper processes compile the rest of
    the physics, the renderer and the networks while this one compiles the physics substep, into the same cache
    (ablations/startup/helpers.py); --no-compile-helper compiles everything in this process."""

    def validate(self) -> None:
        """SHACConfig's checks plus the run options'."""
        super().validate()
        for name in ("checkpoint_every", "keep_checkpoints"):
            v = getattr(self, name)
            if not isinstance(v, int) or v <= 0:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if self.video_every < 0 or self.warmup_iters < 0:
            raise ValueError("video_every and warmup_iters must be >= 0")
        if self.video_steps is not None and self.video_steps <= 0:
            raise ValueError(f"video_steps must be positive, got {self.video_steps}")
        if self.time_limit_min is not None and self.time_limit_min <= 0:
            raise ValueError(f"time_limit_min must be positive, got {self.time_limit_min}")
        if self.compile_cache is not None and not self.compile_cache.strip():
            raise ValueError("compile_cache is empty: give a folder, or 'off' for torch's own cache locations")


def shac_part(cfg: RunConfig) -> SHACConfig:
    """The SHACConfig fields of a RunConfig."""
    names = {f.name for f in dataclasses.fields(SHACConfig)}
    return SHACConfig(**{k: v for k, v in dataclasses.asdict(cfg).items() if k in names})


def git_info(repo: Path | None = None) -> tuple[str, str]:
    """(git.txt text, full diff) of the source tree that runs; explains itself when git is unavailable."""
    repo = repo or Path(__file__).resolve().parents[1]

    def git(*args: str) -> str:
        r = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=30)
        if r.returncode != 0:
            raise RuntimeError(r.stderr.strip())
        return r.stdout

    try:
        commit = git("rev-parse", "HEAD").strip()
        branch = git("rev-parse", "--abbrev-ref", "HEAD").strip()
        status = git("status", "--porcelain")
        stat = git("diff", "HEAD", "--stat")
        diff = git("diff", "HEAD")
    except (OSError, RuntimeError, subprocess.TimeoutExpired) as e:
        return f"git information unavailable: {e}\n", ""
    dirty = bool(status.strip())
    status = status or "(clean)\n"
    stat = stat or "(none)\n"
    text = f"commit {commit}\nbranch {branch}\ndirty {dirty}\n\nstatus:\n{status}\ndiff --stat HEAD:\n{stat}"
    return text, diff


def environment_info(device: torch.device) -> dict:
    info = {
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "platform": platform.platform(),
        "device": str(device),
        "hostname": platform.node(),
    }
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
        info["cuda"] = torch.version.cuda
        # The precision the encoder's convolutions and the linear layers ran in: PyTorch lets cuDNN use TF32
        # for float32 convolutions by default (matmuls stay full float32), which changes gradient bits.
        info["cudnn_allow_tf32"] = torch.backends.cudnn.allow_tf32
        info["float32_matmul_precision"] = torch.get_float32_matmul_precision()
        info["cudnn_benchmark"] = torch.backends.cudnn.benchmark
    try:
        import mujoco
        import pytorch_kinematics

        info["mujoco"] = mujoco.__version__
        info["pytorch_kinematics"] = getattr(pytorch_kinematics, "__version__", "unknown")
    except ImportError:  # pragma: no cover - both are dependencies
        pass
    return info


def read_metrics(run_dir: str | os.PathLike) -> list[dict]:
    """Parsed metrics.jsonl lines; a torn last line (a run killed mid-write) is ignored."""
    path = Path(run_dir) / "metrics.jsonl"
    rows = []
    if not path.exists():
        return rows
    for line in path.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            break
    return rows


def _truncate_metrics(run_dir: Path, upto_iter: int) -> None:
    """Keep metrics lines with iter <= upto_iter (those after the checkpoint will be recomputed)."""
    rows = [r for r in read_metrics(run_dir) if r["iter"] <= upto_iter]
    atomic_write_text(run_dir / "metrics.jsonl", "".join(json.dumps(r) + "\n" for r in rows))


def write_video(path: Path, frames: list[np.ndarray], fps: int = 60) -> None:
    """Frames (H, W, 3) uint8 RGB -> MP4 (mp4v), written to a temp name and renamed."""
    import cv2

    if not frames:
        return
    h, w = frames[0].shape[:2]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.mp4")
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV could not open an MP4 writer for {path}")
    for f in frames:
        writer.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    writer.release()
    os.replace(tmp, path)


def _utc(t: float) -> str:
    """Seconds since the epoch as an ISO-8601 UTC timestamp (what the report prints as started/ended)."""
    return datetime.datetime.fromtimestamp(t, datetime.timezone.utc).isoformat(timespec="seconds")


def _process_started() -> float:
    """When this process started, in seconds since the epoch: from /proc on Linux (interpreter start and imports
    included), else when this module was imported."""
    try:
        # /proc/self/stat field 22 is the start time in clock ticks after boot; the 20th field after the
        # parenthesised command name (which may itself hold spaces)
        ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        boot = next(int(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines()
                    if line.startswith("btime "))
        started = boot + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return _IMPORTED
    # a clock that disagrees with the import time (containers that fake /proc) is not trusted
    return started if 0.0 <= _IMPORTED - started < 3600.0 else _IMPORTED


def _summary(rows: list[dict], cfg: RunConfig, status: str, error: str | None, started: float, *,
             first_iter_s: float | None = None, compiled: dict | None = None,
             startup_s: dict | None = None) -> dict:
    timed = [r for r in rows if r["iter"] > cfg.warmup_iters]
    plain = [r for r in timed if not r.get("probed")]
    probed = [r for r in timed if r.get("probed")]

    def med(key: str, rs: list[dict]) -> float | None:
        vals = [r[key] for r in rs if r.get(key) is not None]
        return median(vals) if vals else None

    def peak(key: str) -> float | None:
        vals = [r[key] for r in rows if r.get(key) is not None]
        return max(vals) if vals else None

    returns = [r["return_mean"] for r in rows if r.get("return_mean") is not None]
    cos = [r["cos_full_decoupled"] for r in rows if r.get("cos_full_decoupled") is not None]
    return {
        "status": status,
        "error": error,
        "ended_utc": _utc(time.time()),
        "task": cfg.task,
        "mode": cfg.mode,
        "seed": cfg.seed,
        "iterations": rows[-1]["iter"] if rows else 0,
        "env_steps": rows[-1]["env_steps"] if rows else 0,
        "wall_s": rows[-1]["wall_s"] if rows else 0.0,
        "final_return": returns[-1] if returns else None,
        "best_return": max(returns) if returns else None,
        "median_fwd_ms": med("fwd_ms", plain),
        "median_bwd_ms": med("bwd_ms", plain),
        "median_critic_ms": med("critic_ms", plain),
        # the critic fit ran alongside the backward (CUDA graphs, overlap_critic): its ms are not in iter_ms
        "critic_overlapped": any(r.get("critic_overlapped", False) for r in plain),
        "median_iter_ms": med("iter_ms", plain),
        "median_iter_ms_probed": med("iter_ms", probed),
        "median_grad_norm": med("grad_norm", rows),
        "median_cos_full_decoupled": median(cos) if cos else None,
        "peak_alloc_mb": peak("peak_alloc_mb"),
        "peak_reserved_mb": peak("peak_reserved_mb"),
        "median_saved_mb": med("saved_mb", plain),
        "warmup_iters_excluded": cfg.warmup_iters,
        "session_seconds": time.time() - started,
        # from this process's start to the end of its first training iteration (imports, setup, compilation)
        "first_iter_s": first_iter_s,
        # seconds of each part of that: imports (process start to ablate's own code), opening the compile cache,
        # building the trainer, its first reset and render, the first iteration (a resumed run: the ones it ran)
        "startup_s": startup_s,
        "compile": compiled,
    }


def check_writable(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        # A unique name: several runs may start in the same folder at once.
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".write-test.")
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise ValueError(f"output folder {folder} is not writable: {e}") from None


def _stored_config(run_dir: Path, cfg_path: Path, overrides: RunConfig) -> RunConfig:
    """The RunConfig of a run folder's config.json; a damaged or foreign file is named in a ValueError."""
    try:
        stored = json.loads(cfg_path.read_text())["config"]
        if not isinstance(stored, dict):
            raise TypeError(f"'config' is a {type(stored).__name__}, not an object")
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"--resume {run_dir}: {cfg_path} cannot be read ({type(e).__name__}: {e}); it is the "
                         f"record of the run's settings, restore it (e.g. from a copy) to resume") from None
    except (KeyError, TypeError) as e:
        raise ValueError(f"--resume {run_dir}: {cfg_path} has no 'config' object ({e}): not written by ablate") \
            from None
    fields = {f.name for f in dataclasses.fields(RunConfig)}
    stored = {k: v for k, v in stored.items() if k in fields}
    for k in ("actor_hidden", "critic_hidden", "betas"):
        if stored.get(k) is not None:
            stored[k] = tuple(stored[k])
    if stored.get("preset") not in PRESETS and all(stored.get(k) is not None for k in PRESET_FIELDS):
        # config.json holds every value a preset supplied, so a run whose preset has no table here (an older
        # folder's) resumes with exactly its values, under the default preset's name
        print(f"note: --resume {run_dir}: preset {stored.get('preset')!r} has no table here; the run resumes with "
              f"the values its config.json records (as --preset {RunConfig.preset} with them set)", file=sys.stderr)
        stored["preset"] = RunConfig.preset
    stored["out"] = Path(stored.get("out", run_dir.parent))
    stored.update(resume=run_dir, progress=overrides.progress)
    # What a resume may change: where it runs, and how long it goes on (a longer run extends the same curve).
    defaults = RunConfig()
    for k in ("device", "iters", "time_limit_min", "compile_cache"):
        if getattr(overrides, k) != getattr(defaults, k):
            stored[k] = getattr(overrides, k)
    try:
        cfg = RunConfig(**stored)
        cfg.validate()
    except (TypeError, ValueError) as e:
        raise ValueError(f"--resume {run_dir}: {cfg_path}: {e}") from None
    return cfg


def _resume_point(run_dir: Path, device: torch.device) -> LoadedCheckpoint:
    """The newest readable checkpoint; damaged newer ones are reported on stderr and renamed aside.

    Renamed (``.damaged`` appended) rather than left in place so that they no longer count among the
    ``keep_checkpoints`` newest files when the resumed run prunes old checkpoints, and kept for inspection.
    """
    try:
        loaded = load_newest_readable(run_dir / "checkpoints", map_location=device)
    except NoReadableCheckpointError as e:
        raise ValueError(f"--resume {run_dir}: {e}") from None
    for path, why in loaded.damaged:
        aside = path.with_name(path.name + ".damaged")
        os.replace(path, aside)
        print(f"warning: checkpoint {path} is damaged ({why}); renamed to {aside.name}, resuming from "
              f"{loaded.path.name}", file=sys.stderr)
    return loaded


def prepare(cfg: RunConfig) -> tuple[RunConfig, Path, torch.device, LoadedCheckpoint | None]:
    """Validate everything and create/locate the run folder, before any expensive work.

    Returns the (resolved) config, the run folder, the device and, on ``--resume``, the checkpoint to start from.
    """
    if cfg.resume is not None:
        run_dir = Path(cfg.resume)
        cfg_path = run_dir / "config.json"
        if not cfg_path.exists():
            raise ValueError(f"--resume {run_dir}: no config.json there (not a run folder)")
        cfg = _stored_config(run_dir, cfg_path, cfg)
        device = resolve_device(cfg.device)
        check_writable(run_dir)
        return cfg, run_dir, device, _resume_point(run_dir, device)
    cfg.validate()
    device = resolve_device(cfg.device)
    name = cfg.name or f"{cfg.task}_{cfg.mode}_seed{cfg.seed}_{time.strftime('%Y%m%d-%H%M%S')}"
    run_dir = Path(cfg.out) / name
    check_writable(Path(cfg.out))
    if run_dir.exists() and any(run_dir.iterdir()):
        raise ValueError(f"run folder {run_dir} exists and is not empty: pass --resume {run_dir} or another --name")
    check_writable(run_dir)
    return cfg, run_dir, device, None


def run(cfg: RunConfig, *, startup: Startup | None = None) -> Path:
    """Train (or resume) a run; returns its folder. Raises ValueError on bad input before any work. ``startup``:
    this process's start-up (``Startup.before_torch``: the bytecode folder, compile helpers on standby); None: one
    that started nothing before torch was imported."""
    started = time.time()
    startup = startup or Startup()
    try:
        cfg, run_dir, device, resume_from = prepare(cfg)
        cache_opened = time.time()
        startup.open(cfg, shac_part(cfg), device, run_dir, resuming=resume_from is not None)
        return _train(cfg, run_dir, device, resume_from, startup, started=started, cache_opened=cache_opened)
    finally:
        startup.close()  # on every way out, an error before the training loop included


def _train(cfg: RunConfig, run_dir: Path, device: torch.device, resume_from: LoadedCheckpoint | None,
           startup: Startup, *, started: float, cache_opened: float) -> Path:
    """The rest of :func:`run` once its folder and start-up are settled: build the trainer, train, write the
    summary."""
    from gradlab.shac import SHAC

    trainer_built = time.time()
    trainer = SHAC(shac_part(cfg), device=device)
    startup.trainer_built(trainer)
    trainer_done = time.time()
    # where the seconds before the first iteration go (summary.json "startup_s"; benchmarks/startup.py): parts
    # that together make up first_iter_s; "run_folder" is the bookkeeping around the trainer (checking the
    # config, the run folder, a checkpoint to resume, git and environment records, the progress bar)
    startup_s = {"imports": started - _process_started(), "compile_cache": trainer_built - cache_opened,
                 "trainer": trainer_done - trainer_built}
    shac_fields = dataclasses.fields(SHACConfig)
    resolved = dataclasses.replace(cfg, **{f.name: getattr(trainer.cfg, f.name) for f in shac_fields})
    ckpt_dir = run_dir / "checkpoints"
    if resume_from is not None:
        trainer.load_state_dict(resume_from.state)
        del resume_from  # not kept alive for the whole run (optimizer states can be large)
        _truncate_metrics(run_dir, trainer.iteration)
    else:
        atomic_write_json(run_dir / "config.json", {
            "config": dataclasses.asdict(resolved),
            # which values the preset supplied and which flags overrode it (flag and preset value side by side)
            "preset": preset_record(shac_part(cfg), trainer.cfg),
            "started_utc": _utc(started),
            "environment": environment_info(device),
            "command": sys.argv,
        })
        text, diff = git_info()
        atomic_write_text(run_dir / "git.txt", text)
        if diff:
            atomic_write_text(run_dir / "git.diff", diff)

    writer = None
    if cfg.tensorboard:
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError as e:
            raise ValueError("--tensorboard needs the tensorboard package: pip install tensorboard") from e
        writer = SummaryWriter(str(run_dir / "tb"))

    from tqdm.auto import tqdm

    base = f"{cfg.task}/{cfg.mode}"
    bar = tqdm(total=cfg.iters, initial=trainer.iteration, disable=not cfg.progress, desc=base, unit="it",
               dynamic_ncols=True)
    first_iter_s = None
    status, error = "running", None
    metrics_path = run_dir / "metrics.jsonl"
    startup_s["run_folder"] = (cache_opened - started) + (time.time() - trainer_done)
    try:
        # The first iterations wait for the compiler: the bar says which part it compiles or captures, then its name.
        ahead_s = startup.before_first_iteration(
            lambda text: bar.set_description(base if text is None else f"{base}: {text}"))
        if ahead_s is not None:
            startup_s["compile_ahead"] = ahead_s
            # compiling counts in the training wall-clock (--time-limit-min, the wall_s curves) wherever it happens:
            # runs with and without helpers spend their budgets alike
            trainer.wall_s += ahead_s
        # The budget is the trainer's own wall-clock, which a checkpoint carries: a run killed and resumed gets
        # the same training time as one that ran through, so that return-against-time curves stay comparable.
        budget_s = None if cfg.time_limit_min is None else 60.0 * cfg.time_limit_min
        spent = budget_s is not None and trainer.wall_s >= budget_s  # a resumed run whose budget is used up
        while trainer.iteration < cfg.iters and not spent:
            m = trainer.train_iteration()
            if first_iter_s is None:
                first_iter_s = time.time() - _process_started()
                # a resumed run starts from its checkpoint's state and frames: no reset and render
                startup_s.update(first_reset_render=trainer.start_s or 0.0, first_iteration=m["iter_ms"] / 1e3)
            startup.after_iteration()
            it = m["iter"]
            last = it == cfg.iters or (budget_s is not None and trainer.wall_s >= budget_s)
            if cfg.video_every and (it % cfg.video_every == 0 or last):
                steps = min(cfg.video_steps or trainer.task.episode_length, trainer.task.episode_length)
                with startup.evaluating():
                    eval_return, frames = trainer.evaluate(steps=steps, record=True)
                m["eval_return"] = eval_return  # undiscounted, deterministic policy, over eval_steps steps
                m["eval_steps"] = steps
                write_video(run_dir / "videos" / f"iter_{it:06d}.mp4", frames)
            with open(metrics_path, "a") as f:
                f.write(json.dumps(m) + "\n")
                f.flush()
                os.fsync(f.fileno())
            if writer is not None:
                for k, v in m.items():
                    if isinstance(v, (int, float)) and not isinstance(v, bool) and v is not None:
                        writer.add_scalar(k, v, it)
            if it % cfg.checkpoint_every == 0 or last:
                save_checkpoint(checkpoint_path(ckpt_dir, it), trainer.state_dict())
                prune_checkpoints(ckpt_dir, keep=cfg.keep_checkpoints)
            ret = m["return_mean"]
            bar.set_postfix(ret="-" if ret is None else f"{ret:.1f}", ms=f"{m['iter_ms']:.0f}",
                            gn=f"{m['grad_norm']:.2g}")
            bar.update(1)
            if last:
                break
        status = "finished" if trainer.iteration >= cfg.iters else "time_limit"
    except NonFiniteError as e:
        status, error = "nonfinite", str(e)
        raise
    except KeyboardInterrupt:
        status, error = "interrupted", "KeyboardInterrupt"
        raise
    except torch.OutOfMemoryError as e:
        status, error = "oom", str(e).splitlines()[0]
        raise
    finally:
        startup.close()
        bar.close()
        if writer is not None:
            writer.close()
        atomic_write_json(run_dir / "summary.json", _summary(read_metrics(run_dir), cfg, status, error, started,
                                                             first_iter_s=first_iter_s, compiled=startup.record(),
                                                             startup_s=startup_s))
    return run_dir
