"""The numeric precision a process trains in (``SHACConfig.precision``; docs/design.md, "Data flow").

* ``fp32``: float32 everywhere, with PyTorch's defaults: matmuls in full float32, and cuDNN free to run the
  encoder's float32 convolutions in TF32 (PyTorch's default for convolutions). What every run did before this
  option existed, bit for bit.
* ``tf32``: TF32 tensor cores for every float32 CUDA matmul and convolution. The switch is process-wide: it also
  reaches the simulator's and the renderer's cuBLAS matmuls (the mass-matrix inverse, forward kinematics) and the
  critic, not only the encoder.
* ``bf16``: the encoder's convolutions under bfloat16 autocast (channels-last kept); their output is cast back to
  float32 before the trunk (Linear, LayerNorm, Tanh), which runs in float32 like everything else. No process-wide
  switch changes: the simulator, renderer, MLP head and critic compute exactly what ``fp32`` computes, so the
  option's effect is the encoder's alone.

The encoder reads its precision at construction (:func:`current`, set by :func:`use`); :func:`encoder_autocast`
is the static branch its forward takes, which torch.compile traces and a CUDA graph captures. The TF32 switches
are process-wide, so a population's members share one precision (``check_population`` refuses others).

These are tensor-core formats: on the CPU :func:`use` refuses ``tf32`` and ``bf16`` unless told otherwise
(``allow_cpu``, for tests and benchmark dry runs: the CPU has no TF32, and its bf16 autocast is an emulation that
says nothing of a GPU's time).
"""

from __future__ import annotations

import contextlib
import warnings

import torch

__all__ = ["PRECISIONS", "backend_flags", "check", "current", "encoder_autocast", "use"]

PRECISIONS = ("fp32", "tf32", "bf16")

_current = "fp32"

# Inductor's advice to enable TF32 matmuls; with an explicit precision option it only repeats a choice made.
_TF32_ADVICE = r"TensorFloat32 tensor cores for float32 matrix multiplication available but not enabled"


def check(precision: str, device: torch.device | str | None = None) -> str:
    """``precision`` if it is one of :data:`PRECISIONS` and, given a ``device``, applies there (only ``fp32`` on
    the CPU); ValueError in one line naming the flag otherwise."""
    if precision not in PRECISIONS:
        raise ValueError(f"--precision: unknown precision {precision!r}; valid: {', '.join(PRECISIONS)}")
    kind = None if device is None else torch.device(device).type
    if kind is not None and kind != "cuda" and precision != "fp32":
        raise ValueError(f"--precision {precision} is for CUDA devices (TF32 and bfloat16 tensor cores); on "
                         f"{kind} runs train in fp32: drop --precision or give --precision fp32")
    return precision


def backend_flags(precision: str) -> dict[str, bool]:
    """The process-wide switches of ``precision``: TF32 for float32 CUDA matmuls (cuBLAS) and for cuDNN's
    float32 convolutions. ``fp32`` and ``bf16`` keep PyTorch's defaults (matmuls off, convolutions on)."""
    check(precision)
    return {"matmul_allow_tf32": precision == "tf32", "cudnn_allow_tf32": True}


def current() -> str:
    """The precision :func:`use` set last (``fp32`` until then): what encoders built now run in."""
    return _current


def encoder_autocast(device_type: str, precision: str) -> contextlib.AbstractContextManager:
    """The context the encoder's convolutions run in: bfloat16 autocast for ``bf16``, nothing otherwise.

    Its weight cache is off: each weight is cast once per call anyway, and a cache filled inside a CUDA-graph
    capture would hand cast tensors of the graph's pool to later calls."""
    if check(precision) == "bf16":
        return torch.autocast(device_type, dtype=torch.bfloat16, cache_enabled=False)
    return contextlib.nullcontext()


def use(precision: str, device: torch.device | str, *, allow_cpu: bool = False) -> None:
    """Make ``precision`` this process's: the TF32 switches on a CUDA device, the precision of encoders built from
    now on. Call it before building the trainer (and before each iteration where trainers of different precisions
    share a process: the switches are process-wide and read when a kernel is launched or captured).

    On the CPU ``tf32`` and ``bf16`` raise ValueError (one line) unless ``allow_cpu``; there the TF32 switches are
    left alone (they are CUDA's) and ``bf16`` runs the CPU's bfloat16 autocast."""
    global _current
    device = torch.device(device)
    check(precision, None if allow_cpu else device)
    if device.type == "cuda":
        flags = backend_flags(precision)
        # the CUDA-only switches: torch.set_float32_matmul_precision would also change the CPU's oneDNN matmuls
        torch.backends.cuda.matmul.allow_tf32 = flags["matmul_allow_tf32"]
        torch.backends.cudnn.allow_tf32 = flags["cudnn_allow_tf32"]
        if not flags["matmul_allow_tf32"]:  # fp32 and bf16 leave TF32 matmuls off by choice
            warnings.filterwarnings("ignore", message=_TF32_ADVICE)
    _current = precision
