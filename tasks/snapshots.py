"""``robot-snapshots``: PNGs of each robot at a few poses, seen from its task camera.

The poses are the seeded reset state and the states reached after some steps of smooth random actions, so
a person can check at a glance that the robots, the floor and the cameras look right. Each image is a row
of poses; ``--size`` sets the resolution (the policy sees 84 x 84).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch

import tasks
from tasks.vision import TaskRenderer

__all__ = ["snapshot", "main"]


@torch.no_grad()
def snapshot(name: str, *, poses: int = 4, size: int = 192, steps_between: int = 20, seed: int = 0,
             detail: int = 2) -> np.ndarray:
    """A (size, poses * size, 3) uint8 RGB strip of ``name`` at ``poses`` poses from its task camera."""
    task = tasks.make(name, 1, seed=seed)
    task.reset()
    renderer = TaskRenderer(task, height=size, width=size, detail=detail)
    gen = torch.Generator().manual_seed(seed)
    phase = 2 * math.pi * torch.rand(task.num_act, generator=gen)
    images, t = [], 0
    for _ in range(poses):
        images.append(renderer(task.qpos)[0])
        for _ in range(steps_between):  # smooth, bounded actions: the robots move without flailing
            action = 0.6 * torch.sin(phase + 0.15 * t).reshape(1, -1).to(task.dtype)
            task.step(action)
            t += 1
    strip = torch.cat(images, dim=2).clamp(0, 1).mul(255).round().byte()
    return strip.permute(1, 2, 0).numpy()


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("docs/robots"), help="folder for <task>.png")
    p.add_argument("--tasks", nargs="+", default=list(tasks.TASKS), choices=tasks.TASKS)
    p.add_argument("--poses", type=int, default=4, help="poses per robot (images side by side)")
    p.add_argument("--size", type=int, default=192, help="image height and width [px]")
    p.add_argument("--steps-between", type=int, default=20, help="control steps between poses")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.poses < 1 or args.size < 16 or args.steps_between < 0:
        p.error("--poses >= 1, --size >= 16 and --steps-between >= 0 are required")
    import cv2

    args.out.mkdir(parents=True, exist_ok=True)
    for name in args.tasks:
        img = snapshot(name, poses=args.poses, size=args.size, steps_between=args.steps_between, seed=args.seed)
        path = args.out / f"{name}.png"
        if not cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
            raise SystemExit(f"error: could not write {path}")
        print(path)


if __name__ == "__main__":
    main()
