"""Fingerprints of the fused rasterizer's compiled kernels: a JSON of sha256 hashes, to show that a change to the
Python around the kernels (moving them between modules, renaming launch code) leaves the compiled kernels as
they were.

Every Triton kernel of ``diffrender.raster.fused`` (a module or a package) and ``diffrender.raster.setup_kernels``
is compiled for an sm_90 target (``triton.compile`` with an explicit ``GPUTarget``: no GPU needed) at the
specialisations the renderer launches with its default settings (each raster model, split or not, blend state
kept or not, float32 and float64 pointers, the default launch options). Recorded per specialisation: the hash
of its PTX and of its Triton IR (TTIR); per ``@triton.jit`` function, kernel or helper, the hash of its source
text. Line information is off (``TRITON_DISABLE_LINE_INFO=1``), so that the file and line a kernel came from
do not enter its PTX.

Compare two trees (here the commit before a change, checked out beside the working tree)::

    git worktree add /tmp/before <commit>
    (cd /tmp/before && PYTHONPATH=/tmp/before python /path/to/benchmarks/fused_ptx.py --out /tmp/before.json)
    python benchmarks/fused_ptx.py --out /tmp/after.json
    python benchmarks/fused_ptx.py --compare /tmp/before.json /tmp/after.json
    git worktree remove /tmp/before

The JSON names the ``diffrender`` it compiled (``diffrender_file``): check that it is the tree you meant.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import json
import os
import pkgutil
import sys
import tempfile
from pathlib import Path

# before triton is imported: compiled kernels, not the interpreter, and PTX without source locations
if os.environ.get("TRITON_INTERPRET", "0") == "1":
    sys.exit("fused_ptx: unset TRITON_INTERPRET (the interpreter compiles nothing)")
os.environ["TRITON_DISABLE_LINE_INFO"] = "1"
os.environ.setdefault("TRITON_DEFAULT_FP_FUSION", "1")  # the default the renderer's kernels run with

import triton
from triton.backends.compiler import GPUTarget
from triton.compiler import ASTSource
from triton.runtime.jit import JITFunction

TARGET = GPUTarget("cuda", 90, 32)
MODELS = {"hard": 0, "softmax": 1, "alpha": 2}
#: the renderer's default launch options per kernel (see the launches in diffrender.raster.fused and
#: setup_kernels): 4 x 4 forward tiles, 64-face blocks, 16 blocks per super-block, 8 x 8 backward tiles; the
#: backward in compacted lanes of 32 on one warp (fused.tuning.BWD_COMPACT, BWD_SUB_BLOCK)
FWD_WARPS, BWD_WARPS, PIXEL_WARPS, SETUP_WARPS = 4, 1, 4, 2
BWD_MAXNREG_SOFT = 128
#: the walk's switches (fused.tuning.FWD_COMPACT, FWD_DEFER_SHADING, BWD_COMPACT): dropped for a tree whose
#: kernels have no such arguments, so that its default kernels compare with this one's
_WALK = ("COMPACT", "DEFER")


def specialisations() -> list[tuple[str, str, dict, dict]]:
    """(label, kernel name, constexprs, options) of every kernel compiled."""
    specs = []
    for model, code in MODELS.items():
        for split in (False, True):
            for save in (False, True):
                # the default walk: block-wise; the hard model defers its shading where nothing is saved
                walk = dict(COMPACT=False, DEFER=code == 0 and not save)
                specs.append((f"_fused_forward[{model},split={split},save={save}]", "_fused_forward",
                              dict(TILE_=4, FB=64, SB=16, FS=64, SAVE=save, SPLIT=split, MODEL=code, **walk),
                              dict(num_warps=FWD_WARPS)))
            # the walk's variants (fused.tuning.FWD_COMPACT): compiled, so that a variant a GPU has not timed
            # yet is known to build for one; labelled apart from the defaults
            for fs in (16, 8):
                walk = dict(COMPACT=True, DEFER=code == 0)
                specs.append((f"_fused_forward[{model},split={split},save=False,compact={fs}]", "_fused_forward",
                              dict(TILE_=4, FB=64, SB=16, FS=fs, SAVE=False, SPLIT=split, MODEL=code, **walk),
                              dict(num_warps=FWD_WARPS)))
        for save in (False, True):
            specs.append((f"_merge_forward[{model},save={save}]", "_merge_forward",
                          dict(BLOCK=256, SAVE=save, MODEL=code), dict(num_warps=4)))
        specs.append((f"_pixel_backward[{model}]", "_pixel_backward", dict(BLOCK=256, MODEL=code),
                      dict(num_warps=PIXEL_WARPS)))
        cap = {} if code == 0 else dict(maxnreg=BWD_MAXNREG_SOFT)
        specs.append((f"_fused_backward[{model}]", "_fused_backward",
                      dict(TILE_=8, FB=64, SB=16, SUB=32, MODEL=code, COMPACT=True), dict(num_warps=BWD_WARPS) | cap))
        # the block-wise lanes of 64 on two warps (BWD_COMPACT off, BWD_SUB_BLOCK=64): the default until 2436d49
        specs.append((f"_fused_backward[{model},compact=off,lanes=64]", "_fused_backward",
                      dict(TILE_=8, FB=64, SB=16, SUB=64, MODEL=code, COMPACT=False), dict(num_warps=2) | cap))
    for cull in (False, True):
        specs.append((f"_setup_forward[cull={cull}]", "_setup_forward", dict(FB=64, CULL=cull),
                      dict(num_warps=SETUP_WARPS)))
        for need in ((True, True, True), (True, False, False), (False, True, True)):
            specs.append((f"_setup_backward[cull={cull},need={need}]", "_setup_backward",
                          dict(FB=64, CULL=cull, NEED_UVZ=need[0], NEED_NORMALS=need[1], NEED_COLORS=need[2]),
                          dict(num_warps=SETUP_WARPS)))
    specs.append(("_super_boxes", "_super_boxes", dict(SB=16, SBP=16), dict(num_warps=4)))
    specs.append(("_floor_forward", "_floor_forward", dict(BLOCK=256), dict(num_warps=4)))
    specs.append(("_floor_backward", "_floor_backward", dict(BLOCK=256), dict(num_warps=4)))
    return specs


def jit_functions() -> dict[str, JITFunction]:
    """Every ``@triton.jit`` function defined in the fused backend's modules, by name."""
    fused = importlib.import_module("diffrender.raster.fused")
    modules = [fused, importlib.import_module("diffrender.raster.setup_kernels")]
    for info in pkgutil.iter_modules(getattr(fused, "__path__", [])):
        modules.append(importlib.import_module(f"{fused.__name__}.{info.name}"))
    found: dict[str, JITFunction] = {}
    for module in modules:
        for name, obj in vars(module).items():
            if isinstance(obj, JITFunction) and obj.fn.__module__ == module.__name__:
                if name in found and found[name] is not obj:
                    raise RuntimeError(f"two jit functions named {name}: the fingerprints key on names")
                found[name] = obj
    return found


