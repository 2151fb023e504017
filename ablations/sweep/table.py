"""The live table: a tqdm bar of finished runs and one bar per running job (a run, or a population of runs in one
process); a line per run's change of status."""

from __future__ import annotations

from typing import Any

from ablations.sweep.manifest import status_counts
from ablations.sweep.packing import Job

__all__ = ["LiveTable", "progress_text", "time_limit_min"]


def _fmt_return(value: Any) -> str:
    return "-" if value is None else f"{value:.4g}"


def time_limit_min(args: Any) -> float | None:
    """The --time-limit-min of a run's ablate arguments, None without one: such a run ends on its training
    wall-clock, which its progress then shows (its --iters is only a ceiling)."""
    args = list(args or ())
    try:
        return float(args[args.index("--time-limit-min") + 1])
    except (ValueError, IndexError):
        return None


def _placement(rec: dict) -> str:
    """Where a run trains (or trained): '  on HOST GPU 0' ('GPU -' on the CPU); empty before it has started."""
    if rec.get("host") is None:
        return ""
    gpus = rec.get("gpus")
    return f"  on {rec['host']} GPU {','.join(gpus) if gpus else '-'}"


def progress_text(rec: dict) -> str:
    """How far a run is: 'it 31/100' or, for a time-limited run, 'time 3.2/60 min (it 31)'; with ' ckpt 30' where
    the sweep folder holds a checkpoint of the run (what a rerun resumes from)."""
    limit = time_limit_min(rec.get("args"))
    ckpt = f" ckpt {rec['checkpoint']}" if rec.get("checkpoint") else ""
    if limit is None:
        return f"it {rec.get('iteration') or 0}/{rec.get('iters')}{ckpt}"
    return f"time {(rec.get('wall_s') or 0.0) / 60:.1f}/{limit:g} min (it {rec.get('iteration') or 0}){ckpt}"


class LiveTable:
    """A tqdm bar of finished runs (counts by status in its postfix) and one bar per running job: a run's
    iteration (a time-limited run's training minutes of its budget) and latest return, or a population's (its
    members' lowest, and their mean latest return).

    Without ``enabled`` there are no bars; the status lines are printed either way.
    """

    def __init__(self, manifest: dict, todo: list[Job], *, enabled: bool):
        self.enabled = enabled
        self.manifest = manifest
        self.jobs = {job.job_id: job for job in todo}
        self.bars: dict[str, Any] = {}
        self.free: list[int] = []
        self.last_status: dict[str, str] = {}
        self.main = None
        if enabled:
            from tqdm.auto import tqdm

            self.tqdm = tqdm
            self.main = tqdm(total=len(manifest["runs"]), desc="sweep", unit="run", dynamic_ncols=True, position=0)
        self.update()

    def _print(self, text: str) -> None:
        if self.enabled:
            self.tqdm.write(text)
        else:
            print(text, flush=True)

    def update(self) -> None:
        """Redraw from the manifest; print a line for every run whose status changed since the last call."""
        runs = self.manifest["runs"]
        for run_id, rec in runs.items():
            status, before = rec["status"], self.last_status.get(run_id)
            if status != before:
                self.last_status[run_id] = status
                if before is not None or status in ("done", "failed"):
                    extra = f"  error: {rec['error']}" if rec.get("error") else ""
                    self._print(f"{status:8s} {run_id}  {progress_text(rec)}  return "
                                f"{_fmt_return(rec.get('latest_return'))}  attempts {rec.get('attempts')}"
                                f"{_placement(rec)}{extra}")
        for job_id, job in self.jobs.items() if self.enabled else ():
            recs = [runs[r] for r in job.run_ids]
            bar = self.bars.get(job_id)
            if any(rec["status"] == "running" for rec in recs):
                limit = time_limit_min(job.args)  # a time-limited run's bar: training minutes of its budget
                if bar is None:
                    pos = self.free.pop(0) if self.free else len(self.bars) + 1
                    desc = f"{job_id} ({len(recs)} runs)" if job.population else job_id
                    bar = self.bars[job_id] = self.tqdm(total=job.iters if limit is None else limit, desc=desc,
                                                        unit="it" if limit is None else "min", position=pos,
                                                        leave=False, dynamic_ncols=True)
                    bar.pos_ = pos
                if limit is None:
                    bar.n = min(rec.get("iteration") or 0 for rec in recs)
                else:
                    bar.n = round(min((rec.get("wall_s") or 0.0) / 60 for rec in recs), 1)
                returns = [r["latest_return"] for r in recs if r.get("latest_return") is not None]
                ckpts = [r.get("checkpoint") or 0 for r in recs]
                bar.set_postfix(ret=_fmt_return(sum(returns) / len(returns) if returns else None),
                                ckpt=min(ckpts) or "-", refresh=False)
                bar.refresh()
            elif bar is not None:
                self.free.append(bar.pos_)
                self.free.sort()
                bar.close()
                del self.bars[job_id]
        if self.main is not None:
            c = status_counts(self.manifest)
            self.main.n = c["done"] + c["failed"]
            self.main.set_postfix_str(" ".join(f"{k} {v}" for k, v in c.items()), refresh=False)
            self.main.refresh()

    def close(self) -> None:
        for bar in self.bars.values():
            bar.close()
        if self.main is not None:
            self.main.close()
