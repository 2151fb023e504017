"""The compile cache root, and Python's bytecode kept there, both decided before torch is imported.

This module imports nothing heavy (no torch), so that ``ablate`` can use it on its first line: where Python is
told not to write bytecode next to the sources (``PYTHONDONTWRITEBYTECODE``, ``python -B``; common in container
images), every process compiles the Python source of torch, inductor, Triton and the rest to bytecode again, and on
an H100 host that is 10-13 s of each warm ``--compile`` start (BENCHMARKS.md section 6). :func:`keep_bytecode`
keeps that bytecode in the compile cache folder instead, where the user sees and clears it with the rest.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = ["BYTECODE_FOLDER", "CACHE_ENV_VAR", "DEFAULT_CACHE_ROOT", "OFF_VALUES", "keep_bytecode",
           "resolve_cache_root"]

#: Environment variable naming the cache root (a path, or ``off`` for torch's own cache locations).
CACHE_ENV_VAR = "PIXELGRAD_COMPILE_CACHE"
#: The cache root when neither the flag nor the environment variable names one.
DEFAULT_CACHE_ROOT = Path("~/.cache/pixelgrad/compile")
#: Values of the flag or the environment variable that leave torch's cache locations alone.
OFF_VALUES = ("off", "none", "0", "false", "no")
#: The subfolder of the cache root that holds Python bytecode (:func:`keep_bytecode`).
BYTECODE_FOLDER = "bytecode"


def resolve_cache_root(path: str | os.PathLike | None = None, *, env: dict | None = None) -> Path | None:
    """The cache root: ``path`` (a flag), else ``$PIXELGRAD_COMPILE_CACHE``, else ``~/.cache/pixelgrad/compile``;
    None where the chosen value is ``off`` (torch's own locations). ``~`` is expanded; the result is absolute."""
    env = os.environ if env is None else env
    value = path if path is not None else env.get(CACHE_ENV_VAR) or None
    if value is None:
        return DEFAULT_CACHE_ROOT.expanduser().resolve()
    if str(value).strip().lower() in OFF_VALUES:
        return None
    if not str(value).strip():
        raise ValueError(f"compile cache folder is empty; give a folder, or 'off' ({CACHE_ENV_VAR}, --compile-cache)")
    return Path(value).expanduser().resolve()


def keep_bytecode(root: Path | None) -> Path | None:
    """Where Python was told not to write bytecode next to the sources, write it under ``root/bytecode`` instead
    (``sys.pycache_prefix``), for this process and the processes it starts (``PYTHONPYCACHEPREFIX`` in the
    environment; compile helpers, inductor's compile workers). Returns that folder, or None where nothing
    changed: no root (``off``), bytecode already written (the usual install, whose own ``__pycache__`` files keep
    being used), or a ``PYTHONPYCACHEPREFIX`` the user chose.

    The sources stay as they were (the reason for ``PYTHONDONTWRITEBYTECODE``); a ``.pyc`` records its source's
    size and modification time and Python recompiles it when they change, and writes it atomically, so
    concurrent processes share the folder safely. Call before the imports it should speed up."""
    if root is None or not sys.dont_write_bytecode or sys.pycache_prefix is not None:
        return None
    folder = Path(root) / BYTECODE_FOLDER
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:  # an unusable cache root is reported where the run opens it; here it only costs time
        return None
    sys.pycache_prefix = str(folder)
    sys.dont_write_bytecode = False
    os.environ["PYTHONPYCACHEPREFIX"] = str(folder)
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
    return folder
