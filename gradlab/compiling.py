"""Where ``torch.compile`` keeps what it compiled, and what it is compiling now.

:class:`CompileCache` is one folder per torch, Triton and Python version and device kind (``cpu``, ``cuda-sm90``)
under a root the user chooses (``--compile-cache``, else ``$PIXELGRAD_COMPILE_CACHE``, else
``~/.cache/pixelgrad/compile``) and may delete at any time::

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

:class:`CompileWatch` counts this process's compilations and names the part of the trainer being compiled
("physics step", "renderer", ...) so that a progress display can say what the first iterations wait for.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import logging
import os
import re
import sys
import time
import warnings
import weakref
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch

from gradlab.checkpoint import atomic_write_bytes, atomic_write_json

__all__ = ["CACHE_ENV_VAR", "DEFAULT_CACHE_ROOT", "CompileCache", "CompileCacheWarning", "CompileWatch",
           "cache_versions", "compile_counters", "compile_phase_seconds", "compiled_graphs", "resolve_cache_root",
           "start_compile_workers"]

#: Environment variable naming the cache root (a path, or ``off`` for torch's own cache locations).
CACHE_ENV_VAR = "PIXELGRAD_COMPILE_CACHE"
#: The cache root when neither the flag nor the environment variable names one.
DEFAULT_CACHE_ROOT = Path("~/.cache/pixelgrad/compile")
#: Values of the flag or the environment variable that leave torch's cache locations alone.
OFF_VALUES = ("off", "none", "0", "false", "no")

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
    simulator's graphs seconds after the first one loads, before the pool is up: the kernels those graphs
    cannot take ready-made from the FX graph cache (on the H100 it kept none of the simulator's, which are
    launched with programmatic dependent launch) were rebuilt there one at a time (4.6 s of the warm start,
    BENCHMARKS.md section 6). Started here, the pool is up by then.

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


def compile_counters() -> dict:
    """Torch's cache counters of this process: FX graph and AOTAutograd cache hits, misses and bypasses, the
    number of distinct graphs dynamo compiled, and inductor's kernel counts (``kernel_compile_*``,
    ``graphs_saved_ready``, ``kernels_loaded_ready``; torch's names are in the code)."""
    from torch._dynamo.utils import counters

    inductor, aot, stats = counters["inductor"], counters["aot_autograd"], counters["stats"]
    return {
        "fxgraph_cache_hit": inductor["fxgraph_cache_hit"],
        "fxgraph_cache_miss": inductor["fxgraph_cache_miss"],
        "fxgraph_cache_bypass": inductor["fxgraph_cache_bypass"],
        "autograd_cache_hit": aot["autograd_cache_hit"],
        "autograd_cache_miss": aot["autograd_cache_miss"],
        "autograd_cache_bypass": aot["autograd_cache_bypass"],
        "unique_graphs": stats["unique_graphs"],
        # kernels sent to be compiled and those found compiled in this process; graphs whose FX graph cache entry
        # was saved with ready-to-launch kernels, and kernels loaded so (a warm start recompiles the others)
        "kernel_compile_miss": inductor["async_compile_cache_miss"],
        "kernel_compile_hit": inductor["async_compile_cache_hit"],
        "graphs_saved_ready": inductor["triton_bundler_save_static_autotuner"],
        "kernels_loaded_ready": inductor["triton_bundler_load_static_autotuner"],
    }


def compile_phase_seconds() -> dict[str, float]:
    """Seconds this process's compilations spent in each phase torch times (dynamo's ``compile_times`` table,
    summed over every compiled function): e.g. ``bytecode_tracing`` (dynamo), ``aot_trace_joint_graph``,
    ``Scheduler.codegen`` (inductor writing kernels), ``async_compile.wait`` (Triton's compiler workers),
    ``PyCodeCache.load_by_key_path`` (loading compiled modules). Phases nest (``compile_fx_inner`` contains
    ``Scheduler.codegen``), so they do not add up. Empty where this torch keeps no such table: it is a private
    one, and its absence costs the breakdown, never the run."""
    try:
        from torch._dynamo.utils import compile_times

        names, values = compile_times(repr="csv", aggregate=True)
    except Exception:
        return {}
    seconds = {}
    for name, value in zip(names, values):
        try:
            seconds[str(name)] = round(float(value), 3)
        except (TypeError, ValueError):
            continue
    return seconds


