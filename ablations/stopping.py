"""How a run stops without losing work silently: a signal as a request to stop at the end of the iteration
(:class:`StopOnSignal`), the copy of the last finished iteration the loop holds between checkpoints
(:func:`copy_state`) and its checkpoint after a stop mid-iteration (:func:`rescue`), both kept by a loop's
:class:`Keeper`, and the one line an error that stopped a run is told in (:func:`describe_error`,
:class:`RunFailed`). Every member of a population (a single
run: one) is checkpointed alike (docs/design.md, "Run folders and resume").
"""

from __future__ import annotations

import contextlib
import copy
import re
import signal
import sys
import threading
import warnings
from collections.abc import Iterator

import torch
from tqdm import tqdm

from ablations.memory.worker import is_oom
from ablations.run_folder import RunFolder
from gradlab.probes import NonFiniteError

__all__ = ["Keeper", "RunFailed", "StopOnSignal", "checkpoint", "copy_state", "describe_error", "plain_warnings",
           "rescue"]


class RunFailed(RuntimeError):
    """A run stopped on an error, after recording it in its summary.json (``status``: nonfinite, oom or failed)
    and checkpointing its last finished iteration where it could; the message is one line: what went wrong, and
    what the run folder keeps or which iterations are lost."""

    def __init__(self, status: str, line: str):
        super().__init__(line)
        self.status = status


def describe_error(e: BaseException, device=None, where: str = "") -> tuple[str, str]:
    """(summary status, one line) of an error that stopped a run ``where`` (e.g. "during iteration 3"): ``oom``
    for running out of memory on either device (torch's OutOfMemoryError, MemoryError, or the CPU allocator's
    RuntimeError), ``nonfinite`` for a NonFiniteError, ``failed`` for any other."""
    first = (str(e).strip().splitlines() or [""])[0]
    at = f" {where}" if where else ""
    if isinstance(e, NonFiniteError):
        return "nonfinite", first
    if is_oom(e):
        on = "GPU" if "cuda" in first.lower() or getattr(device, "type", device) == "cuda" else "CPU"
        size = re.search(r"tried to allocate ([0-9.]+) ?(bytes|[KMGT]i?B)", first, re.IGNORECASE)
        if size and size.group(2) == "bytes":
            what = f"an allocation of {int(size.group(1)) / 2**30:.3g} GiB failed"
        elif size:
            what = f"an allocation of {size.group(1)} {size.group(2)} failed"
        else:
            what = first[:200] or type(e).__name__
        return "oom", (f"out of memory on the {on}{at} ({what}; fewer --num-envs or --eval-envs, a smaller "
                       f"--image-size or --horizon need less: --resume keeps a run's settings, so start a new run "
                       f"with them)")
    return "failed", f"{type(e).__name__}{at}: {first}"[:500]


def copy_state(state):
    """A copy of a trainer's state_dict() that the next iteration does not change (its tensors are the live
    ones): CUDA tensors copied to (pinned) host memory without waiting for them, the rest cloned or deep-copied.
    Host memory, not the device's: the copy must not change a run's measured peak memory. Its cost is mostly the
    encoder's first linear layer and its two Adam moments (hopper, 64 environments: 74 MB a run, about 10 ms on
    the CPU; a few ms over PCIe), paid between iterations."""
    if isinstance(state, torch.Tensor):
        return state.detach().to("cpu", non_blocking=True) if state.is_cuda else state.detach().clone()
    if isinstance(state, dict):
        return {k: copy_state(v) for k, v in state.items()}
    if type(state) in (list, tuple):
        return type(state)(copy_state(v) for v in state)
    return copy.deepcopy(state)


def rescue(live_states, folders: list[RunFolder], between: bool, held, done: int, checkpointed: int,
           keep: int) -> tuple[int, str | None]:
    """After a stop mid-run: checkpoint the last finished iteration (``done``) when it is not on disk, from the
    live trainer (``live_states()``: its members' states) when it stopped between iterations, else from the copy
    ``held``. Returns (the iteration the run
    folder now resumes from, 0 for none; None, or what is lost and why when that is not ``done``)."""
    if done <= checkpointed:
        return checkpointed, None
    try:
        if between:
            states = live_states()
        elif held is not None and held[0] == done:
            states = held[1]
            if torch.cuda.is_available() and torch.cuda.is_initialized():
                torch.cuda.synchronize()  # the copies to host memory were not waited for
        else:
            raise RuntimeError("no copy of it was held")
        checkpoint(states, folders, done, keep)
        return done, None
    except BaseException as e:  # a third signal, a full disk, a device that failed: say what is lost
        why = describe_error(e)[1] if not isinstance(e, KeyboardInterrupt) else f"{str(e) or 'SIGINT'} again"
        since = f"since the checkpoint of iteration {checkpointed}" if checkpointed else "(no checkpoint yet)"
        span = f"iteration {done}" if done == checkpointed + 1 else f"iterations {checkpointed + 1}..{done}"
        return checkpointed, f"lost {span} {since}: checkpointing iteration {done} failed ({why})"


def checkpoint(states: list, folders: list[RunFolder], iteration: int, keep: int) -> None:
    """Every member's checkpoint of ``iteration`` (``states``: one per member) into its folder (a stopped
    member's too, recording why it stopped: a population resumes from an iteration every member has). The older
    checkpoints are pruned only once every member's new one is written: a process killed in between leaves the
    last iteration every member holds, which a resume takes."""
    for folder, state in zip(folders, states, strict=True):
        folder.save_checkpoint(iteration, state)
    for folder in folders:
        folder.prune_checkpoints(keep)


