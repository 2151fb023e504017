"""Where ``torch.compile`` keeps what it compiled: one folder per torch, Triton and Python version and device kind.

:class:`CompileCache` is a folder (``cpu``, ``cuda-sm90``, ...) under a root the user chooses (``--compile-cache``,
else ``$PIXELGRAD_COMPILE_CACHE``, else ``~/.cache/pixelgrad/compile``) and may delete at any time::

    <root>/torch2.13.0-triton3.9.0-py3.11-cuda-sm90/
        manifest.json        the versions the contents were compiled with
        inductor/            TORCHINDUCTOR_CACHE_DIR: FX graph cache, AOTAutograd cache, autotuning results
        triton/              TRITON_CACHE_DIR: Triton binaries (inductor's and the renderer's own kernels)
        artifacts/<label>.bin  torch.compiler.save_cache_artifacts of one run's settings, checksummed

The on-disk caches make a second process on the same machine warm; the artifact file carries the same
entries to another machine (a Ray worker given the folder or the file starts warm). A manifest that records
other versions, or an artifact file that fails its checksum or torch's own loader, is moved aside with one
warning (:class:`CompileCacheWarning`) and the run compiles afresh: a damaged cache costs time, never a crash
or a wrong kernel. Torch's own cache keys (graph, config, versions) decide every hit.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import torch

from ablations.startup.bytecode import OFF_VALUES
from gradlab.files import atomic_write_bytes, atomic_write_json

__all__ = ["CACHE_ENV_VAR", "DEFAULT_CACHE_ROOT", "CompileCache", "CompileCacheWarning", "cache_versions",
           "resolve_cache_root", "start_compile_workers"]

#: Environment variable naming the cache root (a path, or ``off`` for torch's own cache locations).
CACHE_ENV_VAR = "PIXELGRAD_COMPILE_CACHE"
#: The cache root when neither the flag nor the environment variable names one.
DEFAULT_CACHE_ROOT = Path("~/.cache/pixelgrad/compile")

_FORMAT = 1  # of the manifest and the artifact files; a change moves older folders aside
_MAGIC = b"pixelgrad-compile-artifacts\n"


class CompileCacheWarning(UserWarning):
    """The compile cache was moved aside, rebuilt or is unavailable; the run goes on compiling afresh."""


def _warn(message: str) -> None:
    warnings.warn(message, CompileCacheWarning, stacklevel=3)


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


def _triton_version() -> str | None:
    try:
        import triton
    except ImportError:
        return None
    return triton.__version__


def cache_versions(device: torch.device) -> dict:
    """What a compiled artifact depends on beyond its graph: torch, Triton, Python, CUDA and the device kind
    (``cpu`` or ``cuda-sm<major><minor>``). The folder name and the manifest are made of these."""
    kind = device.type
    if device.type == "cuda":
        major, minor = torch.cuda.get_device_capability(device)
        kind = f"cuda-sm{major}{minor}"
    return {"format": _FORMAT, "torch": torch.__version__, "triton": _triton_version(),
            "python": ".".join(map(str, sys.version_info[:2])), "cuda": torch.version.cuda, "device": kind}


def _folder_name(versions: dict) -> str:
    name = f"torch{versions['torch']}-triton{versions['triton'] or 'none'}-py{versions['python']}-{versions['device']}"
    return re.sub(r"[^A-Za-z0-9.+_-]", "_", name)


def _aside(path: Path, suffix: str) -> Path:
    """Rename ``path`` to ``<name><suffix>`` (replacing an older one of that name); returns the new path."""
    import shutil

    target = path.with_name(path.name + suffix)
    if target.is_dir():
        shutil.rmtree(target, ignore_errors=True)
    elif target.exists():
        target.unlink()
    os.replace(path, target)
    return target


def _pack(payload: bytes, versions: dict) -> bytes:
    header = {"sha256": hashlib.sha256(payload).hexdigest(), "bytes": len(payload), **versions}
    return _MAGIC + json.dumps(header, sort_keys=True).encode() + b"\n" + payload


def _unpack(data: bytes, versions: dict) -> bytes:
    """The payload of an artifact file; ValueError saying what is wrong with it."""
    if not data.startswith(_MAGIC):
        raise ValueError("not a pixelgrad artifact file")
    head, sep, payload = data[len(_MAGIC):].partition(b"\n")
    if not sep:
        raise ValueError("no header")
    try:
        header = json.loads(head)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"unreadable header ({e})") from None
    if not isinstance(header, dict):
        raise ValueError("unreadable header")
    other = {k: header.get(k) for k in versions if header.get(k) != versions[k]}
    if other:
        raise ValueError(f"written with {other}, this process has " + str({k: versions[k] for k in other}))
    if header.get("bytes") != len(payload) or header.get("sha256") != hashlib.sha256(payload).hexdigest():
        raise ValueError("checksum mismatch (truncated or damaged)")
    return payload


class CompileCache:
    """The compile cache folder of one device (see the module docstring for its layout).

    Args:
        root: the cache root (:func:`resolve_cache_root`); the folder is ``root / <versions>``.
        device: the device the compiled code runs on.

    Opening checks the manifest (moving a mismatched or unreadable folder aside to ``<folder>.stale``);
    :meth:`activate` points torch at the folder and loads a run's artifact file; :meth:`save` writes it.
    """

    def __init__(self, root: str | os.PathLike, device: torch.device | str):
        device = torch.device(device)
        self.versions = cache_versions(device)
        self.folder = Path(root) / _folder_name(self.versions)
        self.portable = hasattr(torch.compiler, "save_cache_artifacts") and hasattr(torch.compiler,
                                                                                     "load_cache_artifacts")
        self.loaded: dict = {}  # artifact counts by kind, from the file :meth:`activate` loaded
        self.load_s = 0.0  # seconds that load took
        self._check_manifest()

    @property
    def manifest_path(self) -> Path:
        return self.folder / "manifest.json"

    def artifact_path(self, label: str) -> Path:
        """The artifact file of ``label`` (e.g. ``ant_decoupled_64envs``)."""
        return self.folder / "artifacts" / (re.sub(r"[^A-Za-z0-9._-]", "_", label) + ".bin")

    def _check_manifest(self) -> None:
        path = self.manifest_path
        why = None
        if path.exists():
            try:
                recorded = json.loads(path.read_text())
                if not isinstance(recorded, dict):
                    raise ValueError("not a JSON object")
            except (OSError, UnicodeDecodeError, ValueError) as e:
                why = f"its manifest cannot be read ({type(e).__name__}: {e})"
            else:
                other = {k: recorded.get(k) for k in self.versions if recorded.get(k) != self.versions[k]}
                if other:
                    mine = {k: self.versions[k] for k in other}
                    why = f"its manifest records {other}, this process has {mine}"
        if why is not None:
            try:
                aside = _aside(self.folder, ".stale")
                _warn(f"compile cache {self.folder}: {why}; moved aside to {aside.name}, compiling afresh")
            except FileNotFoundError:  # another process moved it aside first
                pass
        self.folder.mkdir(parents=True, exist_ok=True)
        if not path.exists():
            atomic_write_json(path, {**self.versions, "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ",
                                                                                    time.gmtime())})

    def environment(self) -> dict[str, str]:
        """The environment variables that point inductor and Triton at this folder."""
        return {"TORCHINDUCTOR_CACHE_DIR": str(self.folder / "inductor"),
                "TRITON_CACHE_DIR": str(self.folder / "triton")}

    def activate(self, label: str | None = None) -> None:
        """Point this process's inductor and Triton caches at the folder (FX graph and AOTAutograd caches on)
        and load ``label``'s artifact file if there is one. Call before the process's first compilation."""
        import torch._functorch.config as functorch_config
        import torch._inductor.config as inductor_config

        os.environ.update(self.environment())
        inductor_config.fx_graph_cache = True
        inductor_config.autotune_local_cache = True
        functorch_config.enable_autograd_cache = True
        # The simulator's custom autograd Functions (tasks.dynamics) are traced into the graph, forward and
        # backward bodies both part of the cache key (an edited backward misses: tests/gradlab/
        # test_compile_cache.py); without this the substep's and factorisation's AOTAutograd tracing is redone
        # by every warm start.
        if hasattr(functorch_config, "autograd_cache_allow_custom_autograd_functions"):
            functorch_config.autograd_cache_allow_custom_autograd_functions = True
        if not self.portable:
            _warn(f"torch {torch.__version__} has no torch.compiler.save_cache_artifacts/load_cache_artifacts: "
                  f"only this machine's on-disk caches in {self.folder} are kept")
            return
        if label is not None:
            self.load(self.artifact_path(label))

    def load(self, path: Path) -> bool:
        """Hot-load an artifact file into the on-disk caches; a damaged or foreign one is renamed to
        ``<name>.corrupt`` with a warning. Returns whether it loaded."""
        if not path.exists():
            return False
        started = time.perf_counter()
        try:
            payload = _unpack(path.read_bytes(), self.versions)
            # torch logs its own traceback for a payload it cannot parse; the warning below says it once
            torch_log = logging.getLogger("torch.compiler._cache")
            level = torch_log.level
            torch_log.setLevel(logging.ERROR)
            try:
                info = torch.compiler.load_cache_artifacts(payload)
            finally:
                torch_log.setLevel(level)
            if info is None:
                raise ValueError("torch could not read its contents")
        except Exception as e:  # whatever torch raises on a payload it cannot use: a cache miss, not a failure
            try:
                aside = _aside(path, ".corrupt")
                _warn(f"compile cache artifact {path} is unusable ({e}); moved aside to {aside.name}, the run goes "
                      f"on without it")
            except OSError:
                _warn(f"compile cache artifact {path} is unusable ({e}); the run goes on without it")
            return False
        self.loaded = _artifact_counts(info)
        self.load_s = time.perf_counter() - started
        return True

    def save(self, label: str) -> Path | None:
        """Write every artifact this process compiled or hit so far to ``label``'s file (atomically); None
        where torch has nothing to save or no portable artifacts."""
        if not self.portable:
            return None
        saved = torch.compiler.save_cache_artifacts()
        if saved is None:
            return None
        path = self.artifact_path(label)
        atomic_write_bytes(path, _pack(saved[0], self.versions))
        return path


def start_compile_workers(device: torch.device | str) -> bool:
    """Ask inductor to start its pool of Triton compile workers now, not at the process's first compilation.

    Inductor starts its worker processes (one per core, each importing torch) when the first graph compiles, and
    compiles in the calling process, one kernel after another, until they are up. A warm start reaches the
    simulator's graphs seconds after the first one loads, before the pool is up, and the kernels those graphs
    cannot take ready-made from the FX graph cache (the simulator's, launched with programmatic dependent launch)
    would be rebuilt there one at a time (their seconds: BENCHMARKS.md section 6). Started here, the pool is up by
    then.

    Returns whether inductor was asked: not for a CPU device (inductor compiles C++ there), and not where this
    torch lacks inductor's ``maybe_warm_pool`` (a private function; its absence costs only the head start).
    Inductor's own settings still apply (``TORCH_WARM_POOL=0``, one compile thread: no pool). Idempotent."""
    if torch.device(device).type != "cuda":
        return False
    try:
        from torch._inductor.async_compile import maybe_warm_pool

        maybe_warm_pool()
    except Exception:  # a head start, never a reason to fail a run
        return False
    return True


def _artifact_counts(info: Any) -> dict:
    """{kind: count} of a torch CacheInfo (``inductor``, ``aot_autograd``, ``autotune``, ...)."""
    counts = {}
    for kind in ("inductor", "aot_autograd", "autotune", "pgo", "precompile"):
        items = getattr(info, f"{kind}_artifacts", None)
        if items:
            counts[kind] = len(items)
    return counts


