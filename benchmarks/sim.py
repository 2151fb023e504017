"""Simulator benchmark: a SHAC-style horizon forward + backward per task, batch size and execution mode.

One measured iteration = restore the start state, roll ``--horizon`` control steps (each ``substeps`` physics
substeps) with actions ``tanh(theta)``, loss = sum of rewards, backward to ``theta``. Modes:

* ``eager``: plain PyTorch.
* ``compiled``: ``Task.compile()`` (the physics substep and the per-step reward/reset through torch.compile;
  autograd links the compiled pieces across substeps).
* ``graph``: compiled, and the WHOLE forward + backward captured in one CUDA graph (static shapes, the state
  restored by in-place copies into the captured input tensors), then replayed (CUDA only).

``--backends torch warp`` times both simulator backends (``tasks.TaskConfig.sim_backend``) in one process, each
row naming its ``backend``. Before the first timed row of a (task, batch) the Warp backend is checked against the
float64 PyTorch simulator on the same device (``check_*`` fields of the warp rows: the largest state error after
``--check-horizon`` steps beside the torch float32 simulator's own spread, and the cosine and relative error of the
gradient into the actions); a warp row whose check fails has status "error: check ...".

Timing is CUDA-synchronised, warm-up (compilation, capture) is excluded and reported separately, the result
is the median over ``--iters`` iterations. Peak allocated and reserved memory are read after
``reset_peak_memory_stats`` around the measured iterations (CUDA only). With ``--kernels`` one compiled
iteration is profiled and the number of GPU kernels per substep (forward + backward) is reported; with
``--configs`` the launch config that autotuning kept for each Triton kernel is recorded (the same code can keep
different configs in different processes, and on the H100 that alone moved the 64-ant horizon by 25 %).

Not a test. Examples::

    python benchmarks/sim.py --device cuda --quick --out sim_quick.json
    python benchmarks/sim.py --device cuda --tasks ant humanoid --num-envs 64 1024 4096 --out sim.json
    python benchmarks/sim.py --device cpu --tasks cartpole ant --num-envs 4 --horizon 2 --modes eager compiled
    python benchmarks/sim.py --device cuda --quick --backends torch warp --out benchmarks/results/sim_backends.json
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import gc
import hashlib
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import torch
from _common import sync, time_ms, write_json

import tasks
from tasks.device import resolve_device

MODES = ("eager", "compiled", "graph")
BACKENDS = ("torch", "warp")
QUICK = [("ant", 64), ("humanoid", 64), ("ant", 4096)]


class Rollout:
    """The measured computation for one (task, batch, mode): state restore, horizon, loss, backward."""

    def __init__(self, name: str, num_envs: int, horizon: int, device: torch.device, mode: str, seed: int,
                 inductor: dict | None = None, backend: str = "torch"):
        self.task = tasks.make(name, num_envs, device=device, seed=seed, sim_backend=backend)
        if mode in ("compiled", "graph"):
            self.task.compile(**({"options": inductor} if inductor else {}))
        self.task.reset()
        self.start = {k: v.clone() for k, v in self.task.get_state().items()}
        gen = torch.Generator(device="cpu").manual_seed(seed)
        theta = 0.5 * torch.randn(horizon, num_envs, self.task.num_act, generator=gen)
        self.theta = theta.to(device).requires_grad_(True)

    def __call__(self) -> tuple[torch.Tensor, torch.Tensor]:
        t = self.task
        # restore the start state into the SAME tensors every time (a captured graph reads them)
        t.qpos, t.qvel = self.start["qpos"], self.start["qvel"]
        t.progress, t.prev_actions = self.start["progress"], self.start["prev_actions"]
        loss = self.theta.new_zeros(())
        for a in torch.tanh(self.theta):
            loss = loss + t.step(a)[1].sum()
        (grad,) = torch.autograd.grad(loss, self.theta)
        return loss.detach(), grad


def _final_state_and_grad(name: str, num_envs: int, device: torch.device, dtype: torch.dtype, backend: str,
                          horizon: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """State (qpos, qvel) after ``horizon`` steps from a seeded reset, and the gradient of the summed reward into the
    actions, both float64; no early termination, so that no environment resets inside the horizon."""
    task = tasks.make(name, num_envs, device=device, dtype=dtype, seed=seed, sim_backend=backend,
                      early_termination=False)
    task.reset()
    gen = torch.Generator(device="cpu").manual_seed(seed)
    theta = (0.5 * torch.randn(horizon, num_envs, task.num_act, generator=gen, dtype=torch.float64))
    theta = theta.to(device=device, dtype=dtype).requires_grad_(True)
    loss = theta.new_zeros(())
    for a in torch.tanh(theta):
        _, r, _, info = task.step(a)
        loss = loss + r.sum()
    (grad,) = torch.autograd.grad(loss, theta)
    state = torch.cat((info["qpos_before_reset"], info["qvel_before_reset"]), dim=1)
    return state.detach().double(), grad.double()


def check_warp(name: str, num_envs: int, device: torch.device, horizon: int, seed: int) -> dict:
    """The Warp backend (float32) against the float64 PyTorch simulator, and the torch float32 simulator's own
    spread beside it: ``check_state_err``, ``check_torch32_spread`` (largest absolute state difference from float64),
    ``check_grad_cos``, ``check_grad_rel`` (Warp's action gradient against float64's), ``check_torch32_grad_cos``,
    ``check_torch32_grad_rel`` and ``check_ok`` (state error <= 4 x spread + 1e-5, cosine >= 0.999)."""
    ref_s, ref_g = _final_state_and_grad(name, num_envs, device, torch.float64, "torch", horizon, seed)
    t32_s, t32_g = _final_state_and_grad(name, num_envs, device, torch.float32, "torch", horizon, seed)
    w32_s, w32_g = _final_state_and_grad(name, num_envs, device, torch.float32, "warp", horizon, seed)

    def cos_rel(g):
        cos = torch.nn.functional.cosine_similarity(g.flatten(), ref_g.flatten(), dim=0).item()
        return cos, ((g - ref_g).norm() / ref_g.norm()).item()

    out = {"check_horizon": horizon, "check_state_err": (w32_s - ref_s).abs().max().item(),
           "check_torch32_spread": (t32_s - ref_s).abs().max().item()}
    out["check_grad_cos"], out["check_grad_rel"] = cos_rel(w32_g)
    out["check_torch32_grad_cos"], out["check_torch32_grad_rel"] = cos_rel(t32_g)
    out["check_ok"] = bool(out["check_state_err"] <= 4 * out["check_torch32_spread"] + 1e-5
                           and out["check_grad_cos"] >= 0.999)
    return out


def measure(name: str, num_envs: int, mode: str, args, cache: dict, backend: str = "torch") -> dict:
    """One row. ``cache`` carries the compiled rollout from the "compiled" row to the "graph" row of the same
    (task, batch, backend), so the graph mode captures the already compiled code instead of compiling again, and
    the Warp backend's correctness check (:func:`check_warp`) from its first row to the others."""
    device = torch.device(args.device)
    row: dict = {"backend": backend, "task": name, "num_envs": num_envs, "mode": mode, "horizon": args.horizon,
                 "status": "ok"}
    if args.inductor:
        row["inductor"] = args.inductor
    if mode == "graph" and device.type != "cuda":
        row["status"] = "skipped (CUDA graphs need a CUDA device)"
        return row
    held = contextlib.ExitStack()  # the GPU lock, once taken
    try:
        if backend == "warp" and args.check_horizon > 0:
            check = cache.get(("check", name, num_envs))
            if check is None:
                check = cache[("check", name, num_envs)] = check_warp(
                    name, min(num_envs, args.check_envs), device, args.check_horizon, args.seed)
            row.update(check)
            if not check["check_ok"]:
                row["status"] = "error: check (the Warp backend disagrees with the float64 torch simulator)"
                return row
        t0 = time.perf_counter()
        key = (name, num_envs, backend)
        try:
            roll = cache.pop(key, None) if mode == "graph" else None
            if roll is None:
                roll = Rollout(name, num_envs, args.horizon, device, mode, args.seed, args.inductor, backend)
            if args.gpu_lock is not None:
                # compile (the first call) concurrently with the other processes, wait for all of them, then
                # take turns: no measurement overlaps another process's GPU work
                roll()
                sync(device)
        finally:
            if args.gpu_lock is not None:  # a failing setting still arrives, or the others would wait forever
                _barrier(args.gpu_lock, args.parties)
        if mode == "compiled":
            cache[key] = roll
        row["substeps"] = roll.task.substeps
        fn = roll
        held.enter_context(_gpu_lock(args.gpu_lock))
        if mode == "graph":
            side = torch.cuda.Stream(device)
            side.wait_stream(torch.cuda.current_stream(device))
            with torch.cuda.stream(side):  # warm up (compiles) off the capture stream, as CUDA graphs require
                for _ in range(max(1, args.warmup)):
                    roll()
            torch.cuda.current_stream(device).wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                static_out = roll()

            def fn():
                graph.replay()
                return static_out
        else:
            for _ in range(max(1, args.warmup)):
                fn()
        sync(device)
        # replay for a while before timing: the GPU idled through the compilation
        settle = time.perf_counter()
        while time.perf_counter() - settle < args.settle_s:
            fn()
            sync(device)
        row["warmup_s"] = round(time.perf_counter() - t0, 2)
        if mode != "eager":  # what compiling cost, graph by graph (cumulative over the process's rows)
            from ablations.startup import compiled_graphs

            row["compiled_graphs"] = compiled_graphs()
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        times, (loss, grad) = time_ms(fn, device, repeats=args.iters)
        row["ms"] = round(statistics.median(times), 3)
        row["ms_min"] = round(min(times), 3)
        row["ms_per_substep"] = round(row["ms"] / (args.horizon * roll.task.substeps), 4)
        row["loss"] = float(loss)
        row["grad_finite"] = bool(torch.isfinite(grad).all())
        row["grad_norm"] = float(grad.double().norm())  # to compare settings: same maths, same gradient
        if device.type == "cuda":
            row["peak_alloc_mb"] = round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
            row["peak_reserved_mb"] = round(torch.cuda.max_memory_reserved(device) / 2**20, 1)
            if args.kernels:
                row["kernels_per_substep"], row["kernel_table"] = _kernels_per_substep(
                    fn, args.horizon * roll.task.substeps)
            if args.configs:
                row["kernel_configs"] = kernel_configs()
    except Exception as e:  # a failing configuration is a row, not the end of the sweep
        row["status"] = f"error: {type(e).__name__}: {e}"[:400]
    finally:
        held.close()
    return row


