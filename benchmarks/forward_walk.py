"""How much the fused forward's walk evaluates: face-pixel pairs an image, by walk, on anchor.py's scene.

Not a test, and not a timing: a count, the same on any device (the CPU will do). The fused forward kernel
(``diffrender/raster/fused/forward.py``) runs one program per 4 x 4 pixel tile and walks the face blocks whose
boxes reach the tile. For each ``--faces`` scene (``_common.Scene``: the ant at random poses under its task's
camera) it counts, per image:

- ``block``: the pairs the default walk evaluates, every face of every block whose box reaches the tile;
- ``compact_N``: those of ``FWD_COMPACT`` in chunks of N (``FWD_SUB_BLOCK``): of each such block, only the
  faces whose own boxes reach the tile, rounded up to whole chunks;
- ``bound``: pairs whose face box reaches the pixel's tile (what any walk at tile granularity must evaluate).

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


def count(faces: int, batch: int, res: int, chunks: tuple[int, ...], raster_model: str = "softmax") -> dict:
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
    row = {"faces": robot.num_faces, "batch": batch, "res": res, "tile": tile, "face_block": block,
           "raster_model": raster_model,
           "block": _touches(block_box, ranges).sum().item() * block * per_tile / batch,
           "bound": face_hits.sum().item() * per_tile / batch,
           "tiles_reached": _touches(block_box, ranges).any(1).sum().item() / batch,
           "tiles": ranges[0].numel()}
    for n in chunks:
        row[f"compact_{n}"] = (torch.ceil(near / n) * n).sum().item() * per_tile / batch
    return row


def table(rows: list[dict], chunks: tuple[int, ...]) -> str:
    head = ["faces", "tiles reached", "block", *(f"compact {n}" for n in chunks), "bound"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [f"{r['faces']:,}", f"{r['tiles_reached']:.0f} of {r['tiles']}", f"{r['block']:,.0f}",
                 *(f"{r[f'compact_{n}']:,.0f} ({r['block'] / r[f'compact_{n}']:.1f}x)" for n in chunks),
                 f"{r['bound']:,.0f}"]
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
