"""A run's evaluation curve (:class:`Curve`) and the statistics of one run: final return, AUC, collapse rate.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ablations.run_folder import find_runs

#: Evaluations averaged into a run's final return.
FINAL_EVALS = 3
#: Metrics keys of the deterministic evaluation return, in order of preference: the mean over the evaluation
#: environments, else the older single-rollout return logged on video iterations.
EVAL_KEYS = ("eval_return_mean", "eval_return")


def is_finite_number(v) -> bool:
    """A finite int or float (not a bool): a metrics value a statistic can use."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)



# ---------------------------------------------------------------------------------------------------- curves
@dataclass(frozen=True)
class Curve:
    """One run's deterministic evaluation curve.

    ``iters`` (E,) int: the training iterations the evaluations followed (a metrics line's ``iter``: iterations
    done, 1-based); ``returns`` (E,) float: the evaluation return there (undiscounted, deterministic policy);
    ``last_iter``: the run's last metrics line's ``iter`` (how far it trained, evaluated or not); ``key``: the
    metrics key the returns came from (``EVAL_KEYS``), None when the run has no evaluation; ``charged_s``: the
    seconds of training charged to the run before its first iteration (a distilled student's expert's training
    time, its metrics' ``expert_wall_s``, as the reference charges it; 0 for every other run), which a cut at
    equal wall-clock adds to the run's modelled time.
    """

    task: str
    arm: str
    seed: int
    path: str
    iters: np.ndarray
    returns: np.ndarray
    last_iter: int
    key: str | None = None
    charged_s: float = 0.0


def curve_of(run, arm: str) -> Curve:
    """The evaluation curve of a loaded run (anything with ``.config`` (config.json's "config" object),
    ``.metrics`` (metrics.jsonl's lines) and ``.path``, e.g. ``ablations.run_folder.Run``), under arm name ``arm``.

    The key is the first of ``EVAL_KEYS`` any line carries; lines without a finite value of it are skipped.
    """
    cfg = run.config
    for k in ("task", "seed"):
        if k not in cfg:
            raise ValueError(f"{run.path}: config.json's config has no {k!r}")
    rows = run.metrics
    key = next((k for k in EVAL_KEYS if any(is_finite_number(r.get(k)) for r in rows)), None)
    pts = sorted((r["iter"], r[key]) for r in rows if key is not None and is_finite_number(r.get(key)))
    charged = next((float(r["expert_wall_s"]) for r in rows if is_finite_number(r.get("expert_wall_s"))), 0.0)
    return Curve(task=str(cfg["task"]), arm=arm, seed=int(cfg["seed"]), path=str(run.path),
                 iters=np.array([p[0] for p in pts], dtype=np.int64),
                 returns=np.array([p[1] for p in pts], dtype=np.float64),
                 last_iter=int(max((r["iter"] for r in rows), default=0)), key=key, charged_s=charged)


def load_arms(arms: Mapping[str, Iterable[str | Path]]) -> list[Curve]:
    """Arm name -> run folders (a folder holding run folders stands for all of them) -> their curves, in the
    given order. Raises ValueError for a folder that is not a run, or two runs of one task, arm and seed."""
    curves = [curve_of(run, arm) for arm, paths in arms.items() for run in find_runs(list(paths))]
    check_unique(curves)
    return curves


def check_unique(curves: Sequence[Curve]) -> None:
    """ValueError naming both runs where two curves are of one task, arm and seed (a seed would count twice)."""
    seen: dict[tuple[str, str, int], str] = {}
    for c in curves:
        k = (c.task, c.arm, c.seed)
        if k in seen:
            raise ValueError(f"arm {c.arm!r} has two runs of task {c.task!r} with seed {c.seed}: {seen[k]} and "
                             f"{c.path}; give one folder per seed")
        seen[k] = c.path


# ------------------------------------------------------------------------------------- per-run statistics
def final_return(curve: Curve, final_evals: int = FINAL_EVALS) -> float:
    """Mean of the last ``final_evals`` evaluation returns (all of them when there are fewer); NaN without any."""
    if curve.returns.size == 0:
        return math.nan
    return float(np.mean(curve.returns[-final_evals:]))


def auc(curve: Curve) -> float:
    """Area under the evaluation curve divided by its span: the trapezoid integral of the return over training
    iterations, from the first evaluation to the last, over (last - first) iterations. Units: return (the curve's
    mean height, so curves of different lengths compare); the one evaluation's return when there is one; NaN
    without any."""
    x, y = curve.iters.astype(np.float64), curve.returns
    if y.size == 0:
        return math.nan
    if y.size == 1 or x[-1] == x[0]:
        return float(y[-1])
    return float(np.sum((y[1:] + y[:-1]) * np.diff(x)) / 2.0 / (x[-1] - x[0]))


def window_statistic(curve: Curve, kind: str, start: int, end: int) -> float:
    """A run's statistic over the iteration window [``start``, ``end``] (inclusive, iterations done): ``"window"``
    the mean evaluation return at the evaluation iterations inside it; ``"auc"`` the trapezoid area under the
    evaluation curve between its first and last evaluation inside the window, over that span (return units; the
    one evaluation's return where there is one). NaN where no evaluation lies in the window."""
    if kind not in ("window", "auc"):
        raise ValueError(f"statistic kind must be 'window' or 'auc', got {kind!r}")
    if start > end:
        raise ValueError(f"iteration window {start}-{end}: its start is after its end")
    inside = (curve.iters >= start) & (curve.iters <= end)
    if not inside.any():
        return math.nan
    if kind == "window":
        return float(np.mean(curve.returns[inside]))
    return auc(replace(curve, iters=curve.iters[inside], returns=curve.returns[inside]))


def collapse_rate(curve: Curve) -> float:
    """Fraction of evaluations that collapse: with returns r_1..r_E in iteration order and the running best
    b_i = max(r_1, .., r_i), let k be the first index with b_k > 0 (the first positive best; half of a
    non-positive best is no bar). The rate is |{i > k : r_i < b_i / 2}| / (E - k): of the evaluations after
    the first positive best, those below half of the best so far. NaN when no best is positive or no
    evaluation follows it."""
    r = curve.returns
    best = np.maximum.accumulate(r) if r.size else r
    positive = np.flatnonzero(best > 0)
    if positive.size == 0 or positive[0] == r.size - 1:
        return math.nan
    after = slice(positive[0] + 1, None)
    return float(np.mean(r[after] < 0.5 * best[after]))
