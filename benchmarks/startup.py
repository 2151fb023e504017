"""Time to the first training iteration of ``ablate --compile``, cold and warm, per task and mode.

For each task and mode, ``ablate --task T --mode M --compile --iters N`` runs twice in fresh processes: first
with an empty compile cache folder (cold: every graph compiled), then again with the same folder (warm: what a
second run of the same settings on the same machine pays). Each run's ``summary.json`` gives the seconds from
process start to the end of its first iteration (``first_iter_s``), the compilations and recompilations
dynamo made, and inductor's FX graph and AOTAutograd cache hits; the process's own wall time is measured
around it. With ``--compile-helper on off`` each pair runs with ablate's compile helpers and then without them
(``--no-compile-helper``), each pair with a cache folder of its own. Arguments this script does not know are
passed on to ``ablate`` (e.g. ``--horizon 4``).

Where Python writes no bytecode beside the sources (``PYTHONDONTWRITEBYTECODE``), ablate keeps it in its own
folder ($PIXELGRAD_BYTECODE_CACHE, ablations/startup/bytecode.py), which this script leaves as it finds it: each row
records how many modules' bytecode that folder held before the run (``bytecode_pyc_before``; 0: the run compiled
all of its Python too, as the first start in a fresh container does).

Not a test. Examples::

    python benchmarks/startup.py --device cuda --tasks ant --modes decoupled --num-envs 64 --out startup.json
    python benchmarks/startup.py --device cuda --tasks ant --num-envs 64 --iters 8 --compile-helper on off
    python benchmarks/startup.py --device cpu --tasks cartpole --modes state --num-envs 2 --image-size 16 \
        --out /tmp/startup.json --horizon 4
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from _common import commit

from ablations.startup import resolve_bytecode_folder
from gradlab import MODES
from tasks import TASKS

ROOT = Path(__file__).resolve().parents[1]
#: summary.json["compile"] keys copied into each row
COMPILE_KEYS = ("compiles", "recompiles", "backward_compiles", "compile_s", "compile_s_by_part", "fxgraph_cache_hit",
                "fxgraph_cache_miss", "fxgraph_cache_bypass", "autograd_cache_hit", "autograd_cache_miss",
                "artifacts_loaded", "artifacts_load_s", "phase_s", "graphs", "triton_compiles", "triton_compile_s",
                "triton_cache_hits", "triton_compile_s_by_kernel", "kernel_compile_miss", "kernel_compile_hit",
                "graphs_saved_ready", "kernels_loaded_ready", "helpers", "helpers_wait_s", "bytecode")
#: compile phases printed per run (summary.json["compile"]["phase_s"] has them all): dynamo's tracing,
#: AOTAutograd's joint trace, inductor's lowering, fusion decisions and kernel writing, the wait for Triton's
#: compiler workers, autotuning, and loading compiled modules (also from the cache)
PRINTED_PHASES = {"bytecode_tracing": "dynamo trace", "aot_trace_joint_graph": "AOT joint trace",
                  "GraphLowering.run": "lowering", "Scheduler.__init__": "fusion", "Scheduler.codegen": "kernel code",
                  "async_compile.wait": "Triton compile wait", "CachingAutotuner.benchmark_all_configs": "autotune",
                  "PyCodeCache.load_by_key_path": "module load"}

#: graphs printed per run, slowest first (summary.json["compile"]["graphs"] has them all)
PRINTED_GRAPHS = 8


def ablate_command(task: str, mode: str, args, *, cache: Path, runs: Path, name: str) -> list[str]:
    cmd = [sys.executable, "-m", "ablations", "ablate", "--task", task, "--mode", mode, "--compile",
           "--iters", str(args.iters), "--device", args.device, "--compile-cache", str(cache), "--out", str(runs),
           "--name", name, "--video-every", "0", "--no-progress"]
    if args.num_envs is not None:
        cmd += ["--num-envs", str(args.num_envs)]
    if args.image_size is not None:
        cmd += ["--image-size", str(args.image_size)]
    return cmd + list(args.ablate_args)


def run_once(cmd: list[str], run_dir: Path, *, timeout: float) -> dict:
    """One ablate process: its wall time, and what its summary.json says about the start."""
    env = {k: v for k, v in os.environ.items() if k not in ("TORCHINDUCTOR_CACHE_DIR", "TRITON_CACHE_DIR")}
    bytecode = resolve_bytecode_folder() if os.environ.get("PYTHONDONTWRITEBYTECODE") else None
    row = {"bytecode_pyc_before": None if bytecode is None else sum(1 for _ in bytecode.rglob("*.pyc"))}
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT, timeout=timeout)
    row.update(process_s=time.perf_counter() - t0, returncode=proc.returncode)
    if run_dir.is_dir():  # what the run printed (e.g. TORCH_LOGS=recompiles), beside its summary
        (run_dir / "stderr.log").write_text(proc.stderr)
    summary_path = run_dir / "summary.json"
    if proc.returncode != 0 or not summary_path.exists():
        row.update(status="error", error=(proc.stderr.strip().splitlines() or ["(no output)"])[-1][:500])
        return row
    summary = json.loads(summary_path.read_text())
    compiled = summary.get("compile") or {}
    metrics = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    # the losses let a reader check that the warm run computed what the cold one did
    row.update(status=summary["status"], first_iter_s=summary.get("first_iter_s"),
               iter_ms=[m["iter_ms"] for m in metrics], actor_loss=[m["actor_loss"] for m in metrics],
               startup_s=summary.get("startup_s"), **{k: compiled.get(k) for k in COMPILE_KEYS})
    if row["first_iter_s"] is not None and metrics:  # imports, trainer construction, whatever ran before it
        row["before_first_iter_s"] = row["first_iter_s"] - metrics[0]["iter_ms"] / 1e3
    for helper in row.get("helpers") or []:  # each helper's own account of its seconds, the last line it printed
        log = Path(helper["log"])
        lines = log.read_text(errors="replace").strip().splitlines() if log.exists() else []
        helper["report"] = lines[-1][:500] if lines else None
    return row


def measure(task: str, mode: str, args, *, work: Path, helper: str = "on") -> list[dict]:
    """The cold and the warm run of one (task, mode), sharing one compile cache folder; ``helper`` "off" passes
    --no-compile-helper (and gets a cache folder of its own)."""
    suffix = "" if helper == "on" else "_nohelper"
    cache, runs = work / f"cache_{task}_{mode}{suffix}", work / "runs"
    rows = []
    for phase in ("cold", "warm"):
        name = f"{task}_{mode}_{phase}{suffix}"
        cmd = ablate_command(task, mode, args, cache=cache, runs=runs, name=name)
        if helper == "off":
            cmd.append("--no-compile-helper")
        row = {"task": task, "mode": mode, "phase": phase, "compile_helper": helper == "on",
               "num_envs": args.num_envs, "image_size": args.image_size, "iters": args.iters,
               "command": " ".join(cmd[1:])}
        row.update(run_once(cmd, runs / name, timeout=args.timeout))
        rows.append(row)
        print(json.dumps(row), flush=True)
        if row["status"] == "error":
            break
    return rows


def meta(args, argv: list[str]) -> dict:
    import torch

    info = {"device": args.device, "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
            "command": " ".join(["python", "benchmarks/startup.py", *argv]), "commit": commit(),
            "torch": torch.__version__, "python": platform.python_version(), "hostname": platform.node(),
            # set: Python writes no bytecode beside the sources, and ablate keeps it in its own folder instead
            "PYTHONDONTWRITEBYTECODE": os.environ.get("PYTHONDONTWRITEBYTECODE"),
            "bytecode_folder": str(resolve_bytecode_folder())}
    if args.device.startswith("cuda") and torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name()
    return info


def run_label(r: dict) -> str:
    """cold / warm, and whether the run had ablate's compile helpers."""
    return r["phase"] + ("" if r.get("compile_helper", True) else " no-helper")


