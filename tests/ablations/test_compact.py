"""Compacting a run folder for shipping keeps every number the readers see, and runs keep writing plain files."""

from __future__ import annotations

import json

import pytest

from ablations.compact import compact_folder, main
from ablations.run_folder import RunFolder, find_runs, load_run, read_metrics
from tests.ablations.conftest import write_run


def test_a_compacted_folder_reads_as_the_plain_one(tmp_path):
    run = write_run(tmp_path / "plain", task="hopper", mode="full", seed=1, iters=30)
    with open(run / "metrics.jsonl", "a") as f:
        f.write('{"iter": 31, "ret')  # a torn last line stays torn, and ignored
    plain_bytes = {n: (run / n).read_bytes() for n in ("metrics.jsonl", "summary.json")}
    before = load_run(run)
    done = compact_folder(run)
    assert sorted(p.name for p, _, _ in done) == ["metrics.jsonl.xz", "summary.json.xz"]
    assert sorted(p.name for p in run.iterdir()) == ["config.json", "git.txt", "metrics.jsonl.xz", "summary.json.xz"]
    after = load_run(run)
    assert after.metrics == before.metrics and len(after.metrics) == 30
    assert after.summary == before.summary and after.config == before.config
    assert read_metrics(run) == before.metrics
    assert [r.metrics for r in find_runs([tmp_path])] == [before.metrics]
    # lossless to the byte, and deterministic: no time or name in the stream, so a second folder of the same
    # bytes compacts to the same files
    import lzma

    assert {n: lzma.decompress((run / f"{n}.xz").read_bytes()) for n in plain_bytes} == plain_bytes
    twin = write_run(tmp_path / "twin", task="hopper", mode="full", seed=1, iters=30)
    (twin / "metrics.jsonl").write_bytes(plain_bytes["metrics.jsonl"])
    compact_folder(twin)
    for name in ("metrics.jsonl.xz", "summary.json.xz"):
        assert (twin / name).read_bytes() == (run / name).read_bytes()
    assert compact_folder(run) == []  # nothing left to compact


def test_the_command_compacts_every_ended_run_below_a_folder_and_refuses_a_running_one(tmp_path, capsys):
    for seed in (0, 1):
        write_run(tmp_path / "exp" / "population_a", task="cartpole", mode="decoupled", seed=seed)
    running = write_run(tmp_path / "exp" / "population_b", task="cartpole", mode="decoupled", seed=2,
                        summary=False)
    assert main([str(tmp_path / "exp")]) == 2
    assert "has no summary.json" in capsys.readouterr().err
    assert not list((tmp_path / "exp").rglob("*.xz"))  # checked before any folder is changed
    assert main([str(tmp_path / "exp" / "population_a")]) == 0
    assert "2 run folder(s)" in capsys.readouterr().out
    assert len(list((tmp_path / "exp").rglob("*.xz"))) == 4 and (running / "metrics.jsonl").exists()
    assert main([str(tmp_path / "nothing")]) == 2


def test_a_live_run_writes_plain_metrics_and_a_plain_file_wins_over_a_compacted_copy(tmp_path):
    folder = RunFolder.create(tmp_path, "r")
    folder.write_config({"config": {"task": "cartpole", "mode": "state"}})
    folder.append_metrics({"iter": 1, "return_mean": 1.0})
    folder.write_summary({"status": "finished"})
    assert sorted(p.name for p in folder.path.iterdir()) == ["config.json", "metrics.jsonl", "summary.json"]
    compact_folder(folder.path)
    assert folder.read_metrics() == [{"iter": 1, "return_mean": 1.0}]
    assert folder.read_summary() == {"status": "finished"}
    # lines appended after compacting (a compacted folder is for reading, not for resuming) are what is read
    folder.append_metrics({"iter": 2, "return_mean": 2.0})
    assert folder.read_metrics() == [{"iter": 2, "return_mean": 2.0}]


def test_a_damaged_compacted_file_is_an_error_naming_it(tmp_path):
    run = write_run(tmp_path, task="hopper", mode="full", seed=0)
    compact_folder(run)
    (run / "metrics.jsonl.xz").write_bytes(b"not xz")
    with pytest.raises(OSError, match=r"metrics\.jsonl\.xz does not decompress"):
        read_metrics(run)
    (run / "summary.json.xz").write_bytes(b"not xz")
    assert RunFolder(run).read_summary() is None  # as for a summary that does not parse
    assert json.loads((run / "config.json").read_text())["config"]["task"] == "hopper"
