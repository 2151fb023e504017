"""The encoder's precision (``SHACConfig.precision``): how far its gradients are from float32's, and what it saves.

**Agreement.** For each task and mode a float32 run trains ``--iters`` N iterations as the trainer does
(``--compile``: as ``ablate --compile``, CUDA graphs included). At five points (iterations 0, N/4, N/2, 3N/4, N) its
state is taken (``SHAC.state_dict``: parameters, optimisers, statistics, task state, frames and every random stream),
and one trainer per candidate precision, built from the same config in this process, loads it and runs one
iteration: the same parameters, states and noise. Its actor gradient is compared with the float32 run's own
iteration from that state: cosine, norm ratio (pre-clip norms), the encoder's cosine and the loss's relative
difference; then the median over the points. The gradients are read after clipping, which scales a run's gradient
uniformly (the cosine is the raw gradients'). A candidate ``fp32`` is a second float32 trainer: on a GPU two
float32 computations of one window already differ (atomic accumulations in backward), which is the floor any other
precision is read against; ``fp32-ieee`` is float32 with cuDNN's TF32 convolutions off too (the default lets cuDNN
use TF32: what today's fp32 already deviates from strict float32); ``fp32-warp-sim`` is float32 with the Warp
simulator (``--sim-backend warp``) loading the PyTorch simulator's run state: the simulator backends' learning
check. The TF32 switches are the process's: they are set for each trainer before each of its iterations (a
captured graph keeps the kernels it was captured with).

**Time.** ``iteration.py`` once per precision, each in a process of its own (its own switches, its own memory):
median forward, backward and iteration time of one run, CUDA-synchronised after warm-up, peak allocated and reserved
memory around each window. A population's time at each precision: ``population.py --precision fp32 bf16``.

On the CPU (a dry run of the whole path at tiny sizes) there is no TF32 and bfloat16 is an emulation: the numbers
say nothing of a GPU, and the output says so.

    python benchmarks/precision.py --compile --tasks hopper ant --modes decoupled full --iters 200 \\
        --out benchmarks/results/precision.json
    python benchmarks/precision.py --compile --tasks hopper ant --modes decoupled full --iters 200 \\
        --candidates fp32 fp32-warp-sim --parts agreement --out benchmarks/results/sim_agreement.json
    python benchmarks/precision.py --device cpu --tasks cartpole --modes decoupled full --iters 4 --num-envs 2 \\
        --horizon 2 --image-size 16 --time-warmup 1 --time-iters 1 --out /tmp/precision.json
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import gc
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from _common import ROOT, commit, write_json

from gradlab import SHAC, ModePlan, SHACConfig, precision, resolve_device
from gradlab.probes import cosine, flat_grad
from gradlab.seeding import rng_state, set_rng_state

#: What a candidate may be: a precision of SHACConfig, float32 with every TF32 switch off ("fp32-ieee"), or
#: float32 with the Warp simulator (``--sim-backend warp``) in place of the PyTorch one ("fp32-warp-sim").
VARIANTS = (*precision.PRECISIONS, "fp32-ieee", "fp32-warp-sim")


def _precision_of(variant: str) -> str:
    return variant.split("-")[0]


def candidate_config(cfg: SHACConfig, variant: str) -> SHACConfig:
    """The float32 run's config as ``variant`` trains it: its precision, and the Warp simulator for
    ``fp32-warp-sim``."""
    return dataclasses.replace(cfg, precision=_precision_of(variant),
                               sim_backend="warp" if variant == "fp32-warp-sim" else cfg.sim_backend)
CPU_NOTE = ("on the CPU: no TF32 (tf32 and fp32-ieee compute what fp32 does) and bf16 is the CPU's emulated "
            "autocast; a dry run of the benchmark, not a measurement")


def apply(variant: str, device: torch.device) -> None:
    """This process's switches (and the precision of encoders built from now on) for ``variant``."""
    precision.use(_precision_of(variant), device, allow_cpu=True)
    if variant == "fp32-ieee" and device.type == "cuda":
        torch.backends.cudnn.allow_tf32 = False


def points(n: int, count: int = 5) -> list[int]:
    """``count`` iterations evenly from 0 to ``n``, both included (fewer where ``n`` is small)."""
    return sorted({round(k * n / (count - 1)) for k in range(count)})


def _rel(a: float, b: float) -> float:
    return abs(a - b) / max(abs(b), 1e-30)