def per_run(doc: dict, title: str, line: Callable[[dict], str | None]) -> None:
    """Print ``title``, then ``line(row)`` for each run that did not fail, where it has something to say."""
    print(f"\n{title}")
    for r in doc["rows"]:
        text = None if r["status"] == "error" else line(r)
        if text:
            print(f"{r['task']} {r['mode']} {run_label(r)}: {text}")


def fmt(v, nd=1) -> str:
    return "-" if v is None else f"{v:.{nd}f}"


def main(argv: list[str] | None = None) -> dict:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda", help="cpu | cuda | cuda:N (passed to ablate)")
    p.add_argument("--tasks", nargs="+", default=["ant"], choices=TASKS)
    p.add_argument("--modes", nargs="+", default=["decoupled"], choices=MODES)
    p.add_argument("--num-envs", type=int, default=None, help="default: the preset's")
    p.add_argument("--image-size", type=int, default=None, help="default: ablate's")
    p.add_argument("--iters", type=int, default=2, help="iterations per run (the first one is what is timed)")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds one ablate process may take")
    p.add_argument("--compile-helper", nargs="+", choices=("on", "off"), default=["on"],
                   help="with and/or without ablate's compile helpers (a cold GPU start in several processes), "
                        "each with a cache folder of its own, in this order: 'on off' is a same-machine A/B")
    p.add_argument("--work", type=Path, default=None,
                   help="folder for the cache folders and run folders (kept); default: a temporary one, removed")
    p.add_argument("--out", type=Path, default=Path("startup.json"))
    args, args.ablate_args = p.parse_known_args(argv)
    if args.iters < 1:
        p.error(f"--iters must be >= 1, got {args.iters}")
    doc = {"meta": meta(args, argv), "rows": []}
    with tempfile.TemporaryDirectory(prefix="pixelgrad-startup-") as tmp:
        work = args.work or Path(tmp)
        for task in args.tasks:
            for mode in args.modes:
                for helper in args.compile_helper:
                    doc["rows"].extend(measure(task, mode, args, work=work, helper=helper))
                args.out.parent.mkdir(parents=True, exist_ok=True)
                args.out.write_text(json.dumps(doc, indent=2))

    print(f"\nstart of ablate --compile, {doc['meta'].get('gpu', args.device)}: seconds from process start to the "
          f"end of the first iteration, to its start, the whole {args.iters}-iteration process, and compiling")
    print(f"{'task':9} {'mode':9} {'run':15} {'first it s':>10} {'before it s':>11} {'process s':>9} {'compile s':>9} "
          f"{'compiles':>8} {'recompiles':>10} {'fx hit':>6} {'fx miss':>7}")
    for r in doc["rows"]:
        if r["status"] == "error":
            print(f"{r['task']:9} {r['mode']:9} {run_label(r):15} error: {r['error'][:80]}")
            continue
        print(f"{r['task']:9} {r['mode']:9} {run_label(r):15} {fmt(r['first_iter_s']):>10} "
              f"{fmt(r.get('before_first_iter_s')):>11} {fmt(r['process_s']):>9} {fmt(r['compile_s']):>9} "
              f"{r['compiles']!s:>8} {r['recompiles']!s:>10} {r['fxgraph_cache_hit']!s:>6} "
              f"{r['fxgraph_cache_miss']!s:>7}")

    def where_the_seconds_went(r: dict) -> str:
        parts = " ".join(f"{k} {fmt(v)}" for k, v in (r.get("startup_s") or {}).items())
        if r.get("bytecode"):
            parts += f" (Python bytecode kept in {r['bytecode']}: {r.get('bytecode_pyc_before')} modules before)"
        if r.get("artifacts_load_s"):
            parts += f" (of the compile cache's: loading its artifact file {fmt(r['artifacts_load_s'])})"
        by_part = sorted((r.get("compile_s_by_part") or {}).items(), key=lambda kv: -kv[1])
        return f"{parts} | compiling: " + " ".join(f"{k} {fmt(v)}" for k, v in by_part)

    def inside_the_compiler(r: dict) -> str | None:
        phases = r.get("phase_s") or {}
        if not phases:
            return None
        return (" ".join(f"{label} {fmt(phases[k])}" for k, label in PRINTED_PHASES.items() if k in phases)
                + f" | Triton in-process: {r.get('triton_compiles')} compiled in {fmt(r.get('triton_compile_s'))}"
                + f", {r.get('triton_cache_hits')} from its cache | inductor kernels: {r.get('kernel_compile_miss')} "
                + f"compiled, {r.get('kernels_loaded_ready')} loaded ready to launch "
                + f"({r.get('graphs_saved_ready')} graphs saved with such)")

    def triton_kernels(r: dict) -> str | None:
        kernels = r.get("triton_compile_s_by_kernel")
        return " ".join(f"{k} {fmt(v, 2)}" for k, v in kernels.items()) if kernels else None

    def slowest_graphs(r: dict) -> str | None:
        graphs = (r.get("graphs") or [])[:PRINTED_GRAPHS]
        return "; ".join(f"{g['name']} [{g['compile_id']}] {g['kind']} {fmt(g['s'])}/{fmt(g['inductor_s'])}"
                         + (f" ({g['nodes']} nodes)" if g.get("nodes") else "") for g in graphs) or None

    def helpers(r: dict) -> str | None:
        if not r.get("helpers"):
            return None
        reports = "; ".join(h.get("report") or f"({', '.join(h['parts'])}: exit {h['returncode']}, no report)"
                            for h in r["helpers"])
        return f"the run waited {fmt(r.get('helpers_wait_s'))} s for them | {reports}"

    per_run(doc, "where the seconds went (startup_s: the parts before and of the first iteration; compiling, by "
                 "part)", where_the_seconds_went)
    per_run(doc, "the compile helpers (each one's seconds, from its log)", helpers)
    per_run(doc, "inside the compiler (torch's phase times, nested: they do not add up)", inside_the_compiler)
    per_run(doc, "Triton kernels compiled in-process, slowest first (seconds)", triton_kernels)
    per_run(doc, f"the {PRINTED_GRAPHS} slowest graphs (seconds: whole compilation, inductor's part; FX nodes of a "
                 "forward)", slowest_graphs)
    return doc


if __name__ == "__main__":
    main()
