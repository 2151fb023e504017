"""A trainer's arithmetic as one JSON file, to show that a refactor of gradlab changed none of it bit for bit.

Runs a few CPU iterations of every mode (state, blind, decoupled, full with the soft and the hard raster model) on
cartpole and hopper, and populations (mixed modes and seeds; members of differing critic schedules; state
members; a member that goes non-finite), with probes and evaluation on, and writes every metric (clock and memory
readings left out), every evaluation, the hashes of each run's final ``state_dict`` tensors (a checkpoint's
content) and what a run resumed from a checkpoint file computes next. A tool, not a test:

    python benchmarks/fingerprint.py OUT.json [--checkpoints DIR]

``--checkpoints DIR``: resume from the checkpoint files in DIR where they exist (written by an earlier run of this
script, e.g. by the code before a change: checkpoints it wrote must still load), else write them there first.
Compare two outputs with ``cmp``: the file is written with sorted keys, so equal arithmetic gives equal bytes.
Every answer is recorded as a list of members' values (a run alone: a list of one), and a checkpoint file
holding one run's dict (a run folder's format) loads as a list of one: the outputs of trainers that answer a run
alone with one dict or with a list of one compare, and so do their checkpoint files.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

from gradlab.checkpoint import load_checkpoint, save_checkpoint
from gradlab.config import SHACConfig
from gradlab.probes import NonFiniteError
from gradlab.shac import SHAC

#: Readings of the clock and the allocator, not of the arithmetic.
CLOCK = {"wall_s", "fwd_ms", "bwd_ms", "critic_ms", "iter_ms", "peak_alloc_mb", "peak_reserved_mb", "saved_mb"}
ITERS = 3


def _base(task: str, **kw) -> SHACConfig:
    base = dict(task=task, num_envs=3 if task == "cartpole" else 2, horizon=4, image_size=16, iters=ITERS,
                cosine_every=2, episode_length=6, eval_envs=2, critic_iterations=2, critic_batches=2, seed=3)
    base.update(kw)
    return SHACConfig(**base)


def _hash(x) -> str:
    if isinstance(x, torch.Tensor):
        t = x.detach().cpu().contiguous()
        data = t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b""
        return f"{t.dtype}{tuple(t.shape)}:{hashlib.sha256(data).hexdigest()[:16]}"
    if isinstance(x, np.ndarray):
        return f"{x.dtype}{x.shape}:{hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest()[:16]}"
    return repr(x)


def _plain(x):
    """Metrics and states as JSON: tensors and arrays by hash, floats exactly (repr), containers walked."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items() if k not in CLOCK}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, float):
        return "nan" if math.isnan(x) else repr(x)
    if isinstance(x, (torch.Tensor, np.ndarray)):
        return _hash(x)
    if isinstance(x, (int, bool, str)) or x is None:
        return x
    return _hash(x) if hasattr(x, "shape") else repr(x)


def _members(x) -> list:
    """A list of members' values (one run's config, dict or checkpoint: a list of one)."""
    return x if isinstance(x, list) else [x]


def _state(state: dict | list[dict]) -> list:
    """A state_dict (one per member) less its clock reading."""
    return [_plain({k: v for k, v in s.items() if k != "wall_s"}) for s in _members(state)]


def _run(name: str, cfg, ckpt_dir: Path | None, *, batching: str = "grouped", poison: int | None = None) -> dict:
    """Train ``ITERS`` iterations with an evaluation after the first and the last; record the state; resume a
    fresh trainer from a checkpoint file of it and record its next iteration. ``poison``: the member index whose
    actor goes non-finite after the first iteration."""
    out: dict = {"iterations": [], "evaluations": []}
    trainer = SHAC(_members(cfg), device="cpu", batching=batching)
    out["order"] = ([dataclasses.asdict(m.cfg)["mode"] + f"/{m.cfg.seed}/{m.cfg.raster_model}"
                     for m in trainer.members])
    for it in range(ITERS):
        try:
            out["iterations"].append(_plain(_members(trainer.train_iteration())))
        except NonFiniteError as e:
            out["iterations"].append({"raised": str(e)})
            return out
        if it == 0:
            out["evaluations"].append(_plain(_members(trainer.evaluate(video_steps=2, video_size=16))))
            if poison is not None:
                with torch.no_grad():
                    next(trainer.members[poison].actor.parameters()).fill_(float("nan"))
    out["evaluations"].append(_plain(_members(trainer.evaluate())))
    state = trainer.state_dict()
    out["state"] = _state(state)
    if ckpt_dir is not None:
        path = ckpt_dir / f"{name}.pt"
        if not path.exists():
            save_checkpoint(path, state)
        state = load_checkpoint(path)
    else:
        import copy

        state = copy.deepcopy(state)
    resumed = SHAC(_members(cfg), device="cpu", batching=batching)
    resumed.load_state_dict(_members(state))
    out["resumed"] = _plain(_members(resumed.train_iteration()))
    out["resumed_state"] = _state(resumed.state_dict())
    return out


def cases() -> dict:
    """name -> (config or configs, options)."""
    out = {}
    for task in ("cartpole", "hopper"):
        for mode, raster in (("state", None), ("blind", None), ("decoupled", None), ("full", None),
                             ("full", "hard")):
            out[f"{task}-{mode}-{raster or 'default'}"] = (_base(task, mode=mode, raster_model=raster), {})
        out[f"{task}-mixed"] = ([_base(task, mode=m, seed=s) for s in (0, 1) for m in ("decoupled", "full", "blind")],
                                {})
    out["cartpole-mixed-modules"] = ([_base("cartpole", mode=m, seed=s) for s in (0, 1)
                                      for m in ("decoupled", "full", "blind")], {"batching": "modules"})
    out["cartpole-critic-groups"] = ([_base("cartpole", mode="decoupled", seed=0),
                                      _base("cartpole", mode="decoupled", seed=1, critic_iterations=3),
                                      _base("cartpole", mode="full", seed=0, raster_model="hard"),
                                      _base("cartpole", mode="blind", seed=2, critic_lr=3e-4, grad_clip=0.5)], {})
    out["cartpole-state-population"] = ([_base("cartpole", mode="state", seed=s) for s in (0, 1, 2)], {})
    out["cartpole-population-of-one"] = ([_base("cartpole", mode="full", seed=4)], {})
    out["cartpole-member-fails"] = ([_base("cartpole", mode="decoupled", seed=s) for s in (0, 1)], {"poison": 1})
    out["cartpole-single-fails"] = (_base("cartpole", mode="state"), {"poison": 0})
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out")
    parser.add_argument("--checkpoints", type=Path, default=None)
    parser.add_argument("--only", nargs="*", default=None, help="case names (default: all)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # one reduction order
    if args.checkpoints is not None:
        args.checkpoints.mkdir(parents=True, exist_ok=True)
    result = {}
    for name, (cfg, options) in cases().items():
        if args.only and name not in args.only:
            continue
        print(name, file=sys.stderr, flush=True)
        result[name] = _run(name, cfg, args.checkpoints, **options)
    Path(args.out).write_text(json.dumps(result, indent=1, sort_keys=True) + "\n")


if __name__ == "__main__":
    main()
