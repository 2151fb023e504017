"""Jobs: the Ray tasks of a sweep, each one ``ablate`` process that trains one run or a population of runs.

``--pack N`` packs the runs that can share a process (the same group of :func:`~ablations.sweep.grid.plan`: the
same task and every setting but a member's own) into populations of at most N members, one ``ablate --member
...`` process each; a group larger than N is dealt round-robin into as few populations as hold it, so that their
sizes differ by one at most and each mixes the group's arms and seeds alike. A population's folder is
``runs/<task>_population<k>/`` (population.json and one run folder per member, named by ablate's
``ablations.naming.member_name``); a run alone keeps ``runs/<run_id>/``.

A rerun keeps every run whose job folder exists in the job the manifest records for it (whatever --pack says
now), so that nothing trained is lost or trained twice; only runs without one are packed anew.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import tyro

from ablations.naming import member_name, sweep_population_id
from ablations.run_config import AblateConfig, RunConfig, shac_part
from ablations.sweep.grid import RUN_ARGS, RunSpec
from gradlab.roster import Roster

__all__ = ["Job", "pack_runs", "assign_jobs", "member_entry"]


@dataclass(frozen=True)
class Job:
    """One Ray task: one ``ablate`` process and its folder ``runs/<job_id>/``."""

    job_id: str
    #: The runs it trains, by run id.
    run_ids: tuple[str, ...]
    #: Each run's folder inside the job's folder, in ``run_ids``' order; ``("",)``: the job's folder is the run's.
    members: tuple[str, ...]
    #: ``ablate`` arguments of a fresh start, without --out/--name/--progress (the worker adds those).
    args: tuple[str, ...]
    #: --iters of its runs (a setting they share).
    iters: int

    @property
    def population(self) -> bool:
        return self.members != ("",)

    def folder(self, i: int) -> str:
        """Run ``i``'s folder, relative to the sweep folder."""
        return (Path("runs") / self.job_id / self.members[i]).as_posix()

    def record(self) -> dict:
        """What sweep.json keeps of it (its ``jobs`` table)."""
        return {"runs": list(self.run_ids), "members": list(self.members), "args": list(self.args),
                "iters": self.iters, "folder": (Path("runs") / self.job_id).as_posix()}

    @classmethod
    def from_record(cls, job_id: str, rec: dict) -> Job:
        return cls(job_id=job_id, run_ids=tuple(rec["runs"]), members=tuple(rec["members"]), args=tuple(rec["args"]),
                   iters=int(rec["iters"]))


def alone(spec: RunSpec) -> Job:
    """The job of a run that trains in a process of its own (today's layout: ``runs/<run_id>/``)."""
    return Job(job_id=spec.run_id, run_ids=(spec.run_id,), members=("",), args=spec.args, iters=spec.iters)


def member_entry(own: dict) -> str:
    """A run's own settings as one ``ablate --member`` value: ``mode=full,seed=0,preset=shac-diffrender``; lists
    as ``a/b`` (``betas=0.7/0.95``). ValueError for a value that a member entry cannot hold."""
    parts = []
    for name, value in own.items():
        if isinstance(value, bool):
            text = "true" if value else "false"
        elif isinstance(value, (list, tuple)):
            text = "/".join(str(v) for v in value)
        else:
            text = "/".join(str(value).split()) if value is not None else "none"
        if "," in text or "=" in text or not text:
            raise ValueError(f"--{name.replace('_', '-')} {value!r}: a population member's value holds no ',' or "
                             f"'='; --pack 1 trains such runs alone")
        parts.append(f"{name}={text}")
    return ",".join(parts)


def _population(job_id: str, specs: list[RunSpec]) -> Job:
    """The population job of ``specs`` (one group), checked: ablate's own parser makes of its arguments exactly
    these runs, and the trainer accepts them as one population. Member folder names are ablate's."""
    args = (*specs[0].shared, "--member", *(member_entry(s.own) for s in specs))
    ids = ", ".join(s.run_id for s in specs)
    try:
        members = tyro.cli(AblateConfig, args=[*args, *RUN_ARGS]).members()
        Roster.of([shac_part(m) for m in members])
    except SystemExit:  # tyro has printed what it rejected
        raise ValueError(f"runs {ids}: ablate rejects their population's flags: {' '.join(args)}") from None
    except ValueError as e:
        raise ValueError(f"runs {ids} cannot share a process ({e}); --pack 1 trains each alone") from None
    for spec, member in zip(specs, members):
        alone_cfg = tyro.cli(RunConfig, args=[*spec.args, *RUN_ARGS])
        if member != alone_cfg:
            differ = [f.name for f in dataclasses.fields(RunConfig) if getattr(member, f.name) !=
                      getattr(alone_cfg, f.name)]
            raise ValueError(f"run {spec.run_id}: as a population member its {', '.join(differ)} would differ from "
                             f"the run alone; --pack 1 trains it alone")
    return Job(job_id=job_id, run_ids=tuple(s.run_id for s in specs),
               members=tuple(member_name(m, members) for m in members), args=args, iters=specs[0].iters)


def pack_runs(specs: list[RunSpec], size: int, *, taken: Iterable[str] = ()) -> list[Job]:
    """The jobs that train ``specs``: each group (in order of first appearance) dealt round-robin into
    ceil(n / size) populations; a population of one is a run alone. ``taken``: job ids in use (a new population
    takes the lowest free ``<task>_population<k>``)."""
    if size < 1:
        raise ValueError(f"--pack must be at least 1, got {size}")
    groups: dict[str, list[RunSpec]] = {}
    for spec in specs:
        groups.setdefault(spec.group, []).append(spec)
    used = set(taken) | {s.run_id for s in specs}
    jobs = []
    for group in groups.values():
        count = math.ceil(len(group) / size)
        for part in (group[i::count] for i in range(count)):
            if len(part) == 1:
                jobs.append(alone(part[0]))
                continue
            k = 0
            while sweep_population_id(part[0].task, k) in used:
                k += 1
            used.add(job_id := sweep_population_id(part[0].task, k))
            jobs.append(_population(job_id, part))
    order = {s.run_id: i for i, s in enumerate(specs)}
    return sorted(jobs, key=lambda j: order[j.run_ids[0]])


def assign_jobs(specs: list[RunSpec], size: int, manifest: dict, sweep_dir: str | Path) -> list[Job]:
    """The jobs of a (re)run: a run whose job folder exists stays in the job sweep.json records for it (a run
    alone where it records none: a sweep from before populations); the other runs are packed by
    :func:`pack_runs`."""
    sweep_dir = Path(sweep_dir)
    recorded = manifest.get("jobs") or {}
    runs = manifest.get("runs") or {}
    kept: dict[str, Job] = {}
    free = []
    for spec in specs:
        job_id = runs[spec.run_id].get("job", spec.run_id) if spec.run_id in runs else None
        known = job_id == spec.run_id or job_id in recorded
        if job_id is not None and known and (sweep_dir / "runs" / job_id).is_dir():
            if job_id not in kept:
                kept[job_id] = Job.from_record(job_id, recorded[job_id]) if job_id in recorded else alone(spec)
        else:
            free.append(spec)
    taken = set(kept) | {p.name for p in (sweep_dir / "runs").glob("*")}
    jobs = [*kept.values(), *pack_runs(free, size, taken=taken)]
    order = {s.run_id: i for i, s in enumerate(specs)}
    return sorted(jobs, key=lambda j: min(order.get(r, len(order)) for r in j.run_ids))
