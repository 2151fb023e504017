"""Return floors: what a policy that does nothing, or acts at random, scores on each task.

A learning curve means little without them: D.Va's cartpole, whose joint springs swing the pole up on their
own, scores about 2100 of a possible 2400 per episode with zero action, while the spring-free swing-up scores
under 200. :func:`action_floors` measures the mean and standard deviation of the undiscounted episode return
for zero action and for actions drawn uniformly from [-1, 1] at every step; ``task-floors`` runs it for
several tasks, writes the numbers to a JSON file and prints a table.

Every environment runs the same number of whole episodes (``ceil(episodes / num_envs)``), so episodes that
terminate early are not over-represented, as they would be if the first ``episodes`` episodes to finish were
kept. Both policies start from the same seeded reset states; the random actions come from a CPU generator
seeded with ``seed``, so they are the same on every device.
"""

from __future__ import annotations

import json
import math
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
from tqdm import tqdm

from .command_line import fail as _fail
from .command_line import usable_cores
from .device import resolve_device
from .registry import TASKS, make
from .task import Task

__all__ = ["POLICIES", "SHIPPED", "FloorsConfig", "action_floors", "main", "rollout_returns"]

#: the action policies whose returns are measured
POLICIES: tuple[str, ...] = ("zero", "random")


@torch.no_grad()
def rollout_returns(
    env: Task,
    *,
    policy: Literal["zero", "random"],
    episodes_per_env: int,
    generator: torch.Generator | None = None,
    progress: tqdm | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Reset ``env`` and run every environment for ``episodes_per_env`` whole episodes.

    policy: "zero" (all actions 0) or "random" (uniform in [-1, 1), drawn on the CPU from ``generator``).
    progress: a tqdm bar advanced by one per finished episode that is counted.
    Returns ``(returns, lengths)``, each of shape (num_envs * episodes_per_env,): the undiscounted return
    and the number of control steps of every counted episode (float64, CPU).
    """
    if policy not in POLICIES:
        raise ValueError(f"policy must be one of {POLICIES}, got {policy!r}")
    if not (isinstance(episodes_per_env, int) and episodes_per_env >= 1):
        raise ValueError(f"episodes_per_env must be a positive int, got {episodes_per_env!r}")
    if policy == "random" and generator is None:
        raise ValueError("policy 'random' needs a torch.Generator")
    B, A = env.num_envs, env.num_act
    env.reset()
    running = torch.zeros(B, dtype=torch.float64, device=env.device)
    steps = torch.zeros(B, dtype=torch.long, device=env.device)
    finished = torch.zeros(B, dtype=torch.long, device=env.device)
    returns = torch.zeros(B, episodes_per_env, dtype=torch.float64, device=env.device)
    lengths = torch.zeros(B, episodes_per_env, dtype=torch.float64, device=env.device)
    rows = torch.arange(B, device=env.device)
    zero = torch.zeros(B, A, dtype=env.dtype, device=env.device)
    # no episode lasts longer than episode_length steps, so this bound is never the reason the loop ends
    for _ in range(episodes_per_env * env.episode_length):
        if policy == "zero":
            action = zero
        else:
            action = (torch.rand(B, A, generator=generator, dtype=torch.float64) * 2 - 1).to(env.device, env.dtype)
        _, reward, done, _ = env.step(action)
        running += reward.to(torch.float64)
        steps += 1
        count = done & (finished < episodes_per_env)
        if bool(count.any()):
            slot = finished.clamp(max=episodes_per_env - 1)
            returns[rows[count], slot[count]] = running[count]
            lengths[rows[count], slot[count]] = steps[count].to(torch.float64)
            finished += count.long()
            if progress is not None:
                progress.update(int(count.sum()))
        running = torch.where(done, 0.0, running)
        steps = torch.where(done, 0, steps)
        if bool((finished >= episodes_per_env).all()):
            break
    return returns.flatten().cpu(), lengths.flatten().cpu()


def action_floors(
    task: str,
    *,
    episodes: int,
    num_envs: int,
    seed: int = 0,
    device: str | torch.device = "cpu",
    overrides: dict[str, Any] | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Mean and standard deviation of the undiscounted episode return of ``task`` under zero action and under
    uniform random actions in [-1, 1].

    episodes: at least this many episodes per policy; each of the ``num_envs`` environments runs
    ``ceil(episodes / num_envs)`` of them. seed: the task's reset seed and the random actions' seed.
    device: "auto", "cpu", "cuda[:N]" or a torch.device (:func:`tasks.device.resolve_device`).
    overrides: task config fields (:func:`tasks.make`).
    progress: show a tqdm bar per policy on stderr.
    Returns ``{"task", "episode_length", "episodes", "num_envs", "seed", "device", "overrides", "zero",
    "random"}``; each policy entry holds ``mean``, ``std`` (population), ``min``, ``max`` of the return,
    ``mean_length`` [control steps] and ``episodes`` (the number counted).
    """
    if not (isinstance(episodes, int) and episodes >= 1):
        raise ValueError(f"episodes must be a positive int, got {episodes!r}")
    if not (isinstance(num_envs, int) and num_envs >= 1):
        raise ValueError(f"num_envs must be a positive int, got {num_envs!r}")
    dev = resolve_device(device)
    per_env = math.ceil(episodes / num_envs)
    out: dict[str, Any] = {
        "task": task,
        "episodes": per_env * num_envs,
        "num_envs": num_envs,
        "seed": seed,
        "device": dev.type,
        "overrides": dict(overrides or {}),
    }
    for policy in POLICIES:
        env = make(task, num_envs, device=dev, seed=seed, **(overrides or {}))
        out["episode_length"] = env.episode_length
        generator = torch.Generator().manual_seed(seed)
        bar = tqdm(total=per_env * num_envs, desc=f"{task} {policy}", unit="ep", disable=not progress, file=sys.stderr)
        with bar:
            ret, length = rollout_returns(
                env,
                policy=policy,
                episodes_per_env=per_env,
                generator=generator,
                progress=bar,  # type: ignore[arg-type]
            )
        out[policy] = {
            "mean": ret.mean().item(),
            "std": ret.std(correction=0).item(),
            "min": ret.min().item(),
            "max": ret.max().item(),
            "mean_length": length.mean().item(),
            "episodes": ret.numel(),
        }
    return out


def _write_json_atomic(path: Path, data: dict) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and ``os.replace``, so a reader
    never sees a half-written file; readable by others as the umask allows (mkstemp's file is 0600)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=2)
            f.write("\n")
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def format_table(results: dict[str, dict[str, Any]]) -> str:
    """A plain-text table of :func:`action_floors` results keyed by task name."""
    head = f"{'task':<18}{'ep len':>7}{'episodes':>9}  {'zero action':>20}  {'random action':>20}"
    head += f"  {'mean length z/r':>16}"
    lines = [head, "-" * len(head)]
    for name, r in results.items():
        z, u = r["zero"], r["random"]
        zs = f"{z['mean']:.1f} +- {z['std']:.1f}"
        us = f"{u['mean']:.1f} +- {u['std']:.1f}"
        ls = f"{z['mean_length']:.0f} / {u['mean_length']:.0f}"
        lines.append(f"{name:<18}{r['episode_length']:>7}{r['episodes']:>9}  {zs:>20}  {us:>20}  {ls:>16}")
    return "\n".join(lines)


@dataclass
class FloorsConfig:
    """Undiscounted episode returns of zero and of uniform random actions in [-1, 1] per task (the floors a
    learning curve should be read against). Writes JSON and prints a table."""

    # Each field's docstring (its --help) is one source line: tyro breaks the help text where a line ends.

    tasks: tuple[str, ...] = TASKS
    """Tasks to measure."""
    episodes: int = 32
    """Episodes per task and policy, at least: each environment runs ceil(episodes / num-envs) whole ones."""
    num_envs: int = 16
    """Environments stepped in parallel."""
    seed: int = 0
    """Reset seed and random-action seed."""
    device: str = "auto"
    """Where to simulate: auto (CUDA when available, else CPU), cpu or cuda[:N]."""
    out: Path = Path("floors.json")
    # Readers (plots, reports, ablate's closing lines) take the shipped docs/floors.json: updating it is a choice.
    """JSON file to write (other tasks' entries kept unless --fresh); the shipped docs/floors.json only where named."""
    fresh: bool = False
    """Start from an empty file instead of merging into --out."""
    threads: int = 1
    """CPU threads for torch (the simulator's tensors are small: more threads mostly add synchronisation)."""
    progress: bool = True
    """Progress bars per task and policy (--no-progress hides them)."""

    def validate(self) -> torch.device:
        """The device to simulate on; ValueError naming the flag of the first bad value, before any work."""
        unknown = [t for t in self.tasks if t not in TASKS]
        if unknown or not self.tasks:
            raise ValueError(f"--tasks: unknown task(s) {unknown or '(none given)'}; known tasks: {', '.join(TASKS)}")
        for flag, value in (("--episodes", self.episodes), ("--num-envs", self.num_envs), ("--threads", self.threads)):
            if value < 1:
                raise ValueError(f"{flag} must be >= 1, got {value}")
        if self.out.is_dir():
            raise ValueError(f"--out {self.out} is a folder; give the JSON file to write")
        if self.threads > usable_cores():
            raise ValueError(f"--threads {self.threads} is more than the {usable_cores()} cores this process may "
                             f"use (its CPU affinity); give at most {usable_cores()}")
        try:
            return resolve_device(self.device)
        except ValueError as e:
            message = str(e)
            raise ValueError(message if message.startswith("--device") else f"--device: {message}") from None


#: The floors this checkout ships, which every reader of floors takes unless given another file.
SHIPPED = Path(__file__).resolve().parents[1] / "docs" / "floors.json"


def main(argv: list[str] | None = None) -> int:
    """Console entry point ``task-floors`` (``--help`` lists the flags); bad flags exit with status 2 and one
    line naming the flag."""
    from .command_line import cli, scan

    argv = list(sys.argv[1:] if argv is None else argv)
    cfg = cli(FloorsConfig, argv, prog="task-floors")
    try:
        device = cfg.validate()
    except ValueError as e:
        _fail(str(e))
    if cfg.out.resolve() == SHIPPED and not any(g.key == "out" for g in scan(argv)):
        _fail(f"the default --out {cfg.out} here is the shipped {SHIPPED}: run it from another folder, or name "
              f"--out to update the shipped floors")
    torch.set_num_threads(cfg.threads)
    data: dict[str, Any] = {"tasks": {}}
    if cfg.out.exists() and not cfg.fresh:
        try:
            old = json.loads(cfg.out.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            _fail(f"--out {cfg.out} is not a readable JSON file ({e}); pass --fresh to overwrite it")
        if isinstance(old, dict) and isinstance(old.get("tasks"), dict):
            data = old
    data["description"] = (
        "Undiscounted episode return (mean, population std, min, max) and mean episode length in control steps "
        "of zero action and of uniform random actions in [-1, 1], per task; written by task-floors."
    )
    for name in cfg.tasks:
        data["tasks"][name] = action_floors(
            name,
            episodes=cfg.episodes,
            num_envs=cfg.num_envs,
            seed=cfg.seed,
            device=device,
            progress=cfg.progress,
        )
        try:
            _write_json_atomic(cfg.out, data)  # after every task, so a long run keeps what it has measured
        except OSError as e:
            _fail(f"--out {cfg.out}: cannot be written ({e.strerror or e})")
    # entries kept from an older file are shown too, when they have the fields of a measurement
    shown = {n: r for n, r in data["tasks"].items() if isinstance(r, dict) and all(p in r for p in POLICIES)}
    print(format_table(shown))
    print(f"wrote {cfg.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
