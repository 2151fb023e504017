"""Where detached training runs stand, and their thinned copies to bring back (``gpu_session.sh`` stages
``detach``, ``progress`` and ``collect``).

Every run folder under ROOT (a folder holding ``metrics.jsonl``, a population's members included) gets one line:
its last iteration, the median iteration time of its last 50 iterations, its newest deterministic evaluation,
and its status (``summary.json``'s, or ``running``). A ``*.log`` in ROOT whose run has no summary and whose
process is gone gets its tail printed, so a crash shows in the reply.

    python benchmarks/run_progress.py /tmp/runs
    python benchmarks/run_progress.py /tmp/runs --thin /tmp/keep --every 10   # then tar /tmp/keep
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def run_folders(root: Path) -> list[Path]:
    return sorted(p.parent for p in root.rglob("metrics.jsonl"))


def last_rows(path: Path, n: int) -> list[dict]:
    """The last ``n`` readable lines of a metrics file (a line being written is skipped)."""
    rows = []
    for line in path.read_text().splitlines()[-n - 1:]:
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return rows[-n:]


def line(folder: Path, root: Path) -> str:
    rows = last_rows(folder / "metrics.jsonl", 50)
    if not rows:
        return f"{folder.relative_to(root)}: no iterations yet"
    last = rows[-1]
    ms = [r["iter_ms"] for r in rows if "iter_ms" in r and not r.get("probed")]
    evals = [r for r in last_rows(folder / "metrics.jsonl", 600) if "eval_return_mean" in r]
    status = "running"
    if (folder / "summary.json").exists():
        status = json.loads((folder / "summary.json").read_text()).get("status", "?")
    text = f"{folder.relative_to(root)}: iter {last['iter']}"
    if ms:
        text += f", {statistics.median(ms):.0f} ms/it"
    if last.get("return_mean") is not None:
        text += f", train return {last['return_mean']:.0f}"
    if evals:
        text += f", eval {evals[-1]['eval_return_mean']:.0f} at {evals[-1]['iter']}"
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
        from ablations.run_folder import thin_copy

        for folder in folders:
            rel = folder.relative_to(args.root)
            thin_copy(folder, args.thin / rel, every=args.every)
            population = folder.parent / "population.json"
            if population.exists():
                (args.thin / rel.parent).mkdir(parents=True, exist_ok=True)
                (args.thin / rel.parent / "population.json").write_text(population.read_text())
        print(f"thinned {len(folders)} run folders into {args.thin}")


if __name__ == "__main__":
    main()