@contextlib.contextmanager
def _gpu_lock(path: Path | None):
    """An exclusive file lock (``--gpu-lock PATH``) held from warm-up to the end of a row's measurement, so that
    several benchmark processes can compile concurrently on the host's cores while their GPU timings never
    overlap. Without a path it does nothing."""
    if path is None:
        yield
        return
    with open(path, "a") as fd:
        fcntl.flock(fd, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)


def _barrier(lock: Path, parties: int) -> None:
    """Wait until ``parties`` processes sharing ``lock`` have arrived here (one marker file each)."""
    marker = lock.with_name(f"{lock.name}.ready.{time.time_ns()}.{id(lock)}")
    marker.touch()
    while len(list(lock.parent.glob(f"{lock.name}.ready.*"))) < parties:
        time.sleep(0.5)


def kernel_configs(objects=None) -> list[dict]:
    """The launch configuration inductor's autotuner chose for every Triton kernel loaded in this process.

    Each entry: the kernel's name, ``source`` (a hash of its Triton source, equal across processes for the same
    kernel, so that two runs' choices can be compared kernel by kernel, see ``benchmarks/config_diff.py``) and
    ``chosen`` (the config of each launcher kept after autotuning, usually one; why it matters: the module
    docstring). ``objects``: where to look (default: every object the garbage collector tracks).
    """
    try:
        from torch._inductor.runtime.triton_heuristics import CachingAutotuner
    except ImportError:  # pragma: no cover - inductor ships with every supported torch
        return []
    found = []
    for obj in gc.get_objects() if objects is None else objects:
        if not isinstance(obj, CachingAutotuner):
            continue
        src = getattr(getattr(obj, "fn", None), "src", "") or ""
        found.append({
            "name": (getattr(obj, "inductor_meta", None) or {}).get("kernel_name", "?"),
            "source": hashlib.sha1(src.encode()).hexdigest()[:12],
            "chosen": [str(getattr(launcher, "config", None)) for launcher in (getattr(obj, "launchers", None) or [])],
        })
    return sorted(found, key=lambda k: (k["name"], k["source"], k["chosen"]))


