"""A run's start-up behind one object: what an ``ablate`` process does before and around its first iterations.

This module and those it imports at the top import nothing heavy: :meth:`Startup.before_torch` runs on
``ablate``'s first line, before torch is imported. The rest of the wing is imported when a point needs it (the
helpers' module too, which a helper process runs as its main module).
"""

from __future__ import annotations

import contextlib
import sys
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ablations.startup.bytecode import keep_bytecode, resolve_bytecode_folder

if TYPE_CHECKING:
    from ablations.startup.helpers import CompileHelpers

__all__ = ["Startup", "wants_helpers"]


def wants_helpers(cfg: Any, device: Any, cache: Any, label: str, *, resuming: bool) -> bool:
    """Whether a run of ``cfg`` (a RunConfig) starts compile helpers (``ablations.startup.helpers``): with
    --compile on a CUDA device (on the CPU inductor's C++ compiles leave no cores to spare) of a machine with
    ``MIN_CORES`` cores or more, with a compile cache folder to share, on a fresh run whose settings (``label``)
    have no artifact file yet (a warm start loads everything in seconds), unless --no-compile-helper. Not for
    --mode distill: a helper builds a SHAC trainer, whose graphs a distilled student's rollouts do not use."""
    from ablations.startup import helpers

    return (cfg.compile and cfg.compile_helper and cache is not None and device.type == "cuda" and not resuming
            and cfg.mode != "distill"
            and helpers.cores() >= helpers.MIN_CORES and not cache.artifact_path(label).exists())


