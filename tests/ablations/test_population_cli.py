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


@pytest.mark.slow
@pytest.mark.parametrize("signals", [("SIGINT",), ("SIGINT", "SIGTERM")])
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
    from ablations.run_config import RunConfig

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


def test_a_population_killed_between_its_members_checkpoints_resumes_from_the_last_they_all_hold(tmp_path):
    """A process killed (os._exit: nothing after it runs) after one member wrote its new checkpoint and before
    the next did, one checkpoint kept a member: the older ones are pruned only once every member's new one is
    written, so an iteration every member holds is left. The resume trains on from there, repeating nothing."""
    common = [*TINY, "--mode", "state", "--seed", "0", "1", "--iters", "6", "--checkpoint-every", "2",
              "--keep-checkpoints", "1", "--video-every", "0", "--out", str(tmp_path), "--name", "pop"]
    script = tmp_path / "killed.py"
    script.write_text(
        "import os, sys\n"
        "from ablations.run_folder import RunFolder\n"
        "from ablations.cli import ablate_main\n"
        "saved, calls = RunFolder.save_checkpoint, []\n"
        "def save(folder, iteration, state):\n"
        "    calls.append(iteration)\n"
        "    if calls.count(4) == 2:\n"
        "        os._exit(9)  # killed: the second member's checkpoint of iteration 4 never comes\n"
        "    return saved(folder, iteration, state)\n"
        "RunFolder.save_checkpoint = save\n"
        "ablate_main(sys.argv[1:])\n")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.run([sys.executable, str(script), *common], env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 9, proc.stderr[-2000:]
    home = tmp_path / "pop"
    held = {name: sorted(p.name for p in (home / name / "checkpoints").glob("ckpt_*.pt"))
            for name in json.loads((home / POPULATION).read_text())["members"]}
    assert sorted(map(tuple, held.values())) == [("ckpt_000002.pt",), ("ckpt_000002.pt", "ckpt_000004.pt")]
    ablate("--resume", str(home), "--no-progress")
    for name, rows in members_of(home).items():
        assert [r["iter"] for r in rows] == list(range(1, 7)), name


def test_a_signal_while_a_new_population_records_its_members_waits_until_every_record_is_written(tmp_path,
                                                                                                  monkeypatch):
    """SIGINT arriving while the first member's git.txt is written: it is held until every member's config.json
    and git.txt exist, then stops the run before its first iteration; the population resumes."""
    import ablations.run_folder

    written = ablations.run_folder.RunFolder.write_git
    sent = []

    def signalled_once(folder, repo=None):
        written(folder, repo)
        if not sent:
            sent.append(folder.path.name)
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(ablations.run_folder.RunFolder, "write_git", signalled_once)
    with pytest.raises(SystemExit) as e:
        ablate(*TINY, "--mode", "state", "--seed", "0", "1", "--iters", "2", "--video-every", "0",
               "--out", str(tmp_path), "--name", "pop")
    assert e.value.code == 130
    home = tmp_path / "pop"
    for name in json.loads((home / POPULATION).read_text())["members"]:
        assert (home / name / "config.json").is_file() and (home / name / "git.txt").is_file()
        assert json.loads((home / name / "summary.json").read_text())["status"] == "interrupted"
    monkeypatch.setattr(ablations.run_folder.RunFolder, "write_git", written)
    ablate("--resume", str(home), "--no-progress")
    assert all([r["iter"] for r in rows] == [1, 2] for rows in members_of(home).values())


def test_two_starts_in_one_second_never_share_a_folder(tmp_path):
    """The folder ablate names itself (no --name) is created atomically: a second start with the same settings in
    the same second gets the name with _2."""
    from ablations.naming import claim_folder

    assert claim_folder(tmp_path, "cartpole_state_seed0_20261128-181500") == "cartpole_state_seed0_20261128-181500"
    assert claim_folder(tmp_path, "cartpole_state_seed0_20261128-181500") == "cartpole_state_seed0_20261128-181500_2"
    assert claim_folder(tmp_path, "cartpole_state_seed0_20261128-181500") == "cartpole_state_seed0_20261128-181500_3"


def test_a_resumed_population_leaves_a_stopped_members_metrics_as_they_are(tmp_path, capsys):
    """A member stopped by its gradient bound (abort_grad_norm) stays stopped on resume: its metrics end where it
    stopped, and the resume neither warns about them nor sets any aside; the other member trains on."""
    common = [*TINY, "--iters", "4", "--checkpoint-every", "2", "--video-every", "0", "--out", str(tmp_path),
              "--name", "pop", "--member", "mode=state,seed=0", "mode=state,seed=1,abort_grad_norm=1e-9"]
    ablate(*common)
    home = tmp_path / "pop"
    names = json.loads((home / POPULATION).read_text())["members"]
    stopped = [n for n in names if json.loads((home / n / "summary.json").read_text())["status"] == "nonfinite"]
    assert len(stopped) == 1
    metrics = home / stopped[0] / "metrics.jsonl"
    before = metrics.read_text() if metrics.exists() else None  # none: it stopped in its first iteration
    capsys.readouterr()
    ablate("--resume", str(home), "--iters", "6", "--no-progress")
    err = capsys.readouterr().err
    assert "metrics" not in err, err
    assert (metrics.read_text() if metrics.exists() else None) == before
    assert not list((home / stopped[0]).glob("metrics.jsonl.*"))
    (live,) = set(names) - set(stopped)
    assert [r["iter"] for r in read_metrics(home / live)] == list(range(1, 7))


def test_a_member_folder_whose_population_record_is_gone_is_not_resumed_alone(tmp_path, capsys):
    """A member draws its noise from a generator of the population's; resumed alone it would draw from torch's
    default one: with population.json gone, ``--resume`` of the member's folder is refused in one line, naming
    the missing file and the members, and nothing in the folder changes."""
    ablate(*TINY, "--mode", "state", "--seed", "0", "1", "--iters", "2", "--video-every", "0", "--out",
           str(tmp_path), "--name", "pop")
    home = tmp_path / "pop"
    names = json.loads((home / POPULATION).read_text())["members"]
    (home / POPULATION).unlink()
    member = home / names[0]
    before = {p.name: p.stat().st_mtime_ns for p in member.rglob("*")}
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        ablate("--resume", str(member), "--iters", "4", "--no-progress")
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert f"{home / POPULATION} is gone" in err and "a population of 2" in err and names[1] in err
    assert {p.name: p.stat().st_mtime_ns for p in member.rglob("*")} == before


def test_each_member_is_validated_at_most_three_times_and_resolved_once(tmp_path, monkeypatch):
    """From the command line to the trainer's first iteration: the roster resolves each member once (its checks
    before and after the preset fills in), after the command line's own check, and nothing checks again; a
    resume reads each member's config.json (one check) and resolves it once."""
    import gradlab.config
    import gradlab.roster
    from gradlab.config import SHACConfig

    validated, resolved = [], []
    validate, resolve = SHACConfig.validate, gradlab.config.resolve_config

    def counted_validate(self):
        validated.append((self.mode, self.seed))
        return validate(self)

    def counted_resolve(cfg):
        resolved.append((cfg.mode, cfg.seed))
        return resolve(cfg)

    monkeypatch.setattr(SHACConfig, "validate", counted_validate)
    monkeypatch.setattr(gradlab.roster, "resolve_config", counted_resolve)
    keys = [(m, s) for m in ("decoupled", "blind") for s in (0, 1)]
    ablate(*TINY, "--mode", "decoupled", "blind", "--seed", "0", "1", "--iters", "1", "--video-every", "0",
           "--out", str(tmp_path), "--name", "pop")
    assert sorted(resolved) == sorted(keys)
    assert all(validated.count(k) <= 3 for k in keys), validated
    validated.clear(), resolved.clear()
    ablate("--resume", str(tmp_path / "pop"), "--iters", "2", "--no-progress")
    assert sorted(resolved) == sorted(keys)
    assert all(validated.count(k) <= 3 for k in keys), validated
