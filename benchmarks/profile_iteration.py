"""Where a compiled SHAC iteration spends its GPU time: kernels of the captured forward and backward graphs.

For each (task, mode) the real trainer (``gradlab.SHAC``, ``--compile``) runs until its window is captured as
CUDA graphs; then the forward graph and the backward graph are each replayed under ``torch.profiler`` and the
GPU kernels are summed by category (inductor-generated Triton kernels = the compiled simulator and the small
fused element-wise work; cuDNN convolutions = the encoder; GEMMs; the fused rasterizer's kernels; the rest).
The wall time of each replay is measured too (CUDA-synchronised, median of ``--iters``), so the kernel sum
can be compared with it (the gap is GPU idle time between kernels).

``--encoder`` adds a micro-benchmark of the DrQ-v2 encoder alone: forward + weight-gradient backward over
horizon x num_envs frames, once as ``horizon`` calls of ``num_envs`` frames (how the rollout runs it) and once
as one call on all frames; both graph-captured.

``--precision fp32 bf16`` profiles each (task, mode) at each encoder precision (``SHACConfig.precision``, its
process-wide switches set before the trainer is built); ``--variants`` at each setting of the fused rasterizer's
tuning constants (as ``anchor.py --variants``: ``default`` or ``NAME=VALUE,...``). All in one process, so the
rows compare on one device.

Not a test. Example::

    python benchmarks/profile_iteration.py --tasks ant cartpole --modes decoupled full --encoder --out prof.json
    python benchmarks/profile_iteration.py --tasks ant --num-envs 768 --precision fp32 bf16 \
        --variants default FWD_COMPACT=1,FWD_SUB_BLOCK=16 --out prof_768.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import torch
from _common import FUSED_DEFAULTS, apply_fused_variant, commit, graphed, median_ms, write_json

from gradlab import SHAC, SHACConfig, precision, resolve_device
from gradlab.networks import PixelEncoder

#: The renderer's own Triton kernels by launch name (diffrender.raster.fused and diffrender.raster.setup_kernels):
#: the rasterizer's walks and merge, and the per-face setup and floor around them.
RASTER_KERNELS = ("_fused_forward", "_fused_backward", "_merge_forward", "_pixel_backward", "_binned_forward",
                  "_bin_faces")
SETUP_KERNELS = ("_setup_forward", "_setup_backward", "_floor_forward", "_floor_backward", "_super_boxes")


def category(name: str) -> str:
    n = name.lower()
    if n.startswith(RASTER_KERNELS) or "raster" in n:
        return "rasterizer (fused triton)"
    if n.startswith(SETUP_KERNELS):
        return "renderer setup (triton)"
    if n.startswith("triton_"):
        return "inductor triton (sim, elementwise)"
    if any(k in n for k in ("conv", "cudnn", "dgrad", "wgrad", "implicit", "winograd", "fft")):
        return "cudnn conv"
    if any(k in n for k in ("gemm", "gemv", "cutlass", "sm90_xmma", "sm80_xmma", "cublas", "splitk")):
        return "gemm"
    if any(k in n for k in ("potrf", "trsm", "cholesky", "getrf", "lu_", "magma")):
        return "linalg"
    if "memcpy" in n or "memset" in n:
        return "memcpy/memset"
    if "reduce" in n:
        return "aten reduce"
    return "aten elementwise/other"


def profile_replay(fn, iters: int) -> dict:
    """Kernel time by category and the top kernels of one call of ``fn``; wall ms median over ``iters``."""
    from torch.profiler import ProfilerActivity, profile

    wall_ms = median_ms(fn, "cuda", repeats=iters)
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        fn()
        torch.cuda.synchronize()
    cats: dict[str, float] = defaultdict(float)
    counts: dict[str, int] = defaultdict(int)
    kernels = []
    for e in prof.key_averages():
        if e.device_type.name != "CUDA":
            continue
        us = e.self_device_time_total if hasattr(e, "self_device_time_total") else e.self_cuda_time_total
        cats[category(e.key)] += us / 1e3
        counts[category(e.key)] += e.count
        kernels.append((us / 1e3, e.count, e.key[:110]))
    kernels.sort(reverse=True)
    return {"wall_ms": wall_ms, "kernel_ms": sum(cats.values()),
            "kernels": sum(counts.values()),
            "by_category": {k: {"ms": round(v, 3), "count": counts[k]} for k, v in
                            sorted(cats.items(), key=lambda kv: -kv[1])},
            "top": [{"ms": round(ms, 3), "count": c, "name": n} for ms, c, n in kernels[:25]]}


def profile_trainer(task: str, mode: str, precision_: str, args) -> dict:
    cfg = SHACConfig(task=task, mode=mode, num_envs=args.num_envs, horizon=args.horizon,
                     image_size=args.image_size, iters=10_000, cosine_every=0, seed=0, compile=True,
                     precision=precision_)
    precision.use(precision_, "cuda")  # process-wide: before the trainer (its encoder) is built
    trainer = SHAC([cfg], device="cuda")
    for _ in range(4):  # 2 eager warm-up iterations, the capture, one replay
        trainer.train_iteration()
    graph = trainer.window.captured[False]  # the plain (not probe) window's forward and backward graphs
    out = {"task": task, "mode": mode, "precision": precision_}

    def fwd():
        graph.fwd.replay()

    def fwd_bwd():
        graph.fwd.replay()
        graph.bwd.replay()

    out["fwd"] = profile_replay(fwd, args.iters)
    both = profile_replay(fwd_bwd, args.iters)
    # backward = (forward + backward) - forward, per category
    bwd = {"wall_ms": both["wall_ms"] - out["fwd"]["wall_ms"], "kernel_ms": both["kernel_ms"] - out["fwd"]["kernel_ms"],
           "kernels": both["kernels"] - out["fwd"]["kernels"], "by_category": {}}
    for k, v in both["by_category"].items():
        f = out["fwd"]["by_category"].get(k, {"ms": 0.0, "count": 0})
        bwd["by_category"][k] = {"ms": round(v["ms"] - f["ms"], 3), "count": v["count"] - f["count"]}
    bwd["top_fwd_plus_bwd"] = both["top"]
    out["bwd"] = bwd
    return out


def encoder_bench(args) -> dict:
    """Encoder forward + weight-gradient backward over T x B detached frames: T calls of B vs one of T*B."""
    T, B, S = args.horizon, args.num_envs, args.image_size
    enc = PixelEncoder(9, S, S, 50).cuda()
    frames = torch.rand(T, B, 9, S, S, device="cuda")
    g = torch.randn(T, B, 50, device="cuda")
    res = {}

    def per_step():
        feats = [enc(frames[t]) for t in range(T)]
        torch.autograd.backward(feats, list(g.unbind(0)))

    def batched():
        feats = enc(frames.flatten(0, 1))
        feats.backward(g.flatten(0, 1))

    for name, fn in (("per_step", per_step), ("batched", batched)):
        for p in enc.parameters():
            p.grad = torch.zeros_like(p)
        res[name] = profile_replay(graphed(fn, torch.device("cuda"), warmup=3), args.iters)
        res[name].pop("top")
        grads = [p.grad.clone() for p in enc.parameters()]
        res[name]["grad_sum"] = float(sum(gr.double().abs().sum() for gr in grads))
    return res


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", nargs="+", default=["ant"])
    p.add_argument("--modes", nargs="+", default=["decoupled", "full"])
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--horizon", type=int, default=32)
    p.add_argument("--image-size", type=int, default=84)
    p.add_argument("--iters", type=int, default=5, help="timed replays per graph (median)")
    p.add_argument("--encoder", action="store_true", help="also the encoder micro-benchmark")
    p.add_argument("--precision", nargs="+", choices=list(precision.PRECISIONS), default=["fp32"],
                   help="the encoder's precision (SHACConfig.precision): each (task, mode) at each")
    p.add_argument("--variants", nargs="+", default=["default"],
                   help="fused rasterizer tuning: 'default' or NAME=VALUE,... of "
                        f"fused.tuning's constants ({', '.join(FUSED_DEFAULTS)}); each (task, mode) at each")
    p.add_argument("--out", type=Path, default=Path("profile.json"))
    args = p.parse_args()
    try:
        resolve_device("cuda")
    except ValueError:
        p.error("needs a CUDA device (it profiles captured CUDA graphs), and torch sees none")
    for variant in args.variants:
        try:
            apply_fused_variant(variant)
        except ValueError as e:
            p.error(str(e))
    apply_fused_variant("default")
    doc = {"gpu": torch.cuda.get_device_name(), "torch": torch.__version__, "commit": commit(),
           "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "command": " ".join(sys.argv), "results": []}
    if args.encoder:
        doc["encoder"] = encoder_bench(args)
        print(json.dumps(doc["encoder"]), flush=True)
    for variant, task, mode, precision_ in itertools.product(args.variants, args.tasks, args.modes, args.precision):
        apply_fused_variant(variant)
        try:
            r = profile_trainer(task, mode, precision_, args)
        except Exception as e:  # report and go on
            r = {"task": task, "mode": mode, "precision": precision_, "error": f"{type(e).__name__}: {e}"[:400]}
        r["variant"] = variant
        doc["results"].append(r)
        write_json(args.out, doc)
        torch.cuda.empty_cache()
    write_json(args.out, doc)

    if "encoder" in doc:
        e = doc["encoder"]
        print(f"\nencoder fwd+wgrad over {args.horizon}x{args.num_envs} frames: per-step "
              f"{e['per_step']['wall_ms']:.2f} ms, batched {e['batched']['wall_ms']:.2f} ms")
    for r in doc["results"]:
        if "error" in r:
            print(f"{r['task']} {r['mode']} {r['precision']} {r['variant']}: {r['error']}")
            continue
        for phase in ("fwd", "bwd"):
            ph = r[phase]
            cats = ", ".join(f"{k} {v['ms']:.1f} ({v['count']})" for k, v in ph["by_category"].items())
            print(f"{r['task']:9} {r['mode']:9} {r['precision']} {r['variant']} {phase}: "
                  f"wall {ph['wall_ms']:.1f} ms, kernels {ph['kernel_ms']:.1f} ms "
                  f"/ {ph['kernels']}: {cats}")


if __name__ == "__main__":
    main()