class Startup:
    """One run's start-up: the bytecode folder, the compile cache, compile helper processes, compiling ahead, the
    compile statistics and the progress display's texts while the first iterations compile.

    ``ablate`` and :func:`ablations.runs.run` call it at these points, in this order:

    1. :meth:`before_torch` (``ablate``'s first line): keep Python's bytecode; start compile helpers on standby
       for a command line that may want them.
    2. :meth:`open` (run folder and device known): with --compile, open the compile cache, give the helpers
       their shares where the run wants them (else let them go), activate the cache, start inductor's compile
       workers.
    3. :meth:`trainer_built`: compile the trainer (lazily: each part at its first call) and name its parts for
       the progress display.
    4. :meth:`before_first_iteration`: show the progress texts; compile the physics ahead while the helpers
       compile the rest, and wait for them.
    5. :meth:`after_iteration` (after each iteration; :meth:`evaluating` around an evaluation): clear the
       progress text, keep new compilations in the cache's artifact file.
    6. :meth:`close` (every way out): stop the helpers, keep what is left to keep.
    7. :meth:`record`: summary.json's ``compile`` record (None without --compile).

    Each point does nothing where there is nothing to do (a run without --compile keeps only the bytecode).
    """

    def __init__(self, standby: CompileHelpers | None = None):
        self.standby = standby  # helpers started before torch, not yet given shares or let go
        self.helpers: CompileHelpers | None = None
        self.cache = None  # the compile cache (ablations.startup.cache.CompileCache), once activated
        self.label = ""  # of this run's artifact file
        self.watch = None  # ablations.startup.stats.CompileWatch, with --compile once the trainer is built
        self.trainer = None
        self.helpers_wait_s: float | None = None
        self._saved_at = 0  # compilations the artifact file holds

    # ------------------------------------------------------------------ 1. before torch
    @classmethod
    def before_torch(cls, argv: Sequence[str]) -> Startup:
        """ablate's first line, before torch is imported: where the environment keeps Python's bytecode out of
        the install, keep it in its own folder (``ablations.startup.bytecode``), or every start would compile
        torch's Python again; and a cold --compile start on a GPU shares its compiling with helper processes,
        whose imports then overlap this one's (``CompileHelpers.standby_for``)."""
        keep_bytecode(resolve_bytecode_folder())
        from ablations.startup.helpers import CompileHelpers

        return cls(CompileHelpers.standby_for(argv))

    # ------------------------------------------------------------------ 2. run folder and device known
    def open(self, cfgs: Sequence[Any], resolved: Sequence[Any], device: Any, run_dir: Path, *,
             resuming: bool) -> None:
        """Once the run folder and the device are known. ``cfgs``: the members' RunConfigs as given (their shared
        ``compile``, ``compile_cache``, ``compile_helper``); ``resolved``: their trainer settings, resolved
        (``gradlab.roster.Roster.cfgs``, in its order: a helper builds a trainer of the same members, so it compiles
        the population's shapes); ``resuming``: a resumed run.

        With --compile: the cache folder is checked (one unusable is a warning, and torch's own caches are used);
        where the run wants helpers (:func:`wants_helpers`) this process takes its CUDA context first (on a GPU in
        exclusive-process mode the helpers are then the ones that cannot start their own, and the run compiles
        everything itself) and gives them their shares before it activates the cache (the seconds that takes are
        theirs too: they activate it themselves); helpers not wanted are let go. Then torch is pointed at the
        cache, this setting's artifact file loaded and inductor's compile workers started."""
        standby, self.standby = self.standby, None
        cfg = cfgs[0]
        try:
            if cfg.compile:
                import torch

                from ablations.startup.cache import start_compile_workers
                from ablations.startup.helpers import CompileHelpers

                _show_cache_warnings_plainly()
                members, first = list(cfgs), resolved[0]
                kind = first.mode if len(members) == 1 else "population-" + "-".join(sorted(
                    {f"{c.mode}{'' if c.raster_model is None else '.' + c.raster_model}" for c in members}))
                count = len(members) if len(members) > 1 else ""
                self.label = f"{first.task}_{kind}{count}_{first.num_envs}envs_{first.image_size}px"
                cache = _open_cache(cfg.compile_cache, device)
                if wants_helpers(cfg, device, cache, self.label, resuming=resuming):
                    torch.empty(1, device=device)
                    self.helpers, standby = (standby or CompileHelpers.spawn()), None
                    self.helpers.assign(list(resolved), device, cache.folder.parent, run_dir)
                if cache is not None:
                    self.cache = _activate_cache(cache, self.label)
                start_compile_workers(device)  # after activating: the workers inherit the cache folder
        finally:
            if standby is not None:
                standby.dismiss()

    # ------------------------------------------------------------------ 3. trainer built
    def trainer_built(self, trainer: Any) -> None:
        """With --compile: compile ``trainer`` (a gradlab.SHAC: every part of its table, each at its first call)
        and watch this process's compilations, labelled by the trainer's ``COMPILE_SITES`` for the progress
        display; the trainer's own texts (capturing CUDA graphs) go to the same display."""
        if not trainer.cfg.compile:
            return
        from ablations.startup.stats import CompileWatch

        trainer.compile()
        self.trainer, self.watch = trainer, CompileWatch()
        self.watch.label_sites(trainer, trainer.COMPILE_SITES)
        trainer.on_status = self.watch.announce
        self._saved_at = self.watch.done

    # ------------------------------------------------------------------ 4. before the first iteration
    def before_first_iteration(self, show: Callable[[str | None], None]) -> float | None:
        """``show(text)`` gets the progress display's texts from now on ("compiling physics step (3 done)",
        None: nothing to say). With helpers: compile the run's own share of the physics now, then wait for the
        helpers (at most ``WAIT_S`` in all), whose graphs the run then finds in the cache. Returns the seconds
        that took (None without helpers): the run counts them in its training clock."""
        if self.watch is None:
            return None
        self.watch.on_change = show
        if self.helpers is None:
            return None
        from ablations.startup.ahead import compile_physics_ahead
        from ablations.startup.helpers import RUN_SHARE

        ahead = time.time()
        compile_physics_ahead(self.trainer, RUN_SHARE)
        waited = time.time()
        self.helpers.wait(on_wait=lambda parts: self.watch.announce(f"waiting for the compile helpers ({parts})"))
        self.helpers_wait_s = time.time() - waited
        self.watch.announce(None)
        return time.time() - ahead

    # ------------------------------------------------------------------ 5. after each iteration
    def after_iteration(self) -> None:
        """The iteration's compiling is over: the progress text goes back to the run's, and new compilations are
        kept in the artifact file for the next process."""
        if self.watch is not None:
            self.watch.announce(None)
            self._save_new()

    @contextlib.contextmanager
    def evaluating(self) -> Iterator[None]:
        """Around an evaluation: what it compiles (its own task) is shown and counted as "evaluation"."""
        if self.watch is None:
            yield
            return
        with self.watch.part("evaluation"):
            yield
        self.watch.announce(None)

    # ------------------------------------------------------------------ 6. every way out
    def close(self) -> None:
        """Stop the helpers (they die with the run anyway), stop showing texts, keep new compilations. Safe to
        call more than once."""
        for group in (self.standby, self.helpers):
            if group is not None:
                group.stop()
        if self.watch is not None:
            self.watch.on_change = None
            self._save_new()

    # ------------------------------------------------------------------ 7. the summary
    def record(self) -> dict | None:
        """summary.json's ``compile`` record: the cache folder, the artifacts loaded and the seconds that took, the
        helpers (each one's share, exit code and log) and the wait for them, the bytecode folder (where Python's
        bytecode was kept, if not beside the sources), this process's compilations (``CompileWatch.summary``),
        torch's cache counters, compile phases and graphs. None without --compile."""
        if self.watch is None:
            return None
        from ablations.startup.stats import compile_counters, compile_phase_seconds, compiled_graphs

        cache = self.cache
        return {"cache": None if cache is None else str(cache.folder),
                "artifacts_loaded": {} if cache is None else cache.loaded,
                "artifacts_load_s": None if cache is None else round(cache.load_s, 3),
                "helpers": None if self.helpers is None else self.helpers.record(),
                "helpers_wait_s": None if self.helpers_wait_s is None else round(self.helpers_wait_s, 3),
                "bytecode": sys.pycache_prefix,
                **self.watch.summary(), **compile_counters(), "phase_s": compile_phase_seconds(),
                "graphs": compiled_graphs()}

    def _save_new(self) -> None:
        """New compilations since the last save into the artifact file (a full disk loses the file, not the
        run: a warning)."""
        if self.cache is None or self.watch.done == self._saved_at:
            return
        from ablations.startup.cache import CompileCacheWarning

        try:
            self.cache.save(self.label)
        except OSError as e:
            warnings.warn(f"compile cache artifacts not saved to {self.cache.folder}: {e}", CompileCacheWarning,
                          stacklevel=2)
        self._saved_at = self.watch.done


