"""Whole SHAC iterations per task and mode: forward, backward, critic and total time, peak memory.

This is the Table-1-style measurement (the D.Va paper's Table 1 reports backward time per iteration). It
drives the real trainer (``gradlab.SHAC``), so it measures exactly what ``ablate`` runs: rollout + render +
loss (forward), the actor backward, the critic fit, and the whole iteration, each CUDA-synchronised by the
trainer's own timers; warm-up iterations are excluded; medians over the measured iterations. Peak allocated
and reserved memory are read after ``reset_peak_memory_stats`` around the actor's forward+backward.

The probe overhead is measured too: with ``--probe-every K`` one probed iteration (both gradients of the
same rollout) is timed separately and the overhead at K is ``(probed - plain) / K / plain``.

Not a test. Examples::

    python benchmarks/iteration.py --device cuda --tasks cartpole ant --modes decoupled full --out iter.json
    # each arm of the seeded experiment alone (decoupled, full soft and hard, blind), for the reports'
    # equal-wall-clock view (ablate-report --benchmark iter.json)
    python benchmarks/iteration.py --device cuda --compile --tasks hopper --modes decoupled full blind \
        --raster-model softmax hard --out iter.json
    # the fused rasterizer's per-tile face lists against its default walks, in this process
    python benchmarks/iteration.py --device cuda --compile --tasks ant --modes decoupled full \
        --fused-variants default FWD_BIN=1,BIN_CAPACITY=256 --out iter_bin.json
    python benchmarks/iteration.py --device cpu --tasks cartpole --num-envs 4 --horizon 4 --image-size 32 \
        --warmup 1 --iters 2 --out /tmp/iter.json
"""

from __future__ import annotations

import argparse
import contextlib
import json
import platform
import sys
import time
from pathlib import Path
from unittest import mock

import torch
from _common import apply_fused_variant, commit, write_json

import diffrender
import tasks
from gradlab import SHAC, ModePlan, SHACConfig, precision, resolve_config, resolve_device
from gradlab.timing import median
from vocabulary import SIM_BACKENDS

KEYS = ("fwd_ms", "bwd_ms", "critic_ms", "iter_ms", "peak_alloc_mb", "peak_reserved_mb", "saved_mb")


@contextlib.contextmanager
def window_start(kind: str):
    """``leaf``: the trainer as it is (under --compile a window starts from a leaf that requires grad, so the
    first step shares the later steps' compiled graphs); ``detached``: every window starts from a plain cut
    (``Task.detach()`` ignoring ``requires_grad``), for the same-process A/B of that choice."""
    if kind == "leaf":
        yield
        return
    plain = tasks.Task.detach
    with mock.patch.object(tasks.Task, "detach", lambda self, *, requires_grad=False: plain(self)):
        yield


def measure(task: str, mode: str, args, *, renderer: str = "soft", start: str = "leaf",
            overlap_critic: bool = True, raster_model: str | None = None, sim_backend: str = "torch") -> dict:
    with window_start(start):
        row = _measure(task, mode, args, renderer=renderer, overlap_critic=overlap_critic, raster_model=raster_model,
                       sim_backend=sim_backend)
    return {**row, "window_start": start}


