"""The fused raster kernels compile for a GPU (sm_90) on a machine without one.

Elsewhere on a CPU the kernels run in Triton's interpreter, which accepts some programs the compiler rejects;
this builds them for real, in a fresh process (the interpreter, once on, replaces every kernel it defines).
"""

import importlib.util
import os
import subprocess
import sys

import pytest

# find, not import: triton imported here, before another module of the session sets TRITON_INTERPRET, would
# leave that module's kernels compiled instead of interpreted
pytestmark = pytest.mark.skipif(importlib.util.find_spec("triton") is None, reason="triton is not installed")

_BUILD = """
import triton
from triton.backends.compiler import GPUTarget
from triton.compiler import ASTSource
from diffrender.raster.fused import backward, forward, rasterize, tuning

def build(kernel, consts, **options):
    names = kernel.arg_names
    ints = ("bins_ptr", "cnt_ptr", "over_ptr")  # the face lists, their counts and the overflow counter
    sig = {n: "constexpr" if n in consts else "*i32" if n in ints else "*fp32" if n.endswith("_ptr") or n == "prm"
           else "i32" for n in names}
    src = ASTSource(fn=kernel, signature=sig, constexprs={(names.index(k),): v for k, v in consts.items()})
    options = {"num_warps": 2} | options
    return triton.compile(src, target=GPUTarget("cuda", 90, 32), options=options).asm["cubin"]

for model in (0, 1, 2):  # hard, softmax, alpha
    for split in (False, True):
        assert build(forward._fused_forward, dict(TILE_=4, FB=64, SB=16, FS=32, SAVE=True, SPLIT=split,
                                                  MODEL=model, COMPACT=False, DEFER=False))
        for save in (True, False):  # with per-tile face lists (tuning.FWD_BIN); the hard model's deferred walk
            assert build(forward._binned_forward, dict(TILE_=4, FB=64, SB=16, FS=64, SAVE=save, SPLIT=split,
                                                       MODEL=model, COMPACT=False, DEFER=not save, CAP=256))
    assert build(forward._merge_forward, dict(BLOCK=256, SAVE=True, MODEL=model))
    assert build(backward._pixel_backward, dict(BLOCK=256, MODEL=model))
    cap = tuning.BWD_MAXNREG_HARD if model == 0 else tuning.BWD_MAXNREG  # as the renderer launches it
    assert build(backward._fused_backward, dict(TILE_=8, FB=64, SB=16, SUB=32, MODEL=model, COMPACT=True),
                 **rasterize._max_registers(cap))
assert build(forward._bin_faces, dict(TILE_=4, FB=64, SB=16, CAP=256))
print("built")
"""


@pytest.mark.slow
def test_fused_kernels_compile_for_sm90():
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    env["TRITON_DEFAULT_FP_FUSION"] = "1"  # the default fused kernels run with; set to silence Triton's notice
    done = subprocess.run([sys.executable, "-c", _BUILD], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and "built" in done.stdout, done.stderr[-3000:]