def signature(kernel: JITFunction, constexprs: dict, float_type: str) -> dict[str, str]:
    """Argument types as the renderer passes them: tensors of ``float_type`` (faces int64), int32 sizes."""
    sig = {}
    for name in kernel.arg_names:
        if name in constexprs:
            sig[name] = "constexpr"
        elif name == "faces_ptr":
            sig[name] = "*i64"
        elif name.endswith("_ptr") or name == "prm":
            sig[name] = f"*{float_type}"
        else:
            sig[name] = "i32"
    return sig


def compile_one(kernel: JITFunction, constexprs: dict, options: dict, float_type: str) -> dict[str, str]:
    sig = signature(kernel, constexprs, float_type)
    # torch allocations are 16-byte aligned: the launcher marks every pointer so, as here
    attrs = {(i,): [["tt.divisibility", 16]] for i, t in enumerate(sig.values()) if t.startswith("*")}
    src = ASTSource(fn=kernel, signature=sig, constexprs=constexprs, attrs=attrs)
    asm = triton.compile(src, target=TARGET, options=options).asm
    return {key: hashlib.sha256(asm[key].encode()).hexdigest() for key in ("ptx", "ttir")}


def fingerprint() -> dict:
    import diffrender

    fns = jit_functions()
    result: dict = {"diffrender_file": diffrender.__file__, "triton": triton.__version__,
                    "target": f"{TARGET.backend} sm_{TARGET.arch}", "ptx": {}, "ttir": {},
                    "source": {name: hashlib.sha256(fn.src.encode()).hexdigest() for name, fn in sorted(fns.items())}}
    for label, name, constexprs, options in specialisations():
        if name not in fns:
            raise RuntimeError(f"no jit function {name} in the fused backend")
        missing = set(constexprs) - set(fns[name].arg_names)
        if missing and not missing <= set(_WALK):
            raise RuntimeError(f"{name} has no arguments {sorted(missing)}")
        if missing:
            if "compact=" in label and "compact=off" not in label:  # a tree before the walk's variants
                continue
            constexprs = {k: v for k, v in constexprs.items() if k not in missing}
        for float_type in ("fp32", "fp64"):
            hashes = compile_one(fns[name], constexprs, options, float_type)
            for key, digest in hashes.items():
                result[key][f"{label}[{float_type}]"] = digest
            print(f"{label}[{float_type}]: ptx {hashes['ptx'][:12]}", flush=True)
    return result


def compare(a_path: Path, b_path: Path) -> int:
    a, b = json.loads(a_path.read_text()), json.loads(b_path.read_text())
    differ = 0
    for key in ("ptx", "ttir", "source"):
        names = sorted(set(a[key]) | set(b[key]))
        bad = [n for n in names if a[key].get(n) != b[key].get(n)]
        differ += len(bad)
        print(f"{key}: {len(names) - len(bad)} of {len(names)} equal" + "".join(f"\n  differs: {n}" for n in bad))
    return 1 if differ else 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--out", type=Path, help="write the fingerprints of the importable diffrender here (JSON)")
    p.add_argument("--compare", type=Path, nargs=2, metavar=("A", "B"),
                   help="compare two fingerprint files; exit status 1 if any kernel differs")
    args = p.parse_args()
    if args.compare:
        return compare(*args.compare)
    if args.out is None:
        p.error("--out FILE or --compare A B is required")
    with tempfile.TemporaryDirectory(prefix="fused_ptx_cache_") as cache:  # compile every kernel, reuse none
        os.environ["TRITON_CACHE_DIR"] = cache
        result = fingerprint()
    tmp = args.out.with_name(args.out.name + ".tmp")
    tmp.write_text(json.dumps(result, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, args.out)
    print(f"{len(result['ptx'])} kernels -> {args.out} (diffrender at {Path(result['diffrender_file']).parent})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
