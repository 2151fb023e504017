"""``ablate`` with several values per flag: a population in one process, each member a run folder of its own."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ablations.cli import ablate_main
from ablations.population import POPULATION, AblateConfig
from ablations.run_folder import find_runs, read_metrics
from ablations.runs import TIMING_KEYS

TINY = ["--task", "cartpole", "--num-envs", "2", "--horizon", "3", "--image-size", "16", "--critic-iterations", "1",
        "--critic-batches", "1", "--device", "cpu", "--no-progress", "--threads", "1", "--eval-envs", "2",
        "--episode-length", "12"]
MEMBERS = ["--mode", "decoupled", "full", "blind", "--seed", "0", "1"]


def ablate(*args: str) -> None:
    ablate_main(list(args))


def strip_timing(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIMING_KEYS} for r in rows]


def members_of(home: Path) -> dict[str, list[dict]]:
    names = json.loads((home / POPULATION).read_text())["members"]
    return {name: read_metrics(home / name) for name in names}


def test_several_values_train_one_population_whose_members_are_run_folders(tmp_path, capsys):
    ablate(*TINY, *MEMBERS, "--iters", "3", "--cosine-every", "2", "--video-every", "3", "--out", str(tmp_path),
           "--name", "pop")
    home = tmp_path / "pop"
    names = json.loads((home / POPULATION).read_text())["members"]
    assert sorted(names) == sorted(f"cartpole_{m}_seed{s}" for m in ("decoupled", "full", "blind") for s in (0, 1))
    out = capsys.readouterr().out
    assert f"population of 6 ({home.resolve()})" in out and f"ablate --resume {home.resolve()}" in out
    runs = find_runs([home])  # plots, reports and statistics read the members as single runs
    assert len(runs) == 6
    for run in runs:
        record = json.loads((run.path / "config.json").read_text())
        assert record["population"]["folder"] == "pop" and run.path.name in record["population"]["members"]
        assert run.summary["status"] == "finished" and [r["iter"] for r in run.metrics] == [1, 2, 3]
        assert "eval_return_mean" in run.metrics[-1] and (run.path / "videos" / "iter_000003.mp4").exists()
        assert any(r["probed"] for r in run.metrics) == (run.mode != "blind")
        assert (run.path / "checkpoints" / "ckpt_000003.pt").exists()


def test_a_population_of_one_value_per_flag_is_the_single_run(tmp_path):
    assert len(AblateConfig(mode=("full",), seed=(3,)).members()) == 1
    members = AblateConfig(mode=("decoupled", "full"), seed=(0, 1, 2), raster_model=("hard", "softmax")).members()
    assert len(members) == 12 and {(m.mode, m.raster_model, m.seed) for m in members} == {
        (mode, raster, seed) for mode in ("decoupled", "full") for raster in ("hard", "softmax") for seed in (0, 1, 2)}
    listed = AblateConfig(member=("mode=full,raster_model=hard,seed=2", "mode=blind,seed=0,encoder_lr_scale=0.1"))
    full, blind = listed.members()
    assert (full.mode, full.raster_model, full.seed) == ("full", "hard", 2)
    assert (blind.mode, blind.seed, blind.encoder_lr_scale) == ("blind", 0, 0.1)


@pytest.mark.parametrize(("args", "message"), [
    (["--mode", "state", "full"], "--mode state trains on the state vector"),
    (["--seed", "1", "1"], "--seed lists a value twice"),
    (["--member", "mode=full,seed=0", "--mode", "full", "blind"], "--member lists the members one by one"),
    (["--member", "mode=full,num_envs=4"], "not a member's own setting"),
])
def test_members_that_cannot_make_a_population_are_one_clear_line(tmp_path, args, message, capsys):
    with pytest.raises(SystemExit) as e:
        ablate(*TINY, "--iters", "1", "--out", str(tmp_path), *args)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not any(tmp_path.iterdir())  # nothing was created


@pytest.mark.parametrize("signals", [("SIGINT",), pytest.param(("SIGINT", "SIGTERM"), marks=pytest.mark.slow)])
def test_a_signal_stops_a_population_and_its_resume_repeats_nothing(tmp_path, signals):
    """A real SIGINT to a child ablate training a population: every member checkpoints the last finished
    iteration; the resumed population's members equal those of one that ran through. A second signal landing in
    the same iteration (both pending at once) stops it there: every member's last finished iteration is
    checkpointed from the copy the run holds."""
    iters = 30
    common = [*TINY, *MEMBERS, "--iters", str(iters), "--cosine-every", "3", "--video-every", "0",
              "--eval-every", "10", "--checkpoint-every", "1000", "--out", str(tmp_path)]
    cut = tmp_path / "cut"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.Popen([sys.executable, "-m", "ablations", "ablate", *common, "--name", "cut"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first = cut / "cartpole_decoupled_seed0"
    deadline = time.monotonic() + 300
    while len(read_metrics(first)) < 3 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    if len(signals) > 1:
        time.sleep(0.02)  # into the next iteration
    for name in signals:
        proc.send_signal(getattr(signal, name))
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err and f"ablate --resume {cut.resolve()}" in out
    done = {name: len(rows) for name, rows in members_of(cut).items()}
    assert len(set(done.values())) == 1 and 3 <= next(iter(done.values())) < iters
    it = next(iter(done.values()))
    for name in done:
        summary = json.loads((cut / name / "summary.json").read_text())
        assert summary["status"] == "interrupted" and summary["resumes_from"] == it and summary["lost"] is None
        assert [p.name for p in (cut / name / "checkpoints").iterdir()] == [f"ckpt_{it:06d}.pt"]
        if len(signals) > 1:
            assert summary["error"].startswith((f"SIGTERM during iteration {it + 1}: stopped at once",
                                                f"SIGTERM after iteration {it}: stopped at once")), summary
    ablate("--resume", str(cut / "cartpole_full_seed1"), "--no-progress")  # a member's folder resumes them all
    ablate(*common, "--name", "whole")
    resumed, whole = members_of(cut), members_of(tmp_path / "whole")
    for name, rows in resumed.items():
        assert [r["iter"] for r in rows] == list(range(1, iters + 1))
        assert strip_timing(rows) == strip_timing(whole[name]), name


def test_member_folder_names_write_tuple_values_as_the_sweep_does():
    """A member setting that is a tuple (betas) names its folder as ablate-sweep writes flag values
    (``ablations.sweep.config.slug``): no brackets, commas or spaces in folder names."""
    from ablations.population import member_name
    from ablations.runs import RunConfig

    members = [RunConfig(task="cartpole", mode="decoupled", seed=0, betas=b) for b in ((0.7, 0.95), (0.5, 0.9))]
    assert [member_name(m, members) for m in members] == ["cartpole_decoupled_betas0.7-0.95_seed0",
                                                          "cartpole_decoupled_betas0.5-0.9_seed0"]


def test_a_new_population_that_fails_before_any_record_leaves_no_folder(tmp_path, monkeypatch, capsys):
    """A failure while the trainer is built (before any member wrote its config.json) removes the member folders
    and the population folder with its population.json, so that the name is free again."""
    import ablations.runs

    def fails(*args, **kwargs):
        raise ValueError("the trainer could not be built")

    monkeypatch.setattr(ablations.runs, "SHAC", fails)
    with pytest.raises(SystemExit):
        ablate(*TINY, *MEMBERS, "--iters", "2", "--out", str(tmp_path / "runs"), "--name", "pop")
    assert capsys.readouterr().err == "error: the trainer could not be built\n"
    assert not (tmp_path / "runs" / "pop").exists()
