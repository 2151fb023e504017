"""What a training loop tells its run folders and the terminal (:class:`RunLog`): each run's records (config.json,
git.txt, provenance), its metrics lines, TensorBoard scalars, evaluation rows and videos, the progress bar, and
the summary.json each folder ends with; one entry per member, in the trainer's member order (a run alone: one).
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

from tqdm.auto import tqdm

from ablations.population import Prepared
from ablations.run_config import RunConfig, shac_part
from ablations.run_folder import evaluation_of
from ablations.run_records import environment_info
from ablations.tree_hash import tree_hash
from gradlab.config import SHACConfig
from gradlab.presets import preset_record
from gradlab.timing import median

__all__ = ["RunLog", "summary"]

_IMPORTED = time.time()  # when no better process start time is known (process_started)


class RunLog:
    """The records of the prepared runs while ``trainer`` trains them.

    ``statuses`` holds how each member ends (status, error): a member the trainer stopped is ``nonfinite`` from
    the iteration it stopped at (its summary is written then, the others go on); :meth:`end` sets the others'.
    Built before any record is written: ``--tensorboard`` without its package is refused here.
    """

    def __init__(self, prepared: Prepared, trainer: Any, *, started: float, cache_opened: float,
                 trainer_built: float, trainer_done: float):
        self.prepared, self.trainer, self.started = prepared, trainer, started
        self.cfgs, self.folders = prepared.cfgs, prepared.folders
        self.cfg = cfg = self.cfgs[0]  # the settings members share
        if cfg.tensorboard:  # bad input: said before the run records anything
            try:
                from torch.utils.tensorboard import SummaryWriter  # noqa: F401
            except ImportError as e:
                raise ValueError("--tensorboard needs the tensorboard package: pip install tensorboard") from e
        self.members = list(trainer.members)
        self.stopped = [m.failed is not None for m in self.members]  # a resumed population's failed members
        self.statuses: list[tuple[str, str | None]] = [("nonfinite", m.failed) if m.failed is not None
                                                       else ("running", None) for m in self.members]
        # where the seconds before the first iteration go (summary.json "startup_s"; benchmarks/startup.py):
        # parts that together make up first_iter_s; "run_folder" is the bookkeeping around the trainer (checking
        # the config, the run folder, a checkpoint to resume, git and environment records, the progress bar)
        self.startup_s = {"imports": started - process_started(), "compile_cache": trainer_built - cache_opened,
                          "trainer": trainer_done - trainer_built}
        self._before_trainer_s, self._trainer_done = cache_opened - started, trainer_done
        self.first_iter_s: float | None = None
        self.bar = self.writer = None
        self._eval_text = "-"

    # ------------------------------------------------------------------ before the first iteration
    def record_runs(self, iteration: int, *, resuming: bool) -> None:
        """Each run's records: config.json (every setting, resolved, with what the preset supplied) and git.txt of
        a new run, or of a restarted one once its earlier records are set aside beside them (each named); a
        resumed run keeps its own, its metrics lines after the checkpoint of ``iteration`` set aside to be
        trained again (damaged ones named), except a member that stopped before it (its lines end where it
        stopped). Every start appends its code's provenance (provenance.jsonl)."""
        prepared, members = self.prepared, self.members
        tree = tree_hash()  # the code that trains, hashed where a device copy has no repository to name it
        for i, (member_cfg, folder) in enumerate(zip(self.cfgs, self.folders)):
            if folder.config_path.exists():
                if resuming:
                    for note in [] if members[i].failed is not None else folder.settle_metrics(iteration):
                        print(note, file=sys.stderr)
                    folder.append_provenance("resume", iteration)  # the code of this resume, beside the first's
                    continue
                notes = folder.set_aside_for_restart()
                if member_cfg.restart:  # a resume of a folder that trained nothing sets aside its records unasked
                    for note in notes:
                        print(note, file=sys.stderr)
                restarted = True
            else:
                restarted = False
            shac_fields = dataclasses.fields(SHACConfig)
            resolved = dataclasses.replace(member_cfg,
                                           **{f.name: getattr(members[i].cfg, f.name) for f in shac_fields})
            config = dataclasses.asdict(resolved)
            del config["restart"]  # what this start did, not a setting of the run (arms compare the settings)
            record = {
                "config": config,
                # which values the preset supplied and which flags overrode it (flag and preset value side by side)
                "preset": preset_record(shac_part(member_cfg), members[i].cfg),
                "started_utc": _utc(self.started),
                "environment": environment_info(prepared.device),
                "command": sys.argv,
                "tree_hash": tree.value,
                "tree_hash_source": tree.source,
            }
            expert = getattr(members[i], "expert", None)
            if expert is not None:  # a distill student's expert and what it cost
                record["expert"] = {"source": expert.source, "wall_s": expert.wall_s,
                                    "env_steps": expert.env_steps, "iterations": expert.iterations}
            if prepared.population is not None:  # the process it trained in: one of these members, in this folder
                record["population"] = {"folder": prepared.population.path.name,
                                        "members": [f.path.name for f in self.folders], "index": i}
            folder.write_config(record)
            folder.write_git()
            folder.append_provenance("restart" if restarted else "start", 0)

    def open(self, startup: Any) -> None:
        """TensorBoard's writer, the progress bar, and the compiling ahead of the first iteration (its seconds
        count in the training wall-clock: runs with and without compile helpers spend their budgets alike)."""
        cfg, trainer = self.cfg, self.trainer
        if cfg.tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(str(self.folders[0].path / "tb"))
        # the progress label: a run alone's mode, a population's size
        base = f"{cfg.task}/{cfg.mode}" if len(self.cfgs) == 1 else f"{cfg.task}/{len(self.cfgs)} members"
        self.bar = bar = tqdm(total=cfg.iters, initial=trainer.iteration, disable=not cfg.progress, desc=base,
                              unit="it", dynamic_ncols=True)
        self.startup_s["run_folder"] = self._before_trainer_s + (time.time() - self._trainer_done)
        # The first iterations wait for the compiler: the bar says which part it compiles or captures, then its name.
        ahead_s = startup.before_first_iteration(
            lambda text: bar.set_description(base if text is None else f"{base}: {text}"))
        if ahead_s is not None:
            self.startup_s["compile_ahead"] = ahead_s
            trainer.wall_s += ahead_s

    # ------------------------------------------------------------------ every iteration
    def trained(self, rows: list[dict | None]) -> None:
        """Told as soon as an iteration has trained: the first one ends the start-up (``first_iter_s``)."""
        if self.first_iter_s is None:
            self.first_iter_s = time.time() - process_started()
            live = [r for r in rows if r is not None]
            # a resumed run starts from its checkpoint's state and frames: no reset and render
            self.startup_s.update(first_reset_render=self.trainer.start_s or 0.0,
                                  first_iteration=live[0]["iter_ms"] / 1e3)

    def iteration(self, rows: list[dict | None]) -> None:
        """An iteration's metrics lines; a member that stopped in it gets its summary (its record says why, the
        others go on)."""
        for i, (row, folder) in enumerate(zip(rows, self.folders)):
            if row is not None:
                folder.append_metrics(row)
            elif not self.stopped[i]:
                self.stopped[i] = True
                self.statuses[i] = ("nonfinite", self.members[i].failed)
                folder.write_summary(summary(folder.read_metrics(), self.cfgs[i], *self.statuses[i], self.started))

    def evaluation(self, rows: list[dict | None], iteration: int, startup: Any, *, video: bool) -> None:
        """The deterministic policy from the fixed evaluation seed (``SHAC.evaluate``) into the iteration's rows,
        filmed on video iterations."""
        t_eval = time.perf_counter()
        with startup.evaluating():
            evaluated = self.trainer.evaluate(
                video_steps=(self.cfg.video_steps or self.trainer.task.episode_length) if video else 0)
        eval_s = time.perf_counter() - t_eval  # what the evaluation cost beside the iteration (iter_ms)
        for row, folder, ev in zip(rows, self.folders, evaluated):
            if row is not None:
                frames = ev.pop("frames")
                row.update(ev, eval_s=eval_s)
                folder.write_video(iteration, frames)

    def progress(self, rows: list[dict | None], iteration: int) -> None:
        """TensorBoard's scalars (the first member's) and the progress bar's step."""
        live = [r for r in rows if r is not None]
        if self.writer is not None:
            for k, v in live[0].items():
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    self.writer.add_scalar(k, v, iteration)
        evals = [ev for r in live if (ev := evaluation_of(r)) is not None]
        if evals:
            self._eval_text = f"{sum(e[0] for e in evals) / len(evals):.1f}"
        returns = [r["return_mean"] for r in live if r["return_mean"] is not None]
        norms = [r["grad_norm"] for r in live if r["grad_norm"] is not None]  # None: no update (distill)
        self.bar.set_postfix({"ret": f"{sum(returns) / len(returns):.1f}" if returns else "-",
                              "eval": self._eval_text, "ms": f"{live[0]['iter_ms']:.0f}",
                              "gn": f"{max(norms):.2g}" if norms else "-"})
        self.bar.update(1)

    # ------------------------------------------------------------------ the end
    def end(self, status: str, error: str | None) -> None:
        """How every member still training ended."""
        self.statuses = [s if self.stopped[i] else (status, error) for i, s in enumerate(self.statuses)]

    def close(self, *, compiled: dict | None, resumes_from: int | None, lost: str | None) -> None:
        """Close the bar and the writer; each recorded run's summary.json (a member that stopped keeps its own)."""
        if self.bar is not None:
            self.bar.close()
        if self.writer is not None:
            self.writer.close()
        for i, folder in enumerate(self.folders):
            if folder.config_path.exists() and not (self.stopped[i] and folder.summary_path.exists()):
                folder.write_summary(summary(folder.read_metrics(), self.cfgs[i], *self.statuses[i], self.started,
                                             first_iter_s=self.first_iter_s, compiled=compiled,
                                             startup_s=self.startup_s, resumes_from=resumes_from, lost=lost))


