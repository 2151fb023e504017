"""The live table: a tqdm bar of finished runs and one bar per running run; a line per change of status."""

from __future__ import annotations

from typing import Any

from ablations.sweep.grid import RunSpec
from ablations.sweep.manifest import status_counts

__all__ = ["LiveTable"]


def _fmt_return(value: Any) -> str:
    return "-" if value is None else f"{value:.4g}"


class LiveTable:
    """A tqdm bar of finished runs (counts by status in its postfix) and one bar per running run.

    Without ``enabled`` there are no bars; the status lines are printed either way.
    """

    def __init__(self, manifest: dict, todo: list[RunSpec], *, enabled: bool):
        self.enabled = enabled
        self.manifest = manifest
        self.iters = {s.run_id: s.iters for s in todo}
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
                    it = f"{rec.get('iteration') or 0}/{rec.get('iters')}"
                    self._print(f"{status:8s} {run_id}  it {it}  return {_fmt_return(rec.get('latest_return'))}"
                                f"  attempts {rec.get('attempts')}{extra}")
            if not self.enabled:
                continue
            bar = self.bars.get(run_id)
            if status == "running":
                if bar is None:
                    pos = self.free.pop(0) if self.free else len(self.bars) + 1
                    bar = self.bars[run_id] = self.tqdm(total=self.iters.get(run_id, rec.get("iters")), desc=run_id,
                                                        unit="it", position=pos, leave=False, dynamic_ncols=True)
                    bar.pos_ = pos
                bar.n = rec.get("iteration") or 0
                bar.set_postfix(ret=_fmt_return(rec.get("latest_return")), refresh=False)
                bar.refresh()
            elif bar is not None:
                self.free.append(bar.pos_)
                self.free.sort()
                bar.close()
                del self.bars[run_id]
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
