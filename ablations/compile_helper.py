"""Helper processes that compile parts of a cold ``--compile`` run at the same time as the run compiles its own.

Inductor compiles one graph at a time in a process, and a cold run on a GPU compiles about twenty: the physics
step, its mass-matrix factorisation and its reward/reset step, each with its backward (~45 s on an H100), and the
renderer's scene, the actor and the critic with theirs, plus the renderer's own Triton kernels (~30 s more;
BENCHMARKS.md section 6). Every graph goes into the same cache folder under its own key and none needs another
to be compiled first, so the work is split into shares (parts of :data:`gradlab.shac.COMPILE_PARTS`) that
separate processes compile at the same time:

* the run compiles :data:`RUN_SHARE` (the physics substep, the largest graph pair) before its first reset
  (:meth:`gradlab.shac.SHAC.compile_physics_now`), the other physics parts running eagerly meanwhile;
* one helper per share of :data:`HELPER_SHARES`, started as the run opens its compile cache, builds a trainer of
  the same resolved settings that compiles only its share (``SHAC(..., compile_parts=share)``, the rest eager).
  A physics share steps the physics twice and differentiates, as the run does; any other share runs one training
  iteration of :data:`HORIZON` steps (no compiled graph's shapes depend on the horizon: the renderer, actor and
  critic see one step's batch, and a longer eager window only costs time);
* the run waits for its helpers (at most :data:`WAIT_S` in all), then finds their graphs and kernels in the cache.

The helpers only fill the cache; the run never reads anything from it but torch's and Triton's own cache entries,
under their own keys. A helper that cannot start or fails costs its head start; one that hangs costs the wait, at
most :data:`WAIT_S`, after which it is stopped. Either way the run compiles what is missing itself. Each helper
dies with the run (Linux: a parent-death signal), uses a slice of the cores for inductor's compile workers (the
run keeps its full pool: its share is on the critical path), and writes its output to
``compile_helper_<share>.log`` in the run folder.

Started only where it pays: a CUDA device (the CPU has no cores to spare), a cache folder without this setting's
artifact file (a warm start loads everything in seconds), not on resume, and not with ``--no-compile-helper``
(which sweeps pass: their concurrent runs already use the cores).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import pickle
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

__all__ = ["HELPER_SHARES", "HORIZON", "RUN_SHARE", "WAIT_S", "CompileHelper", "CompileHelpers", "helper_shares",
           "main"]

#: Steps of a helper's one training window (at least enough for the critic's minibatches).
HORIZON = 2
#: Longest the run waits for its helpers in all after compiling its own share (s); after that it stops them and
#: compiles whatever they have not finished itself.
WAIT_S = 120.0
#: What the run compiles itself, ahead of its first reset.
RUN_SHARE = ("substep",)
#: What each helper compiles (parts of gradlab.shac.COMPILE_PARTS), one helper per share. The physics' other two
#: parts, the renderer and the networks each cost about as much as the substep alone on the ant (BENCHMARKS.md
#: section 6); a share with nothing to compile for the mode (a renderer that never runs) is dropped.
HELPER_SHARES = (("factorize", "finish"), ("renderer",), ("networks",))


def helper_shares(cfg) -> list[tuple[str, ...]]:
    """The shares of :data:`HELPER_SHARES` with something to compile for the resolved ``cfg`` (a SHACConfig)."""
    from gradlab.config import ModePlan

    renders = ModePlan.of(cfg.mode).renders
    return [share for share in HELPER_SHARES if renders or share != ("renderer",)]


def _compile_threads(helpers: int) -> int:
    """Inductor compile workers of each helper: an even slice of the cores for the run and its helpers."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(2, cores // (helpers + 1))