# ---------------------------------------------------------------------------------------------- the summary
def _utc(t: float) -> str:
    """Seconds since the epoch as an ISO-8601 UTC timestamp (what the report prints as started/ended)."""
    return datetime.datetime.fromtimestamp(t, datetime.timezone.utc).isoformat(timespec="seconds")


def process_started() -> float:
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


def summary(rows: list[dict], cfg: RunConfig, status: str, error: str | None, started: float, *,
            first_iter_s: float | None = None, compiled: dict | None = None,
            startup_s: dict | None = None, resumes_from: int | None = None, lost: str | None = None) -> dict:
    """A run's summary.json from its metrics lines: how it ended, its returns and evaluations, its timings."""
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
    evals = [(r["iter"], *ev) for r in rows if (ev := evaluation_of(r)) is not None]
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
        # the iteration of the newest checkpoint, where ablate --resume starts (None: none); what a stop lost
        "resumes_from": resumes_from,
        "lost": lost,
        "final_return": returns[-1] if returns else None,
        "best_return": max(returns) if returns else None,
        # the deterministic policy's return (metrics eval_return_mean, or eval_return on video iterations): the
        # last evaluation's mean, its std over episodes (None where not logged) and iteration, and the best mean
        "final_eval_return": evals[-1][1] if evals else None,
        "final_eval_std": evals[-1][2] if evals and not math.isnan(evals[-1][2]) else None,
        "final_eval_iter": evals[-1][0] if evals else None,
        "best_eval_return": max(e[1] for e in evals) if evals else None,
        "threads": cfg.threads,
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
