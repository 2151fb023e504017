"""Benchmark of diffrender's soft rasterizer: time, peak memory and saved-for-backward bytes.

Not a test. Sweeps one factor at a time around the target point (64 ant environments at 84 x 84):
batch size, resolution, face count (the ant plus extra sphere meshes attached to its moving bodies) and,
with ``--tiles``, the tile size; per backend. Timing is CUDA-synchronised, after warm-up, median of
repeats; ``torch.cuda.reset_peak_memory_stats`` precedes every measured region.

Reported per point: ``fwd_ms`` (render only, no graph), ``fwdbwd_ms`` (render with grad + backward of a
weighted image sum into the vertices and camera eye), ``fk_fwdbwd_ms`` (the same including forward
kinematics from qpos, the way a task renders), peak allocated / reserved memory of the fwd+bwd region
[MB] and above the region's start, ``grad_finite`` (the qpos gradient is finite; compiled points also
report ``grad_rel_err_vs_eager``), ``saved_mb`` (bytes autograd keeps for the backward of one render,
measured with saved-tensor hooks; the faces tensor, which the caller owns anyway, is excluded),
``pairs`` (tile-face pairs per environment, mean) and ``capacity``.

    python benchmarks/render.py --device cuda --quick --out bench_render.json
    python benchmarks/render.py --device cpu --tiny                  # smoke test on a laptop
    python benchmarks/render.py --silhouette-share --out silhouette_share.json   # gradient share per model
    python benchmarks/render.py --anchor --compile --repeats 5 --out anchor.json  # against nvdiffrast
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
import traceback
from pathlib import Path

import anchor
import torch
from _common import ASSETS, Scene, graphed, median_ms, sync, write_json

import diffrender as dr
from diffrender.profiling import SavedTensorMeter
from diffrender.raster import count_pairs, tiled_static
from diffrender.raster.fused import tuning
from diffrender.settings import RASTER_MODELS
from tasks.device import resolve_device

#: the fused kernels' shape by default: tile, face block, backward tile, backward sub-block, backward warps
DEFAULT_FUSED = (tuning.TILE, tuning.FACE_BLOCK, tuning.BWD_TILE, tuning.BWD_SUB_BLOCK, tuning.BWD_WARPS)
TARGET = dict(fwd_ms=3.0, fwdbwd_ms=8.0, saved_mb=4.0)  # H100, 64 ant envs at 84 x 84
DENSE_MAX_ELEMS = 3e7  # the dense reference materialises B * F * H * W pixel-face pairs (x ~100 floats)


def _time(fn, device, *, warmup: int, repeats: int) -> tuple[float, float]:
    """Median [ms] of ``repeats`` calls after ``warmup`` (the first call included), and the first call's wall
    time [ms] (compilation included)."""
    sync(device)
    t0 = time.perf_counter()
    fn()
    sync(device)
    first = (time.perf_counter() - t0) * 1e3
    return median_ms(fn, device, warmup=max(0, warmup - 1), repeats=repeats), first


def measure(args, *, backend: str, batch: int, res: int, faces: int, tile: int, compile: bool = False,
            fused_tile: int | None = None, fused_block: int | None = None, fused_bwd_tile: int | None = None,
            fused_sub: int | None = None, fused_warps: int | None = None) -> dict:
    device = torch.device(args.device)
    dtype = torch.float64 if args.float64 else torch.float32
    rec = dict(backend=backend, batch=batch, res=res, faces_target=faces, tile=tile, compile=compile,
               raster_model=args.raster_model, cull=not args.no_cull)
    if backend == "fused":
        tuning.TILE = fused_tile or DEFAULT_FUSED[0]
        tuning.FACE_BLOCK = fused_block or DEFAULT_FUSED[1]
        tuning.BWD_TILE = fused_bwd_tile or DEFAULT_FUSED[2]
        tuning.BWD_SUB_BLOCK = fused_sub or DEFAULT_FUSED[3]
        tuning.BWD_WARPS = fused_warps or DEFAULT_FUSED[4]
        rec.update(tile=tuning.TILE, face_block=tuning.FACE_BLOCK, bwd_tile=tuning.BWD_TILE,
                   bwd_sub_block=tuning.BWD_SUB_BLOCK, bwd_warps=tuning.BWD_WARPS)
    scene = Scene(faces, batch, res, device, dtype)
    robot = scene.robot
    rec.update(faces=robot.num_faces, verts=robot.num_vertices)
    if backend == "dense" and batch * robot.num_faces * res * res > DENSE_MAX_ELEMS:
        rec["status"] = "skipped: too large for the dense reference"
        return rec
    settings = dr.RasterSettings(backend=backend, tile_size=tile, compile=compile, sigma=args.sigma,
                                 raster_model=args.raster_model, cull_backfaces=not args.no_cull,
                                 chunk_elems=args.chunk_elems, save_blend_state=args.save_blend_state)
    rec["save_blend_state"] = args.save_blend_state
    cam = scene.camera(scene.qpos)
    verts = scene.verts
    if backend == "tiled":
        st = tiled_static(settings, cam)
        pairs = count_pairs(verts, cam.rotation, cam.eye, robot.faces, st).double()
        rec.update(pairs_mean=float(pairs.mean()), pairs_max=int(pairs.max()))
    weights = torch.rand(batch, 3, res, res, device=device, dtype=dtype)

    def fwd():
        with torch.no_grad():
            return dr.render(verts, robot.faces, robot.colors, cam, settings)

    def fwdbwd():
        v = verts.detach().requires_grad_()
        eye = cam.eye.detach().requires_grad_()
        c = dr.Camera(rotation=cam.rotation, eye=eye, focal=cam.focal, height=res, width=res)
        img = dr.render(v, robot.faces, robot.colors, c, settings)
        (img * weights).sum().backward()

    def fk_fwdbwd():
        q = scene.qpos.detach().requires_grad_()
        v, n = robot.world_vertices_and_normals(q)
        img = dr.render(v, robot.faces, robot.colors, scene.camera(q), settings, normals=n)
        (img * weights).sum().backward()
        return q.grad

    def check_grads():
        """qpos gradient through FK, tracking camera and renderer: finite, and for compiled and fused points
        the relative deviation (2-norm) from the eager tiled kernel's (other rounding and summation order)."""
        g = fk_fwdbwd()
        rec["grad_finite"] = bool(torch.isfinite(g).all())
        if backend == "fused":
            ref = dataclasses.replace(settings, backend="tiled", tile_size=2)
            q = scene.qpos.detach().requires_grad_()
            v, n = robot.world_vertices_and_normals(q)
            img_ref = dr.render(v, robot.faces, robot.colors, scene.camera(q), ref, normals=n)
            (img_ref * weights).sum().backward()
            with torch.no_grad():
                img = dr.render(v, robot.faces, robot.colors, scene.camera(q), settings, normals=n)
            rec["img_max_abs_err_vs_tiled"] = float((img - img_ref).abs().max())
            rec["grad_rel_err_vs_tiled"] = float((g - q.grad).norm() / q.grad.norm())
        if compile:
            eager = dataclasses.replace(settings, compile=False)
            q = scene.qpos.detach().requires_grad_()
            v, n = robot.world_vertices_and_normals(q)
            img = dr.render(v, robot.faces, robot.colors, scene.camera(q), eager, normals=n)
            (img * weights).sum().backward()
            rec["grad_rel_err_vs_eager"] = float((g - q.grad).abs().max() / q.grad.abs().max())

    try:
        rec["fwd_ms"], rec["first_call_ms"] = _time(fwd, device, warmup=args.warmup, repeats=args.repeats)
        rec["fwdbwd_ms"], _ = _time(fwdbwd, device, warmup=args.warmup, repeats=args.repeats)
        rec["fk_fwdbwd_ms"], _ = _time(fk_fwdbwd, device, warmup=args.warmup, repeats=args.repeats)
        if device.type == "cuda" and args.graphs and backend != "dense" and not compile:
            rec["fwd_graph_ms"], _ = _time(graphed(fwd, device), device, warmup=args.warmup,
                                           repeats=args.repeats)
            rec["fwdbwd_graph_ms"], _ = _time(graphed(fwdbwd, device), device, warmup=args.warmup,
                                              repeats=args.repeats)
        check_grads()
        # memory of one fwd+bwd
        if device.type == "cuda":
            sync(device)
            base = torch.cuda.memory_allocated(device)
            torch.cuda.reset_peak_memory_stats(device)
            fwdbwd()
            sync(device)
            rec["peak_alloc_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
            rec["peak_alloc_above_start_mb"] = (torch.cuda.max_memory_allocated(device) - base) / 2**20
            rec["peak_reserved_mb"] = torch.cuda.max_memory_reserved(device) / 2**20
            torch.cuda.reset_peak_memory_stats(device)
            with torch.no_grad():
                fwd()
            sync(device)
            rec["fwd_peak_alloc_above_start_mb"] = (torch.cuda.max_memory_allocated(device) - base) / 2**20
        v = verts.detach().requires_grad_()
        with SavedTensorMeter(exclude=[robot.faces]) as meter:
            img = dr.render(v, robot.faces, robot.colors, cam, settings)
        rec["saved_mb"] = meter.bytes / 2**20
        rec["saved_storages"] = meter.num_storages
        del img
        rec["status"] = "ok"
    except torch.OutOfMemoryError:
        rec["status"] = "oom"
    except Exception as err:  # a benchmark records failures and goes on
        rec["status"] = f"error: {type(err).__name__}: {err}"
        traceback.print_exc()
    finally:
        if device.type == "cuda":
            torch.cuda.empty_cache()
    return rec


def points(args) -> list[dict]:
    """One-factor-at-a-time sweeps around the target point.

    With ``--compile`` every point is measured eager; the target point (each tile size) also compiled, and in
    the full (non-quick) sweep every point: each new shape compiles three graphs (binning, forward, and the
    backward's recompute), tens of seconds each."""
    b0, r0, f0 = 64, 84, 0  # faces 0: the plain ant (detail 1, 1856 faces)
    if args.backends:  # the fast backends: every variant at the target point, then the sweeps on the first
        main = args.backends[0]
        pts = []
        for be in args.backends:
            if be == "fused":
                for var in args.fused_variants or ["x".join(map(str, DEFAULT_FUSED[:2]))]:
                    t, fb, *rest = (int(x) for x in var.split("x"))
                    bt, sub, warps = [*rest, None, None, None][:3]
                    pts.append(dict(backend=be, batch=b0, res=r0, faces=f0, tile=2, fused_tile=t, fused_block=fb,
                                    fused_bwd_tile=bt, fused_sub=sub, fused_warps=warps))
            else:
                pts.append(dict(backend=be, batch=b0, res=r0, faces=f0, tile=2))
        if args.target_only:
            return pts
        for b in (16, 256, 1024):
            pts.append(dict(backend=main, batch=b, res=r0, faces=f0, tile=2))
        for r in (64, 128):
            pts.append(dict(backend=main, batch=b0, res=r, faces=f0, tile=2))
        for f in (1000, 10_000, 30_000, 100_000):
            pts.append(dict(backend=main, batch=b0, res=r0, faces=f, tile=2))
        return pts
    if args.tiny:
        pts = [dict(backend=be, batch=2, res=24, faces=f, tile=4) for be in ("tiled", "dense") for f in (0, 3000)]
        if args.compile:
            pts.insert(1, dict(backend="tiled", batch=2, res=24, faces=0, tile=4, compile=True))
        return pts
    tiles = args.tiles or [dr.RasterSettings().tile_size]
    pts = []
    for tile in tiles:
        pts.append(dict(backend="tiled", batch=b0, res=r0, faces=f0, tile=tile))
        if args.compile:
            pts.append(dict(backend="tiled", batch=b0, res=r0, faces=f0, tile=tile, compile=True))
    t0 = tiles[0]
    batches = [16, 64, 256]
    resolutions = [64, 84, 128]
    face_targets = [1000, 10_000, 30_000, 100_000] if args.quick else [1000, 5000, 10_000, 30_000, 100_000]
    if not args.quick:
        batches = [16, 32, 64, 128, 256]
    for b in batches:
        if b != b0:
            pts.append(dict(backend="tiled", batch=b, res=r0, faces=f0, tile=t0))
    for r in resolutions:
        if r != r0:
            pts.append(dict(backend="tiled", batch=b0, res=r, faces=f0, tile=t0))
    for f in face_targets:
        pts.append(dict(backend="tiled", batch=b0, res=r0, faces=f, tile=t0))
    # the dense reference only where it fits
    pts.append(dict(backend="dense", batch=4, res=64, faces=1000, tile=t0))
    pts.append(dict(backend="tiled", batch=4, res=64, faces=1000, tile=t0))
    if args.compile and not args.quick:
        pts += [dict(p, compile=True) for p in pts if p["backend"] == "tiled" and not p.get("compile")
                and not (p["batch"] == b0 and p["res"] == r0 and p["faces"] == f0)]
    return pts


def table(records: list[dict]) -> str:
    cols = [("backend", "{}"), ("compile", "{}"), ("batch", "{}"), ("res", "{}"), ("faces", "{}"), ("tile", "{}"),
            ("face_block", "{}"),
            ("bwd_tile", "{}"), ("bwd_sub_block", "{}"), ("bwd_warps", "{}"), ("grad_rel_err_vs_tiled", "{:.1e}"),
            ("fwd_graph_ms", "{:.2f}"),
            ("fwdbwd_graph_ms", "{:.2f}"),
            ("pairs_mean", "{:.0f}"), ("fwd_ms", "{:.2f}"), ("fwdbwd_ms", "{:.2f}"), ("fk_fwdbwd_ms", "{:.2f}"),
            ("peak_alloc_above_start_mb", "{:.0f}"), ("peak_reserved_mb", "{:.0f}"), ("saved_mb", "{:.2f}"),
            ("grad_finite", "{}"), ("status", "{}")]
    head = ["backend", "compiled", "B", "res", "faces", "tile", "fblock", "btile", "bsub", "bwarps", "grad err",
            "fwd graph", "f+b graph",
            "pairs", "fwd ms", "f+b ms",
            "fk+f+b", "peak MB",
            "resv MB", "saved MB", "grad ok", "status"]
    rows = [head]
    for r in records:
        row = []
        for key, fmt in cols:
            val = r.get(key)
            row.append("-" if val is None else fmt.format(val) if not isinstance(val, str) else val[:40])
        rows.append(row)
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    return "\n".join("  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in rows)


def _silhouette_pixels(robot, q, cam, settings) -> torch.Tensor:
    """(B, 1, H, W) bool: pixels whose 3 x 3 neighbourhood holds both robot and floor/sky in the hard model's
    image at ``q`` (the robot's pixels: those that differ from the floor and sky rendered alone)."""
    hard = dataclasses.replace(settings, raster_model="hard")
    with torch.no_grad():
        v, n = robot.world_vertices_and_normals(q)
        img = dr.render(v, robot.faces, robot.colors, cam, hard, normals=n)
        empty = dr.render(v[:, :0], robot.faces[:0], robot.colors[:0], cam, hard)
    robot_px = ((img - empty).abs().amax(1, keepdim=True) > 0).double()
    near_robot = torch.nn.functional.max_pool2d(robot_px, 3, 1, 1) > 0
    near_rest = torch.nn.functional.max_pool2d(1.0 - robot_px, 3, 1, 1) > 0
    return near_robot & near_rest


def silhouette_share(args) -> list[dict]:
    """Per raster model (and culling): of the image's change when one joint moves, the part the model's
    analytic gradient predicts, at silhouette pixels and over the whole image.

    The ant at ``--res`` (default 84) under its task camera, ``--poses`` random poses x four hinge joints,
    float64, the ``--device``'s automatic backend (fused on CUDA, tiled elsewhere). Per joint, the finite
    difference ``FD = (I(q + h e) - I(q - h e)) / 2h`` (``h = --fd-step`` rad, which moves edges by about a
    hundredth of a pixel) and the analytic derivative ``AN = dI/dq e`` (one backward pass: only its
    projection on FD is needed). Share = ``sum <FD, AN> / sum <FD, FD>`` over the pixels of the silhouette
    (next to both robot and floor/sky in the hard image) or the whole image, summed over poses and joints:
    1 where the gradient predicts the change, 0 where the image moves only by jumps (a hard edge crossing a
    pixel centre, a pair crossing the coverage cut-off, a face culled as it turns away)."""
    dev = torch.device(args.device)
    f64 = torch.float64
    robot = dr.RobotModel.from_mjcf(ASSETS / "ant.xml", detail=1, dtype=f64, device=dev)
    h = args.fd_step
    out = []
    for model in args.models:
        for cull in (True, False):
            s = dr.RasterSettings(raster_model=model, sigma=args.sigma, cull_backfaces=cull)
            sums = dict(sil_fd_an=0.0, sil_fd_fd=0.0, img_fd_an=0.0, img_fd_fd=0.0)
            sil_pixels = 0
            for seed in range(args.poses):
                scene = Scene(0, 1, args.res, dev, f64, seed=seed)
                q0 = scene.qpos
                cam = scene.camera(q0)
                sil = _silhouette_pixels(robot, q0, cam, s)
                sil_pixels += int(sil.sum())

                def img(q, s=s, cam=cam):
                    v, n = robot.world_vertices_and_normals(q)
                    return dr.render(v, robot.faces, robot.colors, cam, s, normals=n)

                for joint in (7, 9, 11, 13):  # the first hinge of each leg
                    e = torch.zeros_like(q0)
                    e[0, joint] = 1.0
                    with torch.no_grad():
                        fd = (img(q0 + h * e) - img(q0 - h * e)) / (2 * h)
                    for where, mask in (("sil", sil), ("img", None)):
                        u = fd if mask is None else fd * mask
                        q = q0.clone().requires_grad_()
                        (g,) = torch.autograd.grad((img(q) * u).sum(), q)
                        sums[f"{where}_fd_an"] += float(g[0, joint])
                        sums[f"{where}_fd_fd"] += float((u * fd).sum())
            rec = dict(raster_model=model, cull=cull, sigma=args.sigma, res=args.res, poses=args.poses, fd_step=h,
                       backend=dr.backend_for(s, dev), silhouette_pixels=sil_pixels,
                       silhouette_share=sums["sil_fd_an"] / sums["sil_fd_fd"],
                       image_share=sums["img_fd_an"] / sums["img_fd_fd"],
                       silhouette_part_of_change=sums["sil_fd_fd"] / sums["img_fd_fd"])
            print(json.dumps(rec), flush=True)
            out.append(rec)
    return out


def anchor_comparison(args) -> int:
    """``--anchor``: :mod:`anchor`'s time part with this command's models, repeats, warm-up, compile choice and
    output."""
    argv = ["--parts", "time", "--no-warp", "--out", str(args.out), "--models", *args.models]
    argv += ["--repeats", str(args.repeats)] if args.repeats is not None else []
    argv += ["--warmup", str(args.warmup)] if args.warmup is not None else []
    argv += ["--compile", "off", "on"] if args.compile else []
    return anchor.main(argv)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="auto", help="auto (CUDA when present, else CPU), cpu or cuda[:N]")
    p.add_argument("--quick", action="store_true", help="the target point, batch/resolution/face sweeps (<4 min)")
    p.add_argument("--tiny", action="store_true", help="a few tiny points (CPU smoke test)")
    p.add_argument("--backends", nargs="*", choices=["fused", "tiled", "dense"],
                   help="compare these backends at the target point and sweep batch (16-1024), resolution and "
                        "faces on the first (replaces the tiled-only --quick sweep)")
    p.add_argument("--save-blend-state", action="store_true",
                   help="fused: keep the per-pixel blend state for the backward (as the trainer does) instead of "
                        "a second forward pass in backward")
    p.add_argument("--graphs", action="store_true",
                   help="CUDA: also time fwd and fwd+bwd replayed from a captured CUDA graph (as the trainer runs)")
    p.add_argument("--fused-variants", nargs="*",
                   help="fused kernel shapes TILExFACE_BLOCK[xBWD_TILE[xBWD_SUB_BLOCK[xBWD_WARPS]]], e.g. 4x64 "
                        "4x64x8x32 4x64x4x64x2")
    p.add_argument("--target-only", action="store_true",
                   help="with --backends: only the target point (64 ant images, 84x84), no sweeps")
    p.add_argument("--tiles", type=int, nargs="*", help="tile sizes to compare at the target point")
    p.add_argument("--compile", action="store_true", help="also measure with torch.compile (see points())")
    p.add_argument("--raster-model", choices=RASTER_MODELS, default=dr.RasterSettings().raster_model,
                   help="the image model timed (RasterSettings.raster_model)")
    p.add_argument("--no-cull", action="store_true", help="keep back faces (cull_backfaces=False)")
    p.add_argument("--chunk-elems", type=int, default=dr.RasterSettings().chunk_elems)
    p.add_argument("--float64", action="store_true")
    p.add_argument("--sigma", type=float, default=dr.RasterSettings().sigma)
    p.add_argument("--warmup", type=int, default=None)
    p.add_argument("--repeats", type=int, default=None)
    p.add_argument("--out", type=Path, default=Path("bench_render.json"))
    p.add_argument("--anchor", action="store_true",
                   help="instead of the sweeps: the fused backend against nvdiffrast by face count in this process "
                        "(benchmarks/anchor.py's time part: rows with faces, backend, raster_model, fwd_ms, "
                        "fwdbwd_ms, anchor_fwd_ms, anchor_fwdbwd_ms, saved_mb, peak memory), for --models, "
                        "compiled and eager setup with --compile, into --out; needs CUDA and nvdiffrast "
                        "(source ../shared/tools/nvdiffrast-build.sh)")
    p.add_argument("--silhouette-share", action="store_true",
                   help="instead of timing: per raster model, the part of the image's change at silhouette pixels "
                        "(and over the image) when a joint moves that the analytic gradient predicts")
    p.add_argument("--models", nargs="*", choices=RASTER_MODELS, default=list(RASTER_MODELS),
                   help="--silhouette-share and --anchor: the raster models compared")
    p.add_argument("--res", type=int, default=84, help="--silhouette-share: image side [px]")
    p.add_argument("--poses", type=int, default=4, help="--silhouette-share: random ant poses")
    p.add_argument("--fd-step", type=float, default=1e-3, help="--silhouette-share: joint step h [rad]")
    args = p.parse_args(argv)
    try:
        device = resolve_device(args.device)
    except ValueError as e:
        p.error(str(e))
    args.device = str(device)
    if args.anchor:
        return anchor_comparison(args)
    if args.silhouette_share:
        recs = silhouette_share(args)
        write_json(args.out, recs, indent=2)
        print("\nmodel    cull   sigma  silhouette share  image share  silhouette part of change  backend")
        for r in recs:
            print(f"{r['raster_model']:7}  {r['cull']!s:5}  {r['sigma']:5}  {r['silhouette_share']:16.3f}  "
                  f"{r['image_share']:11.3f}  {r['silhouette_part_of_change']:25.3f}  {r['backend']}")
        return 0
    args.warmup = args.warmup if args.warmup is not None else (3 if args.compile else 2)
    args.repeats = args.repeats if args.repeats is not None else (3 if args.tiny else 7 if args.quick else 15)
    torch.manual_seed(0)
    if args.compile:
        # one compiled graph set per point shape; the default limit (8) would silently fall back to eager
        torch._dynamo.config.cache_size_limit = max(torch._dynamo.config.cache_size_limit, 64)
    records = []
    start = time.perf_counter()
    for pt in points(args):
        rec = measure(args, **pt)
        records.append(rec)
        print(json.dumps(rec), flush=True)
        write_json(args.out, dict(partial=True, records=records), indent=2)  # survives a kill
    info = dict(torch=torch.__version__, python=platform.python_version(), device=args.device,
                device_name=torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor(),
                threads=torch.get_num_threads(), compile=args.compile, dtype="float64" if args.float64 else "float32",
                sigma=args.sigma, raster_model=args.raster_model, cull=not args.no_cull, chunk_elems=args.chunk_elems,
                wall_s=time.perf_counter() - start, targets=TARGET)
    # the target point per backend, its best variant; graph-replayed times where measured (how the trainer
    # renders under --compile), else eager
    info["target_point"], info["target_met"] = {}, {}
    for be in sorted({r["backend"] for r in records}):
        at_target = [r for r in records if r.get("status") == "ok" and r["backend"] == be and r["batch"] == 64
                     and r["res"] == 84 and r["faces_target"] == 0]
        if not at_target:
            continue

        def timed(r, key):
            return r.get(key.replace("_ms", "_graph_ms"), r.get(key))

        target = min(at_target, key=lambda r: timed(r, "fwdbwd_ms"))
        point = {k: timed(target, k) for k in ("fwd_ms", "fwdbwd_ms")}
        point.update({k: target.get(k) for k in ("saved_mb", "tile", "face_block", "compile")},
                     graphed="fwd_graph_ms" in target)
        info["target_point"][be] = point
        info["target_met"][be] = {k: point.get(k) is not None and point[k] <= v for k, v in TARGET.items()}
    write_json(args.out, dict(info=info, records=records), indent=2)
    print(f"\nwrote {args.out} ({len(records)} points, {info['wall_s']:.0f} s, {info['device_name']}, "
          f"torch {torch.__version__}, compile={args.compile})")
    for be, point in info["target_point"].items():
        print(f"target point, {be} (64 ant envs, 84x84): {point} vs {TARGET} -> {info['target_met'][be]}")
    print(table(records))
    return 0


if __name__ == "__main__":
    sys.exit(main())
