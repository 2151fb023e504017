"""``ablate-sweep`` on a machine of several GPUs: one job a GPU, and the sweep folder says which. A local Ray
cluster that declares two GPUs (no GPU is touched: the stand-in ablate only records what it was given)."""

from __future__ import annotations

import json
import logging
import sys

import pytest

from ablations.sweep import SweepConfig, run_sweep

from .test_sweep import FAKE_ABLATE, TINY


@pytest.fixture(scope="module")
def two_gpu_cluster():
    ray = pytest.importorskip("ray")
    if ray.is_initialized():  # another module's cluster: this one needs its own resources
        ray.shutdown()
    ray.init(address="local", num_cpus=2, num_gpus=2, include_dashboard=False, logging_level=logging.WARNING,
             log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.mark.usefixtures("two_gpu_cluster")
@pytest.mark.slow
def test_each_job_gets_a_gpu_of_its_own_and_the_manifest_and_status_lines_name_it(tmp_path, capsys):
    """Two runs, one GPU each (--gpus-per-run 1, --pack 1), at once: each process sees its own GPU
    (CUDA_VISIBLE_DEVICES, set by Ray), sweep.json records that GPU and the host beside each run, and the
    run's status line names them."""
    out, log = tmp_path / "sweep", tmp_path / "runs.jsonl"
    cfg = SweepConfig(out=out, tasks=("cartpole",), modes=("decoupled",), seeds=(0, 1), set=TINY, progress=False,
                      gpus_per_run=1.0, cpus_per_run=1.0, pack="1")
    manifest = run_sweep(cfg, program=(sys.executable, str(FAKE_ABLATE), "record", str(log), "3", "--"))
    runs = manifest["runs"]
    assert {r["status"] for r in runs.values()} == {"done"}
    seen = {json.loads(line)["run"]: json.loads(line) for line in log.read_text().splitlines()}
    assert set(seen) == set(runs)
    for run_id, rec in runs.items():
        assert rec["gpus"] is not None and len(rec["gpus"]) == 1 and rec["host"]
        assert seen[run_id]["cuda_visible_devices"] == rec["gpus"][0]
    assert sorted(r["gpus"][0] for r in runs.values()) == ["0", "1"]
    a, b = seen.values()
    assert a["start"] < b["end"] and b["start"] < a["end"]  # at once, on different GPUs
    assert json.loads((out / "sweep.json").read_text())["runs"] == runs
    printed = capsys.readouterr().out
    for run_id, rec in runs.items():
        assert f"done     {run_id}" in printed and f"on {rec['host']} GPU {rec['gpus'][0]}" in printed