def _open_cache(flag: str | None, device: Any):
    """The compile cache folder (checked, not yet activated) of ``--compile-cache`` ``flag``; None where it is off
    or the folder is not usable (a warning)."""
    from ablations.startup.cache import CompileCache, resolve_cache_root

    root = resolve_cache_root(flag)
    if root is None:
        print("compile cache: torch's own locations (--compile-cache off)", file=sys.stderr)
        return None
    try:
        return CompileCache(root, device)
    except OSError as e:
        _unusable(root, e)
        return None


def _activate_cache(cache: Any, label: str):
    """Point torch at the cache folder and load the artifact file of ``label``; says where the cache is. None
    where the folder turns out not usable (a warning)."""
    try:
        cache.activate(label)
    except OSError as e:
        _unusable(cache.folder, e)
        return None
    loaded = ", ".join(f"{n} {kind}" for kind, n in cache.loaded.items())
    print(f"compile cache: {cache.folder}" + (f" (loaded {loaded} artifacts)" if loaded else ""), file=sys.stderr)
    return cache


def _unusable(where: Path, error: OSError) -> None:
    from ablations.startup.cache import CompileCacheWarning

    warnings.warn(f"compile cache under {where} is not usable ({error}); compiling with torch's own caches",
                  CompileCacheWarning, stacklevel=3)


def _show_cache_warnings_plainly() -> None:
    """A compile cache warning as one ``warning: ...`` line, like the run's other warnings, not Python's
    file:line format (installed once per process)."""
    from ablations.startup.cache import CompileCacheWarning

    show = warnings.showwarning
    if getattr(show, "plain_compile_cache_warnings", False):
        return

    def show_plainly(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, CompileCacheWarning):
            print(f"warning: {message}", file=sys.stderr)
        else:
            show(message, category, filename, lineno, file, line)

    show_plainly.plain_compile_cache_warnings = True
    warnings.showwarning = show_plainly
