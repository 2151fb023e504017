"""Which source tree a benchmark measured: the commit every results file records."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def commit() -> str:
    """``$PIXELGRAD_COMMIT`` when set, else the short HEAD with ``+dirty`` when tracked files differ from it.

    The variable exists for copies of the tree whose ``.git`` lags behind their files (a GPU machine that is
    sent the working tree with the repository it was started from): the caller names the commit it sent."""
    named = os.environ.get("PIXELGRAD_COMMIT")
    if named:
        return named

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, timeout=30,
                              check=True).stdout.strip()

    try:
        head = git("rev-parse", "--short", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")
