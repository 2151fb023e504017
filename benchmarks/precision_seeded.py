"""The seeded comparison of a setting's values: does the encoder's precision, or the simulator's backend, change
what a run learns?

Reads run folders (``ablate`` runs or populations; docs/precision_h200 ships the hopper's), groups them by task,
arm (as the reports name arms, ``ablations.reports.arms.arm_names``) and the setting (``--setting``:
``SHACConfig.precision``, or ``SHACConfig.sim_backend``), and sets each value's runs beside the reference value's
(``--reference``; the setting's default) of the same task, arm and seeds with the reports' comparison
(``ablations.reports.stats.compare`` and ``correct``): each run's final return is its deterministic evaluation
return averaged over the last 3 evaluations every run of the arm has, at either precision; per arm the per-seed
differences (candidate minus reference), how many agree in sign, the mean with its exact bootstrap CI, the exact
sign-flip p-value and Holm's correction over every comparison made here. With 5 paired seeds the smallest
sign-flip p is 0.0625, so nothing "differs" at 0.05: the per-seed differences and their signs are the evidence.
Beside the returns, each arm's median probe statistics (cos(full, decoupled) and the render term's norm) over the
probes where its policy looks at its image, pooled over seeds, as the reports count them.

Not a test. Example::

    python benchmarks/precision_seeded.py docs/precision_h200/runs \\
        --out benchmarks/results/precision_seeded_hopper_h200_20261128.json
    python benchmarks/precision_seeded.py RUNS --setting sim_backend --out sim_seeded.json
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from _common import write_json

from ablations.reports.arms import arm_names
from ablations.reports.seeds import arm_probes
from ablations.reports.stats import DEFAULT_REPS, compare, correct, curve_of, seeds_to_resolve
from ablations.run_folder import find_runs

PROBE_KEYS = ("cos_full_decoupled", "grad_norm_render_term")
#: The settings compared, each with its default (the reference and the value of a config that does not name it).
SETTINGS = {"precision": "fp32", "sim_backend": "torch"}


def _probe_medians(runs, label) -> dict:
    """(task, arm label) -> PROBE_KEYS key -> {median, n} over the probes where the policy looks, pooled over
    seeds (``ablations.reports.seeds.arm_probes``, as the reports count them)."""
    return {(a.task, a.arm): {k: {"median": a.medians[k], "n": a.counts[k]} if a.medians.get(k) is not None
                              else None for k in PROBE_KEYS}
            for a in arm_probes(runs, label=label)}


def _arms_but(runs, setting: str) -> dict:
    """Run folder -> its arm as the reports name it (``ablations.reports.arms.arm_names``: vocabulary.ARMS, then
    every other setting that differs between the runs), ``setting`` left out: the runs a value is read against
    are those of the same arm."""
    names = {}
    for path, name in arm_names(runs).items():
        name = re.sub(setting + r"=[^,)]*(, )?", "", name).replace(", )", ")").replace(" ()", "")
        names[path] = name
    return names


def compare_precisions(paths: list[Path], *, setting: str = "precision", reference: str | None = None,
                       reps: int = DEFAULT_REPS) -> dict:
    """Per (task, arm, candidate value of ``setting``): the paired difference against ``reference`` (None: the
    setting's default; see the module text)."""
    if setting not in SETTINGS:
        raise ValueError(f"--setting: unknown setting {setting!r}; valid: {', '.join(SETTINGS)}")
    default = SETTINGS[setting]
    reference = default if reference is None else reference
    runs = find_runs(paths)
    if not runs:
        raise ValueError(f"no run folders under {', '.join(map(str, paths))}")
    arms = _arms_but(runs, setting)

    def value(run) -> str:
        return str(run.config.get(setting) or default)

    groups: dict[tuple[str, str, str], list] = {}
    for run in runs:
        groups.setdefault((str(run.config["task"]), arms[run.path], value(run)), []).append(run)
    probes = _probe_medians(runs, lambda r: f"{arms[r.path]} {value(r)}")
    keys, comparisons = [], []
    for task, arm, prec in sorted(groups):
        if prec == reference or (task, arm, reference) not in groups:
            continue
        names = {prec: f"{arm} {prec}", reference: f"{arm} {reference}"}
        curves = [curve_of(r, names[p]) for p in (prec, reference) for r in groups[(task, arm, p)]]
        keys.append((task, arm, prec))
        comparisons.append(compare(curves, reference=names[reference], reps=reps))
    comparisons = correct(comparisons)
    rows = []
    for (task, arm, prec), c in zip(keys, comparisons):
        d = c.differences[f"{arm} {prec}"]
        rows.append({"task": task, "arm": arm, "setting": setting, setting: prec, "reference": reference,
                     "window": list(c.arms[d.reference].window), "candidate": c.arms[d.arm].final,
                     "reference_returns": c.arms[d.reference].final, "diff": d.diff, "agree": d.agree,
                     "mean": d.mean.value if d.mean else None,
                     "ci": [d.mean.ci_low, d.mean.ci_high] if d.mean else None,
                     "p": d.p_value, "p_holm": d.p_holm, "differs": d.differs(),
                     "probes": {p: probes.get((task, f"{arm} {p}"), dict.fromkeys(PROBE_KEYS))
                                for p in (prec, reference)}})
    family = sum(r["p"] is not None for r in rows)
    return {"setting": setting, "rows": rows, "family": family,
            "seeds_to_resolve": seeds_to_resolve(family) if family else None}


def table(doc: dict) -> str:
    setting = doc.get("setting", "precision")
    lines = [f"| task | arm | {setting} - reference per seed | agree | mean [95 % CI] | sign-flip p | Holm p | "
             "median cos(full, decoupled): cand., ref. | median render-term norm: cand., ref. |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in doc["rows"]:
        if r["mean"] is None:
            lines.append(f"| {r['task']} | {r['arm']} | {r[setting]} - {r['reference']}: no paired seeds "
                         "| - | - | - | - | - | - |")
            continue
        per_seed = ", ".join(f"s{s}: {v:+.0f}" for s, v in sorted(r["diff"].items()))

        def probe(key, r=r):
            vals = [r["probes"][p][key] for p in (r[setting], r["reference"])]
            return ", ".join("-" if v is None else f"{v['median']:.3g}" for v in vals)
        lines.append(f"| {r['task']} | {r['arm']} | {r[setting]} - {r['reference']}: {per_seed} | "
                     f"{r['agree']} of {len(r['diff'])} | {r['mean']:+.0f} [{r['ci'][0]:+.0f}, {r['ci'][1]:+.0f}] | "
                     f"{r['p']:.3f} | {r.get('p_holm', float('nan')):.3f} | {probe('cos_full_decoupled')} | "
                     f"{probe('grad_norm_render_term')} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="+", type=Path, help="run folders, or folders that hold them")
    p.add_argument("--setting", choices=sorted(SETTINGS), default="precision",
                   help="the setting whose values are compared (SHACConfig.precision or .sim_backend)")
    p.add_argument("--reference", default=None,
                   help="the value the others are read against (default: the setting's default, fp32 or torch)")
    p.add_argument("--reps", type=int, default=DEFAULT_REPS, help="bootstrap resamples where seeds are many")
    p.add_argument("--out", type=Path, default=None, help="JSON output")
    args = p.parse_args(argv)
    try:
        doc = compare_precisions(args.paths, setting=args.setting, reference=args.reference, reps=args.reps)
    except ValueError as e:
        p.error(str(e))
    doc["command"] = "python benchmarks/precision_seeded.py " + " ".join(argv if argv is not None else sys.argv[1:])
    if args.out:
        write_json(args.out, doc)
    print(table(doc))
    print(f"\n{doc['family']} comparisons under Holm; a difference can differ only with at least "
          f"{doc['seeds_to_resolve']} paired seeds.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
