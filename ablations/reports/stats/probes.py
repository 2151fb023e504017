"""Probe iterations where the policy looks at its image (:func:`looking_probes`) and the early blind phase.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ablations.reports.stats.curves import is_finite_number

#: A probe counts as looking when its image sensitivity exceeds this fraction of the run's first probe's (the
#: untrained policy's): the blind phase drops it by orders of magnitude, so the bar needs no precision.
LOOKING_FRACTION = 0.1
_SENSITIVITY_KEY = re.compile(r"image_sensitivity_f(\d+)$")


# ------------------------------------------------------------------------------------------ looking probes
@dataclass(frozen=True)
class LookingProbes:
    """A run's probe iterations split by whether the policy looks at its image.

    ``probe_iters`` / ``sensitivity`` (P,): every probe (a metrics line with ``image_sensitivity_f<i>``) and its
    image sensitivity (the sum or mean over frames, ``reduce``, of |d mean action / d frame|); ``initial``: the
    first probe's; ``looking_iters``: the probes with sensitivity > ``fraction`` x ``initial``. ``medians``:
    probe key -> median over the looking probes that carry it (None when none does), ``counts``: how many did,
    ``values``: probe key -> those values in iteration order (to pool the probes of several seeds).
    """

    fraction: float
    reduce: str
    initial: float | None
    probe_iters: tuple[int, ...]
    sensitivity: tuple[float, ...]
    looking_iters: tuple[int, ...]
    medians: dict[str, float | None]
    counts: dict[str, int]
    values: dict[str, tuple[float, ...]] = field(default_factory=dict)

    @property
    def n_probes(self) -> int:
        return len(self.probe_iters)

    @property
    def n_looking(self) -> int:
        return len(self.looking_iters)


def _is_probe_statistic(key: str) -> bool:
    """The probe's cosines and gradient norms (gradlab.shac's probe keys), not the every-iteration norms."""
    return key.startswith("cos_") or (key.startswith("grad_norm_") and key != "grad_norm_clipped")


def looking_probes(metrics: Sequence[Mapping], *, fraction: float = LOOKING_FRACTION, reduce: str = "sum",
                   keys: Sequence[str] | None = None) -> LookingProbes:
    """Where a run's policy looks at its image, and its probe statistics there.

    A probe is a metrics line with finite ``image_sensitivity_f0 .. f{k-1}``; its sensitivity is their sum
    (``reduce="sum"``) or mean (``"mean"``). The policy looks on a probe whose sensitivity exceeds ``fraction``
    of the first probe's (the untrained policy's). ``keys``: the probe statistics to take the median of over
    the looking probes; None: every ``cos_*`` and ``grad_norm_*`` key those probes carry (the cosine of full
    and decoupled, the gradient norms, the render term and its groups), except ``grad_norm_clipped``.
    """
    if not (is_finite_number(fraction) and fraction >= 0):
        raise ValueError(f"fraction must be a number >= 0, got {fraction!r}")
    if reduce not in ("sum", "mean"):
        raise ValueError(f"reduce must be 'sum' or 'mean', got {reduce!r}")
    probes = []
    for row in sorted(metrics, key=lambda r: r["iter"]):
        frames = [v for k, v in row.items() if _SENSITIVITY_KEY.match(k)]
        if frames and all(is_finite_number(v) for v in frames):
            probes.append((row, float(np.sum(frames) if reduce == "sum" else np.mean(frames))))
    initial = probes[0][1] if probes else None
    looking = [row for row, s in probes if s > fraction * initial] if probes else []
    if keys is None:
        keys = sorted({k for row in looking for k in row if _is_probe_statistic(k)})
    medians, counts, values = {}, {}, {}
    for k in keys:
        vals = [float(row[k]) for row in looking if is_finite_number(row.get(k))]
        medians[k] = float(np.median(vals)) if vals else None
        counts[k] = len(vals)
        values[k] = tuple(vals)
    return LookingProbes(fraction=float(fraction), reduce=reduce, initial=initial,
                         probe_iters=tuple(int(r["iter"]) for r, _ in probes),
                         sensitivity=tuple(s for _, s in probes),
                         looking_iters=tuple(int(r["iter"]) for r in looking), medians=medians, counts=counts,
                         values=values)


#: Iterations from the start over which ``blind_phase`` looks for the blind phase (the first 500).
BLIND_PHASE_ITERS = 500


@dataclass(frozen=True)
class BlindPhase:
    """How far and how long a run's policy stops looking at its image early in training (the blind phase): over
    the probes after the first up to iteration ``within``: ``probes`` of them, ``blind`` where the policy does not
    look (sensitivity at most ``fraction`` x the first probe's), ``lowest`` the lowest sensitivity relative to the
    first probe's (None without such probes, or when the first probe is 0 and sets no bar); ``looks_again_at`` the
    first probe after a blind one where it looks again (None when it never stopped looking or is still blind at
    its last probe in the window); ``last_blind`` the last blind probe (None without any): a policy may look again
    and stop once more."""

    within: int
    probes: int
    blind: int
    lowest: float | None
    looks_again_at: int | None
    last_blind: int | None = None


def blind_phase(looking: LookingProbes, *, within: int = BLIND_PHASE_ITERS) -> BlindPhase:
    """:class:`BlindPhase` of a run's probes (``looking``: :func:`looking_probes` of its metrics)."""
    if not (isinstance(within, int) and within > 0):
        raise ValueError(f"within must be a positive integer, got {within!r}")
    early = [(i, s) for i, s in zip(looking.probe_iters[1:], looking.sensitivity[1:]) if i <= within]
    if not early or not looking.initial:
        return BlindPhase(within, len(early), 0, None, None)
    threshold = looking.fraction * looking.initial
    blind = [s <= threshold for _, s in early]
    again = None
    if any(blind):
        first_blind = blind.index(True)
        again = next((i for (i, _), b in zip(early[first_blind:], blind[first_blind:]) if not b), None)
    last = max((i for (i, _), b in zip(early, blind) if b), default=None)
    return BlindPhase(within, len(early), sum(blind), min(s for _, s in early) / looking.initial, again, last)
