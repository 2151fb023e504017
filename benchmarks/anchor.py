"""The renderer against an anchor: nvdiffrast, and the Warp ray tracer, on the same scene and camera.

Not a test. On a CUDA device, for the ant at 64 x 84 x 84 with extra meshes up to each face count, one process:

- ``time``: per face count and backend, forward and forward+backward [ms] (median of ``--repeats`` after
  warm-up, CUDA-synchronised), peak allocated/reserved memory of the fwd+bwd region and the bytes autograd
  saves. Backends: ours ``fused`` for each raster model, eager and CUDA-graph-replayed (as the trainer runs
  it under ``--compile``); ``warp`` (forward only, eager and graph-replayed); ``nvdiffrast`` (rasterize +
  interpolate colours and normals + Lambert shading + antialias; eager), when it is importable
  (``source ../shared/tools/nvdiffrast-build.sh``). The backward is that of a fixed random weighting of the
  image, into the world vertices. nvdiffrast is timed first, so each fused row carries ``anchor_fwd_ms`` and
  ``anchor_fwdbwd_ms`` and the ratios; and the device time of one eager fwd+bwd by stage (torch.profiler,
  kernels by name: ``raster_fwd_ms`` the forward kernels (binning, walk and merge), ``raster_bwd_ms`` the backward
  kernels (per pixel and per face), ``setup_fwd_ms`` everything else of a no-grad render, i.e. the per-face
  setup with its box levels and the floor, and ``setup_bwd_ms`` the rest of the fwd+bwd: the backward's
  recompute of the setup and its autograd). ``--variants`` times the fused backend again with some of
  ``diffrender.raster.fused.tuning``'s constants changed (e.g. ``SUPER_BLOCK=1``, a single-level walk over
  the faces), each row tagged with its ``variant``; ``--compile on`` with the setup's PyTorch part compiled, as
  the trainer runs it. A variant with ``FWD_BIN=1`` (per-tile face lists of ``BIN_CAPACITY``) also records
  ``bin_overflows``, the tile lists of its renders that overflowed (``fused.bin_overflows``).
- ``iou``: the sharp-limit silhouette of each of our models and of the ray tracer against nvdiffrast's
  coverage (no floor, black background, white unlit robot), 64 ant poses: intersection over union and our
  mask's size relative to the anchor's.

    python benchmarks/anchor.py --out benchmarks/results/anchor.json            # both parts
    python benchmarks/anchor.py --faces 0 --models softmax --repeats 5         # a quick look
    python benchmarks/anchor.py --parts time --variants default COEF_ELEMS=16777216,SUPER_BLOCK=1
    python benchmarks/anchor.py --parts time --batch 768 --faces 0 21000 --variants default FWD_BIN=1,BIN_CAPACITY=256

The scene, poses and camera are ``benchmarks/_common.py``'s ``Scene`` (the ant task's tracking camera).
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import json
import platform
import sys
import time
import traceback
from pathlib import Path

import torch
from _common import FUSED_DEFAULTS, Scene, apply_fused_variant, commit, graphed, median_ms, sync, write_json

import diffrender as dr
from diffrender.profiling import SavedTensorMeter
from diffrender.raster import fused
from diffrender.settings import RASTER_MODELS

CUDA = torch.device("cuda")
FACES = (0, 4500, 21000, 100000)  # 0: the plain ant (1,856 faces); extra spheres up to about the rest


def _stages(fn_fwd, fn_fwdbwd) -> dict:
    """Device time [ms] of one call of each, by stage: the fused kernels by name, the rest as setup."""
    from torch.profiler import ProfilerActivity, profile

    def by_kernel(fn) -> dict:
        sync(CUDA)
        with profile(activities=[ProfilerActivity.CUDA]) as prof:
            fn()
            sync(CUDA)
        out = {"fwd": 0.0, "bwd": 0.0, "other": 0.0, "kernels": 0, "by_name": {}}
        for e in prof.events():
            if e.device_type != torch.autograd.DeviceType.CUDA:
                continue
            ms = e.time_range.elapsed_us() / 1e3
            raster_fwd = any(k in e.name for k in ("_fused_forward", "_binned_forward", "_merge_forward", "_bin_faces"))
            raster_bwd = "_fused_backward" in e.name or "_pixel_backward" in e.name
            key = "fwd" if raster_fwd else "bwd" if raster_bwd else "other"
            out[key] += ms
            out["kernels"] += 1
            count, total = out["by_name"].get(e.name, (0, 0.0))
            out["by_name"][e.name] = (count + 1, total + ms)
        return out

    f, fb = by_kernel(fn_fwd), by_kernel(fn_fwdbwd)
    top = sorted(fb["by_name"].items(), key=lambda kv: -kv[1][1])[:12]
    return {"setup_fwd_ms": f["other"], "raster_fwd_ms": f["fwd"], "raster_bwd_ms": fb["bwd"],
            "setup_bwd_ms": max(0.0, fb["other"] - f["other"]), "kernels_fwd": f["kernels"],
            "kernels_fwdbwd": fb["kernels"],
            # the fwd+bwd's costliest kernels: [name (cut to 80 characters), launches, ms]
            "top_kernels_fwdbwd": [[name[:80], n, round(ms, 4)] for name, (n, ms) in top]}


def _peak(fn) -> dict:
    """Peak allocated / reserved memory [MB] of one call, above what was allocated before it."""
    sync(CUDA)
    torch.cuda.reset_peak_memory_stats()
    base = torch.cuda.memory_allocated()
    fn()
    sync(CUDA)
    return {"peak_alloc_mb": (torch.cuda.max_memory_allocated() - base) / 2**20,
            "peak_reserved_mb": torch.cuda.max_memory_reserved() / 2**20}


def clip_space(verts: torch.Tensor, cam: dr.Camera, settings: dr.RasterSettings) -> torch.Tensor:
    """World vertices (B, V, 3) -> nvdiffrast clip coordinates (B, V, 4) for the same pinhole camera.

    Our camera frame is x right, y down, z forward with pixel ``u = f x / z + W / 2``; nvdiffrast's image row
    0 is clip y = -w, so ``clip = (2 f x / W, 2 f y / H, depth, z)`` puts every vertex on the same pixel.
    """
    p = torch.einsum("bij,bnj->bni", cam.rotation, verts - cam.eye[:, None, :])
    x, y, z = p.unbind(-1)
    n, f = settings.znear, settings.zfar
    zc = z * (f + n) / (f - n) - 2 * f * n / (f - n)
    return torch.stack([2 * cam.focal * x / cam.width, 2 * cam.focal * y / cam.height, zc, z], dim=-1)


class Anchor:
    """nvdiffrast's rasterize + interpolate + Lambert + antialias on our scene (robot only, no floor)."""

    def __init__(self, robot: dr.RobotModel, settings: dr.RasterSettings, res: int):
        import nvdiffrast.torch as ndr

        self.ndr, self.ctx = ndr, ndr.RasterizeCudaContext()
        self.tri = robot.faces.to(torch.int32).contiguous()
        self.colors, self.settings, self.res = robot.colors, settings, res
        light = torch.tensor(settings.light_dir, device=robot.device, dtype=torch.float32)
        self.light = light / light.norm()

    def coverage(self, verts: torch.Tensor, cam: dr.Camera) -> torch.Tensor:
        clip = clip_space(verts, cam, self.settings).contiguous()
        rast, _ = self.ndr.rasterize(self.ctx, clip, self.tri, (self.res, self.res))
        return rast[..., 3] > 0  # (B, H, W): a triangle covers the pixel centre

    def image(self, verts: torch.Tensor, cam: dr.Camera) -> torch.Tensor:
        ndr, s = self.ndr, self.settings
        clip = clip_space(verts, cam, s).contiguous()
        rast, _ = ndr.rasterize(self.ctx, clip, self.tri, (self.res, self.res))
        # area-weighted vertex normals, as the rasterizer computes them when none are given
        faces = self.tri.long()
        fv = verts[:, faces]
        fn = torch.linalg.cross(fv[:, :, 1] - fv[:, :, 0], fv[:, :, 2] - fv[:, :, 0])
        acc = torch.zeros_like(verts).index_add_(1, faces.reshape(-1), fn.repeat_interleave(3, 1))
        normals = acc * torch.rsqrt((acc * acc).sum(-1, keepdim=True) + 1e-30)
        colors = self.colors.expand(verts.shape[0], -1, -1) if self.colors.ndim == 2 else self.colors
        attr = torch.cat([colors, normals], dim=-1).contiguous()
        feat, _ = ndr.interpolate(attr, rast, self.tri)
        n = torch.nn.functional.normalize(feat[..., 3:], dim=-1)
        shade = s.ambient + s.diffuse * (n @ self.light).clamp(min=0)
        rgb = feat[..., :3] * shade[..., None]
        bg = torch.tensor(s.background, device=verts.device, dtype=verts.dtype)
        rgb = torch.where(rast[..., 3:] > 0, rgb, bg)
        return ndr.antialias(rgb.contiguous(), rast, clip, self.tri).permute(0, 3, 1, 2)