def agreement(task: str, mode: str, args) -> list[dict]:
    """One row per (point, candidate) for the float32 run of ``task`` and ``mode``."""
    device = torch.device(args.device)
    cfg = SHACConfig(task=task, mode=mode, num_envs=args.num_envs, horizon=args.horizon, image_size=args.image_size,
                     iters=args.iters + 1, cosine_every=0, eval_every=0, seed=args.seed, compile=args.compile)
    # Candidates first: building a trainer seeds the process, so the run built last starts as a fresh run does.
    trainers = {}
    for variant in args.candidates:
        apply(variant, device)
        trainers[variant] = SHAC([candidate_config(cfg, variant)], device=device)
    apply("fp32", device)
    run = SHAC([cfg], device=device)
    sees = ModePlan.of(mode).renders
    at = points(args.iters)
    rows = []
    for it in range(args.iters + 1):
        snapshot = copy.deepcopy(run.state_dict()) if it in at else None
        apply("fp32", device)
        (ref,) = run.train_iteration()
        if snapshot is None:
            continue
        actor = run.members[0].actor
        g_ref = flat_grad(actor.parameters())
        e_ref = flat_grad(actor.encoder.parameters()) if sees else None
        after = rng_state()  # the run goes on with its own noise, whatever the candidates drew
        for variant, trainer in trainers.items():
            row = {"task": task, "mode": mode, "iteration": it, "candidate": variant, "status": "ok"}
            try:
                apply(variant, device)
                # a copy each time: loading keeps some tensors of the dict (optimiser state) and steps them in place
                trainer.load_state_dict(copy.deepcopy(snapshot))
                (out,) = trainer.train_iteration()
                g = flat_grad(trainer.members[0].actor.parameters())
                row.update(cos=float(cosine(g, g_ref)), norm_ratio=out["grad_norm"] / ref["grad_norm"],
                           grad_norm=out["grad_norm"], grad_norm_fp32=ref["grad_norm"],
                           loss_rel_diff=_rel(out["actor_loss"], ref["actor_loss"]), graph=out["graph"])
                if sees:
                    row["cos_encoder"] = float(cosine(flat_grad(trainer.members[0].actor.encoder.parameters()), e_ref))
            except torch.OutOfMemoryError as e:
                row.update(status="oom", error=str(e).splitlines()[0])
            except Exception as e:  # a benchmark reports a failing point and goes on
                row.update(status="error", error=f"{type(e).__name__}: {e}"[:500])
            rows.append(row)
            print(json.dumps(row), flush=True)
        apply("fp32", device)
        set_rng_state(after)
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    """Per task, mode and candidate: the medians over the points (and the worst cosine)."""
    out = []
    keys = dict.fromkeys((r["task"], r["mode"], r["candidate"]) for r in rows if r["candidate"] != "-")
    for task, mode, cand in keys:
        ok = [r for r in rows if (r["task"], r["mode"], r["candidate"]) == (task, mode, cand) and r["status"] == "ok"]
        s = {"task": task, "mode": mode, "candidate": cand, "points": len(ok)}
        for k in ("cos", "cos_encoder", "norm_ratio", "loss_rel_diff"):
            vals = [r[k] for r in ok if r.get(k) is not None]
            s[f"median_{k}"] = statistics.median(vals) if vals else None
        s["min_cos"] = min((r["cos"] for r in ok), default=None)
        out.append(s)
    return out


