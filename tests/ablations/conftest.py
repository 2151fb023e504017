"""Fixtures: small run folders in the format of ablations/runs.py, and the environment of the sweep seam."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def write_run(parent: Path, *, task: str, mode: str, seed: int, iters: int = 12, bwd_ms: float = 10.0,
              num_envs: int = 4, horizon: int = 8, image_size: int = 32, probe_every: int = 3,
              summary: bool = True, device: str = "cpu", gpu: str | None = None, name: str | None = None,
              settings: dict | None = None, started_utc: str | None = None, ended_utc: str | None = None,
              wall_per_iter: float | None = None) -> Path:
    """A run folder as `ablate` writes it: config.json, git.txt, metrics.jsonl and (optionally) summary.json.

    Metrics are smooth functions of the iteration and the seed, so tests can check aggregates exactly:
    return_mean = 10 * iter + seed (None for the first two iterations: no finished episode yet),
    grad_norm = 10 ** (seed + 1), bwd_ms = bwd_ms (+ 1000 on warm-up iterations 1-2 and probe iterations),
    wall_s = iter * wall_per_iter (default 1 + seed / 2: seeds run at different speeds). Probe iterations
    carry grad_norm_full = 2 + seed, grad_norm_decoupled = 1, cos_full_decoupled = cos(0.1 iter + seed), the
    render term 3 with its groups (encoder 2, mlp 1, log_std 0.5) and image_sensitivity_f0..f2 = 0.1, 0.2, 0.4.
    settings: more config entries (preset, raster_model, renderer, ...); started_utc/ended_utc: the times
    config.json and summary.json record.
    """
    run = parent / (name or f"{task}_{mode}_seed{seed}")
    run.mkdir(parents=True)
    config = dict(task=task, mode=mode, seed=seed, iters=iters, num_envs=num_envs, horizon=horizon,
                  image_size=image_size, warmup_iters=2, device=device, cosine_every=probe_every,
                  **(settings or {}))
    env = {"python": "3.11.7", "torch": "2.13.0+cpu", "platform": "Linux", "device": device, "hostname": "h"}
    if gpu:
        env.update(gpu=gpu, cuda="13.0")
    record = {"config": config, "environment": env,
              "command": ["ablate", "--task", task, "--mode", mode, "--seed", str(seed)]}
    if started_utc:
        record["started_utc"] = started_utc
    (run / "config.json").write_text(json.dumps(record))
    (run / "git.txt").write_text("commit 0123456789abcdef0123\nbranch main\ndirty False\n")
    lines = []
    wall = 0.0
    for it in range(1, iters + 1):
        probed = mode in ("full", "decoupled") and probe_every > 0 and (it - 1) % probe_every == 0
        wall += 1.0 + 0.5 * seed if wall_per_iter is None else wall_per_iter
        m = {
            "iter": it, "env_steps": it * num_envs * horizon, "wall_s": wall,
            "return_mean": None if it <= 2 else 10.0 * it + seed,
            "actor_loss": -1.0, "critic_loss": 0.5, "grad_norm": 10.0 ** (seed + 1), "grad_norm_clipped": 1.0,
            "fwd_ms": 5.0, "bwd_ms": bwd_ms + (1000.0 if it <= 2 or probed else 0.0), "critic_ms": 1.0,
            "iter_ms": 20.0, "peak_alloc_mb": 100.0 * (it % 3 + 1) if gpu else None,
            "peak_reserved_mb": 200.0 if gpu else None, "saved_mb": 3.0 + seed, "probed": probed,
        }
        if probed:
            m.update(cos_full_decoupled=math.cos(0.1 * it + seed), grad_norm_full=2.0 + seed, grad_norm_decoupled=1.0,
                     grad_norm_render_term=3.0, grad_norm_render_term_encoder=2.0, grad_norm_render_term_mlp=1.0,
                     grad_norm_render_term_log_std=0.5, image_sensitivity_f0=0.1, image_sensitivity_f1=0.2,
                     image_sensitivity_f2=0.4)
        lines.append(json.dumps(m))
    (run / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    if summary:
        (run / "summary.json").write_text(json.dumps({
            "status": "finished", "task": task, "mode": mode, "seed": seed, "iterations": iters,
            "env_steps": iters * num_envs * horizon, "final_return": 10.0 * iters + seed, "median_fwd_ms": 5.0,
            "median_bwd_ms": bwd_ms, "peak_alloc_mb": 300.0 if gpu else None, "median_saved_mb": 3.0 + seed,
            **({"ended_utc": ended_utc} if ended_utc else {})}))
    return run


@pytest.fixture
def fake_env(tmp_path, monkeypatch):
    """Environment for sweeps through tests.ablations.fake_workers: importable seam, call log, CSV checks.

    Returns a function ``configure(behaviour: dict, out: Path) -> Path`` that sets the behaviours and returns
    the log file.
    """
    # The worker processes import the fake from this checkout (a subprocess does not inherit pytest's sys.path).
    old = os.environ.get("PYTHONPATH")
    monkeypatch.setenv("PYTHONPATH", str(ROOT) + (os.pathsep + old if old else ""))
    log = tmp_path / "calls.jsonl"

    def configure(behaviour: dict | None = None, out: Path | None = None) -> Path:
        monkeypatch.setenv("FAKE_BEHAVIOUR", json.dumps(behaviour or {}))
        monkeypatch.setenv("FAKE_LOG", str(log))
        if out is not None:
            monkeypatch.setenv("FAKE_OUT", str(out))
        return log

    return configure


def calls(log: Path) -> list[dict]:
    """The fake worker's calls, in order."""
    if not log.exists():
        return []
    return [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
