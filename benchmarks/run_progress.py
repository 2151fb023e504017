"""Where detached training runs stand, and their thinned copies to bring back (``gpu_session.sh`` stages
``detach``, ``progress`` and ``collect``).

Every run folder under ROOT (a folder holding ``metrics.jsonl``, a population's members included) gets one line:
its last iteration, the median iteration time of its last 50 iterations, its newest deterministic evaluation,
and its status (``summary.json``'s, or ``running``). A ``*.log`` in ROOT that ends in a traceback or an error
gets its tail printed, so a crash shows in the reply.

    python benchmarks/run_progress.py /tmp/runs
    python benchmarks/run_progress.py /tmp/runs --thin /tmp/keep --every 10   # then tar /tmp/keep
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
from pathlib import Path

from ablations.population import POPULATION
from ablations.run_folder import METRICS, SUMMARY, evaluation_of, read_metrics, thin_copy


def run_folders(root: Path) -> list[Path]:
    return sorted(p.parent for p in root.rglob(METRICS))


def line(folder: Path, root: Path) -> str:
    rows = read_metrics(folder)  # a line still being written is left out
    if not rows:
        return f"{folder.relative_to(root)}: no iterations yet"
    last = rows[-1]
    ms = [r["iter_ms"] for r in rows[-50:] if "iter_ms" in r and not r.get("probed")]
    evals = [(r["iter"], ev) for r in rows if (ev := evaluation_of(r)) is not None]
    status = "running"
    if (folder / SUMMARY).exists():
        status = json.loads((folder / SUMMARY).read_text()).get("status", "?")
    text = f"{folder.relative_to(root)}: iter {last['iter']}"
    if ms:
        text += f", {statistics.median(ms):.0f} ms/it"
    if last.get("return_mean") is not None:
        text += f", train return {last['return_mean']:.0f}"
    if evals:
        text += f", eval {evals[-1][1][0]:.0f} at {evals[-1][0]}"
    return f"{text}, {status}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", type=Path, help="folder the detached runs write under (their --out)")
    ap.add_argument("--thin", type=Path, default=None,
                    help="copy every run folder, thinned (ablations.run_folder.thin_copy), under this folder")
    ap.add_argument("--every", type=int, default=10, help="with --thin: keep every K-th iteration's metrics line")
    args = ap.parse_args()
    folders = run_folders(args.root)
    for folder in folders:
        print(line(folder, args.root))
    for log in sorted(args.root.glob("*.log")):
        text = log.read_text(errors="replace").splitlines()
        if any("Traceback" in t or "Error" in t for t in text[-8:]):
            print(f"--- {log.name} (last lines)\n" + "\n".join(text[-15:]))
    if args.thin is not None:
        for folder in folders:
            thin_copy(folder, args.thin / folder.relative_to(args.root), every=args.every)
        for record in args.root.rglob(POPULATION):  # a population's record beside its members' copies
            shutil.copy2(record, args.thin / record.relative_to(args.root))
        print(f"thinned {len(folders)} run folders into {args.thin}")


if __name__ == "__main__":
    main()
