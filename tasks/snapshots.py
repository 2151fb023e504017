"""``robot-snapshots``: PNGs of each robot at a few poses, seen from its task camera.

The poses are the seeded reset state and the states reached after some steps of smooth random actions, so
a person can check at a glance that the robots, the floor and the cameras look right. Each image is a row
of poses; ``--size`` sets the resolution (the policy sees 84 x 84).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

import tasks
from tasks.command_line import cli
from tasks.command_line import fail as _fail
from tasks.vision import TaskRenderer

__all__ = ["SnapshotsConfig", "snapshot", "write_palette_png", "main"]


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


@dataclass
class SnapshotsConfig:
    """PNGs of each robot at a few poses (the seeded reset state, then after some steps of smooth random
    actions), seen from its task camera: <out>/<task>.png, one row of poses per image."""

    # Each field's docstring (its --help) is one source line: tyro breaks the help text where a line ends.
    out: Path = Path("robots")
    """Folder for <task>.png (the shipped ones, docs/robots, only where named: --out docs/robots)."""
    tasks: tuple[str, ...] = tasks.TASKS
    """Robots to draw, by task name."""
    poses: int = 4
    """Poses per robot (images side by side)."""
    size: int = 192
    """Image height and width [px] (>= 16; the policy sees 84 x 84)."""
    steps_between: int = 20
    """Control steps between poses."""
    seed: int = 0
    """Reset seed and seed of the actions' phases."""

    def validate(self) -> None:
        """ValueError naming the flag of the first bad value, before any work."""
        unknown = [t for t in self.tasks if t not in tasks.TASKS]
        if unknown or not self.tasks:
            raise ValueError(f"--tasks: unknown task(s) {unknown or '(none given)'}; known tasks: "
                             f"{', '.join(tasks.TASKS)}")
        for flag, value, least in (("--poses", self.poses, 1), ("--size", self.size, 16),
                                   ("--steps-between", self.steps_between, 0)):
            if value < least:
                raise ValueError(f"{flag} must be >= {least}, got {value}")
        if self.out.exists() and not self.out.is_dir():
            raise ValueError(f"--out {self.out} is a file; give the folder for the PNGs")


def main(argv: list[str] | None = None) -> None:
    """Console entry point ``robot-snapshots`` (``--help`` lists the flags); prints the path of every PNG. Bad
    flags exit with status 2 and one line naming the flag."""
    cfg = cli(SnapshotsConfig, argv, prog="robot-snapshots")
    try:
        cfg.validate()
        cfg.out.mkdir(parents=True, exist_ok=True)
    except (ValueError, OSError) as e:
        _fail(str(e) if isinstance(e, ValueError) else f"--out {cfg.out}: cannot be created ({e.strerror or e})")
    for name in cfg.tasks:
        img = snapshot(name, poses=cfg.poses, size=cfg.size, steps_between=cfg.steps_between, seed=cfg.seed)
        path = cfg.out / f"{name}.png"
        try:
            write_palette_png(path, img)
        except OSError as e:
            _fail(f"--out {cfg.out}: could not write {path} ({e.strerror or e})")
        print(path)


def write_palette_png(path: Path, img: np.ndarray) -> None:
    """``img`` (H, W, 3) uint8 RGB as a 256-colour palette PNG at ``path``, written atomically.

    A palette PNG is a third of the RGB one's size for these pictures (flat Lambert shading, a checker floor), and the
    shipped pictures count against the tracked tree's budget; an image of at most 256 colours is kept exactly."""
    from PIL import Image

    quantized = Image.fromarray(img, mode="RGB").quantize(256, method=Image.Quantize.MEDIANCUT,
                                                          dither=Image.Dither.NONE)
    tmp = path.with_name(f".{path.name}.tmp")
    quantized.save(tmp, format="PNG", optimize=True)
    os.replace(tmp, path)


if __name__ == "__main__":
    main()
