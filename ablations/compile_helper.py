"""A second process that compiles the renderer and the networks while a cold ``--compile`` run compiles its physics.

Inductor compiles one graph at a time in a process, and a cold run on a GPU compiles about twenty: the physics
step, its mass-matrix factorisation and its reward/reset step, each with its backward (~45 s on an H100), and the
renderer's scene, the actor and the critic with theirs, plus the renderer's own Triton kernels (~30 s more;
BENCHMARKS.md section 6). Both halves go into the same cache folder and neither needs the other, so they can be
compiled at the same time:

* the run compiles its physics first (:meth:`gradlab.shac.SHAC.compile_physics_now`), before its first reset;
* the helper, started as the run opens its compile cache, builds a trainer of the same resolved settings with the
  physics eager (``SHAC(..., compile_physics=False)``) and runs one training iteration, which compiles everything
  else into the cache folder. Its window is :data:`HORIZON` steps: no compiled graph's shapes depend on the
  horizon (the renderer, actor and critic see one step's batch), and the eager physics of a full window took
  longer than the compiling (a 32-step ant window cost ~15 s of the helper's 71 s on an H100);
* the run waits for the helper (at most :data:`WAIT_S`), then finds those graphs and kernels in the cache.

The helper only fills the cache; the run never reads anything from it but torch's and Triton's own cache entries,
under their own keys. A helper that cannot start or fails costs the head start; one that hangs costs the wait,
at most :data:`WAIT_S`, after which it is stopped. Either way the run compiles what is missing itself. The helper
dies with the run (Linux: a parent-death signal). Its output goes to ``compile_helper.log`` in the run folder.

Started only where it pays: a CUDA device (the CPU has no cores to spare), a cache folder without this setting's
artifact file (a warm start loads everything in seconds), not on resume, and not with ``--no-compile-helper``
(which sweeps pass: their concurrent runs already use the cores).
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path

__all__ = ["HORIZON", "WAIT_S", "CompileHelper", "main"]

#: Steps of the helper's one training window (at least enough for the critic's minibatches).
HORIZON = 2
#: Longest the run waits for its helper after compiling its physics (s); after that it stops the helper and
#: compiles whatever the helper has not finished itself.
WAIT_S = 120.0


class CompileHelper:
    """The helper process of one run (see the module docstring). :meth:`start` launches it; :meth:`wait` waits for
    it to finish (True when it finished cleanly); :meth:`stop` ends it if it still runs."""

    def __init__(self, process: subprocess.Popen, log: Path, spec: Path):
        self.process, self.log, self._spec = process, log, spec
        self.started = time.time()
        self._warned = False

    @classmethod
    def start(cls, cfg, device, cache_root: Path, log: Path, *,
              command: list[str] | None = None) -> CompileHelper | None:
        """Launch a helper for the resolved ``cfg`` (a SHACConfig) on ``device``, compiling into the cache under
        ``cache_root``; its output goes to ``log``. ``command`` replaces the helper's command line (tests). None,
        with one warning, where it cannot be started (the run then compiles everything itself)."""
        spec = None
        try:
            fd, spec = tempfile.mkstemp(prefix="pixelgrad-compile-helper-", suffix=".pkl")
            with os.fdopen(fd, "wb") as f:
                pickle.dump({"config": cfg, "device": str(device), "cache_root": str(cache_root),
                             "parent": os.getpid()}, f)
            log.parent.mkdir(parents=True, exist_ok=True)
            with open(log, "wb") as out:
                process = subprocess.Popen(command or [sys.executable, "-m", "ablations.compile_helper", spec],
                                           stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        except (OSError, pickle.PicklingError, ValueError) as e:
            if spec is not None:
                Path(spec).unlink(missing_ok=True)
            warnings.warn(f"compile helper could not start ({type(e).__name__}: {e}); the run compiles everything "
                          f"itself", RuntimeWarning, stacklevel=2)
            return None
        return cls(process, log, Path(spec))

    def wait(self, timeout: float = WAIT_S, *, on_wait: Callable[[], None] | None = None) -> bool:
        """Wait until the helper exits or ``timeout`` seconds have passed; ``on_wait`` is called first if it is
        still running. True where it exited cleanly; otherwise one warning naming its log."""
        if self.process.poll() is None and on_wait is not None:
            on_wait()
        try:
            code = self.process.wait(timeout=timeout)
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

    def _warn(self, what: str) -> None:
        if not self._warned:
            self._warned = True
            warnings.warn(f"compile helper {what} (its output: {self.log})", RuntimeWarning, stacklevel=3)


def main(argv: list[str] | None = None) -> int:
    """The helper process: open the cache, build the trainer with the physics eager, run one iteration. Prints
    where its seconds went (to ``compile_helper.log``): with the run's own ``startup_s`` it shows which of the
    two was the slower half."""
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

    device = torch.device(spec["device"])
    seconds = {"imports": time.perf_counter() - began}
    mark = time.perf_counter()
    CompileCache(spec["cache_root"], device).activate()
    start_compile_workers(device)
    seconds["cache"], mark = time.perf_counter() - mark, time.perf_counter()
    cfg = spec["config"]
    horizon = min(cfg.horizon, max(HORIZON, -(-cfg.critic_batches // cfg.num_envs)))
    trainer = SHAC(dataclasses.replace(cfg, horizon=horizon), device=device, compile_physics=False)
    seconds["trainer"], mark = time.perf_counter() - mark, time.perf_counter()
    trainer.train_iteration()
    seconds["iteration"] = time.perf_counter() - mark
    watch = trainer.compile_watch.summary()
    parts = ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items())
    print(f"compile helper: {parts}; in the iteration {watch['compiles']} graphs compiled in "
          f"{watch['compile_s']:.1f} s and {watch['triton_compiles']} Triton kernels in "
          f"{watch['triton_compile_s']:.1f} s; done after {time.perf_counter() - began:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