def _kernels_per_substep(fn, n_substeps: int) -> tuple[float, list[dict]]:
    """GPU kernels per substep (forward + backward) of one call, kernels inside a replayed graph included, and
    the per-kernel table (name, launches and microseconds per substep), most time first."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        fn()
        torch.cuda.synchronize()
    events = [e for e in prof.key_averages() if e.device_type.name == "CUDA"]
    n = sum(e.count for e in events)
    per = [
        {"name": e.key[:120], "per_substep": round(e.count / n_substeps, 2),
         "us_per_substep": round(e.device_time_total / n_substeps, 2)}
        for e in sorted(events, key=lambda e: -e.device_time_total)
    ]
    return round(n / n_substeps, 1), per


def _setting(kv: str, p: argparse.ArgumentParser) -> tuple[str, object]:
    key, sep, value = kv.partition("=")
    if not sep:
        p.error(f"--inductor takes KEY=VALUE, got {kv!r}")
    low = value.lower()
    if low in ("true", "false"):
        return key, low == "true"
    try:
        return key, int(value)
    except ValueError:
        return key, value


def table(rows: list[dict]) -> str:
    cols = (
        "backend",
        "task",
        "num_envs",
        "mode",
        "substeps",
        "ms",
        "ms_per_substep",
        "peak_alloc_mb",
        "peak_reserved_mb",
        "kernels_per_substep",
        "warmup_s",
        "inductor",
        "status",
    )
    lines = [" | ".join(cols)]
    for r in rows:
        lines.append(" | ".join(str(r.get(c, "")) for c in cols))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="auto", help="auto (CUDA when present, else CPU), cpu or cuda[:N]")
    p.add_argument("--tasks", nargs="+", default=list(tasks.TASKS), choices=tasks.TASKS)
    p.add_argument("--num-envs", nargs="+", type=int, default=[64, 1024, 4096])
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    p.add_argument("--backends", nargs="+", default=["torch"], choices=BACKENDS,
                   help="simulator backends to time (tasks.TaskConfig.sim_backend), each row naming its own")
    p.add_argument("--check-horizon", type=int, default=8,
                   help="steps of the Warp backend's check against float64 torch before its first timed row (0: none)")
    p.add_argument("--check-envs", type=int, default=256, help="environments of that check (at most the row's)")
    p.add_argument("--horizon", type=int, default=32)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--iters", type=int, default=None, help="measured iterations (default 5; 3 with --quick)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--settle-s", type=float, default=2.0, help="untimed iterations for this long before timing")
    p.add_argument("--kernels", action="store_true", help="count GPU kernels per substep (forward + backward)")
    p.add_argument(
        "--configs",
        action="store_true",
        help="record the launch config autotuning chose for every Triton kernel (kernel_configs in the JSON; compare "
        "two runs with benchmarks/config_diff.py)",
    )
    p.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch.set_num_threads; default 1 on the CPU: the tensors are tiny, and on a shared 2-core box two "
        "OpenMP threads measured 40x slower than one",
    )
    p.add_argument("--quick", action="store_true", help="ant and humanoid at 64 envs, ant at 4096; all modes")
    p.add_argument(
        "--inductor",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="inductor settings for the compiled modes, e.g. combo_kernels=true aggressive_fusion=true",
    )
    p.add_argument(
        "--gpu-lock",
        type=Path,
        default=None,
        help="a lock file shared by concurrent benchmark processes: each compiles freely but holds the lock while "
        "it warms up, captures and times, so that no two measurements overlap on the GPU",
    )
    p.add_argument("--parties", type=int, default=1, help="with --gpu-lock: how many processes share it")
    p.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    args = p.parse_args(argv)
    args.inductor = dict(_setting(kv, p) for kv in args.inductor)
    try:
        device = resolve_device(args.device)
    except ValueError as e:
        p.error(str(e))
    args.device = str(device)
    if args.iters is None:
        args.iters = 3 if args.quick else 5
    if args.threads or device.type == "cpu":
        torch.set_num_threads(args.threads or 1)
    configs = QUICK if args.quick else [(t, n) for t in args.tasks for n in args.num_envs]
    meta = {
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or "cpu",
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "argv": sys.argv[1:] if argv is None else argv,
    }
    rows: list[dict] = []
    cache: dict = {}
    modes = [m for m in MODES if m in args.modes]  # compiled before graph: the graph row reuses its compile
    backends = [b for b in BACKENDS if b in args.backends]
    for name, n in configs:
        for backend in backends:
            for mode in modes:
                row = measure(name, n, mode, args, cache, backend)
                rows.append(row)
                print(json.dumps(row), flush=True)
                if args.out:
                    write_json(args.out, {"meta": meta, "rows": rows})
    print(f"\n# {meta['device']}, torch {meta['torch']}, {meta['date']}")
    print(table(rows))


if __name__ == "__main__":
    main()
