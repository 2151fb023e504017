"""Populations against separate processes: N members (mixed modes) trained in one process as one batched
simulation, and, as the anchor, N single runs as N processes sharing the GPU at once.

Every population runs ``--compile`` (compiled simulator, renderer and networks; the window and the critic fit
replayed from CUDA graphs). Compiling one population's shapes takes minutes, so the populations of a wave of
jobs compile at the same time in processes of their own (as many as the GPU's memory takes), then wait for each
other and are timed one at a time on an otherwise idle GPU. The anchor's N processes are timed at once.

Members cycle through decoupled, full (the soft silhouette model), full with the hard raster model and blind,
seeds 0, 1, ...; a population of one is a decoupled single run. ``--precision fp32 bf16`` times every job at each
precision (SHACConfig.precision; each job is a process of its own, so each has its own process-wide switches).

    python benchmarks/population.py --tasks ant hopper --members 1 2 4 8 12 16 --anchor 4 12 --out population.json
    python benchmarks/population.py --tasks ant --members 1 12 --anchor --precision fp32 bf16 --out pop_bf16.json
    python benchmarks/population.py --device cpu --tasks cartpole --members 1 2 --anchor 2 --num-envs 2 \\
        --horizon 2 --image-size 16 --warmup 1 --iters 1 --out /tmp/population.json
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import commit, write_json

from vocabulary import ARMS, POPULATION_BENCHMARK_ARMS

#: The members' arms, cycled in this order (a row's ``arm`` indexes it).
MEMBER_ARMS = tuple(ARMS[name] for name in POPULATION_BENCHMARK_ARMS)


def member_configs(job: dict, args) -> list:
    """The job's members: arms cycling through :data:`MEMBER_ARMS` (a separate run: its own arm), seeds 0, 1,
    ..."""
    from gradlab.config import SHACConfig

    out = []
    for i in range(job["members"]):
        arm = MEMBER_ARMS[job.get("arm", i) % len(MEMBER_ARMS)]
        out.append(SHACConfig(task=job["task"], mode=arm.mode, raster_model=arm.raster_flag, preset=arm.preset,
                              seed=i // len(MEMBER_ARMS),
                              num_envs=args.num_envs, horizon=args.horizon, image_size=args.image_size,
                              iters=10_000, cosine_every=0, compile=args.device != "cpu" or args.compile,
                              eval_every=0, precision=job.get("precision", "fp32")))
    return out


def _wait_for(path: Path, count: int) -> None:
    """Block until ``count`` files exist in the folder ``path`` (a barrier between processes)."""
    while len(list(path.iterdir())) < count:
        time.sleep(0.2)


def child(args) -> None:
    """One job: build the trainer, warm up (compile, capture), meet the others, time, print one JSON row."""
    import torch

    from gradlab import SHAC, precision

    job = json.loads(args.child)
    cfgs = member_configs(job, args)
    row = {**job, "status": "ok"}
    try:
        t0 = time.perf_counter()
        # process-wide, before the trainer is built (on the CPU a dry run: no TF32 there, bf16 emulated)
        precision.use(cfgs[0].precision, args.device, allow_cpu=True)
        trainer = SHAC(cfgs, device=args.device, batching=job["batching"])
        for _ in range(args.warmup):
            trainer.train_iteration()
        row["warmup_s"] = round(time.perf_counter() - t0, 1)
    except torch.OutOfMemoryError as e:
        row.update(status="oom", error=str(e).splitlines()[0])
    except Exception as e:  # a benchmark reports a failing point and goes on
        row.update(status="error", error=f"{type(e).__name__}: {e}"[:500])
    ready = Path(job["barrier"])
    (ready / f"{os.getpid()}").touch()
    _wait_for(ready, job["wave"])
    if row["status"] == "ok":
        lock = open(job["lock"], "w") if job["lock"] else None  # held for the timed iterations
        try:
            if lock is not None:
                fcntl.flock(lock, fcntl.LOCK_EX)
            if args.device != "cpu":
                torch.cuda.synchronize()
                torch.cuda.reset_peak_memory_stats()
            rows = []
            for _ in range(args.iters):
                rows.append(next(r for r in trainer.train_iteration() if r is not None))
            row["iter_ms"] = round(statistics.median(r["iter_ms"] for r in rows), 2)
            row["fwd_ms"] = round(statistics.median(r["fwd_ms"] for r in rows), 2)
            row["bwd_ms"] = round(statistics.median(r["bwd_ms"] for r in rows), 2)
            critic = [r["critic_ms"] for r in rows if r.get("critic_ms") is not None]
            # the critic fit, beside the backward where it overlaps: what batching the members' critics buys
            row["critic_ms"] = round(statistics.median(critic), 2) if critic else None
            row["peak_reserved_mb"] = max(r["peak_reserved_mb"] or 0 for r in rows)
            if args.device != "cpu":
                row["max_reserved_mb"] = round(torch.cuda.max_memory_reserved() / 2**20)
                row["max_allocated_mb"] = round(torch.cuda.max_memory_allocated() / 2**20)
            steps = job["members"] * args.num_envs * args.horizon
            row["env_steps_per_s"] = round(steps / (row["iter_ms"] / 1e3))
            row["graph"] = all(r["graph"] for r in rows)
        finally:
            if lock is not None:
                lock.close()
    print("ROW " + json.dumps(row), flush=True)


def run_wave(jobs: list[dict], args, *, timed_alone: bool) -> list[dict]:
    """Start every job of the wave at once; they warm up together, then are timed one at a time (timed_alone) or
    all at once (the anchor)."""
    with tempfile.TemporaryDirectory() as tmp:
        barrier = Path(tmp) / "ready"
        barrier.mkdir()
        lock = str(Path(tmp) / "gpu.lock") if timed_alone else ""
        procs = []
        for job in jobs:
            spec = {**job, "barrier": str(barrier), "wave": len(jobs), "lock": lock}
            cmd = [sys.executable, __file__, "--child", json.dumps(spec), *args.passthrough]
            # the wave's processes compile at once: they share the machine's cores
            threads = max(1, min(args.compile_threads, (os.cpu_count() or 1) // len(jobs)))
            env = {**os.environ, "TORCHINDUCTOR_COMPILE_THREADS": str(threads)}
            procs.append(subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env))
        rows = []
        for job, p in zip(jobs, procs):
            out, _ = p.communicate()
            found = [json.loads(line[4:]) for line in out.splitlines() if line.startswith("ROW ")]
            rows.append(found[0] if found else {**job, "status": "crashed", "error": out[-800:]})
            print(json.dumps(rows[-1]), flush=True)
    return rows


def waves(jobs: list[dict], budget_gb: float, per_member_gb: float) -> list[list[dict]]:
    """Jobs packed, largest first, into waves whose estimated memory fits the budget."""
    need = {id(j): 1.5 + per_member_gb * j["members"] for j in jobs}
    out: list[list[dict]] = []
    for job in sorted(jobs, key=lambda j: -j["members"]):
        for wave in out:
            if sum(need[id(j)] for j in wave) + need[id(job)] <= budget_gb:
                wave.append(job)
                break
        else:
            out.append([job])
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda", help="cuda or cpu (cpu: a check that the script runs)")
    p.add_argument("--tasks", nargs="+", default=["ant", "hopper"])
    p.add_argument("--members", type=int, nargs="+", default=[1, 2, 4, 8, 12, 16])
    p.add_argument("--batchings", nargs="+", default=["grouped"], help="MemberStack batchings to time")
    p.add_argument("--anchor", type=int, nargs="*", default=[4, 12],
                   help="N for the anchor: N single runs (the population's members' arms) as N processes at once")
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--horizon", type=int, default=32)
    p.add_argument("--image-size", type=int, default=84)
    p.add_argument("--warmup", type=int, default=4, help="untimed iterations (compile, CUDA-graph capture)")
    p.add_argument("--iters", type=int, default=6, help="timed iterations (median)")
    p.add_argument("--compile", action="store_true", help="on the CPU too (always on a GPU)")
    p.add_argument("--memory-gb", type=float, default=70.0, help="GPU memory a wave of jobs may use")
    p.add_argument("--member-gb", type=float, default=3.5, help="estimated GPU memory per member")
    p.add_argument("--compile-threads", type=int, default=4, help="inductor compile threads per process")
    p.add_argument("--precision", nargs="+", choices=["fp32", "tf32", "bf16"], default=["fp32"],
                   help="SHACConfig.precision: every job (anchor processes included) at each")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    p.add_argument("--out", type=Path, default=Path("population.json"))
    args = p.parse_args()
    args.passthrough = [a for a in sys.argv[1:] if not a.startswith("--child")]
    if args.child is not None:
        child(args)
        return
    jobs = [{"kind": "population", "task": t, "members": n, "batching": b, "precision": pr}
            for pr in args.precision for t in args.tasks for n in args.members for b in args.batchings
            if n > 1 or b == args.batchings[0]]
    doc = {"commit": commit(), "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "command": " ".join(sys.argv),
           "device": args.device, "rows": [], "complete": False}
    if args.device != "cpu":
        import torch

        doc["gpu"] = torch.cuda.get_device_name()
        doc["torch"] = torch.__version__
    # the file is rewritten after every wave: a call cut short by its time limit keeps the waves it finished
    plan = [(wave, True) for wave in waves(jobs, args.memory_gb, args.member_gb)]
    for pr in args.precision:
        for task in args.tasks:
            for n in args.anchor:
                # the anchor: the members of an N-population as N single runs, all at once
                plan.append(([{"kind": "separate", "task": task, "members": 1, "batching": "grouped",
                               "arm": i % len(MEMBER_ARMS), "processes": n, "precision": pr} for i in range(n)],
                             False))
    for wave, timed_alone in plan:
        doc["rows"] += run_wave(wave, args, timed_alone=timed_alone)
        write_json(args.out, doc)
    doc["complete"] = True
    write_json(args.out, doc)
    print_table(doc["rows"], args)


def print_table(rows: list[dict], args) -> None:
    """Per task and N: the population's iteration and throughput, against its single run (N = 1) and against N
    separate processes at once (their median iteration, their summed throughput)."""
    print(f"\npopulations ({args.num_envs} envs per member, horizon {args.horizon}, {args.image_size} px; "
          f"members cycle {', '.join(a.name for a in MEMBER_ARMS)})")
    print(f"{'task':8} {'prec':5} {'N':>3} {'batching':9} {'iter ms':>9} {'x single':>9} {'steps/s':>9} "
          f"{'reserved MB':>12} {'sep. iter ms':>13} {'sep. steps/s':>13} {'gain':>6}")
    ok = [r for r in rows if r["status"] == "ok"]
    for r in rows:
        if r["kind"] != "population":
            continue
        pr = r.get("precision", "fp32")
        if r["status"] != "ok":
            print(f"{r['task']:8} {pr:5} {r['members']:>3} {r['batching']:9} {r['status']}: {r.get('error', '')[:70]}")
            continue
        same = [x for x in ok if x["task"] == r["task"] and x.get("precision", "fp32") == pr]
        single = next((x for x in same if x["kind"] == "population" and x["members"] == 1), None)
        apart = [x for x in same if x["kind"] == "separate" and x["processes"] == r["members"]]
        ratio = f"{r['iter_ms'] / single['iter_ms']:.2f}" if single else "-"
        sep_ms = f"{statistics.median(x['iter_ms'] for x in apart):.1f}" if apart else "-"
        sep_rate = sum(x["env_steps_per_s"] for x in apart)
        gain = f"{r['env_steps_per_s'] / sep_rate:.2f}" if apart else "-"
        print(f"{r['task']:8} {pr:5} {r['members']:>3} {r['batching']:9} {r['iter_ms']:>9.1f} {ratio:>9} "
              f"{r['env_steps_per_s']:>9} {r.get('max_reserved_mb', r['peak_reserved_mb']):>12} {sep_ms:>13} "
              f"{sep_rate if apart else '-':>13} {gain:>6}")


if __name__ == "__main__":
    main()