def _time_scene(args, faces: int, *, anchor_ok: bool) -> list[dict]:
    rows = []
    # each scene compiles the setup afresh, as a trainer (one mesh) would: the shapes of earlier scenes would
    # otherwise count towards dynamo's recompile limit, past which it falls back to eager
    torch._dynamo.reset()
    scene = Scene(faces, args.batch, args.res, torch.device("cuda"), torch.float32)
    robot, cam = scene.robot, scene.camera(scene.qpos)
    base = dict(faces=robot.num_faces, batch=args.batch, res=args.res)
    weights = torch.rand(args.batch, 3, args.res, args.res, device="cuda")
    verts0 = scene.verts.detach()

    def fwdbwd_of(render_fn):
        verts = verts0.clone().requires_grad_(True)

        def step():
            verts.grad = None
            (render_fn(verts) * weights).sum().backward()
        return step, verts

    anchor_row = None
    if anchor_ok:
        anchor_row = dict(base, backend="nvdiffrast", raster_model="hard+antialias")
        try:
            anchor = Anchor(robot, dr.RasterSettings(floor=None), args.res)
            with torch.no_grad():
                anchor_row["fwd_eager_ms"] = median_ms(lambda: anchor.image(verts0, cam), CUDA, warmup=args.warmup,
                                                        repeats=args.repeats)
            step, _ = fwdbwd_of(lambda v: anchor.image(v, cam))
            anchor_row["fwdbwd_eager_ms"] = median_ms(step, CUDA, warmup=args.warmup, repeats=args.repeats)
            anchor_row.update(_peak(step))
        except Exception as e:
            anchor_row["error"] = f"{type(e).__name__}: {e}"
            traceback.print_exc()
        print(json.dumps(anchor_row), flush=True)

    for variant, compile_ in itertools.product(args.variants, args.compile):
        constants = apply_fused_variant(variant)
        for model in args.models:
            settings = dr.RasterSettings(raster_model=model, backend="fused", sync_checks=False,
                                         save_blend_state=True, compile=compile_ == "on")
            row = dict(base, backend="fused", raster_model=model, variant=variant, compile=compile_ == "on",
                       fused_constants=constants)
            try:
                def render(v, settings=settings):
                    return dr.render(v, robot.faces, robot.colors, cam, settings)

                def fwd_nograd(render=render):
                    with torch.no_grad():
                        render(verts0)
                row["fwd_eager_ms"] = median_ms(fwd_nograd, CUDA, warmup=args.warmup, repeats=args.repeats)
                step, _ = fwdbwd_of(render)
                row["fwdbwd_eager_ms"] = median_ms(step, CUDA, warmup=args.warmup, repeats=args.repeats)
                row.update(_peak(step))
                with SavedTensorMeter(exclude=[robot.faces]) as meter:
                    kept = render(verts0.clone().requires_grad_(True))  # alive: its graph holds the saved tensors
                row["saved_mb"] = meter.bytes / 2**20
                del kept
                try:
                    row.update(_stages(fwd_nograd, step))
                except Exception as e:  # the breakdown is optional: a profiler failure keeps the timings
                    row["stages_error"] = f"{type(e).__name__}: {e}"
                row["fwd_ms"] = median_ms(graphed(fwd_nograd, CUDA, warmup=3), CUDA, warmup=args.warmup,
                                           repeats=args.repeats)
                row["fwdbwd_ms"] = median_ms(graphed(step, CUDA, warmup=3), CUDA, warmup=args.warmup,
                                              repeats=args.repeats)
            except Exception as e:  # an OOM or a failed capture is a result: record it and go on
                row["error"] = f"{type(e).__name__}: {e}"
                traceback.print_exc()
            if constants["FWD_BIN"]:  # the row's tile lists that overflowed BIN_CAPACITY (read outside the graphs)
                row["bin_overflows"] = fused.bin_overflows()
            if anchor_row is not None and "fwdbwd_eager_ms" in anchor_row:
                row["anchor_fwd_ms"] = anchor_row["fwd_eager_ms"]
                row["anchor_fwdbwd_ms"] = anchor_row["fwdbwd_eager_ms"]
                for key in ("fwd_ms", "fwdbwd_ms", "fwd_eager_ms", "fwdbwd_eager_ms"):
                    if key in row:
                        anchor_key = "anchor_fwd_ms" if key.startswith("fwd_") else "anchor_fwdbwd_ms"
                        row[key.replace("_ms", "_vs_anchor")] = row[key] / row[anchor_key]
            rows.append(row)
            print(json.dumps(row), flush=True)
    apply_fused_variant("default")

    if args.warp:
        row = dict(base, backend="warp", raster_model="hard")
        try:
            settings = dr.RasterSettings(sync_checks=False)
            tracer = dr.RayTracer(robot.faces, num_envs=args.batch, num_verts=robot.num_vertices,
                                  device="cuda", settings=settings)

            def trace():
                with torch.no_grad():
                    tracer(verts0, robot.colors, cam)
            trace()
            row["fwd_eager_ms"] = median_ms(trace, CUDA, warmup=args.warmup, repeats=args.repeats)
            row["images_per_s_eager"] = args.batch / row["fwd_eager_ms"] * 1e3
            if args.warp_graph:  # a failed capture leaves the CUDA context unusable: opt in
                row["fwd_ms"] = median_ms(graphed(trace, CUDA, warmup=3), CUDA, warmup=args.warmup,
                                           repeats=args.repeats)
                row["images_per_s"] = args.batch / row["fwd_ms"] * 1e3
        except Exception as e:
            row["error"] = f"{type(e).__name__}: {e}"
            traceback.print_exc()
        rows.append(row)
        print(json.dumps(row), flush=True)
    if anchor_row is not None:
        rows.append(anchor_row)
    return rows