class CompileHelper:
    """One helper process (see the module docstring). :meth:`start` launches it; :meth:`wait` waits for it to
    finish (True when it finished cleanly); :meth:`stop` ends it if it still runs."""

    def __init__(self, process: subprocess.Popen, log: Path, spec: Path, parts: tuple[str, ...]):
        self.process, self.log, self._spec, self.parts = process, log, spec, parts
        self.started = time.time()
        self._warned = False

    @classmethod
    def start(cls, cfg, device, cache_root: Path, log: Path, *, parts: Sequence[str], threads: int | None = None,
              command: list[str] | None = None) -> CompileHelper | None:
        """Launch a helper that compiles ``parts`` (of gradlab.shac.COMPILE_PARTS) of the resolved ``cfg`` (a
        SHACConfig) on ``device`` into the cache under ``cache_root``; its output goes to ``log``. ``threads``:
        its inductor compile workers (None: inductor's default, unless the environment sets them). ``command``
        replaces the helper's command line (tests). None, with one warning, where it cannot be started (the run
        then compiles those parts itself)."""
        spec = None
        env = None
        if threads is not None and "TORCHINDUCTOR_COMPILE_THREADS" not in os.environ:
            env = {**os.environ, "TORCHINDUCTOR_COMPILE_THREADS": str(threads)}
        try:
            fd, spec = tempfile.mkstemp(prefix="pixelgrad-compile-helper-", suffix=".pkl")
            with os.fdopen(fd, "wb") as f:
                pickle.dump({"config": cfg, "device": str(device), "cache_root": str(cache_root),
                             "parts": tuple(parts), "parent": os.getpid()}, f)
            log.parent.mkdir(parents=True, exist_ok=True)
            with open(log, "wb") as out:
                process = subprocess.Popen(command or [sys.executable, "-m", "ablations.compile_helper", spec],
                                           stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        except (OSError, pickle.PicklingError, ValueError) as e:
            if spec is not None:
                Path(spec).unlink(missing_ok=True)
            warnings.warn(f"compile helper ({', '.join(parts)}) could not start ({type(e).__name__}: {e}); the run "
                          f"compiles that itself", RuntimeWarning, stacklevel=2)
            return None
        return cls(process, log, Path(spec), tuple(parts))

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
        finally:
            self._spec.unlink(missing_ok=True)
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
        self._spec.unlink(missing_ok=True)

    def record(self) -> dict:
        """What the run's summary keeps of this helper: its share, exit code (None: still running) and log."""
        return {"parts": list(self.parts), "returncode": self.process.poll(), "log": str(self.log)}

    def _warn(self, what: str) -> None:
        if not self._warned:
            self._warned = True
            warnings.warn(f"compile helper ({', '.join(self.parts)}) {what} (its output: {self.log})",
                          RuntimeWarning, stacklevel=3)


class CompileHelpers:
    """A run's helpers, one per share of :func:`helper_shares`: started, waited for and stopped together."""

    def __init__(self, helpers: list[CompileHelper]):
        self.helpers = helpers

    @classmethod
    def start(cls, cfg, device, cache_root: Path, folder: Path, *,
              shares: Sequence[Sequence[str]] | None = None) -> CompileHelpers:
        """One helper per share (None: :func:`helper_shares` of ``cfg``), each logging to
        ``folder/compile_helper_<share>.log``. Those that cannot start are left out (a warning each)."""
        shares = helper_shares(cfg) if shares is None else [tuple(share) for share in shares]
        threads = _compile_threads(len(shares))
        helpers = [CompileHelper.start(cfg, device, cache_root, folder / f"compile_helper_{'_'.join(share)}.log",
                                       parts=share, threads=threads) for share in shares]
        return cls([h for h in helpers if h is not None])

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


def main(argv: list[str] | None = None) -> int:
    """The helper process: open the cache, build a trainer that compiles only this helper's share, and run what
    compiles it. Prints where its seconds went (to its log): with the run's own ``startup_s`` it shows which
    process was the slowest."""
    began = time.perf_counter()
    argv = sys.argv[1:] if argv is None else argv
    with open(argv[0], "rb") as f:
        spec = pickle.load(f)  # imports torch and the trainer's modules, to rebuild the settings
    Path(argv[0]).unlink(missing_ok=True)  # read once: nothing left behind whatever happens next
    if sys.platform.startswith("linux"):  # die with the run even if it is SIGKILLed (elsewhere: its stop())
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
        if os.getppid() != spec.get("parent", os.getppid()):
            return 1  # the run ended before this process got here
    import torch

    from gradlab.compiling import CompileCache, start_compile_workers
    from gradlab.shac import SHAC
    from tasks import PHYSICS_PARTS

    device, parts = torch.device(spec["device"]), spec["parts"]
    seconds = {"imports": time.perf_counter() - began}
    mark = time.perf_counter()
    CompileCache(spec["cache_root"], device).activate()
    start_compile_workers(device)
    seconds["cache"], mark = time.perf_counter() - mark, time.perf_counter()
    cfg = spec["config"]
    horizon = min(cfg.horizon, max(HORIZON, -(-cfg.critic_batches // cfg.num_envs)))
    trainer = SHAC(dataclasses.replace(cfg, horizon=horizon), device=device, compile_parts=parts)
    seconds["trainer"], mark = time.perf_counter() - mark, time.perf_counter()
    if set(parts) <= set(PHYSICS_PARTS):
        trainer.compile_physics_now()  # the run's own way of compiling the physics: the same guards
    else:
        trainer.train_iteration()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    seconds["compiling"] = time.perf_counter() - mark
    watch = trainer.compile_watch.summary()
    spent = ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items())
    print(f"compile helper ({', '.join(parts)}): {spent}; {watch['compiles']} graphs compiled in "
          f"{watch['compile_s']:.1f} s and {watch['triton_compiles']} Triton kernels in "
          f"{watch['triton_compile_s']:.1f} s; done after {time.perf_counter() - began:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
