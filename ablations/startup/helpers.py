"""Helper processes that compile parts of a cold ``--compile`` run at the same time as the run compiles its own.

Inductor compiles one graph at a time in a process, and a cold run on a GPU compiles about twenty: the physics
step, its mass-matrix factorisation and its reward/reset step, each with its backward, and the renderer's scene,
the actor and the critic with theirs, plus the renderer's own Triton kernels (their seconds: BENCHMARKS.md
section 6). Every graph goes into the same cache folder under its own key and none needs another to be compiled
first, so the work is split into shares (parts of :data:`gradlab.shac.COMPILE_PARTS`) that separate processes
compile at the same time:

* the run compiles :data:`RUN_SHARE` (the physics substep, the largest graph pair) before its first reset
  (:func:`ablations.startup.ahead.compile_physics_ahead`), the other physics parts running eagerly meanwhile;
* one helper per share of :data:`HELPER_SHARES` builds a trainer of the same resolved settings that compiles
  only its share (``SHAC.compile(parts=share)``, the rest eager).
  A physics share steps the physics twice and differentiates, as the run does; any other share runs one training
  iteration of :data:`HORIZON` steps (no compiled graph's shapes depend on the horizon: the renderer, actor and
  critic see one step's batch, and a longer eager window only costs time);
* the run waits for its helpers (at most :data:`WAIT_S` in all), then finds their graphs and kernels in the cache.

``ablate`` starts the helpers on standby from its first line, before it imports torch
(:meth:`CompileHelpers.standby_for`): each imports torch, the trainer's modules, dynamo and inductor's compiler
(none of it reads the cache folders' environment variables), then waits on stdin. The run sends each its share
once it holds its CUDA context (on a GPU in exclusive-process mode the helpers are then the ones that cannot start
theirs), or closes stdin to let them go when it wants none (a warm start, a CPU device); a helper looks at stdin
between its imports, so one let go stops within one module's import.

The helpers only fill the cache; the run never reads anything from it but torch's and Triton's own cache entries,
under their own keys. A helper that cannot start or fails costs its head start; one that hangs costs the wait, at
most :data:`WAIT_S`, after which it is stopped. Either way the run compiles what is missing itself. Each helper
dies with the run (Linux: a parent-death signal), uses a slice of the cores for inductor's compile workers (the
run keeps its full pool: its share is on the critical path), and writes its output to
``compile_helper_<share>.log`` in the run folder.

Started only where it pays: a CUDA device (the CPU has no cores to spare), :data:`MIN_CORES` cores or more, a
cache folder without this setting's artifact file (a warm start loads everything in seconds), not on resume, and
not with ``--no-compile-helper`` (which sweeps pass: their concurrent runs already use the cores).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import os
import pickle
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

__all__ = ["HELPER_SHARES", "HORIZON", "MIN_CORES", "RUN_SHARE", "WAIT_S", "CompileHelper", "CompileHelpers", "cores",
           "helper_shares", "main"]

#: Steps of a helper's one training window (at least enough for the critic's minibatches).
HORIZON = 2
#: Longest the run waits for its helpers in all after compiling its own share (s); after that it stops them and
#: compiles whatever they have not finished itself.
WAIT_S = 120.0
#: What the run compiles itself, ahead of its first reset.
RUN_SHARE = ("substep",)
#: Fewest CPU cores on which helpers are started: the run and three helpers each keep a core busy with their own
#: compiling (inductor's lowering and code generation run in the calling process) besides their compile workers.
MIN_CORES = 8
#: What each helper compiles (parts of gradlab.shac.COMPILE_PARTS), one helper per share, split so that the shares
#: take similar times (BENCHMARKS.md section 6); a share with nothing to compile for the mode (a renderer that never
#: runs) is dropped.
HELPER_SHARES = (("factorize", "finish"), ("renderer",), ("networks",))


def helper_shares(cfgs) -> list[tuple[str, ...]]:
    """The shares of :data:`HELPER_SHARES` with something to compile for the resolved members ``cfgs`` (SHACConfigs:
    a run alone's one, a population's members)."""
    from gradlab.config import ModePlan

    renders = any(ModePlan.of(c.mode).renders for c in cfgs)
    return [share for share in HELPER_SHARES if renders or share != ("renderer",)]


def cores() -> int:
    """The CPU cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _compile_threads(helpers: int) -> int:
    """Inductor compile workers of each helper: an even slice of the cores for the run and its helpers."""
    return max(2, cores() // (helpers + 1))


#: Helpers let go while still importing: they end by themselves (or with the run).
_LET_GO: list[subprocess.Popen] = []


class CompileHelper:
    """One helper process (see the module docstring). :meth:`spawn` starts it on standby: it imports what it needs
    and waits for its share; :meth:`assign` sends it; :meth:`dismiss` lets a helper on
    standby go; :meth:`wait` waits for it to finish (True when it finished cleanly); :meth:`stop` ends it."""

    def __init__(self, process: subprocess.Popen, early_log: Path):
        self.process, self._early_log = process, early_log
        self.log: Path | None = None
        self.parts: tuple[str, ...] = ()
        self.started = time.time()
        self._warned = False

    @classmethod
    def spawn(cls, *, threads: int | None = None, command: list[str] | None = None) -> CompileHelper | None:
        """Start a helper on standby. ``threads``: its inductor compile workers (None: inductor's default, unless
        the environment sets them). ``command`` replaces the helper's command line (tests). None, with one
        warning, where it cannot be started (the run then compiles everything itself)."""
        env = None
        if threads is not None and "TORCHINDUCTOR_COMPILE_THREADS" not in os.environ:
            env = {**os.environ, "TORCHINDUCTOR_COMPILE_THREADS": str(threads)}
        early = None
        try:
            # what it prints before it has a run folder to write to; moved there once it has one
            fd, early = tempfile.mkstemp(prefix="pixelgrad-compile-helper-", suffix=".log")
            with os.fdopen(fd, "wb") as out:
                process = subprocess.Popen(
                    command or [sys.executable, "-m", "ablations.startup.helpers", early, str(os.getpid())],
                    stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.PIPE, env=env)
        except (OSError, ValueError) as e:
            if early is not None:
                Path(early).unlink(missing_ok=True)
            warnings.warn(f"compile helper could not start ({type(e).__name__}: {e}); the run compiles that itself",
                          RuntimeWarning, stacklevel=2)
            return None
        return cls(process, Path(early))

    def assign(self, cfgs, device, cache_root: Path, log: Path, *, parts: Sequence[str]) -> bool:
        """Give the helper its share: compile ``parts`` (of gradlab.shac.COMPILE_PARTS) of a trainer of the resolved
        members ``cfgs`` (SHACConfigs, in the roster's order) on ``device`` into the cache under ``cache_root``, writing
        its output to ``log``. False, with one warning and the helper dismissed, where the log's folder cannot be made
        or the settings cannot be sent; a helper that has ended already is told by :meth:`wait` (its exit code)."""
        self.parts = tuple(parts)
        try:
            log.parent.mkdir(parents=True, exist_ok=True)
            log.touch()
            payload = pickle.dumps({"configs": list(cfgs), "device": str(device), "cache_root": str(cache_root),
                                    "parts": self.parts, "log": str(log)})
        except (OSError, pickle.PicklingError) as e:
            self._warn(f"could not be given its share ({type(e).__name__}: {e}); the run compiles that itself")
            self.dismiss()
            return False
        self.log = log
        try:
            self.process.stdin.write(payload)
            self.process.stdin.close()
        except OSError:  # it has ended already (a broken pipe): its exit code says how
            pass
        return True

    def dismiss(self) -> None:
        """Let a helper on standby go (the run needs none): it exits by itself once its imports are done,
        without doing anything; the run does not wait for that. (It dies with the run in any case.)"""
        if not self.process.stdin.closed:
            try:
                self.process.stdin.close()
            except OSError:
                pass
        self._early_log.unlink(missing_ok=True)  # nothing it says matters now
        _LET_GO.append(self.process)  # kept until it ends by itself, not garbage-collected while it runs

    def wait(self, timeout: float = WAIT_S, *, on_wait: Callable[[], None] | None = None) -> bool:
        """Wait until the helper exits or ``timeout`` seconds have passed; ``on_wait`` is called first if it is
        still running. True where it exited cleanly; otherwise one warning naming its log."""
        if self.process.poll() is None and on_wait is not None:
            on_wait()
        try:
            code = self.process.wait(timeout=max(timeout, 0.0))
        except subprocess.TimeoutExpired:
            # a helper that long is stuck or hopeless; left running it would compete with the run's own iterations
            self._warn(f"is still compiling after {timeout:.0f} s of waiting; stopped, the run compiles the rest")
            self.stop()
            return False
        self._keep_early_log()
        if code != 0:
            self._warn(f"exited with code {code}; the run compiles what it needed itself")
        return code == 0

    def stop(self) -> None:
        """End the helper if it still runs (the run is over or gave up on it)."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._keep_early_log()

    def record(self) -> dict:
        """What the run's summary keeps of this helper: its share, exit code (None: still running) and log."""
        return {"parts": list(self.parts), "returncode": self.process.poll(),
                "log": None if self.log is None else str(self.log)}

    def _keep_early_log(self) -> None:
        """What an ended helper printed before it had its log (its own code moves it there itself once it has
        its share; a helper that never got that far leaves it), appended to its log, or dropped if it has none."""
        try:
            early = self._early_log.read_bytes()
        except OSError:
            return
        if early and self.log is not None:
            with open(self.log, "ab") as f:
                f.write(early)
        self._early_log.unlink(missing_ok=True)

    def _warn(self, what: str) -> None:
        if not self._warned:
            self._warned = True
            where = "" if self.log is None else f" (its output: {self.log})"
            warnings.warn(f"compile helper ({', '.join(self.parts)}) {what}{where}", RuntimeWarning, stacklevel=3)


class CompileHelpers:
    """A run's helpers, one per share of :func:`helper_shares`: started, waited for and stopped together."""

    def __init__(self, helpers: list[CompileHelper]):
        self.helpers = helpers

    @classmethod
    def spawn(cls, n: int = len(HELPER_SHARES), *, command: list[str] | None = None) -> CompileHelpers:
        """``n`` helpers on standby (those that cannot start are left out, a warning each)."""
        helpers = [CompileHelper.spawn(threads=_compile_threads(n), command=command) for _ in range(n)]
        return cls([h for h in helpers if h is not None])

    @classmethod
    def standby_for(cls, argv: Sequence[str]) -> CompileHelpers | None:
        """Helpers on standby for an ``ablate`` command line that may want them (--compile, a device that may
        be a GPU, not a resume, not --no-compile-helper, not --help; :data:`MIN_CORES` cores or more), started
        before the run imports torch:
        their own imports then overlap the run's. None for any other command line. The run gives them their
        shares (:meth:`assign`) or lets them go (:meth:`dismiss`)."""
        args = list(argv)
        flags = {a.split("=", 1)[0] for a in args}
        device = next((a.split("=", 1)[1] for a in args if a.startswith("--device=")), None)
        if "--device" in args and args.index("--device") + 1 < len(args):
            device = args[args.index("--device") + 1]
        if ("--compile" not in flags or flags & {"--no-compile-helper", "--resume", "--help", "-h"}
                or (device or "auto") == "cpu" or cores() < MIN_CORES):
            return None
        return cls.spawn()

    def assign(self, cfgs, device, cache_root: Path, folder: Path, *,
               shares: Sequence[Sequence[str]] | None = None) -> CompileHelpers:
        """Give each share (None: :func:`helper_shares` of the resolved members ``cfgs``) to a helper, each logging to
        ``folder/compile_helper_<share>.log``; helpers left over are dismissed, and shares without one are
        spawned a helper. Returns self."""
        shares = helper_shares(cfgs) if shares is None else [tuple(share) for share in shares]
        for helper in self.helpers[len(shares):]:
            helper.dismiss()
        self.helpers = self.helpers[:len(shares)]
        while len(self.helpers) < len(shares):
            helper = CompileHelper.spawn(threads=_compile_threads(len(shares)))
            if helper is None:
                break
            self.helpers.append(helper)
        self.helpers = [helper for helper, share in zip(self.helpers, shares, strict=False)
                        if helper.assign(cfgs, device, cache_root, folder / f"compile_helper_{'_'.join(share)}.log",
                                         parts=share)]
        return self

    def dismiss(self) -> None:
        """Let every helper go unused."""
        for helper in self.helpers:
            helper.dismiss()
        self.helpers = []

    def wait(self, timeout: float = WAIT_S, *, on_wait: Callable[[str], None] | None = None) -> bool:
        """Wait for every helper, ``timeout`` seconds in all; ``on_wait`` gets the parts still being compiled
        before each wait. True where all finished cleanly (each that did not: one warning)."""
        deadline = time.monotonic() + timeout
        ok = True
        for helper in self.helpers:
            tell = None if on_wait is None else functools.partial(on_wait, self._running())
            ok &= helper.wait(deadline - time.monotonic(), on_wait=tell)
        return ok

    def _running(self) -> str:
        return ", ".join(p for h in self.helpers if h.process.poll() is None for p in h.parts)

    def stop(self) -> None:
        for helper in self.helpers:
            helper.stop()

    def record(self) -> list[dict]:
        return [helper.record() for helper in self.helpers]


#: What a helper imports on standby, in this order.
_STANDBY_IMPORTS = ("torch", "gradlab.shac", "torch._dynamo", "torch._inductor.compile_fx")


def _has_word(stream) -> bool:
    """Whether ``stream`` has something to read or has been closed (select: readable either way)."""
    import select

    try:
        return bool(select.select([stream], [], [], 0)[0])
    except (OSError, ValueError):  # not selectable (not a pipe): read it when the imports are done
        return False


def _standby(early_log: Path, parent: int) -> tuple[dict | None, float]:
    """A helper's first half: import what compiling needs while the run starts, then read its share from stdin
    and send its output to its log. Returns the share (None where the run let it go or is gone) and when the
    imports were done (``time.perf_counter``)."""
    if sys.platform.startswith("linux"):  # die with the run even if it is SIGKILLed (elsewhere: its stop())
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
        if os.getppid() != parent:
            return None, time.perf_counter()  # the run ended before this process got here
    # What the run imports, and dynamo and inductor's compiler, which it imports at its first compilation; none
    # of it reads the cache folders' environment variables before the first compilation. Between modules, a
    # word from the run (its share, or stdin closed to let it go: a warm start) ends the head start, so that a
    # helper let go stops taking CPU from the run within one module's import.
    for module in _STANDBY_IMPORTS:
        if _has_word(sys.stdin):
            break
        importlib.import_module(module)
    imported = time.perf_counter()
    try:
        spec = pickle.load(sys.stdin.buffer)
    except EOFError:  # dismissed: the run needs no helper
        return None, imported
    with open(spec["log"], "ab") as log:
        log.write(early_log.read_bytes())
        for fd in (1, 2):
            os.dup2(log.fileno(), fd)
    early_log.unlink(missing_ok=True)
    return spec, imported


def main(argv: list[str] | None = None) -> int:
    """The helper process (arguments: the file for its early output, the run's process id): import, wait for its
    share, open the cache, build a trainer that compiles only that share, and run what compiles it. Prints where
    its seconds went (to its log): with the run's own ``startup_s`` it shows which process was the slowest."""
    argv = sys.argv[1:] if argv is None else argv
    began = time.perf_counter()
    spec, imported = _standby(Path(argv[0]), int(argv[1]))
    if spec is None:
        Path(argv[0]).unlink(missing_ok=True)
        return 0
    import torch

    from ablations.startup.ahead import compile_physics_ahead
    from ablations.startup.cache import CompileCache, start_compile_workers
    from ablations.startup.stats import CompileWatch
    from gradlab import precision
    from gradlab.shac import SHAC
    from tasks import PHYSICS_PARTS

    device, parts = torch.device(spec["device"]), spec["parts"]
    seconds = {"imports": imported - began, "standby": time.perf_counter() - imported}
    mark = time.perf_counter()
    CompileCache(spec["cache_root"], device).activate()
    start_compile_workers(device)
    seconds["cache"], mark = time.perf_counter() - mark, time.perf_counter()
    cfgs = spec["configs"]
    # the members share the horizon and the batch; the window covers every member's critic minibatches
    horizon = min(cfgs[0].horizon, max(HORIZON, *(-(-c.critic_batches // c.num_envs) for c in cfgs)))
    precision.use(cfgs[0].precision, device)  # as the run does: the same graphs, so the same cache entries
    trainer = SHAC([dataclasses.replace(c, horizon=horizon) for c in cfgs], device=device)
    trainer.compile(parts=parts)
    watch = CompileWatch()
    seconds["trainer"], mark = time.perf_counter() - mark, time.perf_counter()
    if set(parts) <= set(PHYSICS_PARTS):
        compile_physics_ahead(trainer)  # the run's own way of compiling the physics: the same guards
    else:
        trainer.train_iteration()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    seconds["compiling"] = time.perf_counter() - mark
    counts = watch.summary()
    spent = ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items())
    print(f"compile helper ({', '.join(parts)}): {spent}; {counts['compiles']} graphs compiled in "
          f"{counts['compile_s']:.1f} s and {counts['triton_compiles']} Triton kernels in "
          f"{counts['triton_compile_s']:.1f} s; done after {time.perf_counter() - began:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