def timing(variant: str, args) -> list[dict]:
    """iteration.py at ``variant`` in a process of its own: its rows (one per task and mode)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "iteration.json"
        cmd = [sys.executable, str(ROOT / "benchmarks" / "iteration.py"), "--device", args.device,
               "--tasks", *args.tasks, "--modes", *args.modes, "--num-envs", str(args.num_envs),
               "--horizon", str(args.horizon), "--image-size", str(args.image_size), "--warmup",
               str(args.time_warmup), "--iters", str(args.time_iters), "--probe-every", "0", "--precision", variant,
               "--seed", str(args.seed), "--out", str(out)]
        if args.compile:
            cmd.append("--compile")
        done = subprocess.run(cmd, capture_output=True, text=True)
        if not out.exists():
            return [{"precision": variant, "status": "crashed", "error": (done.stdout + done.stderr)[-800:]}]
        return json.loads(out.read_text())["results"]


def fmt(v, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def print_tables(doc: dict) -> None:
    print(f"\nprecision against float32 ({doc['device']}{', ' + doc['gpu'] if doc.get('gpu') else ''}; "
          f"{doc['args']['num_envs']} envs, horizon {doc['args']['horizon']}, {doc['args']['image_size']} px, "
          f"compile={doc['args']['compile']})")
    if doc.get("note"):
        print(f"NOTE {doc['note']}")
    print(f"{'task':9} {'mode':9} {'candidate':9} {'points':>6} {'median cos':>11} {'min cos':>9} {'enc cos':>9} "
          f"{'norm ratio':>10} {'loss diff':>9}")
    for s in doc["agreement_summary"]:
        print(f"{s['task']:9} {s['mode']:9} {s['candidate']:9} {s['points']:>6} {fmt(s['median_cos'], '.6f'):>11} "
              f"{fmt(s['min_cos'], '.6f'):>9} {fmt(s['median_cos_encoder'], '.6f'):>9} "
              f"{fmt(s['median_norm_ratio'], '.4f'):>10} {fmt(s['median_loss_rel_diff'], '.1e'):>9}")
    for r in doc["agreement"]:
        if r["status"] != "ok":
            print(f"{r['task']:9} {r['mode']:9} {r['candidate']:9} at {r.get('iteration', '-')}: {r['status']}: "
                  f"{r.get('error', '')[:70]}")
    if doc["time"]:
        print(f"\n{'task':9} {'mode':9} {'precision':9} {'fwd ms':>8} {'bwd ms':>8} {'iter ms':>8} {'x fp32':>7} "
              f"{'alloc MB':>9} {'resv MB':>9}")
        ok = [r for r in doc["time"] if r.get("status") == "ok"]
        for r in doc["time"]:
            if r.get("status") != "ok":
                print(f"{r.get('task', '-'):9} {r.get('mode', '-'):9} {r['precision']:9} {r.get('status')}: "
                      f"{r.get('error', '')[:70]}")
                continue
            base = next((x for x in ok if (x["task"], x["mode"], x["precision"]) == (r["task"], r["mode"], "fp32")),
                        None)
            ratio = f"{r['iter_ms'] / base['iter_ms']:.3f}" if base else "-"
            print(f"{r['task']:9} {r['mode']:9} {r['precision']:9} {fmt(r['fwd_ms'], '.1f'):>8} "
                  f"{fmt(r['bwd_ms'], '.1f'):>8} {fmt(r['iter_ms'], '.1f'):>8} {ratio:>7} "
                  f"{fmt(r['peak_alloc_mb'], '.0f'):>9} {fmt(r['peak_reserved_mb'], '.0f'):>9}")


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="auto", help="auto | cpu | cuda (cpu: a dry run at tiny sizes)")
    p.add_argument("--tasks", nargs="+", default=["hopper", "ant"])
    p.add_argument("--modes", nargs="+", choices=["decoupled", "full"], default=["decoupled", "full"])
    p.add_argument("--candidates", nargs="+", choices=VARIANTS, default=["fp32", "tf32", "bf16"],
                   help="precisions compared with the float32 run (fp32: a second float32 trainer, the floor; "
                        "fp32-ieee: float32 with cuDNN's TF32 off too; fp32-warp-sim: float32 on the Warp "
                        "simulator)")
    p.add_argument("--iters", type=int, default=200, help="N: the float32 run's iterations; points at 0, N/4 .. N")
    p.add_argument("--compile", action="store_true", help="the trainer's --compile path (CUDA graphs on a GPU)")
    p.add_argument("--parts", nargs="+", choices=["agreement", "time"], default=["agreement", "time"])
    p.add_argument("--time-warmup", type=int, default=3, help="time: untimed iterations (compile, capture)")
    p.add_argument("--time-iters", type=int, default=6, help="time: timed iterations (median)")
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--horizon", type=int, default=32)
    p.add_argument("--image-size", type=int, default=84)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "precision.json")
    args = p.parse_args(argv)
    try:
        args.device = str(resolve_device(args.device))
    except ValueError as e:
        p.error(str(e))
    if args.iters < 0:
        p.error("--iters must be >= 0")
    device = torch.device(args.device)
    doc = {"commit": commit(), "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "command": " ".join(sys.argv),
           "device": args.device, "torch": torch.__version__, "args": {k: str(v) if isinstance(v, Path) else v
                                                                       for k, v in vars(args).items()},
           "points": points(args.iters), "agreement": [], "agreement_summary": [], "time": [], "complete": False}
    if device.type == "cuda":
        doc["gpu"] = torch.cuda.get_device_name(device)
    else:
        doc["note"] = CPU_NOTE
        print(f"NOTE {CPU_NOTE}", flush=True)
    if "agreement" in args.parts:
        for task in args.tasks:
            for mode in args.modes:
                try:
                    doc["agreement"] += agreement(task, mode, args)
                except Exception as e:  # the float32 run itself failed (out of memory, non-finite): say so, go on
                    doc["agreement"].append({"task": task, "mode": mode, "candidate": "-", "status": "error",
                                             "error": f"{type(e).__name__}: {e}"[:500]})
                    print(json.dumps(doc["agreement"][-1]), flush=True)
                gc.collect()  # this run's trainers, before the next one's
                if device.type == "cuda":
                    torch.cuda.empty_cache()
                doc["agreement_summary"] = summarise(doc["agreement"])
                write_json(args.out, doc)  # after every run: a call cut short keeps what it finished
    if "time" in args.parts:
        for variant in dict.fromkeys(["fp32", *(c for c in args.candidates if c in precision.PRECISIONS)]):
            rows = timing(variant, args)
            doc["time"] += rows
            for r in rows:
                print(json.dumps(r), flush=True)
            write_json(args.out, doc)
    doc["complete"] = True
    write_json(args.out, doc)
    print_tables(doc)
    return doc


if __name__ == "__main__":
    main()
