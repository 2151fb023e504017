"""The deterministic evaluation's cost: one evaluation of a run or population, its steps replayed from a CUDA
graph (what ``--compile`` on a GPU does) against the same compiled kernels launched eagerly, in one process.

Members cycle through decoupled, full, full with the hard raster model and blind (as ``population.py``); the
policies are untrained, so episodes end early: the figure that carries over to trained policies (whole
1000-step episodes) is the time per evaluation step. Every variant's episodes are compared with the captured
ones (``max_rel_diff`` of the members' returns; the same kernels, so float rounding at most).

    python benchmarks/evaluation.py --tasks hopper --members 1 12 --out evaluation.json
    python benchmarks/evaluation.py --device cpu --tasks cartpole --members 2 --num-envs 2 --eval-envs 2 \\
        --image-size 16 --repeats 1 --out /tmp/evaluation.json
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

from _common import commit, write_json

from vocabulary import ARMS, POPULATION_BENCHMARK_ARMS

#: The members' arms, cycled in this order (a row's ``arm`` indexes it).
MEMBER_ARMS = tuple(ARMS[name] for name in POPULATION_BENCHMARK_ARMS)


def timed_evaluation(trainer, device) -> tuple[float, list[dict]]:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)
    start = time.perf_counter()
    out = trainer.evaluate()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - start, out


def measure(task: str, members: int, args) -> list[dict]:
    import torch

    from gradlab import SHAC, SHACConfig

    base = SHACConfig(task=task, num_envs=args.num_envs, eval_envs=args.eval_envs, image_size=args.image_size,
                      compile=args.device == "cuda", eval_every=0, cosine_every=0)
    arms = [MEMBER_ARMS[i % len(MEMBER_ARMS)] for i in range(members)]
    cfgs = [dataclasses.replace(base, mode=a.mode, raster_model=a.raster_flag, preset=a.preset, seed=i)
            for i, a in enumerate(arms)]
    trainer = SHAC(cfgs, device=args.device)
    device = trainer.device
    first_s, reference = timed_evaluation(trainer, device)  # compiles the evaluation's shapes, then captures
    rows = [{"task": task, "members": members, "variant": "first evaluation (compiling, capturing)",
             "seconds": round(first_s, 3), "steps": reference[0]["eval_steps"]}]
    for variant, graphs in (("captured", trainer.graphs), ("eager (same compiled kernels)", False)):
        trainer.graphs = graphs
        times, diffs = [], []
        for _ in range(args.repeats):
            seconds, out = timed_evaluation(trainer, device)
            times.append(seconds)
            diffs += [abs(o["eval_return_mean"] - r["eval_return_mean"]) / max(abs(r["eval_return_mean"]), 1e-6)
                      for o, r in zip(out, reference)]
        steps = out[0]["eval_steps"]
        median = statistics.median(times)
        rows.append({"task": task, "members": members, "variant": variant, "seconds": round(median, 4),
                     "steps": steps, "ms_per_step": round(1e3 * median / steps, 3),
                     "s_per_1000_steps": round(median / steps * 1000, 2), "max_rel_diff": max(diffs)})
    del trainer
    if device.type == "cuda":
        torch.cuda.empty_cache()
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda", help="cuda or cpu (cpu: a check that the script runs; no capture)")
    p.add_argument("--tasks", nargs="+", default=["hopper"])
    p.add_argument("--members", type=int, nargs="+", default=[1, 12])
    p.add_argument("--num-envs", type=int, default=64, help="training environments per member (sizes the trainer)")
    p.add_argument("--eval-envs", type=int, default=16, help="evaluation environments per member")
    p.add_argument("--image-size", type=int, default=84)
    p.add_argument("--repeats", type=int, default=3, help="timed evaluations per variant (median)")
    p.add_argument("--out", type=Path, default=Path("evaluation.json"))
    args = p.parse_args()
    doc = {"commit": commit(), "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "command": " ".join(sys.argv),
           "device": args.device, "rows": [], "complete": False}
    if args.device != "cpu":
        import torch

        doc["gpu"], doc["torch"] = torch.cuda.get_device_name(), torch.__version__
    for task in args.tasks:
        for n in args.members:
            for row in measure(task, n, args):
                print(row, flush=True)
                doc["rows"].append(row)
            write_json(args.out, doc)  # after every case: a call cut short keeps what it measured
    doc["complete"] = True
    write_json(args.out, doc)
    print(f"\n{'task':8} {'N':>3} {'variant':38} {'s':>8} {'steps':>6} {'ms/step':>8} {'s/1000 steps':>13}")
    for r in doc["rows"]:
        print(f"{r['task']:8} {r['members']:>3} {r['variant']:38} {r['seconds']:>8} {r['steps']:>6} "
              f"{r.get('ms_per_step', '-'):>8} {r.get('s_per_1000_steps', '-'):>13}")


if __name__ == "__main__":
    main()
