"""CUDA-graph capture and replay of a SHAC iteration, behind two small objects the trainer calls every iteration.

``WindowGraphs.run(iteration=, probe=)`` runs one window's forward (rollout + loss) and backward, eagerly or by
replaying the CUDA graphs captured from it; ``GraphedCriticPhase(buf)`` runs the critic phase the same way.
With capture off (the CPU, or no ``--compile``) both are the eager calls they wrap, so the trainer reads the
same either way (docs/design.md, "CUDA graphs").

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
        """task: the Task whose ``qpos, qvel, progress, prev_actions`` carry over; frames: its FrameStack, or
        None where the trainer does not render."""
        current = {"qpos": task.qpos, "qvel": task.qvel, "progress": task.progress,
                   "prev_actions": task.prev_actions}
        if frames is not None:
            current.update({f"frame{i}": f for i, f in enumerate(frames.frames)})
        live = self.tensors
        with torch.no_grad():
            for k, v in current.items():
                if k not in live:
                    live[k] = v.detach().clone()
                elif v is not live[k]:
                    live[k].copy_(v)
        task.qpos, task.qvel = live["qpos"], live["qvel"]
        task.progress, task.prev_actions = live["progress"], live["prev_actions"]
        if frames is not None:
            frames.frames = [live[f"frame{i}"] for i in range(len(frames.frames))]


@dataclass
class Window:
    """What one window's forward and backward leave behind (a replay's static outputs, overwritten by the next).

    loss: the actor loss (0-d); buffers: the rollout's (T, B, ...) buffers; probe_metrics: 0-d tensors of a
    probe iteration (empty otherwise); saved_bytes: bytes autograd kept for backward; memory: the peak memory
    of forward and backward (a capture is outside it); replayed: the window ran as a CUDA-graph replay.
    """

    loss: torch.Tensor
    buffers: dict
    probe_metrics: dict
    saved_bytes: int
    memory: MemoryProbe
    replayed: bool


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
        torch.cuda.synchronize(owner.device)
        with torch.cuda.graph(self.fwd, pool=pool):
            with SavedTensorMeter() as saved:
                self.loss, self.buffers = owner.forward(probe)
        with torch.cuda.graph(self.bwd, pool=pool):
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
        timer: times the regions "fwd" and "bwd" (a capture is outside them).
        device: the device the window runs on.
        capture: capture and replay (a CUDA device and ``--compile``); False runs every window eagerly.
    """

    def __init__(self, *, forward: Callable[[bool], tuple[torch.Tensor, dict]],
                 backward: Callable[[torch.Tensor, bool], dict], commit: Callable[[], None],
                 params: list[torch.nn.Parameter], timer: RegionTimer, device: torch.device, capture: bool):
        self.forward, self.backward, self.commit = forward, backward, commit
        self.params, self.timer, self.device, self.capture = params, timer, device, capture
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
        with MemoryProbe(self.device) as memory:
            if replay:
                graph = self.captured[probe]
                with self.timer("fwd"):
                    graph.fwd.replay()
                with self.timer("bwd"):
                    graph.bwd.replay()
                loss, buffers, probe_metrics, saved_bytes = (graph.loss, graph.buffers, graph.probe_metrics,
                                                             graph.saved_bytes)
            else:
                with self.timer("fwd"), SavedTensorMeter() as saved:
                    loss, buffers = self.forward(probe)
                with self.timer("bwd"):
                    probe_metrics = self.backward(loss, probe)
                    self.commit()
                saved_bytes = saved.bytes
        return Window(loss, buffers, probe_metrics, saved_bytes, memory, replay)


class GraphedCriticPhase:
    """The critic phase (targets, minibatch steps, Polyak) captured as one CUDA graph and replayed.

    The first call runs the phase eagerly (it is that iteration's real update and warms up the capturable
    Adam's state), then captures it reading ``inputs``, which later calls fill from their window's buffers
    before replaying. The critic's Adam must be ``capturable`` with its learning rate in a tensor that the
    decay updates in place.

    Args:
        phase: ``phase(buffers) -> critic loss`` (0-d); reads ``KEYS`` of the buffers.
        critic: the critic being fitted (its gradients must exist before the capture).
        device: a CUDA device.
    """

    KEYS = ("rewards", "next_values", "dones", "critic_obs")

    def __init__(self, phase: Callable[[dict], torch.Tensor], critic: torch.nn.Module, device: torch.device):
        self.phase, self.critic, self.device = phase, critic, device
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
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            first_loss = self.phase(self.inputs).clone()
        torch.cuda.current_stream(self.device).wait_stream(side)
        for p in self.critic.parameters():  # capture needs existing gradient tensors, zeroed in place
            if p.grad is None:
                p.grad = torch.zeros_like(p)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.loss = self.phase(self.inputs)
        return first_loss
