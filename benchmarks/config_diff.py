"""Which Triton kernels kept different launch configs in two benchmark runs of the same code.

Reads the ``kernel_configs`` of two rows written by ``benchmarks/sim.py --configs`` and lists, kernel by kernel
(matched by name and source hash), the configs that differ, with each row's time. Same code, different
configs: the autotuner chose differently (its timings are noisy). Not a test. Example::

    python benchmarks/config_diff.py fast.json slow.json --task ant --num-envs 64
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path


def load_row(path: Path, task: str | None, num_envs: int | None) -> dict:
    """The first row of ``path`` (a sim.py JSON file) with kernel configs, matching task and batch if given."""
    data = json.loads(path.read_text())
    for row in data.get("rows", []):
        if "kernel_configs" not in row:
            continue
        if (task is None or row.get("task") == task) and (num_envs is None or row.get("num_envs") == num_envs):
            return row
    wanted = " ".join(f"{k}={v}" for k, v in (("task", task), ("num_envs", num_envs)) if v is not None)
    raise SystemExit(f"{path}: no row with kernel_configs" + (f" for {wanted}" if wanted else ""))


def diff(a: list[dict], b: list[dict]) -> tuple[int, list[tuple[str, str, list, list]]]:
    """How many kernels (name, source) both lists hold, and those whose chosen configs differ: (name, source,
    chosen in a, chosen in b). Kernels that occur several times with the same name and source are compared as
    multisets."""
    def group(entries):
        out: dict[tuple[str, str], Counter] = {}
        for e in entries:
            out.setdefault((e["name"], e["source"]), Counter())[json.dumps(e["chosen"])] += 1
        return out

    ga, gb = group(a), group(b)
    common = sorted(ga.keys() & gb.keys())
    rows = [(*key, sorted(ga[key].elements()), sorted(gb[key].elements())) for key in common if ga[key] != gb[key]]
    return len(common), rows


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("a", type=Path, help="first sim.py JSON file")
    p.add_argument("b", type=Path, help="second sim.py JSON file")
    p.add_argument("--task", default=None, help="row's task (default: the first row with configs)")
    p.add_argument("--num-envs", type=int, default=None, help="row's batch size")
    args = p.parse_args(argv)
    ra, rb = load_row(args.a, args.task, args.num_envs), load_row(args.b, args.task, args.num_envs)
    ka, kb = ra["kernel_configs"], rb["kernel_configs"]
    print(f"a: {args.a} {ra.get('ms')} ms, {len(ka)} kernels; b: {args.b} {rb.get('ms')} ms, {len(kb)} kernels")
    n_common, rows = diff(ka, kb)
    print(f"{n_common} kernels in both, {len(rows)} with different configs")
    for name, source, ca, cb in rows:
        print(f"{name} [{source}]\n  a: {', '.join(ca)}\n  b: {', '.join(cb)}")


if __name__ == "__main__":
    main()