def iou_rows(args) -> list[dict]:
    """Sharp-limit silhouettes against nvdiffrast's coverage, the ant (no extra meshes), 64 poses."""
    if not _nvdiffrast_available():
        return [{"part": "iou", "error": "nvdiffrast is not importable"}]
    scene = Scene(0, args.batch, args.res, torch.device("cuda"), torch.float32, seed=1)
    robot, cam = scene.robot, scene.camera(scene.qpos)
    white = torch.ones_like(robot.colors)
    unlit = dict(floor=None, background=(0.0, 0.0, 0.0), ambient=1.0, diffuse=0.0)
    ref = Anchor(robot, dr.RasterSettings(floor=None), args.res).coverage(scene.verts, cam)
    rows = []
    candidates = [(m, "fused") for m in args.models] + [("hard", "warp")]
    for model, backend in candidates:
        row = dict(part="iou", backend=backend, raster_model=model, sigma=args.iou_sigma, gamma=args.iou_gamma,
                   faces=robot.num_faces, batch=args.batch, res=args.res)
        try:
            with torch.no_grad():
                if backend == "warp":
                    s = dr.RasterSettings(**unlit)
                    img = dr.render_raytraced(scene.verts, robot.faces, white, cam, s)
                else:
                    s = dr.RasterSettings(raster_model=model, sigma=args.iou_sigma, gamma=args.iou_gamma,
                                          backend="fused", **unlit)
                    img = dr.render(scene.verts, robot.faces, white, cam, s)
            mask = img[:, 0] > 0.5
            inter = (mask & ref).sum().item()
            union = (mask | ref).sum().item()
            row.update(iou=inter / max(union, 1), size_vs_anchor=mask.sum().item() / max(ref.sum().item(), 1),
                       anchor_pixels=int(ref.sum().item()))
        except Exception as e:
            row["error"] = f"{type(e).__name__}: {e}"
            traceback.print_exc()
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def _nvdiffrast_available() -> bool:
    try:
        import nvdiffrast.torch  # noqa: F401
    except ImportError:
        return False
    return True