def compiled_graphs() -> list[dict]:
    """One record per graph this process compiled (or loaded from the caches), slowest first: which function
    (``name``, with dynamo's ``compile_id`` "frame/attempt"; a backward graph has its forward's), ``kind``
    (``forward`` or ``backward``), seconds of the whole compilation (``s``, dynamo's tracing included for a
    forward; None where torch did not time it) and of inductor's part (``inductor_s``), the FX graph's node
    count (``nodes``, forwards only) and whether inductor's FX graph cache missed (``cache_miss``). From torch's
    own per-compilation records (``torch._dynamo.utils.get_compilation_metrics``); empty where this torch keeps
    none. This is where a cold start's minutes go, graph by graph."""
    try:
        from torch._dynamo.utils import get_compilation_metrics

        metrics = list(get_compilation_metrics())
    except Exception:
        return []

    def seconds(value: Any, scale: float = 1.0) -> float | None:
        return None if value is None else round(float(value) * scale, 3)

    def compile_id(m: Any) -> str:
        return str(getattr(m, "compile_id", "") or "")

    # a backward graph's record has no function name: it carries its forward's compile id
    names = {compile_id(m): m.co_name for m in metrics if getattr(m, "co_name", None)}
    graphs = []
    for m in metrics:
        get = functools.partial(getattr, m)
        forward = get("is_forward", None) is not False
        total = (get("entire_frame_compile_time_s", None) if forward
                 else seconds(get("backward_cumulative_compile_time_us", None), 1e-6))
        misses = get("inductor_fx_local_cache_miss_count", None)
        inductor_s = seconds(get("inductor_compile_time_s", None))
        if total is None and inductor_s is None:  # torch's record of the frame itself, beside its graphs'
            continue
        graphs.append({"name": names.get(compile_id(m)), "compile_id": compile_id(m),
                       "kind": "forward" if forward else "backward", "s": seconds(total), "inductor_s": inductor_s,
                       "nodes": get("graph_node_count", None) if forward else None,
                       "cache_miss": None if misses is None or inductor_s is None else bool(misses)})
    return sorted(graphs, key=lambda g: -(g["s"] or g["inductor_s"] or 0.0))


# ---------------------------------------------------------------------------------------------- CompileWatch
#: kernels named in a watch's summary (``triton_compile_s_by_kernel``), slowest first
TRITON_KERNELS_KEPT = 20
_watches: weakref.WeakSet = weakref.WeakSet()
_hooked = _triton_hooked = False


def _tell_watches(method: str, *args: Any) -> None:
    """Call ``method`` of every live watch. A display must never fail a compilation: an error in a watch (or in
    its on_change) is dropped here."""
    for w in list(_watches):
        with contextlib.suppress(Exception):
            getattr(w, method)(*args)


def _hook_dynamo() -> bool:
    """Register one start and one end callback with dynamo for the process; False where torch has none."""
    global _hooked
    if _hooked:
        return True
    try:
        from torch._dynamo.callback import callback_handler
    except ImportError:
        return False

    def start(args: Any = None) -> None:
        _tell_watches("_compile_started", args)

    def end(args: Any = None) -> None:
        _tell_watches("_compile_ended", args)

    callback_handler.register_start_callback(start)
    callback_handler.register_end_callback(end)
    _hooked = True
    return True


def _hook_triton() -> bool:
    """Register one Triton compilation listener for the process (a public knob since Triton 3.4), chaining a
    listener already set; False where this Triton has none."""
    global _triton_hooked
    if _triton_hooked:
        return True
    try:
        from triton import knobs

        compilation = knobs.compilation
        previous = compilation.listener
    except Exception:  # no Triton, or one without the knob
        return False

    def listener(*, src: Any = None, times: Any = None, cache_hit: bool = False, **more: Any) -> None:
        _tell_watches("_triton_compiled", str(getattr(src, "name", "?")), times, cache_hit)
        if previous is not None:  # whatever Triton passes, the listener set before gets it unchanged
            previous(src=src, times=times, cache_hit=cache_hit, **more)

    compilation.listener = listener
    _triton_hooked = True
    return True


#: compilation records torch keeps for :func:`compiled_graphs` (its default, 64, lets a long run's later
#: compilations, e.g. the evaluation's, push the first iteration's out)
COMPILATION_RECORDS = 1024


def _keep_compilation_records() -> None:
    with contextlib.suppress(Exception):  # a private setter: without it the record is shorter, nothing else
        import torch._dynamo.utils as dynamo_utils

        if (dynamo_utils._compilation_metrics.maxlen or 0) < COMPILATION_RECORDS:
            dynamo_utils.set_compilation_metrics_limit(COMPILATION_RECORDS)


def _compile_id(args: Any) -> tuple[str, str, bool]:
    """(trigger name, compile id, is a recompile) of dynamo's callback arguments (``compile_id`` "frame/attempt";
    a lazily compiled backward graph carries its forward's)."""
    trigger = getattr(getattr(args, "callback_trigger", None), "name", "DYNAMO")
    compile_id = str(getattr(args, "compile_id", ""))
    match = re.search(r"(\d+)/(\d+)", compile_id)
    return trigger, compile_id, bool(match and int(match.group(2)) > 0)


