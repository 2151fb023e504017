"""Variants of the Warp ray tracer (:class:`diffrender.RayTracer`): where a frame's time goes, and which options
are fastest.

Not a test. One process. For each scene (64 ant environments at 84 x 84; ``--faces`` 0 is the plain ant,
1,856 faces, larger targets add extra sphere meshes to its moving bodies as ``benchmarks/_common.py``'s
``Scene`` does: ~20k and ~100k faces per robot) and each variant (constructor options of ``RayTracer``), it
times, after warm-up, the median of ``--repeats`` (CUDA events on the GPU, wall clock on the CPU):

- ``refit``: posed vertices copied into the BVH's point buffer and the BVH refitted (``RayTracer.refit``);
- ``trace``: normals, colours and camera copied, one trace launch (``RayTracer.trace``);
- ``frame``: both, through ``RayTracer.__call__`` with the trainer's inputs (given normals), as a frame runs;
- each eager and (CUDA, unless ``--no-graphs``) replayed from a captured CUDA graph (``_common.graphed``),
  which is how the trainer runs it;
- ``build_s``: the first call (the tree built from that frame's poses; ``"sah"`` and ``"median"`` build on
  the host), and ``rebuild`` [ms] for ``"lbvh"`` (a new tree on the GPU every frame instead of a refit; eager:
  it allocates).

Rows also give images/s of ``frame`` and the share of rays that see the robot. A variant's image is checked
against the default variant's (max abs difference; options other than the tree give the same image).

Where the time should go (64 ant environments, 118,784 triangles, 451,584 rays; H100, graph-replayed). A frame is
about 13 dependent kernels: five small copies (vertices, normals, colours, camera rotation and eye), Warp's mesh
refit (triangle edge lengths, a CUB scan of them with its temporary allocation, their mean, triangle bounds, a
counter reset and the bottom-up refit: seven kernels and two memory nodes) and the trace. Bytes are no limit:
about 12 MB in all (5.4 MB of image), a few microseconds of bandwidth. Predicted: ~0.03 ms of launch gaps and
copies; the refit ~0.1 ms, bound by the latency of its leaf-to-root climb (a fence and an atomic per tree level,
~30 levels in an LBVH, ~20 in an SAH tree with 4 triangles per leaf); the trace ~0.15 ms with 4 x 8 pixel tiles
and each group's subtree root looked up once per build (found per pixel, it costs two binary searches over the
leaves and two leaf-to-root climbs: ~200 dependent loads per pixel). So ~0.25-0.3 ms per frame (BENCHMARKS.md,
section 2, has the measured one). At ~100k faces per robot (6.4M triangles) bytes do count: an LBVH keeps 2
nodes per triangle (12.8M nodes, ~0.8 GB of node traffic per refit, ~3 ms), an SAH tree with 4 triangles per
leaf a quarter of that, so ~1 ms per frame with ``"sah"``.

    python benchmarks/raytrace.py --out benchmarks/results/raytrace.json          # CUDA, < 4 min on an H100
    python benchmarks/raytrace.py --faces 0 --out /tmp/raytrace_ant.json          # the ant scene only
    python benchmarks/raytrace.py --device cpu --tiny --out /tmp/raytrace.json    # smoke test (Warp's CPU device)
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import sys
import time
import traceback
from pathlib import Path

import torch
from _common import Scene, commit, graphed, median_ms, sync, write_json

import diffrender as dr
from tasks.device import resolve_device

FACES = (0, 20_000, 100_000)  # 0: the plain ant (1,856 faces); extra spheres up to about the rest
TARGET_MS = {0: 0.25, 100_000: 1.0}  # per 64-image frame, graph-replayed (H100)

# Variants by name: RayTracer options. "default" is RayTracer's own defaults; the others change one thing
# (the last two combine the tree builder with the pixel order the tracer had before tiles).
VARIANTS: dict[str, dict] = {
    "default": {},
    "lbvh": dict(bvh_constructor="lbvh"),
    "median": dict(bvh_constructor="median"),
    "leaf1": dict(bvh_leaf_size=1),
    "leaf2": dict(bvh_leaf_size=2),
    "leaf8": dict(bvh_leaf_size=8),
    "rows": dict(tile=None),
    "tile8x4": dict(tile=(8, 4)),
    "tile2x16": dict(tile=(2, 16)),
    "tile8x8": dict(tile=(8, 8)),
    "rays2": dict(rays_per_thread=2),
    "rays4": dict(rays_per_thread=4),
    "block128": dict(block_dim=128),
    "block64": dict(block_dim=64),
    "lbvh_rows": dict(bvh_constructor="lbvh", tile=None),
    "shadows": dict(shadows=True),
}
# the variants timed on the scenes with extra meshes (each host-built tree of 6.4M triangles takes seconds)
LARGE_VARIANTS = ("default", "lbvh", "median", "leaf2", "leaf8", "rows", "lbvh_rows")
TINY_VARIANTS = ("default", "lbvh", "rows", "rays2", "leaf1")


def time_scene(args, faces: int, names: list[str]) -> list[dict]:
    device = torch.device(args.device)
    scene = Scene(faces, args.batch, args.res, device, torch.float32)
    robot = scene.robot
    cam = scene.camera(scene.qpos)
    with torch.no_grad():
        verts, normals = robot.world_vertices_and_normals(scene.qpos)
    colors = robot.colors
    settings = dr.RasterSettings(sync_checks=False)
    base = dict(faces_target=faces, faces=robot.num_faces, verts=robot.num_vertices, batch=args.batch,
                res=args.res, rays=args.batch * args.res * args.res)
    empty = dr.RayTracer(robot.faces[:0], num_envs=args.batch, num_verts=robot.num_vertices, device=device,
                         settings=settings)
    with torch.no_grad():
        floor = empty(verts, colors, cam, normals=normals)
    reference = None
    rows = []
    for name in names:
        options = VARIANTS[name]
        row = dict(base, variant=name, options={k: (list(v) if isinstance(v, tuple) else v)
                                                for k, v in options.items()})
        try:
            tracer = dr.RayTracer(robot.faces, num_envs=args.batch, num_verts=robot.num_vertices, device=device,
                                  settings=settings, **options)
            row.update(bvh_constructor=tracer.bvh_constructor, bvh_leaf_size=tracer.bvh_leaf_size,
                       tile=None if tracer.tile is None else list(tracer.tile),
                       rays_per_thread=tracer.rays_per_thread, block_dim=tracer.block_dim)

            def frame(tracer=tracer):
                with torch.no_grad():
                    return tracer(verts, colors, cam, normals=normals)

            def refit(tracer=tracer):
                tracer.refit(verts)

            def trace(tracer=tracer):
                return tracer.trace(colors, cam, normals=normals)

            sync(device)
            t0 = time.perf_counter()
            image = frame()
            sync(device)
            row["build_s"] = time.perf_counter() - t0
            if reference is None:
                reference = image
                row["robot_ray_share"] = float((image != floor).any(1).double().mean())
            row["max_abs_diff_vs_first"] = float((image - reference).abs().max())
            timing = dict(warmup=args.warmup, repeats=args.repeats)
            row["refit_ms"] = median_ms(refit, device, **timing)
            row["trace_ms"] = median_ms(trace, device, **timing)
            row["frame_ms"] = median_ms(frame, device, **timing)
            if tracer.bvh_constructor == "lbvh" and device.type == "cuda":
                row["rebuild_ms"] = median_ms(tracer.rebuild, device, **timing)
                frame()  # back to a tree of this frame, refitted
            if device.type == "cuda" and args.graphs:
                for key, fn in (("refit", refit), ("trace", trace), ("frame", frame)):
                    row[f"{key}_graph_ms"] = median_ms(graphed(fn, device, warmup=3), device, **timing)
            best = row.get("frame_graph_ms", row["frame_ms"])
            row["images_per_s"] = args.batch / best * 1e3
            row["mrays_per_s"] = base["rays"] / best * 1e-3
            row["status"] = "ok"
            del tracer
        except Exception as e:  # a variant that fails is a result: record it and go on
            row["status"] = f"error: {type(e).__name__}: {e}"[:300]
            traceback.print_exc()
        rows.append(row)
        print(json.dumps(row), flush=True)
        if device.type == "cuda":
            torch.cuda.empty_cache()
    return rows


def table(rows: list[dict]) -> str:
    cols = [("faces", "{}"), ("variant", "{}"), ("build_s", "{:.2f}"), ("refit_ms", "{:.3f}"),
            ("trace_ms", "{:.3f}"), ("frame_ms", "{:.3f}"), ("refit_graph_ms", "{:.3f}"), ("trace_graph_ms", "{:.3f}"),
            ("frame_graph_ms", "{:.3f}"), ("rebuild_ms", "{:.3f}"), ("images_per_s", "{:.0f}"),
            ("max_abs_diff_vs_first", "{:.1e}"), ("status", "{}")]
    head = ["faces", "variant", "build s", "refit", "trace", "frame", "refit g", "trace g", "frame g", "rebuild",
            "images/s", "diff", "status"]
    out = [head]
    for r in rows:
        out.append(["-" if r.get(k) is None else (f.format(r[k]) if not isinstance(r[k], str) else r[k][:40])
                    for k, f in cols])
    widths = [max(len(r[i]) for r in out) for i in range(len(head))]
    return "\n".join("  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="auto", help="auto (CUDA when present, else CPU), cpu or cuda[:N]")
    p.add_argument("--faces", type=int, nargs="*", default=None,
                   help="face-count targets per robot (0: the plain ant); default 0 20000 100000")
    p.add_argument("--variants", nargs="*", choices=list(VARIANTS), default=None,
                   help="variants to time (default: all on the ant, a subset on the larger scenes)")
    p.add_argument("--batch", type=int, default=None, help="environments per frame (default 64; --tiny 2)")
    p.add_argument("--res", type=int, default=None, help="image side [px] (default 84; --tiny 20)")
    p.add_argument("--warmup", type=int, default=None, help="untimed calls before each timing (default 5)")
    p.add_argument("--repeats", type=int, default=None, help="timed calls; the median is reported (default 30)")
    p.add_argument("--no-graphs", dest="graphs", action="store_false", help="CUDA: skip the graph-replayed times")
    p.add_argument("--tiny", action="store_true", help="a smoke test: 2 ant environments at 20 x 20, few variants")
    p.add_argument("--out", type=Path, default=Path("raytrace.json"), help="JSON output")
    args = p.parse_args(argv)
    try:
        device = resolve_device(args.device)
    except ValueError as e:
        p.error(str(e))
    args.device = str(device)
    args.batch = args.batch or (2 if args.tiny else 64)
    args.res = args.res or (20 if args.tiny else 84)
    args.warmup = args.warmup if args.warmup is not None else (1 if args.tiny else 5)
    args.repeats = args.repeats or (3 if args.tiny else 30)
    faces_list = args.faces if args.faces is not None else ([0] if args.tiny else list(FACES))
    started = time.time()
    meta = dict(device=torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu ({platform.processor()})",
                torch=torch.__version__, python=platform.python_version(),
                date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), commit=commit(),
                command="python benchmarks/raytrace.py " + " ".join(argv if argv is not None else sys.argv[1:]),
                args={k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}, targets_ms=TARGET_MS)
    try:
        import warp

        meta["warp"] = warp.__version__
    except ImportError:
        p.error("the ray tracer needs Warp (pip install warp-lang)")
    rows: list[dict] = []

    def save() -> None:  # after every scene: a crash later keeps what was measured
        meta["seconds"] = round(time.time() - started, 1)
        write_json(args.out, {"meta": meta, "rows": rows})

    for faces in faces_list:
        if args.variants is not None:
            names = args.variants
        else:
            names = list(TINY_VARIANTS if args.tiny else VARIANTS if faces == 0 else LARGE_VARIANTS)
        rows += time_scene(args, faces, names)
        save()
    print(f"\n{meta['device']}, warp {meta['warp']}, {args.batch} envs at {args.res}x{args.res}, medians of "
          f"{args.repeats} [ms]; g: graph-replayed; diff: max |image - first variant's| of the scene")
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
