"""How much the fused rasterizer's walks evaluate, by walk, on anchor.py's scene: the forward's face-pixel pairs
and the backward's lane-pixel steps an image.

Not a test, and not a timing: a count, the same on any device (the CPU will do). The fused forward kernel
(``diffrender/raster/fused/forward.py``) runs one program per 4 x 4 pixel tile and walks the face blocks whose
boxes reach the tile. For each ``--faces`` scene (``_common.Scene``: the ant at random poses under its task's
camera) it counts, per image:

- ``block``: the pairs the default walk evaluates, every face of every block whose box reaches the tile;
- ``compact_N``: those of ``FWD_COMPACT`` in chunks of N (``FWD_SUB_BLOCK``): of each such block, only the
  faces whose own boxes reach the tile, rounded up to whole chunks;
- ``bound``: pairs whose face box reaches the pixel's tile (what any walk at tile granularity must evaluate).

The backward (``backward.py``) runs one program per 8 x 8 tile, keeps one face a lane in sub-blocks of
``BWD_SUB_BLOCK`` and walks the tile's pixels inside the union of the sub-block's boxes that reach it. Per image:

- ``bwd_block_N``: lanes x pixels walked with sub-blocks of N of each block's faces (idle lanes included);
- ``bwd_compact_N``: the same with ``BWD_COMPACT``: only the faces whose boxes reach the tile, packed.

The GPU decides which walk is fastest (``anchor.py --variants FWD_COMPACT=1,FWD_SUB_BLOCK=16``); this says how
much work each one leaves, so a timing can be read against it.

    python benchmarks/forward_walk.py                       # the plain ant, 64 images at 84 px
    python benchmarks/forward_walk.py --faces 0 21000 --batch 16
"""

from __future__ import annotations

import argparse
import datetime
import platform
import sys
from pathlib import Path

import torch
from _common import Scene, commit, write_json

import diffrender as dr
from diffrender.raster.fused import reference, tuning
from diffrender.raster.kernel import Static


