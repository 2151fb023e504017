"""CUDA-graph capture and replay of a SHAC iteration, behind two small objects the trainer calls every iteration.

``WindowGraphs.run(iteration=, probe=)`` runs one window's forward (rollout + loss) and backward, eagerly or by
replaying the CUDA graphs captured from it; ``GraphedCriticPhase(buf)`` runs the critic fit the same way. With
capture off (the CPU, or no ``--compile``) both are the eager calls they wrap, so the trainer reads the same
either way (docs/design.md, "CUDA graphs").

The critic fit reads only the forward's buffers and writes only the critic and its optimiser, and the actor's
backward never reads either, so a replayed window may run the fit's graph on a second stream while the backward
replays: the same numbers, and its time hidden behind the backward's (both are chains of small kernels that
leave most of the GPU idle).

A captured graph replays fixed device addresses: every tensor it reads or writes must be the same tensor
object at every replay. ``LiveState`` is why that holds for the state one window hands to the next (task
state, frame buffer): the window's end state is copied into fixed tensors and the task is pointed back at
them. Eager iterations commit the same way, so eager and replayed iterations interleave freely (a first
probe iteration runs eagerly between replays of the plain window).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import torch

from gradlab.timing import MemoryProbe, RegionTimer, SavedTensorMeter

__all__ = ["WARMUP_ITERS", "LiveState", "Window", "WindowGraphs", "GraphedCriticPhase", "zero_grads_"]

#: Eager iterations before a window is captured (compilation and library warm-up happen in them).
WARMUP_ITERS = 2


def zero_grads_(params: Iterable[torch.nn.Parameter]) -> None:
    """Zero the gradients IN PLACE, creating them where missing: captured graphs write into these very tensors."""
    for p in params:
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        else:
            p.grad.zero_()


class LiveState:
    """The state a window starts from, held in fixed tensors.

    ``commit`` copies the state a window ended in into the fixed tensors and points the task (and the frame
    buffer) at them. A captured graph that reads them at the start and writes them at the end (after its
    backward, which may still read the old values) thereby carries the state from one replay to the next.
    """

    def __init__(self):
        self.tensors: dict[str, torch.Tensor] = {}

    def commit(self, task, frames=None) -> None:
        """task: the Task whose state tensors (``Task.STATE_TENSORS``) carry over; frames: its FrameStack, or
        None where the trainer does not render."""
        current = task.state_tensors()
        if frames is not None:
            current.update({f"frame{i}": f for i, f in enumerate(frames.frames)})
        live = self.tensors
        with torch.no_grad():
            for k, v in current.items():
                if k not in live:
                    live[k] = v.detach().clone()
                elif v is not live[k]:
                    live[k].copy_(v)
        task.use_state_tensors(live)
        if frames is not None:
            frames.frames = [live[f"frame{i}"] for i in range(len(frames.frames))]


@dataclass
class Window:
    """What one window's forward and backward leave behind (a replay's static outputs, overwritten by the next).

    loss: the actor loss (0-d; a population's: one per member); buffers: the rollout's (T, B, ...) buffers;
    probe_metrics: 0-d tensors of a probe iteration (empty otherwise); saved_bytes: bytes autograd kept for
    backward; memory: the peak memory of forward and backward (a capture is outside it); replayed: the window
    ran as a CUDA-graph replay; critic_loss: the critic fit's loss where the fit ran alongside the backward
    (``overlapped``), else None (the trainer fits the critic after the actor's step).
    """

    loss: torch.Tensor
    buffers: dict
    probe_metrics: dict
    saved_bytes: int
    memory: MemoryProbe
    replayed: bool
    critic_loss: torch.Tensor | None = None
    overlapped: bool = False


class _CapturedWindow:
    """One window's rollout + loss (``fwd``) and backward (``bwd``) captured as two CUDA graphs.

    Two graphs sharing one memory pool (as ``torch.cuda.make_graphed_callables`` does) so forward and backward
    stay separately timed. ``bwd`` ends with the live-state commit (after the backward, which still reads the
    old values). ``loss``, ``buffers`` and ``probe_metrics`` are the graphs' static outputs. Capturing records
    work without doing it: the caller replays both graphs afterwards, so the capture iteration is real.
    """

    def __init__(self, owner: WindowGraphs, *, probe: bool):
        zero_grads_(owner.params)
        pool = torch.cuda.graph_pool_handle()
        self.fwd, self.bwd = torch.cuda.CUDAGraph(), torch.cuda.CUDAGraph()
        for generator in owner.generators:  # a population's noise streams: each replay continues each one
            self.fwd.register_generator_state(generator)
        torch.cuda.synchronize(owner.device)
        with torch.cuda.graph(self.fwd, pool=pool, stream=owner.capture_stream):
            with SavedTensorMeter() as saved:
                self.loss, self.buffers = owner.forward(probe)
        with torch.cuda.graph(self.bwd, pool=pool, stream=owner.capture_stream):
            self.probe_metrics = owner.backward(self.loss, probe)
            owner.commit()
        self.saved_bytes = saved.bytes


class WindowGraphs:
    """Runs one SHAC window's forward and backward, eagerly or by replaying CUDA graphs captured from it.

    The first ``WARMUP_ITERS`` iterations run eagerly (torch.compile, cuBLAS/cuDNN handles, the allocator warm
    up in them), then the window is captured once and replayed. Plain and probe windows run different code (a
    probe renders with grad and differentiates twice), so they are captured separately, and each kind runs
    eagerly at least once before its capture: compiling inside a capture would invalidate it.

    Args:
        forward: ``forward(probe) -> (loss, buffers)``, the rollout and the actor loss.
        backward: ``backward(loss, probe) -> probe_metrics``, the actor's gradients into ``.grad``.
        commit: writes the window's end state into the live-state tensors (``LiveState.commit``).
        params: the actor's parameters (their ``.grad`` are written in place by a replay).
        timer: times the regions "fwd", "bwd" and "critic" (a capture is outside them).
        device: the device the window runs on.
        capture: capture and replay (a CUDA device and ``--compile``); False runs every window eagerly.
        critic: the critic fit's graph, run on its own stream while a replayed backward replays (once it is
            captured); None: the window never runs the fit (the trainer runs it after the actor's step).
        generators: random generators other than torch's default one that the forward draws from (a
            population's per-member action noise): registered with the captured forward, so that every replay
            draws their next numbers as eager code would.
    """

    def __init__(self, *, forward: Callable[[bool], tuple[torch.Tensor, dict]],
                 backward: Callable[[torch.Tensor, bool], dict], commit: Callable[[], None],
                 params: list[torch.nn.Parameter], timer: RegionTimer, device: torch.device, capture: bool,
                 critic: GraphedCriticPhase | None = None, generators: Iterable[torch.Generator] = ()):
        self.forward, self.backward, self.commit = forward, backward, commit
        self.generators = list(generators)
        self.params, self.timer, self.device, self.capture = params, timer, device, capture
        self.critic = critic
        # The window's graphs are captured on a stream of their own, never the critic's: cuBLAS keeps a
        # workspace per stream, a graph keeps the one it was captured with, and two graphs that replay at once
        # must not share one. (Streams come from a pool that repeats every 32 draws.)
        self.capture_stream = None
        if capture:
            self.capture_stream = torch.cuda.Stream(device)
            if critic is not None and self.capture_stream == critic.stream:
                self.capture_stream = torch.cuda.Stream(device)
        self.captured: dict[bool, _CapturedWindow] = {}  # plain (False) and probe (True) windows
        self._eager_runs = {False: 0, True: 0}
        if capture:
            # The encoder's convolutions have one static shape per run: let cuDNN time its algorithms once (in
            # the eager warm-up iterations, before any capture) instead of taking its heuristic's choice. A
            # process-wide switch; the run's info.json records it.
            torch.backends.cudnn.benchmark = True

    def run(self, *, iteration: int, probe: bool) -> Window:
        """The window of training iteration ``iteration`` (0-based); ``probe``: a probe iteration."""
        replay = self.capture and iteration >= WARMUP_ITERS and self._eager_runs[probe] > 0
        if not replay:
            self._eager_runs[probe] += 1
        elif probe not in self.captured:
            self.captured[probe] = _CapturedWindow(self, probe=probe)
        overlap = replay and self.critic is not None and self.critic.graph is not None
        critic_loss = None
        with MemoryProbe(self.device) as memory:
            if replay:
                graph = self.captured[probe]
                with self.timer("fwd"):
                    graph.fwd.replay()
                with self.timer("bwd"):
                    if overlap:
                        critic_loss = self._critic_beside(graph.bwd, graph.buffers)
                    else:
                        graph.bwd.replay()
                if overlap:  # after the region, so that "bwd" times the backward alone
                    torch.cuda.current_stream(self.device).wait_stream(self.critic.stream)
                loss, buffers, probe_metrics, saved_bytes = (graph.loss, graph.buffers, graph.probe_metrics,
                                                             graph.saved_bytes)
            else:
                with self.timer("fwd"), SavedTensorMeter() as saved:
                    loss, buffers = self.forward(probe)
                with self.timer("bwd"):
                    probe_metrics = self.backward(loss, probe)
                    self.commit()
                saved_bytes = saved.bytes
        return Window(loss, buffers, probe_metrics, saved_bytes, memory, replay, critic_loss, overlap)

    def _critic_beside(self, backward: torch.cuda.CUDAGraph, buffers: dict) -> torch.Tensor:
        """Replay ``backward`` on the current stream and the critic fit on its own stream, starting once the
        forward's buffers are written (not after the backward). The caller makes the current stream wait for
        the fit's (the next forward overwrites the buffers; the target update reads the critic)."""
        main, side = torch.cuda.current_stream(self.device), self.critic.stream
        forward_done = main.record_event()
        backward.replay()
        side.wait_event(forward_done)
        with torch.cuda.stream(side), self.timer.concurrent("critic", side):
            return self.critic(buffers)


class GraphedCriticPhase:
    """The critic fit (TD(lambda) targets, minibatch steps) captured as one CUDA graph and replayed.

    The first call runs the fit eagerly (it is that iteration's real update and warms up the capturable Adam's
    state), then captures it reading ``inputs``, which later calls fill from their window's buffers before
    replaying, on the current stream. The critic's Adam must be ``capturable`` with its learning rate in a
    tensor that the decay updates in place.

    The fit runs and is captured on its own ``stream`` (cuBLAS keeps a workspace per stream and a graph keeps
    the one it was captured with), so that it can replay beside the window's graphs, captured on another.

    Args:
        phase: ``phase(buffers) -> critic loss`` (0-d); reads ``KEYS`` of the buffers.
        critic: the critic being fitted (its gradients must exist before the capture).
        device: a CUDA device.
    """

    KEYS = ("rewards", "next_values", "dones", "critic_obs")

    def __init__(self, phase: Callable[[dict], torch.Tensor], critic: torch.nn.Module, device: torch.device):
        self.phase, self.critic, self.device = phase, critic, device
        self.stream = torch.cuda.Stream(device)
        self.inputs: dict[str, torch.Tensor] | None = None
        self.graph: torch.cuda.CUDAGraph | None = None
        self.loss: torch.Tensor | None = None

    def __call__(self, buffers: dict) -> torch.Tensor:
        if self.graph is None:
            return self._run_then_capture(buffers)
        for k, v in self.inputs.items():
            if buffers[k] is not v:
                v.copy_(buffers[k])
        self.graph.replay()
        return self.loss

    def _run_then_capture(self, buffers: dict) -> torch.Tensor:
        self.inputs = {k: buffers[k].detach().clone() for k in self.KEYS}
        main = torch.cuda.current_stream(self.device)
        self.stream.wait_stream(main)
        with torch.cuda.stream(self.stream):
            first_loss = self.phase(self.inputs).clone()
        main.wait_stream(self.stream)
        for p in self.critic.parameters():  # capture needs existing gradient tensors, zeroed in place
            if p.grad is None:
                p.grad = torch.zeros_like(p)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph, stream=self.stream):
            self.loss = self.phase(self.inputs)
        return first_loss
