"""How a population's visual actors batch on one device: ``MemberStack``'s batchings (grouped convolutions, one
convolution per member, each member's own module), forward and backward of the mean action at the paper's sizes,
by member count.
Also checks that a CUDA graph replays per-member noise generators as eager code draws them.

    python benchmarks/member_stack.py --device cuda --members 1 2 4 8 12 16 --out member_stack.json
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from _common import commit, median_ms, write_json

from gradlab.networks import MemberStack, VisualActor


def _actors(n: int, device: torch.device) -> list[VisualActor]:
    out = []
    for seed in range(n):
        torch.manual_seed(seed)
        out.append(VisualActor(9, 84, 84, 8, trunk_dim=128, hidden=(128, 64, 32), init="default").to(device))
    return out


def _generator_replay_check(device: torch.device) -> dict:
    """Three member generators drawn inside a captured graph: do replays continue each stream as eager does?"""
    if device.type != "cuda":
        return {"skipped": "needs CUDA"}
    register = hasattr(torch.cuda.CUDAGraph, "register_generator_state")
    gens = [torch.Generator(device=device).manual_seed(s) for s in (0, 1, 2)]
    ref = [torch.Generator(device=device).manual_seed(s) for s in (0, 1, 2)]
    out = torch.empty(3, 64, 8, device=device)

    def draw():
        for i, g in enumerate(gens):
            out[i].copy_(torch.randn(64, 8, device=device, generator=g))

    draw()
    expected = [torch.stack([torch.randn(64, 8, device=device, generator=g) for g in ref]) for _ in range(4)]
    graph = torch.cuda.CUDAGraph()
    try:
        if register:
            for g in gens:
                graph.register_generator_state(g)
        with torch.cuda.graph(graph):
            draw()
    except Exception as e:  # the point is to record what this torch does
        return {"register_generator_state": register, "captured": False, "error": repr(e)[:300]}
    # capturing reserves one draw of each registered generator: replay k gives the (k + 2)-th draw after the
    # eager one, and every replay continues each member's own stream
    same = []
    for k in range(3):
        graph.replay()
        same.append(bool(torch.equal(out, expected[k + 1])))
    return {"register_generator_state": register, "captured": True, "replays_continue_each_stream": same}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda")
    p.add_argument("--members", type=int, nargs="+", default=[1, 2, 4, 8, 12, 16])
    p.add_argument("--envs", type=int, default=64, help="environments (images) per member")
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--out", type=Path, default=Path("member_stack.json"))
    args = p.parse_args()
    device = torch.device(args.device)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True  # as the trainer's captured runs
    rows = []
    for n in args.members:
        actors = _actors(n, device)
        x = torch.rand(n * args.envs, 9, 84, 84, device=device)
        row = {"members": n, "envs_per_member": args.envs}
        for variant in ("grouped", "loop", "modules"):
            stack = MemberStack(actors, batching=variant)

            def step(stack=stack, x=x):
                stack.mean(stack.stack(), x).sum().backward()

            try:
                row[f"{variant}_ms"] = round(median_ms(step, device, warmup=3, repeats=args.repeats), 3)
            except torch.OutOfMemoryError:
                row[f"{variant}_ms"] = "oom"
                torch.cuda.empty_cache()
        print(row, flush=True)
        rows.append(row)
    result = {"commit": commit(), "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
              "torch": torch.__version__, "rows": rows, "generator_replay": _generator_replay_check(device)}
    print(result["generator_replay"])
    write_json(args.out, result)


if __name__ == "__main__":
    main()
