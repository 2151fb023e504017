"""A confirmatory experiment's registration as data: ``preregistration.json`` (docs/confirmatory/README.md gives
its prose), loaded and checked by :func:`load_registration`, and the checks of run folders against it
(:func:`check_runs`).

The file (every key required unless marked optional):

* ``name``; ``tree_hash``: the training tree the runs must come from (``ablations.tree_hash``), ``null`` until
  pinned (:func:`pin`, ``ablate-plan --pin``), and a registration with ``null`` checks no run;
* ``correction``: ``"holm"``; ``looks``: a list of ``{"seeds": [...], "alpha": a}`` with growing seed sets, each
  look's alpha its share of the family-wise level (Bonferroni over the looks: the alphas sum to at most 0.05
  unless ``familywise_alpha`` says otherwise);
* ``iterations``: the training iterations every run trains; ``budget_axis``: ``"iterations"`` (equal iterations;
  equal modelled wall-clock is then shown without a verdict);
* ``tasks``, ``arms`` (vocabulary.ARMS names);
* ``hypotheses``: each ``{"id", "task", "arm", "reference", "alternative", "statistic", "role"}`` with
  ``alternative`` ``"greater"`` / ``"less"`` / ``"two-sided"`` (of arm minus reference), ``statistic``
  ``{"kind": "window" | "auc", "from": i, "to": j}`` (the mean evaluation return at the evaluation iterations in
  [i, j], or the area under the evaluation curve over [i, j] divided by its span), ``role`` ``"gate"`` or
  ``"comparison"``, and optional ``smallest_effect`` (> 0, return units: the power the plan reports) and
  ``equivalence_margin`` (> 0: a TOST at +-margin, outside the Holm family);
* ``settings``: config fields and the value every run must have; ``must_equal``: the config fields that must
  equal the registration (their value in ``settings``) or, where ``settings`` gives none, be the same for every
  run of one task and arm; ``may_differ``: fields free to differ (name, out, device, threads, ...); a config
  field neither names is held as ``must_equal`` without a value (the same within a task and arm);
* ``incomplete_looks``: the policy, as text.

Reads JSON only (no torch).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from ablations.tree_hash import tree_hash
from gradlab.files import atomic_write_text
from vocabulary import ARMS, arm_of

ALTERNATIVES = ("greater", "less", "two-sided")
STATISTICS = ("window", "auc")
ROLES = ("gate", "comparison")
BUDGET_AXES = ("iterations",)
_REQUIRED = ("name", "tree_hash", "correction", "looks", "iterations", "budget_axis", "tasks", "arms", "hypotheses",
             "settings", "must_equal", "may_differ", "incomplete_looks")


@dataclass(frozen=True)
class Statistic:
    """``kind`` ``"window"`` or ``"auc"`` over the evaluation iterations ``start`` to ``end`` (inclusive)."""

    kind: str
    start: int
    end: int


@dataclass(frozen=True)
class Hypothesis:
    """One registered comparison: ``arm`` minus ``reference`` on ``task`` by ``statistic``, tested with
    ``alternative``; ``role`` gate or comparison; optional ``smallest_effect`` and ``equivalence_margin``."""

    id: str
    task: str
    arm: str
    reference: str
    alternative: str
    statistic: Statistic
    role: str
    smallest_effect: float | None = None
    equivalence_margin: float | None = None


@dataclass(frozen=True)
class Look:
    """A look: the ``seeds`` analysed there (every earlier look's included) and its ``alpha``."""

    seeds: tuple[int, ...]
    alpha: float


@dataclass(frozen=True)
class Registration:
    path: Path
    name: str
    tree_hash: str | None
    looks: tuple[Look, ...]
    iterations: int
    budget_axis: str
    tasks: tuple[str, ...]
    arms: tuple[str, ...]
    hypotheses: tuple[Hypothesis, ...]
    settings: dict
    must_equal: tuple[str, ...]
    may_differ: tuple[str, ...]
    incomplete_looks: str
    raw: dict


class RegistrationError(ValueError):
    """A registration file that is not one: the message names the file and the key."""


def _fail(path: Path, msg: str):
    raise RegistrationError(f"{path}: {msg}")


def _number(path: Path, where: str, v, *, positive: bool = True) -> float:
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or (positive and v <= 0):
        _fail(path, f"{where} must be a {'positive ' if positive else ''}finite number, got {v!r}")
    return float(v)


def _integer(path: Path, where: str, v, minimum: int = 0) -> int:
    if not isinstance(v, int) or isinstance(v, bool) or v < minimum:
        _fail(path, f"{where} must be an integer >= {minimum}, got {v!r}")
    return v


def parse_registration(data, path: Path | str = "<registration>") -> Registration:
    """The :class:`Registration` of a loaded JSON object; RegistrationError naming ``path`` and the key."""
    path = Path(path)
    if not isinstance(data, dict):
        _fail(path, f"a registration is a JSON object, got {type(data).__name__}")
    missing = [k for k in _REQUIRED if k not in data]
    if missing:
        _fail(path, f"missing key(s): {', '.join(missing)}")
    th = data["tree_hash"]
    if th is not None and not (isinstance(th, str) and th.startswith("sha256:") and len(th) == 71):
        _fail(path, f"tree_hash must be null (not pinned yet) or 'sha256:' and 64 hex digits, got {th!r}")
    if data["correction"] != "holm":
        _fail(path, f"correction must be 'holm', got {data['correction']!r}")
    if not isinstance(data["looks"], list) or not data["looks"]:
        _fail(path, "looks must be a non-empty list of {\"seeds\": [...], \"alpha\": a}")
    looks, previous = [], set()
    for i, lk in enumerate(data["looks"]):
        where = f"looks[{i}]"
        if not isinstance(lk, dict) or set(lk) - {"seeds", "alpha"} or "seeds" not in lk or "alpha" not in lk:
            _fail(path, f"{where} must be {{\"seeds\": [...], \"alpha\": a}}, got {lk!r}")
        seeds = lk["seeds"]
        if not isinstance(seeds, list) or not seeds or len(set(map(repr, seeds))) != len(seeds):
            _fail(path, f"{where}.seeds must be a non-empty list of distinct seeds, got {seeds!r}")
        seeds = [_integer(path, f"{where}.seeds", s) for s in seeds]
        if not previous < set(seeds):
            _fail(path, f"{where}.seeds must hold every earlier look's seeds and more")
        alpha = _number(path, f"{where}.alpha", lk["alpha"])
        if alpha >= 1:
            _fail(path, f"{where}.alpha must be below 1, got {alpha}")
        previous = set(seeds)
        looks.append(Look(tuple(seeds), alpha))
    familywise = _number(path, "familywise_alpha", data.get("familywise_alpha", 0.05))
    if sum(lk.alpha for lk in looks) > familywise + 1e-12:
        _fail(path, f"the looks' alphas sum to {sum(lk.alpha for lk in looks):g}, above the family-wise "
                    f"{familywise:g} (Bonferroni over the looks)")
    iterations = _integer(path, "iterations", data["iterations"], 1)
    if data["budget_axis"] not in BUDGET_AXES:
        _fail(path, f"budget_axis must be one of {', '.join(BUDGET_AXES)}, got {data['budget_axis']!r}")
    for key in ("tasks", "arms", "must_equal", "may_differ"):
        if not isinstance(data[key], list) or not all(isinstance(x, str) for x in data[key]):
            _fail(path, f"{key} must be a list of names")
    unknown = [a for a in data["arms"] if a not in ARMS]
    if unknown:
        _fail(path, f"arms: unknown arm(s) {', '.join(unknown)}; valid: {', '.join(ARMS)}")
    both = sorted(set(data["must_equal"]) & set(data["may_differ"]))
    if both:
        _fail(path, f"field(s) both in must_equal and may_differ: {', '.join(both)}")
    if not isinstance(data["settings"], dict):
        _fail(path, "settings must be an object of config field -> value")
    loose = sorted(set(data["settings"]) - set(data["must_equal"]))
    if loose:
        _fail(path, f"settings gives value(s) for field(s) not in must_equal: {', '.join(loose)}")
    if data["settings"].get("iters", iterations) != iterations:
        _fail(path, f"settings.iters {data['settings']['iters']} is not iterations {iterations}")
    if not isinstance(data["hypotheses"], list) or not data["hypotheses"]:
        _fail(path, "hypotheses must be a non-empty list")
    hyps, ids = [], set()
    for i, h in enumerate(data["hypotheses"]):
        where = f"hypotheses[{i}]"
        if not isinstance(h, dict):
            _fail(path, f"{where} must be an object")
        need = [k for k in ("id", "task", "arm", "reference", "alternative", "statistic", "role") if k not in h]
        if need:
            _fail(path, f"{where} has no {', '.join(need)}")
        hid = h["id"]
        if not isinstance(hid, str) or hid in ids:
            _fail(path, f"{where}.id must be a name of its own, got {hid!r}")
        ids.add(hid)
        where = f"hypothesis {hid}"
        if h["task"] not in data["tasks"]:
            _fail(path, f"{where}: task {h['task']!r} is not among tasks {data['tasks']}")
        for k in ("arm", "reference"):
            if h[k] not in data["arms"]:
                _fail(path, f"{where}: {k} {h[k]!r} is not among arms {data['arms']}")
        if h["arm"] == h["reference"]:
            _fail(path, f"{where}: arm and reference are both {h['arm']!r}")
        if h["alternative"] not in ALTERNATIVES:
            _fail(path, f"{where}: alternative must be one of {', '.join(ALTERNATIVES)}, got {h['alternative']!r}")
        if h["role"] not in ROLES:
            _fail(path, f"{where}: role must be one of {', '.join(ROLES)}, got {h['role']!r}")
        st = h["statistic"]
        if not isinstance(st, dict) or set(st) != {"kind", "from", "to"} or st["kind"] not in STATISTICS:
            _fail(path, f"{where}: statistic must be {{\"kind\": {' or '.join(STATISTICS)}, \"from\": i, "
                        f"\"to\": j}}, got {st!r}")
        lo, hi = _integer(path, f"{where}: statistic.from", st["from"], 1), _integer(path, f"{where}: statistic.to",
                                                                                       st["to"], 1)
        if not lo <= hi <= iterations:
            _fail(path, f"{where}: statistic window {lo}-{hi} must satisfy from <= to <= iterations ({iterations})")
        extra = {}
        for k in ("smallest_effect", "equivalence_margin"):
            if h.get(k) is not None:
                extra[k] = _number(path, f"{where}: {k}", h[k])
        hyps.append(Hypothesis(hid, h["task"], h["arm"], h["reference"], h["alternative"],
                               Statistic(st["kind"], lo, hi), h["role"], **extra))
    if not isinstance(data["incomplete_looks"], str) or not data["incomplete_looks"].strip():
        _fail(path, "incomplete_looks must state the policy as text")
    return Registration(path=path, name=str(data["name"]), tree_hash=th, looks=tuple(looks), iterations=iterations,
                        budget_axis=data["budget_axis"], tasks=tuple(data["tasks"]), arms=tuple(data["arms"]),
                        hypotheses=tuple(hyps), settings=dict(data["settings"]), must_equal=tuple(data["must_equal"]),
                        may_differ=tuple(data["may_differ"]), incomplete_looks=data["incomplete_looks"], raw=data)


def load_registration(path: Path | str) -> Registration:
    """Read and check a ``preregistration.json``; RegistrationError (a ValueError) naming the file and the key."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise RegistrationError(f"{path}: no such registration file") from None
    except (OSError, json.JSONDecodeError) as e:
        raise RegistrationError(f"{path}: not readable JSON ({type(e).__name__}: {e})") from None
    return parse_registration(data, path)


def pin(path: Path | str, value: str | None = None) -> str:
    """Write ``value`` (default: this copy's training tree hash) into the registration's ``tree_hash``, the rest
    of the file kept (key order too); returns the value. Refuses a registration already pinned to another."""
    reg = load_registration(path)
    value = value or tree_hash().value
    if reg.tree_hash not in (None, value):
        raise RegistrationError(f"{reg.path}: tree_hash is already pinned to {reg.tree_hash}; a registration is "
                                "pinned once, before its runs")
    data = dict(reg.raw, tree_hash=value)
    parse_registration(data, reg.path)
    atomic_write_text(reg.path, json.dumps(data, indent=2) + "\n")
    return value


# ------------------------------------------------------------------------------------------ runs against it
def run_arm(run) -> str | None:
    """The vocabulary arm of a loaded run (``ablations.run_folder.Run``), None where no arm is."""
    cfg = run.config
    return arm_of(str(cfg.get("mode")), cfg.get("raster_model"), run.setting("preset"))


def check_runs(reg: Registration, runs) -> list[str]:
    """Why each run cannot be analysed under ``reg``, one line a reason naming the run (empty: every run fits):
    a tree hash other than the pinned one (or none), a registered field whose value differs from the
    registration's, a field of ``must_equal`` without a registered value that differs between runs of one task
    and arm, a task, arm or seed the registration does not have. Raises RegistrationError for a registration
    whose tree hash is not pinned."""
    if reg.tree_hash is None:
        raise RegistrationError(f"{reg.path}: tree_hash is not pinned (ablate-plan --pin --registration {reg.path}): "
                                "no run can be checked against it")
    problems: list[str] = []
    first: dict[tuple, tuple[str, object]] = {}
    seeds = set(reg.looks[-1].seeds)
    for run in runs:
        name = str(run.path)
        if run.tree_hash != reg.tree_hash:
            problems.append(f"{name}: tree hash {run.tree_hash or 'not recorded'}, registered {reg.tree_hash}")
        arm = run_arm(run)
        if run.task not in reg.tasks or arm not in reg.arms or run.seed not in seeds:
            problems.append(f"{name}: task {run.task!r}, arm {arm!r}, seed {run.seed!r} is not registered")
        # a field neither list names (one this code's registration did not know) is held like must_equal's
        unlisted = sorted(set(run.config) - set(reg.must_equal) - set(reg.may_differ) - {"seed"})
        for field in (*reg.must_equal, *unlisted):
            value = run.config.get(field)
            if field in reg.settings:
                if value != reg.settings[field]:
                    problems.append(f"{name}: {field} is {value!r}, registered {reg.settings[field]!r}")
                continue
            key = (run.task, arm, field)
            if key in first and first[key][1] != value:
                problems.append(f"{name}: {field} is {value!r}, but {first[key][0]} of the same task and arm has "
                                f"{first[key][1]!r}")
            first.setdefault(key, (name, value))
    return problems
