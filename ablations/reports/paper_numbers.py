"""The D.Va authors' published numbers, as data: ``paper_numbers.json`` beside this module.

Every entry names its source (``sources``: citation, device, and whether values were read off a plot or
stated); ``approx: true`` marks a value read off a plot, printed with a leading ``~``. Nothing here is
estimated: a comparison the sources do not cover is left out. Tables:

    final_return    task, method, value (or low/high for a range read off a plot), optional std, note
    return_at_time  task, minutes, and the return of each method at that wall-clock time
    backward_s      task, backward seconds per iteration of each method

Methods are keys of ``methods``: ``dva`` (our decoupled mode) and ``shac-diffrender`` (our full mode with the
``shac-diffrender`` preset: the hard rasterizer).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

__all__ = ["PaperNumbers", "load_paper_numbers", "PAPER_NUMBERS_FILE", "format_value"]

PAPER_NUMBERS_FILE = Path(__file__).with_name("paper_numbers.json")
_TABLES = ("final_return", "return_at_time", "backward_s")


@dataclass(frozen=True)
class PaperNumbers:
    """The parsed file: sources by key, method names, and the three tables (lists of dicts)."""

    path: Path
    sources: dict[str, dict]
    methods: dict[str, str]
    final_return: list[dict]
    return_at_time: list[dict]
    backward_s: list[dict]

    def cite(self, key: str) -> str:
        """'<citation> (<device>; <kind>)' of a source."""
        src = self.sources[key]
        extra = "; ".join(str(v) for v in (src.get("device"), src.get("kind")) if v)
        return f"{src['cite']} ({extra})" if extra else src["cite"]

    def table1_ms(self) -> dict[str, tuple[float, float]]:
        """task -> (D.Va, SHAC with rendering) backward ms per iteration (Table 1, converted from seconds)."""
        return {r["task"]: (1000.0 * r["dva"], 1000.0 * r["shac-diffrender"]) for r in self.backward_s}

    def table1_device(self) -> str:
        devices = {self.sources[r["source"]].get("device") for r in self.backward_s}
        return " / ".join(sorted(str(d) for d in devices if d)) or "?"


def _num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def load_paper_numbers(path: str | os.PathLike | None = None) -> PaperNumbers:
    """Parse and check the file (default: the packaged one); ValueError naming the entry that is wrong."""
    path = Path(PAPER_NUMBERS_FILE if path is None else path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"paper numbers {path}: no such file") from None
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"paper numbers {path}: cannot be read ({e})") from None
    sources, methods = data.get("sources"), data.get("methods")
    if not isinstance(sources, dict) or not all(isinstance(s, dict) and s.get("cite") for s in sources.values()):
        raise ValueError(f"paper numbers {path}: 'sources' must map keys to objects with a 'cite'")
    if not isinstance(methods, dict):
        raise ValueError(f"paper numbers {path}: 'methods' must map method keys to names")
    for table in _TABLES:
        rows = data.get(table)
        if not isinstance(rows, list):
            raise ValueError(f"paper numbers {path}: '{table}' must be a list")
        for i, r in enumerate(rows):
            where = f"paper numbers {path}: {table}[{i}]"
            if not isinstance(r, dict) or not isinstance(r.get("task"), str):
                raise ValueError(f"{where} needs a task")
            if r.get("source") not in sources:
                raise ValueError(f"{where}: source {r.get('source')!r} is not in 'sources'")
            if not isinstance(r.get("approx"), bool):
                raise ValueError(f"{where}: 'approx' must be true (read off a plot) or false (stated)")
            if table == "final_return":
                if r.get("method") not in methods:
                    raise ValueError(f"{where}: method {r.get('method')!r} is not in 'methods'")
                if not (_num(r.get("value")) or (_num(r.get("low")) and _num(r.get("high")))):
                    raise ValueError(f"{where}: needs a numeric value, or low and high")
            else:
                if table == "return_at_time" and not _num(r.get("minutes")):
                    raise ValueError(f"{where}: needs numeric minutes")
                if not any(_num(r.get(m)) for m in methods):
                    raise ValueError(f"{where}: no numeric value of any method ({', '.join(methods)})")
    return PaperNumbers(path=path, sources=sources, methods=methods,
                        **{t: data[t] for t in _TABLES})


def format_value(entry: dict, key: str = "value") -> str:
    """A value as the source gives it: ``~5k`` style for plot readings (``~7.5-8k`` for a range), the stated
    number with ``+- std`` otherwise."""
    approx = entry.get("approx")
    if key == "value" and "value" not in entry and "low" in entry:
        lo, hi = entry["low"], entry["high"]
        if approx and lo >= 1000 and hi >= 1000:
            return f"~{lo / 1000:g}-{hi / 1000:g}k"
        return f"{'~' if approx else ''}{lo:g}-{hi:g}"
    v = entry[key]
    if approx:
        return f"~{v / 1000:g}k" if abs(v) >= 1000 else f"~{v:g}"
    text = f"{v:g}"
    if key == "value" and _num(entry.get("std")):
        text += f" +- {entry['std']:g}"
    return text