def _measure(task: str, mode: str, args, *, renderer: str = "soft", overlap_critic: bool = True,
             raster_model: str | None = None, sim_backend: str = "torch") -> dict:
    cfg = SHACConfig(task=task, mode=mode, num_envs=args.num_envs, horizon=args.horizon, image_size=args.image_size,
                     iters=10_000, cosine_every=0, seed=args.seed, compile=args.compile, renderer=renderer,
                     raster_model=raster_model, extra_meshes=args.extra_meshes,
                     extra_mesh_verts=args.extra_mesh_verts, overlap_critic=overlap_critic, precision=args.precision,
                     sim_backend=sim_backend)
    row = {"task": task, "mode": mode, "renderer": renderer, "sim_backend": sim_backend, "num_envs": args.num_envs,
           "horizon": args.horizon,
           "image_size": args.image_size, "compile": args.compile, "overlap_critic": overlap_critic,
           "precision": args.precision, "status": "ok"}
    try:
        # num_envs None: the preset's, per task and mode (SHAC's 256 for the hopper on the state vector), so that
        # each arm is timed at the size `ablate` trains it
        row["num_envs"] = resolve_config(cfg).num_envs
        t0 = time.perf_counter()
        trainer = SHAC([cfg], device=args.device)
        row["setup_s"] = time.perf_counter() - t0
        (member,) = trainer.members
        renderer = trainer.renderers.get(member.cfg.raster_model) if member.plan.renders else None
        if renderer is not None:  # which rasterizer backend "auto" resolved to (fused / tiled)
            row["render_backend"] = diffrender.backend_for(renderer.settings, trainer.device)
            row["faces"] = renderer.num_faces
            row["raster_model"] = member.cfg.raster_model
        t0 = time.perf_counter()
        for _ in range(args.warmup):
            trainer.train_iteration()
        row["warmup_s"] = time.perf_counter() - t0
        rows = [trainer.train_iteration()[0] for _ in range(args.iters)]
        row["critic_overlapped"] = bool(rows) and all(r["critic_overlapped"] for r in rows)
        for k in KEYS:
            vals = [r[k] for r in rows if r.get(k) is not None]
            row[k] = median(vals) if vals else None
        row["grad_norm"] = median([r["grad_norm"] for r in rows])
        if ModePlan.of(mode).probes and args.probe_every > 0:
            trainer.cfg.cosine_every = 1  # from now on every iteration is probed
            # warm-up: with --compile the first probe runs eagerly (compiling the grad-mode render), the second
            # captures the probe graphs; neither is timed
            trainer.train_iteration()
            if args.compile:
                trainer.train_iteration()
            probed = [trainer.train_iteration()[0] for _ in range(max(1, args.iters // 2))]
            p_iter = median([r["iter_ms"] for r in probed])
            row["probed_iter_ms"] = p_iter
            row["probed_bwd_ms"] = median([r["bwd_ms"] for r in probed])
            row["probe_overhead_at_k"] = (p_iter - row["iter_ms"]) / args.probe_every / row["iter_ms"]
            row["cos_full_decoupled"] = median([r["cos_full_decoupled"] for r in probed])
            row["grad_norm_full"] = median([r["grad_norm_full"] for r in probed])
            row["grad_norm_decoupled"] = median([r["grad_norm_decoupled"] for r in probed])
    except torch.OutOfMemoryError as e:
        row.update(status="oom", error=str(e).splitlines()[0])
    except Exception as e:  # a benchmark reports a failing point and goes on
        row.update(status="error", error=f"{type(e).__name__}: {e}"[:500])
    finally:
        if torch.cuda.is_available():
            torch.cuda.empty_cache()
    return row


def fmt(v, nd=1):
    return "-" if v is None else f"{v:.{nd}f}"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="auto", help="auto | cpu | cuda")
    p.add_argument("--tasks", nargs="+", default=["cartpole", "hopper", "ant", "humanoid", "cheetah"])
    p.add_argument("--modes", nargs="+", default=["decoupled", "full"])
    p.add_argument("--num-envs", type=int, default=None,
                   help="environments per iteration (default: the preset's for each task and mode, as ablate trains)")
    p.add_argument("--horizon", type=int, default=32)
    p.add_argument("--image-size", type=int, default=84)
    p.add_argument("--warmup", type=int, default=2, help="iterations excluded from the medians")
    p.add_argument("--iters", type=int, default=4, help="measured iterations")
    p.add_argument("--probe-every", type=int, default=10, help="K for the probe-overhead estimate (0: skip)")
    p.add_argument("--compile", action="store_true", help="the trainer's --compile path")
    p.add_argument("--renderers", nargs="+", choices=["soft", "warp"], default=["soft"],
                   help="image sources to time (warp: the ray tracer, for modes without image gradient)")
    p.add_argument("--raster-model", nargs="+", choices=["hard", "softmax", "alpha"], default=[None],
                   help="the rasterizer's image models, each timed for every mode that renders (default: the "
                        "preset's); modes without images (blind, state) are timed once")
    p.add_argument("--extra-meshes", type=int, default=0, help="extra meshes on the robot's links (scene size)")
    p.add_argument("--extra-mesh-verts", type=int, default=64, help="vertices per extra mesh")
    p.add_argument("--window-starts", nargs="+", choices=["leaf", "detached"], default=["leaf"],
                   help="how a window's start state is cut: leaf (the trainer's) or detached (the plain cut), "
                        "each timed in this process (an A/B of the choice; see window_start)")
    p.add_argument("--overlap-critic", nargs="+", choices=["on", "off"], default=["on"],
                   help="the critic fit alongside the replayed backward (on, the trainer's default) or after it "
                        "(off); several: each timed in this process (SHACConfig.overlap_critic)")
    p.add_argument("--sim-backends", nargs="+", choices=SIM_BACKENDS, default=["torch"],
                   help="the simulator backends (SHACConfig.sim_backend), each timed in this process")
    p.add_argument("--fused-variants", nargs="+", default=["default"],
                   help="the fused rasterizer's tuning constants, each timed in this process: 'default' or "
                        "NAME=VALUE,NAME=VALUE (diffrender.raster.fused.tuning, e.g. FWD_BIN=1,BIN_CAPACITY=256; "
                        "as benchmarks/anchor.py --variants). Rows name theirs (fused_variant); a backend other "
                        "than the fused one (the CPU's) ignores them")
    p.add_argument("--precision", choices=precision.PRECISIONS, default="fp32",
                   help="SHACConfig.precision for every row (on the CPU a dry run: no TF32 there, bf16 emulated)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("iteration.json"))
    args = p.parse_args()
    try:
        args.device = str(resolve_device(args.device))
    except ValueError as e:
        p.error(str(e))
    precision.use(args.precision, args.device, allow_cpu=True)  # process-wide, before any trainer is built

    env = {"torch": torch.__version__, "python": platform.python_version(), "device": args.device,
           "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "command": " ".join(sys.argv), "commit": commit()}
    if args.device.startswith("cuda"):
        env["gpu"] = torch.cuda.get_device_name()
    results = []
    try:
        for variant in args.fused_variants:
            apply_fused_variant(variant)
    except ValueError as e:
        p.error(str(e).replace("--variants", "--fused-variants"))
    runs = [(t, m, r, w, o, rm, sb, fv) for t in args.tasks for m in args.modes for r in args.renderers
            for w in args.window_starts for o in args.overlap_critic for sb in args.sim_backends
            for rm in (args.raster_model if ModePlan.of(m).renders and r == "soft" else [None])
            for fv in (args.fused_variants if ModePlan.of(m).renders and r == "soft" else ["default"])
            if r == "soft" or not ModePlan.of(m).grad_through_images]
    for task, mode, renderer, start, overlap, raster, backend, variant in runs:
        apply_fused_variant(variant)
        row = {**measure(task, mode, args, renderer=renderer, start=start, overlap_critic=overlap == "on",
                         raster_model=raster, sim_backend=backend), "fused_variant": variant}
        results.append(row)
        print(json.dumps(row), flush=True)
        # The format ablate-report reads: provenance at the top level, one row per (task, mode).
        doc = {"date": env["date"], "command": env["command"], "commit": env["commit"], "device": args.device,
               "gpu": env.get("gpu"),
               "versions": {"torch": env["torch"], "python": env["python"]}, "results": results}
        write_json(args.out, doc, indent=2)
    apply_fused_variant("default")  # the process's tuning as it was, for a caller that goes on rendering

    envs = "/".join(sorted({str(r["num_envs"]) for r in results}, key=lambda e: (len(e), e)))
    print(f"\nSHAC iteration, {envs} envs, horizon {args.horizon}, {args.image_size}px, "
          f"{env.get('gpu', args.device)}, compile={args.compile}, precision={args.precision} "
          f"(medians of {args.iters} after {args.warmup} warm-up)")
    print(f"{'task':9} {'mode':9} {'render':6} {'raster':7} {'start':8} {'variant':28} {'fwd ms':>9} {'bwd ms':>9} "
          f"{'critic':>8} "
          f"{'overlap':>7} {'sim':>5} {'iter ms':>9} "
          f"{'alloc MB':>9} {'resv MB':>9} {'saved MB':>9} {'probe+%':>8} {'cos':>6}")
    for r in results:
        head = (f"{r['task']:9} {r['mode']:9} {r['renderer']:6} {r.get('raster_model') or '-':7} "
                f"{r['window_start']:8} {r['fused_variant']:28}")
        if r["status"] != "ok":
            print(f"{head} {r['status']}: {r.get('error', '')[:80]}")
            continue
        ov = r.get("probe_overhead_at_k")
        print(f"{head} {fmt(r['fwd_ms']):>9} {fmt(r['bwd_ms']):>9} "
              f"{fmt(r['critic_ms']):>8} {('yes' if r['critic_overlapped'] else 'no'):>7} {r['sim_backend']:>5} "
              f"{fmt(r['iter_ms']):>9} {fmt(r['peak_alloc_mb'], 0):>9} "
              f"{fmt(r['peak_reserved_mb'], 0):>9} "
              f"{fmt(r['saved_mb'], 1):>9} {('-' if ov is None else f'{100 * ov:.1f}'):>8} "
              f"{fmt(r.get('cos_full_decoupled'), 3):>6}")

if __name__ == "__main__":
    main()
