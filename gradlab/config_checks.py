"""Checks of configuration values whose errors name the command-line flag as the user typed it.

``SHACConfig.validate`` and the checks of the options a command adds to it raise these, so that every
bad value is one line that starts with its flag (``--num-envs must be a positive integer, got 0``), NaN included.
"""

from __future__ import annotations

import math

__all__ = ["flag", "check_integers", "check_number"]


def flag(name: str) -> str:
    """The command-line flag of a config field: ``num_envs`` -> ``--num-envs``."""
    return "--" + name.replace("_", "-")


def check_integers(cfg, names: tuple[str, ...], *, minimum: int, optional: bool = False) -> None:
    """Each field of ``cfg`` in ``names`` is an integer >= ``minimum`` (or None where ``optional``); ValueError
    naming the flag otherwise."""
    for name in names:
        v = getattr(cfg, name)
        if optional and v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
            kind = {0: "a non-negative integer", 1: "a positive integer"}.get(minimum, f"an integer >= {minimum}")
            raise ValueError(f"{flag(name)} must be {kind}, got {v!r}")


def check_number(name: str, value, interval: str, *, what: str | None = None) -> None:
    """``value`` is a number in ``interval`` ("(0, 1]", "[0, inf)", "(0, inf]": brackets include the end, inf only
    where its bracket is closed; NaN never); ValueError naming the flag (``what``, default ``--<name>``)."""
    low, high = (x.strip() for x in interval[1:-1].split(","))
    lo, hi = float(low), float(high)
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and not math.isnan(value)
    if ok:
        above = value >= lo if interval[0] == "[" else value > lo
        below = value <= hi if interval[-1] == "]" else value < hi
        ok = above and below
    if not ok:
        raise ValueError(f"{what or flag(name)} must be in {interval}, got {value!r}")