def table(rows: list[dict]) -> str:
    """Markdown: per face count and backend the times [ms] (graph-replayed and eager), nvdiffrast's in the same
    process, the ratios, memory [MB] and the fused backend's stages [ms] of one eager fwd+bwd."""
    lines = ["| faces | backend | model | variant | fwd graph | fwd+bwd graph | fwd eager | fwd+bwd eager | "
             "nvdiffrast fwd | nvdiffrast fwd+bwd | fwd+bwd graph / nvdr | fwd+bwd eager / nvdr | "
             "fwd graph / nvdr | saved MB | peak MB | setup fwd | raster fwd | raster bwd | setup bwd |",
             "|" + "---|" * 19]

    def f(r, k):
        v = r.get(k)
        return "-" if v is None else f"{v:.3g}"
    for r in rows:
        if r.get("part") == "iou":
            continue
        variant = r.get("variant", "-") + (" +compile" if r.get("compile") else "")
        lines.append("| " + " | ".join([str(r["faces"]), r["backend"], r["raster_model"], variant]
                                       + [f(r, k) for k in ("fwd_ms", "fwdbwd_ms", "fwd_eager_ms", "fwdbwd_eager_ms",
                                                            "anchor_fwd_ms", "anchor_fwdbwd_ms",
                                                            "fwdbwd_vs_anchor", "fwdbwd_eager_vs_anchor",
                                                            "fwd_vs_anchor", "saved_mb", "peak_alloc_mb",
                                                            "setup_fwd_ms", "raster_fwd_ms", "raster_bwd_ms",
                                                            "setup_bwd_ms")])
                     + " |" + (f" {r['error'][:60]}" if "error" in r else ""))
    ious = [r for r in rows if r.get("part") == "iou" and "iou" in r]
    if ious:
        lines += ["", "| silhouette vs nvdiffrast | model | IoU | size / anchor |", "|---|---|---|---|"]
        lines += [f"| {r['backend']} | {r['raster_model']} | {r['iou']:.4f} | {r['size_vs_anchor']:.4f} |"
                  for r in ious]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--faces", type=int, nargs="*", default=list(FACES),
                   help="face-count targets (0: the plain ant); extra sphere meshes fill the rest")
    p.add_argument("--models", nargs="*", choices=RASTER_MODELS, default=list(RASTER_MODELS),
                   help="raster models of our fused backend to time and compare")
    p.add_argument("--batch", type=int, default=64, help="environments per frame")
    p.add_argument("--res", type=int, default=84, help="image side [px]")
    p.add_argument("--warmup", type=int, default=5, help="untimed calls before timing")
    p.add_argument("--repeats", type=int, default=20, help="timed calls; the median is reported")
    p.add_argument("--iou-sigma", type=float, default=0.02, help="sigma [px] of the sharp-limit silhouettes")
    p.add_argument("--iou-gamma", type=float, default=1e-4, help="gamma of the sharp-limit silhouettes")
    p.add_argument("--variants", nargs="*", default=["default"],
                   help="fused backend settings to time: 'default', or NAME=VALUE,NAME=VALUE of diffrender.raster."
                        f"fused.tuning's constants ({', '.join(FUSED_DEFAULTS)})")
    p.add_argument("--compile", nargs="+", choices=["off", "on"], default=["off"],
                   help="time the fused backend with its setup's PyTorch part eager (off) and/or through "
                        "torch.compile (on: RasterSettings.compile, as the trainer renders under --compile); "
                        "each row says which")
    p.add_argument("--no-warp", dest="warp", action="store_false", help="leave the Warp ray tracer out")
    p.add_argument("--warp-graph", action="store_true",
                   help="also time the ray tracer replayed from a CUDA graph (a failed capture ends the process)")
    p.add_argument("--parts", nargs="*", choices=["time", "iou"], default=["iou", "time"])
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/anchor.json"), help="JSON output")
    args = p.parse_args(argv)
    if not torch.cuda.is_available():
        p.error("needs a CUDA device (nvdiffrast and the timed fused kernels are CUDA-only)")
    started = time.time()
    meta = dict(device=torch.cuda.get_device_name(), torch=torch.__version__, python=platform.python_version(),
                date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), commit=commit(),
                command="python benchmarks/anchor.py " + " ".join(argv if argv is not None else sys.argv[1:]),
                args={k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
                seconds=None)
    rows: list[dict] = []

    def save() -> None:  # after every part: a crash later keeps what was measured
        meta["seconds"] = round(time.time() - started, 1)
        write_json(args.out, {"meta": meta, "rows": rows})
    if "iou" in args.parts:
        rows += iou_rows(args)
        save()
    if "time" in args.parts:
        for faces in args.faces:
            rows += _time_scene(args, faces, anchor_ok=_nvdiffrast_available())
            save()
            torch.cuda.empty_cache()
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

