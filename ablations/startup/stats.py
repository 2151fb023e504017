"""What this process compiled, read from torch's and Triton's own records, and which part is compiling now.

:func:`compile_counters`, :func:`compile_phase_seconds` and :func:`compiled_graphs` read torch's counters, phase
times and per-compilation records (private tables: where a torch lacks one, the record is shorter, never the
run). :class:`CompileWatch` counts this process's compilations and names the part of the trainer being compiled
("physics step", "renderer", ...) so that a progress display can say what the first iterations wait for. This
module imports torch only when asked, so that the start-up wing can be imported before torch.
"""

from __future__ import annotations

import contextlib
import functools
import re
import time
import weakref
from collections.abc import Callable, Iterator
from typing import Any

__all__ = ["TRITON_KERNELS_KEPT", "CompileWatch", "compile_counters", "compile_phase_seconds", "compiled_graphs"]


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
    none. This is where a cold start's time goes, graph by graph."""
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

    def label_sites(self, owner: Any, sites: dict[str, str]) -> None:
        """Label the callables ``owner`` calls its compiled parts through: ``sites`` maps a label to an attribute
        path from ``owner`` (``"window.backward"``), whose callable is replaced by :meth:`labelled` of it."""
        for label, path in sites.items():
            *parents, name = path.split(".")
            holder = functools.reduce(getattr, parents, owner)
            setattr(holder, name, self.labelled(label, getattr(holder, name)))

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
