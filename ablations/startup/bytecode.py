"""Python's bytecode, kept for the next start where the environment keeps it out of the install.

Where Python is told not to write bytecode beside the sources (``PYTHONDONTWRITEBYTECODE``, ``python -B``; common
in container images, the GPU image included), every process compiles the Python source of torch, inductor,
Triton and the rest again, seconds of every start (BENCHMARKS.md section 6). ``ablate`` calls :func:`keep_bytecode`
on its first line, before torch is imported (this module imports nothing heavy), so that the bytecode goes to a
folder of its own instead. Not the compile cache's folder: bytecode belongs to the Python install, not to what was
compiled, and clearing the compile cache for a cold-compiled comparison should not make the next start recompile
torch's Python.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = ["BYTECODE_ENV_VAR", "DEFAULT_BYTECODE_FOLDER", "OFF_VALUES", "keep_bytecode", "resolve_bytecode_folder"]

#: Environment variable naming the bytecode folder (a path, or ``off``: keep none).
BYTECODE_ENV_VAR = "PIXELGRAD_BYTECODE_CACHE"
#: The bytecode folder when the environment variable names none.
DEFAULT_BYTECODE_FOLDER = Path("~/.cache/pixelgrad/bytecode")
#: Values that turn a start-up folder off, the bytecode folder's and the compile cache's.
OFF_VALUES = ("off", "none", "0", "false", "no")


def resolve_bytecode_folder(*, env: dict | None = None) -> Path | None:
    """The bytecode folder: ``$PIXELGRAD_BYTECODE_CACHE``, else ``~/.cache/pixelgrad/bytecode``; None where it is
    ``off``. ``~`` is expanded; the result is absolute."""
    env = os.environ if env is None else env
    value = (env.get(BYTECODE_ENV_VAR) or "").strip()
    if value.lower() in OFF_VALUES:
        return None
    return Path(value or DEFAULT_BYTECODE_FOLDER).expanduser().resolve()


def keep_bytecode(folder: Path | None) -> Path | None:
    """Where Python was told not to write bytecode beside the sources, write it under ``folder`` instead
    (``sys.pycache_prefix``), for this process and the processes it starts (``PYTHONPYCACHEPREFIX`` in the
    environment: compile helpers, inductor's compile workers). Returns ``folder``, or None where nothing changed:
    no folder (``off``) or one that cannot be made, bytecode already written (the usual install, whose own
    ``__pycache__`` files keep being used), or a ``PYTHONPYCACHEPREFIX`` the user chose.

    The sources stay as they were (the reason for ``PYTHONDONTWRITEBYTECODE``). A ``.pyc`` records its source's
    size and modification time, and Python recompiles it when they change; Python writes it atomically, so
    concurrent processes share the folder safely. Call before the imports it should speed up."""
    if folder is None or not sys.dont_write_bytecode or sys.pycache_prefix is not None:
        return None
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:  # no bytecode kept costs time, never the run
        return None
    sys.pycache_prefix = str(folder)
    sys.dont_write_bytecode = False
    os.environ["PYTHONPYCACHEPREFIX"] = str(folder)
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
    return folder
