"""memory.csv and memory.json: the sweep's rows, their columns and units, read and written atomically."""

from __future__ import annotations

import csv
import datetime as _dt
import io
import os
from pathlib import Path

from ablations.memory.config import SWEPT_MODES
from gradlab.files import atomic_write_json, atomic_write_text

__all__ = ["COLUMNS", "FIXED", "FINAL_STATUSES", "TIMED_COLUMNS", "point_key", "read_csv", "csv_text",
           "sort_rows", "write_results", "check_compatible", "now"]

#: Columns of memory.csv, in order. Units: ms (medians over the measured iterations), MB = 2**20 bytes.
COLUMNS = (
    "task", "mode", "renderer", "meshes", "verts_per_mesh", "status",
    "scene_faces", "scene_verts",
    "fwd_ms", "bwd_ms", "critic_ms", "iter_ms",
    "peak_alloc_mb", "peak_reserved_mb", "saved_mb", "max_rss_mb",
    "point_s", "num_envs", "horizon", "image_size", "warmup_iters", "iters", "device", "seed", "gpu",
    "started", "error", "log",
)
_INT_COLUMNS = {"meshes", "verts_per_mesh", "scene_faces", "scene_verts", "num_envs", "horizon", "image_size",
                "warmup_iters", "iters", "seed"}
_FLOAT_COLUMNS = {"fwd_ms", "bwd_ms", "critic_ms", "iter_ms", "peak_alloc_mb", "peak_reserved_mb", "saved_mb",
                  "max_rss_mb", "point_s"}
#: Measurements that a failed point does not have (emptied in its row: they would not be measurements).
TIMED_COLUMNS = ("fwd_ms", "bwd_ms", "critic_ms", "iter_ms", "peak_alloc_mb", "peak_reserved_mb", "saved_mb")
#: Settings every row of one memory.csv must share (otherwise its rows are not comparable).
FIXED = ("task", "renderer", "num_envs", "horizon", "image_size", "warmup_iters", "iters", "device", "seed")
#: Statuses that are results: a restarted sweep never re-runs them.
FINAL_STATUSES = ("ok", "oom")


def now() -> str:
    """Local time with its UTC offset, to the second (the dates in memory.json and the rows)."""
    return _dt.datetime.now().astimezone().isoformat(timespec="seconds")


def point_key(row: dict) -> tuple:
    """(mode, meshes, verts_per_mesh): what identifies a point within one sweep."""
    return (row["mode"], int(row["meshes"]), int(row["verts_per_mesh"]))


def _parse(key: str, value: str):
    if value == "":
        return None
    if key in _INT_COLUMNS:
        return int(float(value))
    if key in _FLOAT_COLUMNS:
        return float(value)
    return value


def read_csv(path: str | os.PathLike) -> list[dict]:
    """Rows of a memory.csv with numbers parsed (empty cells are None)."""
    path = Path(path)
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in ("task", "mode", "meshes", "verts_per_mesh", "status") if c not in
                   (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path} is not an ablate-memory CSV: columns {missing} missing")
        rows = [{k: _parse(k, v if v is not None else "") for k, v in r.items() if k in COLUMNS} for r in reader]
    for r in rows:  # sweeps from before the renderer column rendered with the soft rasterizer
        if r.get("renderer") is None:
            r["renderer"] = "soft"
    return rows


def csv_text(rows: list[dict]) -> str:
    """The text of a memory.csv holding rows (``COLUMNS`` in order, floats to 6 significant digits)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: "" if r.get(k) is None else (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k])
                    for k in COLUMNS})
    return buf.getvalue()


def sort_rows(rows: list[dict]) -> list[dict]:
    """Rows by mode (full first), then meshes, then vertices per mesh."""
    return sorted(rows, key=lambda r: (SWEPT_MODES.index(r["mode"]) if r["mode"] in SWEPT_MODES else 9,
                                       r["meshes"], r["verts_per_mesh"]))


def write_results(out: Path, rows: list[dict], meta: dict) -> None:
    """memory.csv and memory.json, each replaced atomically: a reader (or a killed sweep) never sees half.

    ``meta`` (settings, commands, environment) gets its ``updated`` date set here.
    """
    rows = sort_rows(rows)
    atomic_write_text(out / "memory.csv", csv_text(rows))
    meta["updated"] = now()
    atomic_write_json(out / "memory.json", {**meta, "rows": [{k: r.get(k) for k in COLUMNS} for r in rows]})


def check_compatible(rows: list[dict], points: list[dict], csv_path: Path) -> None:
    """Refuse to extend a memory.csv whose rows were measured with other ``FIXED`` settings than ``points``."""
    if not rows or not points:
        return
    want = {k: points[0][k] for k in FIXED}
    for r in rows:
        diff = {k: (r.get(k), want[k]) for k in FIXED if r.get(k) != want[k]}
        if diff:
            text = ", ".join(f"{k}: {a!r} there vs {b!r} now" for k, (a, b) in diff.items())
            raise ValueError(f"{csv_path} holds a sweep with other settings ({text}); its rows would not be "
                             f"comparable: use another --out")