def _touches(box: torch.Tensor, lo_hi: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """(B, 4, N) boxes (x_min, x_max, y_min, y_max) [px] against the tiles' pixel-centre ranges -> (B, N, T)."""
    x_lo, x_hi, y_lo, y_hi = lo_hi
    return ((box[:, 1, :, None] >= x_lo) & (box[:, 0, :, None] <= x_hi)
            & (box[:, 3, :, None] >= y_lo) & (box[:, 2, :, None] <= y_hi))


def _tile_ranges(height: int, width: int, tile: int) -> tuple[torch.Tensor, ...]:
    """Each tile's pixel-centre range, as the kernels' ``_tile_pixels`` forms it: (T,) each, row-major."""
    ty, tx = torch.meshgrid(torch.arange(-(-height // tile)), torch.arange(-(-width // tile)), indexing="ij")
    tx, ty = tx.flatten(), ty.flatten()
    return (tx * tile + 0.5, torch.clamp(tx * tile + tile, max=width) - 0.5,
            ty * tile + 0.5, torch.clamp(ty * tile + tile, max=height) - 0.5)


def _lane_pixels(box: torch.Tensor, hits: torch.Tensor, groups: torch.Tensor, ranges: tuple[torch.Tensor, ...],
                 lanes: int) -> float:
    """Lanes x pixels the backward walks: for each (image, tile, group of faces), ``lanes`` times the tile's
    pixel centres inside the union of the boxes of the group's faces that reach the tile, where any does.
    ``box``: (B, 4, Fp); ``hits``: (B, Fp, T); ``groups``: (B, Fp, T) each face's group id (-1: none)."""
    x_lo, x_hi, y_lo, y_hi = ranges
    b, _, t = hits.shape
    n = int(groups.max()) + 1
    bi, fi, ti = torch.nonzero(hits & (groups >= 0), as_tuple=True)
    key = (bi * n + groups[bi, fi, ti]) * t + ti  # one slot per (image, group, tile)
    big = torch.finfo(box.dtype).max
    union = []
    for row, reduce, fill in ((0, "amin", big), (1, "amax", -big), (2, "amin", big), (3, "amax", -big)):
        out = torch.full((b * n * t,), fill, dtype=box.dtype)
        union.append(out.scatter_reduce(0, key, box[bi, row, fi], reduce=reduce))
    x0, x1, y0, y1 = (u.view(b, n, t) for u in union)
    # pixel centres px + 0.5 in [max(x0, x_lo), min(x1, x_hi)], as the kernel counts them
    nx = (torch.floor(torch.minimum(x1, x_hi) - 0.5) - torch.ceil(torch.maximum(x0, x_lo) - 0.5) + 1).clamp(min=0)
    ny = (torch.floor(torch.minimum(y1, y_hi) - 0.5) - torch.ceil(torch.maximum(y0, y_lo) - 0.5) + 1).clamp(min=0)
    return float((lanes * nx * ny).sum())


def backward_lanes(box: torch.Tensor, block: int, res: int, subs: tuple[int, ...]) -> dict:
    """Lane-pixel steps an image of the backward's walks (see the module's docstring), per sub-block size."""
    ranges = tuple(r.to(box.dtype) for r in _tile_ranges(res, res, 8))
    hits = _touches(box, ranges)  # (B, Fp, T)
    b, fp, t = hits.shape
    face = torch.arange(fp).view(1, fp, 1).expand(b, fp, t)
    # rank of each reaching face among its block's reaching faces, in face order
    rank = hits.view(b, fp // block, block, t).cumsum(2).view(b, fp, t) - 1
    out = {}
    for sub in subs:
        out[f"bwd_block_{sub}"] = _lane_pixels(box, hits, face // sub, ranges, sub) / b
        compact = (face // block) * (block // sub) + rank // sub
        out[f"bwd_compact_{sub}"] = _lane_pixels(box, hits, torch.where(hits, compact, -1), ranges, sub) / b
    return out


def count(faces: int, batch: int, res: int, chunks: tuple[int, ...], raster_model: str = "softmax",
          subs: tuple[int, ...] = (64, 32)) -> dict:
    """Pairs an image each walk evaluates on the ``faces`` scene (see the module's docstring)."""
    scene = Scene(faces, batch, res, torch.device("cpu"), torch.float64)
    robot, cam = scene.robot, scene.camera(scene.qpos)
    settings = dr.RasterSettings(raster_model=raster_model, backend="fused")
    tile, block = tuning.TILE, tuning.FACE_BLOCK
    st = Static.make(settings, focal=cam.focal, height=res, width=res, tile_h=tile, tile_w=tile)
    with torch.no_grad():
        _, box, block_box = reference.face_coefficients(scene.verts, None, robot.colors, cam.rotation, cam.eye,
                                                        robot.faces, st, face_block=block)
    ranges = _tile_ranges(res, res, tile)
    per_tile = tile * tile
    face_hits = _touches(box, ranges)  # (B, Fp, T)
    near = face_hits.view(batch, -1, block, face_hits.shape[-1]).sum(2)  # (B, NB, T) faces reaching each tile
    block_hits = _touches(block_box, ranges)  # (B, NB, T)
    row = {"faces": robot.num_faces, "batch": batch, "res": res, "tile": tile, "face_block": block,
           "raster_model": raster_model,
           "block": block_hits.sum().item() * block * per_tile / batch,
           "bound": face_hits.sum().item() * per_tile / batch,
           "tiles_reached": block_hits.any(1).sum().item() / batch,
           "tiles": ranges[0].numel()}
    for n in chunks:
        row[f"compact_{n}"] = (torch.ceil(near / n) * n).sum().item() * per_tile / batch
    row.update(backward_lanes(box, block, res, subs))
    return row


def table(rows: list[dict], chunks: tuple[int, ...]) -> str:
    bwd = [k for k in rows[0] if k.startswith("bwd_")]
    head = ["faces", "tiles reached", "block", *(f"compact {n}" for n in chunks), "bound",
            *(k.replace("bwd_", "backward ").replace("_", " ") for k in bwd)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [f"{r['faces']:,}", f"{r['tiles_reached']:.0f} of {r['tiles']}", f"{r['block']:,.0f}",
                 *(f"{r[f'compact_{n}']:,.0f} ({r['block'] / r[f'compact_{n}']:.1f}x)" for n in chunks),
                 f"{r['bound']:,.0f}", *(f"{r[k]:,.0f}" for k in bwd)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--faces", type=int, nargs="*", default=[0],
                   help="scene face counts (0: the plain ant, 1,856 faces; more adds extra spheres)")
    p.add_argument("--batch", type=int, default=64, help="images (random ant poses) averaged over")
    p.add_argument("--res", type=int, default=84, help="image side [px]")
    p.add_argument("--chunks", type=int, nargs="*", default=[32, 16, 8],
                   help="FWD_SUB_BLOCK values of the compacted walk to count")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/forward_walk.json"), help="JSON output")
    args = p.parse_args(argv)
    chunks = tuple(args.chunks)
    rows = [count(f, args.batch, args.res, chunks) for f in args.faces]
    write_json(args.out, {"benchmark": "forward_walk", "commit": commit(), "date": datetime.date.today().isoformat(),
                          "command": " ".join(["python", "benchmarks/forward_walk.py", *sys.argv[1:]]),
                          "host": platform.node(), "rows": rows})
    print(table(rows, chunks))
    return 0


if __name__ == "__main__":
    sys.exit(main())
