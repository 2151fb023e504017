"""The names of run folders: one scheme for a run alone, a population and its members, and the sweep's runs.

``ablate`` names a run alone ``<task>_<mode>_seed<seed>_<date>-<time>``, a population
``<task>_population<N>_<date>-<time>`` and each member inside it ``<task>_<mode>[_<what sets it apart>]_seed<seed>``
(:func:`folder_name`, :func:`member_name`). A sweep names its runs ``<task>_<arm or mode>_seed<seed>[_<flag><value>]``
and its populations ``<task>_population<k>`` (:func:`sweep_run_id`, :func:`sweep_population_id`): the names its
existing folders and manifests hold. Flag values are written into every name by :func:`slug`. Kept apart from the
modules that train, so that the sweep and the run path both name folders from here without importing each other.
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from vocabulary import MEMBER_FIELDS

__all__ = ["slug", "member_name", "folder_name", "claim_folder", "sweep_run_id", "sweep_population_id"]


def slug(value: Any) -> str:
    """A flag value as a piece of a folder name."""
    text = " ".join(str(v) for v in value) if isinstance(value, (list, tuple)) else str(value)
    return re.sub(r"[^A-Za-z0-9.+]+", "-", text).strip("-") or "none"


def member_name(cfg, members: Sequence) -> str:
    """A member's run folder name: task, mode, the member settings that differ between members and that it sets
    (a raster model or preset by its name, another setting as name-value), seed; e.g. ``hopper_full_hard_seed0``
    beside ``hopper_full_seed0``. A member alone (a single run) is ``<task>_<mode>_seed<seed>``."""
    varying = [k for k in MEMBER_FIELDS if k not in ("mode", "seed")
               and len({repr(getattr(c, k)) for c in members}) > 1 and getattr(cfg, k) is not None]
    # values as the sweep writes them into folder names (a tuple such as betas: "betas0.5-0.9", not "(0.5, 0.9)")
    labels = [str(getattr(cfg, k)) if k in ("raster_model", "preset")
              else f"{k.replace('_', '-')}{slug(getattr(cfg, k))}" for k in varying]
    return "_".join([cfg.task, cfg.mode, *labels, f"seed{cfg.seed}"])


def folder_name(members: Sequence) -> str:
    """The folder ``ablate`` makes when ``--name`` is not given: a run alone's, or a population's (which holds
    one folder per member, :func:`member_name`)."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    if len(members) == 1:
        return f"{member_name(members[0], members)}_{stamp}"
    return f"{members[0].task}_population{len(members)}_{stamp}"


def claim_folder(parent: str | os.PathLike, name: str) -> str:
    """Create the new, empty folder ``parent/name`` and return its name; where it exists (another ``ablate`` that
    started in the same second with the same settings), ``name_2``, ``name_3``, ... : creating a folder is atomic,
    so two starts never share one. ``parent`` must exist."""
    candidate, k = name, 1
    while True:
        try:
            (Path(parent) / candidate).mkdir()
            return candidate
        except FileExistsError:
            k += 1
            candidate = f"{name}_{k}"


def sweep_run_id(task: str, column: str, seed: int, flags: dict) -> str:
    """A sweep run's folder: its task, arm (or mode), seed and each ``--vary`` flag's value."""
    return f"{task}_{column}_seed{seed}" + "".join(f"_{name.replace('_', '-')}{slug(value)}"
                                                   for name, value in flags.items())


def sweep_population_id(task: str, k: int) -> str:
    """The folder of a sweep's ``k``-th population of ``task`` (``--pack``)."""
    return f"{task}_population{k}"