class CompileWatch:
    """This process's compilations, seen from one trainer: how many, how long, and which part is compiling.

    ``labelled(part, fn)`` wraps a callable so that a compilation it triggers is reported as compiling that
    ``part``, and the backward graph of what it compiled, compiled on first use, as ``"<part> backward"``
    (wherever the backward pass runs). ``on_change(text)`` is called with a short status ("compiling physics
    step (3 done)", a text given to :meth:`announce`, or None when there is nothing to say). Counts every
    compilation of the process while the watch lives, whichever trainer triggered it.

    Attributes:
        compiles: dynamo frame compilations (recompiles included); recompiles: those of a frame compiled before;
        backward_compiles: backward graphs compiled on first use; compile_s: seconds spent compiling;
        compile_s_by_part: those seconds by the ``part`` that was compiling ("model" where none was named);
        triton_compiles, triton_compile_s, triton_cache_hits: Triton kernels this process compiled itself (the
        renderer's own; inductor's worker processes compile most of its kernels, and those are in
        :func:`compile_phase_seconds`), seconds they took, and those loaded from Triton's on-disk cache.
    """

    def __init__(self, on_change: Callable[[str | None], None] | None = None):
        self.on_change = on_change
        self.compiles = self.recompiles = self.backward_compiles = 0
        self.compile_s = 0.0
        self.compile_s_by_part: dict[str, float] = {}
        self.triton_compiles = self.triton_cache_hits = 0
        self.triton_compile_s = 0.0
        self._triton_by_kernel: dict[str, float] = {}
        self.available = _hook_dynamo()
        _hook_triton()
        _keep_compilation_records()
        self._forward_part: dict[str, str] = {}  # compile id -> the part that compiled the forward
        self.text: str | None = None
        self._parts: list[str] = []
        self._started: float | None = None
        self._compiling = "model"
        _watches.add(self)

    @property
    def done(self) -> int:
        return self.compiles + self.backward_compiles

    def labelled(self, part: str, fn: Callable) -> Callable:
        """``fn`` reporting its compilations as compiling ``part``."""

        @functools.wraps(fn)
        def call(*args, **kwargs):
            with self.part(part):
                return fn(*args, **kwargs)

        return call

    @contextlib.contextmanager
    def part(self, name: str) -> Iterator[None]:
        self._parts.append(name)
        try:
            yield
        finally:
            self._parts.pop()

    def announce(self, text: str | None) -> None:
        """Show ``text`` (None: nothing), calling ``on_change`` only when it differs from what is shown."""
        if text != self.text:
            self.text = text
            if self.on_change is not None:
                self.on_change(text)

    def _compile_started(self, args: Any) -> None:
        self._started = time.perf_counter()
        trigger, compile_id, _ = _compile_id(args)
        label = self._parts[-1] if self._parts else "model"
        if trigger == "LAZY_BACKWARD" and compile_id in self._forward_part:
            label = f"{self._forward_part[compile_id]} backward"
        elif trigger == "DYNAMO":
            self._forward_part[compile_id] = label
        self._compiling = label
        self.announce(f"compiling {self._compiling} ({self.done} done)")

    def _triton_compiled(self, name: str, times: Any, cache_hit: bool) -> None:
        if cache_hit:
            self.triton_cache_hits += 1
        else:
            seconds = times.total / 1e6  # Triton's CompileTimes are in microseconds
            self.triton_compiles += 1
            self.triton_compile_s += seconds
            self._triton_by_kernel[name] = self._triton_by_kernel.get(name, 0.0) + seconds

    def _compile_ended(self, args: Any) -> None:
        trigger, _, recompile = _compile_id(args)
        if trigger == "LAZY_BACKWARD":
            self.backward_compiles += 1
        elif trigger == "DYNAMO":
            self.compiles += 1
            self.recompiles += recompile
        if self._started is not None:
            elapsed = time.perf_counter() - self._started
            self.compile_s += elapsed
            by_part = self.compile_s_by_part
            by_part[self._compiling] = by_part.get(self._compiling, 0.0) + elapsed
            self._started = None

    def summary(self) -> dict:
        """Counts for a run's summary: compiles, recompiles, backward_compiles, compile_s, compile_s_by_part,
        triton_compiles, triton_compile_s, triton_cache_hits, triton_compile_s_by_kernel (the slowest
        :data:`TRITON_KERNELS_KEPT` kernels by name)."""
        return {"compiles": self.compiles, "recompiles": self.recompiles,
                "backward_compiles": self.backward_compiles, "compile_s": self.compile_s,
                "compile_s_by_part": {k: round(v, 3) for k, v in self.compile_s_by_part.items()},
                "triton_compiles": self.triton_compiles, "triton_compile_s": round(self.triton_compile_s, 3),
                "triton_cache_hits": self.triton_cache_hits,
                "triton_compile_s_by_kernel": {k: round(v, 3) for k, v in sorted(
                    self._triton_by_kernel.items(), key=lambda kv: -kv[1])[:TRITON_KERNELS_KEPT]}}
