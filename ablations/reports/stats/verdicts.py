"""How a task's arms may be read: the control rule's gate and the verdict (the package docstring says why).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from ablations.reports.stats.comparisons import Comparison, PairedDifference, correct
from ablations.reports.stats.estimates import ALPHA, MIN_SEEDS, Estimate


# ------------------------------------------------------------------------------------------------ verdict
@dataclass(frozen=True)
class Gate:
    """Whether the reference arm beats the control (decoupled against blind) on one task: ``passed`` when the
    paired difference reference minus control is above zero and differs after Holm correction
    (:meth:`PairedDifference.differs`); ``by`` is then ``"paired difference"``, else None. ``paired``: reference
    minus control final return over the paired seeds (None without any), ``p_holm`` its Holm-adjusted p-value;
    ``reference_iqm`` / ``control_iqm``: the arms' IQMs, shown beside it; ``why``: one sentence."""

    passed: bool
    by: str | None
    paired: Estimate | None
    reference_iqm: Estimate | None
    control_iqm: Estimate | None
    why: str
    p_holm: float | None = None


@dataclass(frozen=True)
class Verdict:
    """How one task's arms may be read against the reference. ``ranks``: whether they may; ``reason``: why (or
    why not), one sentence; ``gate``: the reference against the control (None when the task does not rank arms
    or an arm is missing); ``readings``: arm -> ``"better"``, ``"worse"`` (the paired difference differs after
    Holm correction, on that side), ``"not resolved"`` (it does not), ``"too few seeds"`` (fewer than
    ``MIN_SEEDS`` paired seeds) or ``"no paired seeds"``; empty unless ``ranks``. ``alpha``: the family-wise
    level."""

    task: str
    reference: str
    control: str
    ranks: bool
    reason: str
    gate: Gate | None
    readings: dict[str, str]
    alpha: float = ALPHA


def _negated(e: Estimate) -> Estimate:
    """The estimate of minus the statistic: a percentile bootstrap of a mean flips exactly under negation."""
    return replace(e, value=-e.value, ci_low=-e.ci_high, ci_high=-e.ci_low)


def _ci(e: Estimate) -> str:
    return f"{e.value:.4g} [{e.ci_low:.4g}, {e.ci_high:.4g}]"


def _test_text(d: PairedDifference) -> str:
    """``3 of 5 seeds agree in sign, sign-flip p = 0.0625, Holm-adjusted p = 1 (18 comparisons)``."""
    text = f"{d.agree} of {d.mean.n} seeds agree in sign, sign-flip p = {d.p_value:.3g}"
    if d.p_holm is not None:
        text += f", Holm-adjusted p = {d.p_holm:.3g} ({d.family} comparison{'s' if d.family != 1 else ''})"
    return text


def verdict(cmp: Comparison, *, control: str = "blind", not_ranking: str | None = None,
            alpha: float = ALPHA) -> Verdict:
    """The control rule: the arms of ``cmp`` are read against its reference (decoupled) only where the reference
    beats ``control`` (blind: the same pixels, never looked at), i.e. reference minus control differs after Holm
    correction and is positive; otherwise pixels have not yet been shown to help on this task and the arms
    cannot be ranked. Each arm's reading follows its own Holm-corrected paired difference. A comparison not yet
    corrected (:func:`correct`) is corrected here over its own paired differences alone. The minimum-seeds rule
    holds throughout: fewer than ``MIN_SEEDS`` paired seeds decide nothing. ``not_ranking``: a reason the task
    ranks no arms whatever the numbers (a task that doing nothing solves)."""
    ref = cmp.reference or "reference"
    if not_ranking is not None:
        return Verdict(cmp.task, ref, control, False, not_ranking, None, {}, alpha)
    missing = [a for a in (ref, control) if a not in cmp.arms or cmp.arms[a].final_iqm is None]
    if missing:
        return Verdict(cmp.task, ref, control, False, f"the arms cannot be ranked: no {' and no '.join(missing)} "
                       "run with an evaluation to hold them against", None, {}, alpha)
    if any(d.p_value is not None and d.p_holm is None for d in cmp.differences.values()):
        cmp = correct([cmp])[0]
    r, c = cmp.arms[ref].final_iqm, cmp.arms[control].final_iqm
    d = cmp.differences[control]
    paired = _negated(d.mean) if d.mean is not None else None
    iqms = f"IQMs {_ci(r)} (n={r.n}) and {_ci(c)} (n={c.n})"
    if paired is None:
        why = f"no {ref} seed has a {control} run of the same seed to pair with ({iqms})"
    elif paired.n < MIN_SEEDS:
        why = (f"too few seeds to read {ref} against {control}: {paired.n} paired seed(s), and no verdict rests on "
               f"fewer than {MIN_SEEDS} ({ref} minus {control} {_ci(paired)})")
    elif d.differs(alpha) and paired.value > 0:
        why = f"{ref} beats {control}: {ref} minus {control} {_ci(paired)}, {_test_text(d)} <= {alpha:g}"
    elif d.differs(alpha):
        why = f"{control} beats {ref}: {ref} minus {control} {_ci(paired)}, {_test_text(d)} <= {alpha:g}"
    else:
        why = (f"{ref} is not shown to beat {control} after Holm correction: {ref} minus {control} {_ci(paired)}, "
               f"{_test_text(d)} > {alpha:g}")
    passed = paired is not None and paired.n >= MIN_SEEDS and d.differs(alpha) and paired.value > 0
    gate = Gate(passed, "paired difference" if passed else None, paired, r, c, why, d.p_holm)
    if not passed:
        return Verdict(cmp.task, ref, control, False, f"{why}; the pixel arms cannot be ranked on this task yet",
                       gate, {}, alpha)
    readings = {}
    for arm, diff in cmp.differences.items():
        if arm == control:
            continue
        m = diff.mean
        readings[arm] = ("no paired seeds" if m is None else "too few seeds" if m.n < MIN_SEEDS
                         else ("better" if m.value > 0 else "worse") if diff.differs(alpha) else "not resolved")
    return Verdict(cmp.task, ref, control, True, why, gate, readings, alpha)
