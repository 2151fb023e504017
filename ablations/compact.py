"""Compact finished run folders (to keep or move many of them): each folder's metrics.jsonl and summary.json
replaced by an xz copy of the same bytes (``metrics.jsonl.xz``, ``summary.json.xz``), which ``ablations.run_folder``
reads as it reads the plain files, so ``ablate-plot``, ``ablate-report`` and the statistics see the same numbers
(docs/design.md, "Shipped run data")::

    python -m ablations.compact RUNS_FOLDER

A path stands for the run folder it is (it holds config.json) or for every run folder below it. Folders already
compacted are left as they are; a folder whose run has not ended (no summary.json) is refused, since its run may
still append metrics lines. The copies are deterministic: the same file always compacts to the same bytes (xz
records no time or name), so compacting again changes nothing that git sees. Reading imports no torch, and neither
does this.
"""

from __future__ import annotations

import argparse
import lzma
import os
import sys
import tempfile
from pathlib import Path

from ablations.run_folder import COMPACTED, CONFIG, METRICS, SUMMARY

#: What is compacted: the metrics (the bulk of a run folder) and the summary (its compile record makes it the next
#: largest). config.json stays plain: it is what marks a folder as a run folder; git.txt is a few lines.
COMPACTED_FILES = (METRICS, SUMMARY)
#: xz's strongest preset: the files are small (hundreds of kB), so it costs little time, and its window covers each.
PRESET = 9 | lzma.PRESET_EXTREME


def pack(data: bytes) -> bytes:
    """``data`` xz-compressed, the same bytes for the same data."""
    return lzma.compress(data, format=lzma.FORMAT_XZ, check=lzma.CHECK_CRC64, preset=PRESET)


def check_ended(run_dir: str | os.PathLike) -> Path:
    """``run_dir`` as a Path; ValueError when it is not a run folder or its run has not ended."""
    run_dir = Path(run_dir)
    if not (run_dir / CONFIG).exists():
        raise ValueError(f"{run_dir}: no config.json there (not a run folder)")
    if not any((run_dir / name).exists() for name in (SUMMARY, SUMMARY + COMPACTED)):
        raise ValueError(f"{run_dir} has no summary.json: its run has not ended and may still append metrics lines")
    return run_dir


def compact_folder(run_dir: str | os.PathLike) -> list[tuple[Path, int, int]]:
    """Replace the run folder's metrics.jsonl and summary.json by their compacted copies; (copy, plain bytes,
    compacted bytes) of each file compacted ([] when there was nothing left to compact). ValueError when
    ``run_dir`` is not a run folder or its run has not ended."""
    run_dir = check_ended(run_dir)
    done = []
    for name in COMPACTED_FILES:
        plain = run_dir / name
        if not plain.exists():
            continue
        data = plain.read_bytes()
        blob = pack(data)
        if lzma.decompress(blob) != data:
            raise RuntimeError(f"{plain}: the xz copy does not decompress to the file; nothing replaced")
        copy = plain.with_name(name + COMPACTED)
        # the copy in place before the plain file goes: a reader finds one or the other at every moment
        fd, tmp = tempfile.mkstemp(dir=run_dir, prefix=f".{copy.name}.")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(blob)
            os.chmod(tmp, plain.stat().st_mode & 0o777)
            os.replace(tmp, copy)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        plain.unlink()
        done.append((copy, len(data), len(blob)))
    return done


def run_folders(paths: list[str | os.PathLike]) -> list[Path]:
    """The run folders the paths stand for: a path holding config.json is one, any other folder stands for every
    run folder below it (a run's own subfolders are not searched), in path order. ValueError for a path that is
    neither."""
    found: list[Path] = []
    for p in map(Path, paths):
        if (p / CONFIG).exists():
            found.append(p)
            continue
        below = _below(p) if p.is_dir() else []
        if not below:
            raise ValueError(f"{p}: neither a run folder nor a folder with run folders below it")
        found.extend(below)
    return found


def _below(folder: Path) -> list[Path]:
    found = []
    for child in sorted(c for c in folder.iterdir() if c.is_dir()):
        found.extend([child] if (child / CONFIG).exists() else _below(child))
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m ablations.compact",
        description="Compact finished run folders for shipping: metrics.jsonl and summary.json replaced by xz copies "
                    "of the same bytes, which ablate-plot, ablate-report and ablations.run_folder read as before.")
    parser.add_argument("paths", nargs="+", help="run folders, or folders with run folders below them")
    args = parser.parse_args(argv)
    try:
        folders = [check_ended(f) for f in run_folders(args.paths)]  # all checked before any is changed
        before = after = 0
        for folder in folders:
            for copy, plain_bytes, packed_bytes in compact_folder(folder):
                before, after = before + plain_bytes, after + packed_bytes
                print(f"{copy}: {plain_bytes} -> {packed_bytes} bytes")
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"{len(folders)} run folder(s): {before} -> {after} bytes compacted")
    return 0


if __name__ == "__main__":
    sys.exit(main())
