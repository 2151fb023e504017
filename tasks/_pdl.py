"""Programmatic dependent launch (PDL) for inductor's Triton kernels, made race-free.

With ``triton.enable_pdl`` inductor launches every Triton kernel so that it may start while the kernel before it
is still running, and puts a device-side wait (``gdc_wait``) before the first access that touches a buffer the
*previous* kernel wrote. A kernel that only reads older buffers, or only writes (a zero fill), gets no wait
before those accesses. Then a kernel can read a buffer two kernels back while that kernel is still running: the
previous kernel, having waited for nothing, may have finished first (the transitive race of NVIDIA/cccl#3131).
The compiled simulator has such kernels: its backward graphs contain store-only zero fills (inductor's
``triton_poi_fused_new_zeros_*``). The race depends on timing, so a run without a wrong result proves nothing;
it is closed here rather than tested for.

:func:`install` replaces inductor's wait placement with "wait before the first global access of every kernel".
Each kernel then starts only after the one before it has finished, and so, by induction, after all earlier ones.
What PDL still saves is the launch: the next kernel is scheduled while the previous one drains, which at ~2 us
per dependent kernel is most of the time of a small simulator substep (BENCHMARKS.md section 3: at 64
environments the horizon is launch latency).

The patch is private to inductor's code generator, so it is version-checked: where the method it replaces is
missing, :func:`install` returns False and callers must leave PDL off. A custom post-grad pass with its own
``uuid`` goes into the options as well, so inductor's FX-graph cache never hands kernels compiled without the
wait to a process that has it (the cache key includes the pass's uuid).
"""

from __future__ import annotations

import warnings
from typing import Any

__all__ = ["install", "options"]

_UUID = "pixelgrad-pdl-wait-first-v1"


def install() -> bool:
    """Make inductor's PDL kernels wait before their first global access. Idempotent; False if unsupported."""
    try:
        from torch._inductor.codegen.triton import TritonKernel
    except ImportError:  # pragma: no cover - inductor always ships with torch >= 2.11
        return False
    current = getattr(TritonKernel, "_handle_pdl_before_access", None)
    if current is None or not hasattr(TritonKernel, "_enable_pdl_codegen") or not hasattr(TritonKernel, "GDC_WAIT"):
        return False
    if getattr(current, "_wait_first", False):
        return True

    def wait_before_every_access(self, wait_buffer, *dependencies, consider_reads=False):
        if not self._enable_pdl_codegen():
            return
        if self.inside_reduction and self.range_trees[-1].is_loop:
            wait_buffer = self.body  # before the reduction loop, as inductor hoists it
        # inductor keeps only the first wait of a kernel body (``_filter_pdl``): the one before its first access
        wait_buffer.writeline(self.GDC_WAIT)

    wait_before_every_access._wait_first = True  # type: ignore[attr-defined]
    TritonKernel._handle_pdl_before_access = wait_before_every_access
    return True


def _cache_marker() -> Any:
    """A no-op post-grad pass whose uuid puts "waits before every access" into inductor's cache key."""
    from torch._inductor.custom_graph_pass import CustomGraphPass

    class WaitFirstMarker(CustomGraphPass):
        def __call__(self, graph) -> None:
            return None

        def uuid(self) -> str:
            return _UUID

    return WaitFirstMarker()


def options(opts: dict[str, Any]) -> dict[str, Any]:
    """``opts`` with PDL made safe: if ``triton.enable_pdl`` is on, install the wait placement and add the cache
    marker (unless the caller set its own post-grad pass); if the installed torch cannot be patched, PDL off."""
    if not opts.get("triton.enable_pdl"):
        return opts
    if not install():
        warnings.warn(
            "this torch's inductor has no hook for PDL wait placement (tasks._pdl): compiling without "
            "programmatic dependent launch",
            stacklevel=2,
        )
        return {**opts, "triton.enable_pdl": False}
    if "post_grad_custom_post_pass" in opts:
        return opts
    return {**opts, "post_grad_custom_post_pass": _cache_marker()}