class Keeper:
    """The members' checkpoints while a loop trains them (one per member, in ``folders``' order), and the one
    rescue for every way out of it (:meth:`rescue`).

    ``done`` is the newest iteration whose metrics every member's folder holds, ``checkpointed`` the newest one on
    disk, ``held`` (iteration, states) a copy of the newest finished iteration that is not on disk yet, and
    ``between`` whether the live trainer is at a finished iteration (not inside one), so that its own state is
    that iteration's; ``lost``: what a rescue could not keep.
    """

    def __init__(self, trainer, folders: list[RunFolder], *, keep: int, device: torch.device):
        self.trainer, self.folders, self.keep, self.device = trainer, folders, keep, device
        self.done = self.checkpointed = trainer.iteration
        self.held: tuple[int, object] | None = None
        self.between = True
        self.lost: str | None = None

    def begin(self) -> None:
        """An iteration starts: the live trainer is inside it until :meth:`finished`."""
        self.between = False

    def finished(self, iteration: int, *, save: bool) -> None:
        """Iteration ``iteration`` is finished and recorded: checkpoint it (``save``), else hold a copy of it."""
        self.done, self.between = iteration, True
        if save:
            self.save()
        else:
            self.held = None  # the older copy first: two at once would double what it holds
            self.held = (iteration, copy_state(self.trainer.state_dict()))
            if self.device.type == "cuda":  # waited for here, outside the next iteration's measured time
                torch.cuda.synchronize(self.device)

    def save(self) -> None:
        """Checkpoint the live trainer's iteration, unless it is on disk already."""
        if self.checkpointed != self.trainer.iteration:
            checkpoint(self.trainer.state_dict(), self.folders, self.trainer.iteration, self.keep)
            self.checkpointed = self.trainer.iteration
        self.held = None

    def rescue(self, e: BaseException, *, ran: bool, home) -> tuple[str, str]:
        """After ``e`` stopped the loop (a second signal, an error, SystemExit and its like): the last finished
        iteration checkpointed where it can be (:func:`rescue`), and (status, line) for the summary of every
        member still training. ``ran``: an iteration had started (else the stop came while building, recording
        or compiling ahead); ``home``: the folder ``ablate --resume`` takes."""
        done = self.done
        where = (f"during iteration {done + 1}" if not self.between else
                 f"before iteration {done + 1}" if not ran else f"after iteration {done}")
        kept, lost = rescue(self.trainer.state_dict, self.folders, self.between, self.held, done,
                            self.checkpointed, self.keep)
        self.checkpointed, self.lost = kept, lost
        if isinstance(e, KeyboardInterrupt):
            name = str(e) or "SIGINT"  # Python's own handler raises it without one
            why = f"{name} {where}: stopped at once" + (f", iteration {done + 1} is lost" if not self.between else "")
            return "interrupted", why + (f"; {lost}" if lost else (f"; resumes from iteration {kept}" if kept else ""))
        if isinstance(e, Exception):
            status, text = describe_error(e, self.device, where)  # a NonFiniteError names its iteration itself
            return status, text + (f"; {lost}" if lost else f"; the run resumes from iteration {kept}: ablate "
                                                            f"--resume {home}"
                                   if kept else "; no iteration finished, nothing to resume")
        return "failed", f"{type(e).__name__} after iteration {done}"


class StopOnSignal:
    """SIGINT and SIGTERM as a request to stop, inside ``with``.

    Before :meth:`defer_to_iteration_end` (building the trainer, compiling ahead) a signal raises
    KeyboardInterrupt at once; after it the first signal only sets :attr:`requested` (its name), so that the
    training loop finishes the iteration it is in, checkpoints it and stops; a second one raises
    KeyboardInterrupt. After :meth:`finishing` (the run is writing its last checkpoint and summary) a signal is
    only answered: those writes are what keeps the run resumable. Outside the main thread (where Python delivers
    signals) it does nothing.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested: str | None = None
        self._deferring = False
        self._finishing = False
        self._holding = False
        self._held: str | None = None
        self._previous: dict = {}

    def __enter__(self) -> StopOnSignal:
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in self.SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)

    def defer_to_iteration_end(self) -> None:
        self._deferring = True

    def finishing(self) -> None:
        self._finishing = True

    @contextlib.contextmanager
    def held(self) -> Iterator[None]:
        """Inside: a signal waits for the block's end, then acts as it would have (writes that must all happen
        or none, such as a new population's member records: stopped half-way, the population would not resume)."""
        self._holding = True
        try:
            yield
        finally:
            self._holding = False
        if self._held is not None:
            name, self._held = self._held, None
            self._act(name)

    def _handle(self, signum: int, frame) -> None:
        name = signal.Signals(signum).name
        if self._holding:
            self._held = self._held or name
            return
        self._act(name)

    def _act(self, name: str) -> None:
        if self._finishing:
            tqdm.write(f"{name}: already stopping; writing the last checkpoint and summary.json first (SIGKILL stops "
                       f"at once, without them)", file=sys.stderr)
            return
        if not self._deferring or self.requested is not None:
            raise KeyboardInterrupt(name)
        self.requested = name
        tqdm.write(f"{name}: stopping once this iteration has finished and is checkpointed (send it again to stop "
                   f"at once: this iteration is then lost, the one before it checkpointed)", file=sys.stderr)


@contextlib.contextmanager
def plain_warnings() -> Iterator[None]:
    """Inside: every warning is one line ``warning: <message>`` on stderr, each message once, written through
    tqdm so that it does not tear the progress bar (Python's own form adds the source line and repeats per place
    it is raised). The warning filters stay as they are."""
    shown: set[tuple[type, str]] = set()

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        key = (category, str(message))
        if key not in shown:
            shown.add(key)
            tqdm.write(f"warning: {message}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.showwarning = show
        yield


