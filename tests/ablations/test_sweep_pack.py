"""``ablate-sweep --pack``: grid cells packed into populations (one ``ablate --member ...`` process each), their
folders as archives, the store and the manifest, and packed sweeps on a local Ray cluster (every member folder
written once, a killed population worker resumed with nothing lost or repeated, the recorded command rerun)."""

from __future__ import annotations

import io
import json
import shlex
import sys
import tarfile
from pathlib import Path

import pytest

from ablations.run_folder import POPULATION_RECORD, RunFolder, read_metrics
from ablations.sweep import (
    Job,
    RunStore,
    SweepConfig,
    dry_run,
    load_manifest,
    main,
    pack_run,
    plan,
    run_sweep,
    unpack_run,
)
from ablations.sweep.manifest import plan_jobs
from ablations.sweep.packing import member_entry, pack_runs
from ablations.sweep.store import common_checkpoint, job_state
from tests.ablations.test_sweep import (
    FAKE_ABLATE,
    TINY,
    assert_complete_run,
    fake_run,
    kill_worker_once,
    ray_cluster,  # noqa: F401 - the module's Ray cluster fixture
)


def jobs_of(cfg: SweepConfig, arms: dict | None = None) -> list[Job]:
    return pack_runs(plan(cfg, arms=arms), cfg.pack_size())


def composition(jobs: list[Job]) -> list[tuple[str, ...]]:
    return [job.run_ids for job in jobs]


# ---------------------------------------------------------------------------------------------------------
# Which cells share a process (no Ray)

PIXEL = ("decoupled", "full", "blind")


@pytest.mark.parametrize(("kw", "arms", "expected"), [
    # one run per process: every job is its run, as without --pack
    (dict(modes=PIXEL, seeds=(0, 1)), None,
     [("cartpole_decoupled_seed0",), ("cartpole_decoupled_seed1",), ("cartpole_full_seed0",),
      ("cartpole_full_seed1",), ("cartpole_blind_seed0",), ("cartpole_blind_seed1",)]),
    # every pixel mode and seed in one process
    (dict(modes=PIXEL, seeds=(0, 1), pack="12"), None,
     [("cartpole_decoupled_seed0", "cartpole_decoupled_seed1", "cartpole_full_seed0", "cartpole_full_seed1",
       "cartpole_blind_seed0", "cartpole_blind_seed1")]),
    # state runs form a population of their own
    (dict(modes=("decoupled", "state"), seeds=(0, 1), pack="12"), None,
     [("cartpole_decoupled_seed0", "cartpole_decoupled_seed1"), ("cartpole_state_seed0", "cartpole_state_seed1")]),
    # a group larger than --pack: as few populations as hold it, dealt round-robin (here one per seed)
    (dict(modes=PIXEL, seeds=(0, 1, 2), pack="4"), None,
     [("cartpole_decoupled_seed0", "cartpole_full_seed0", "cartpole_blind_seed0"),
      ("cartpole_decoupled_seed1", "cartpole_full_seed1", "cartpole_blind_seed1"),
      ("cartpole_decoupled_seed2", "cartpole_full_seed2", "cartpole_blind_seed2")]),
    # sizes differ by one at most: 5 cells at --pack 2 are 2 + 2 + 1, and a population of one is a run alone
    (dict(modes=("decoupled",), seeds=(0, 1, 2, 3, 4), pack="2"), None,
     [("cartpole_decoupled_seed0", "cartpole_decoupled_seed3"), ("cartpole_decoupled_seed1",
                                                                 "cartpole_decoupled_seed4"),
      ("cartpole_decoupled_seed2",)]),
    # tasks never share a process, nor do values of a shared setting (--vary image-size)
    (dict(tasks=("cartpole", "hopper"), modes=("full",), seeds=(0, 1), vary=("image-size=24,32",), pack="12"),
     None,
     [("cartpole_full_seed0_image-size24", "cartpole_full_seed1_image-size24"),
      ("cartpole_full_seed0_image-size32", "cartpole_full_seed1_image-size32"),
      ("hopper_full_seed0_image-size24", "hopper_full_seed1_image-size24"),
      ("hopper_full_seed0_image-size32", "hopper_full_seed1_image-size32")]),
    # a member's own setting varied (--vary actor-lr) shares the process
    (dict(modes=("full",), seeds=(0,), vary=("actor-lr=0.001,0.002",), pack="12"), None,
     [("cartpole_full_seed0_actor-lr0.001", "cartpole_full_seed0_actor-lr0.002")]),
    # arms whose flags are members' own (preset, raster model) share it; one setting of the population's not
    (dict(modes=("full",), seeds=(0,), pack="12"),
     {"full-hard": {"mode": "full", "flags": {"preset": "shac-diffrender"}},
      "full-hard-dva": {"mode": "full", "flags": {"raster-model": "hard"}},
      "full-soft": {"mode": "full"}, "blind": {"mode": "blind"},
      "wide": {"mode": "full", "flags": {"trunk-dim": 64}}},
     [("cartpole_full-hard_seed0", "cartpole_full-hard-dva_seed0", "cartpole_full-soft_seed0",
       "cartpole_blind_seed0"), ("cartpole_wide_seed0",)]),
])
def test_cells_that_can_share_a_process_are_packed(kw, arms, expected):
    kw.setdefault("set", ("iters=7",))
    jobs = jobs_of(SweepConfig(**kw), arms)
    assert composition(jobs) == expected
    for job in jobs:
        assert job.population == (len(job.run_ids) > 1)
        assert job.iters == 7


def test_pack_1_keeps_one_run_per_process_as_before():
    cfg = SweepConfig(modes=PIXEL, seeds=(0, 1), set=("iters=7",))
    specs = plan(cfg)
    jobs = pack_runs(specs, cfg.pack_size())
    assert cfg.pack == "1" and cfg.pack_size() == 1
    assert [(j.job_id, j.run_ids, j.members, j.args) for j in jobs] == [
        (s.run_id, (s.run_id,), ("",), s.args) for s in specs]
    assert [j.folder(0) for j in jobs] == [f"runs/{s.run_id}" for s in specs]


def test_a_population_is_one_ablate_command_whose_members_are_the_runs():
    arms = {"full-hard": {"mode": "full", "flags": {"preset": "shac-diffrender"}},
            "full-hard-dva": {"mode": "full", "flags": {"raster-model": "hard"}},
            "decoupled": {"mode": "decoupled"}}
    cfg = SweepConfig(tasks=("hopper",), seeds=(0, 1), set=("iters=7", "num-envs=8"), pack="12")
    (job,) = jobs_of(cfg, arms)
    assert job.job_id == "hopper_population0" and job.population
    assert list(job.args) == [
        "--task", "hopper", "--iters", "7", "--num-envs", "8", "--member",
        "mode=full,seed=0,preset=shac-diffrender", "mode=full,seed=1,preset=shac-diffrender",
        "mode=full,seed=0,raster_model=hard", "mode=full,seed=1,raster_model=hard",
        "mode=decoupled,seed=0", "mode=decoupled,seed=1"]
    # the members' run folders are named as ablate names them (what sets them apart)
    assert dict(zip(job.run_ids, job.members)) == {
        "hopper_full-hard_seed0": "hopper_full_shac-diffrender_seed0",
        "hopper_full-hard_seed1": "hopper_full_shac-diffrender_seed1",
        "hopper_full-hard-dva_seed0": "hopper_full_hard_dva_seed0",
        "hopper_full-hard-dva_seed1": "hopper_full_hard_dva_seed1",
        "hopper_decoupled_seed0": "hopper_decoupled_dva_seed0",
        "hopper_decoupled_seed1": "hopper_decoupled_dva_seed1"}
    assert job.folder(0) == "runs/hopper_population0/hopper_full_shac-diffrender_seed0"


def test_member_entries():
    assert member_entry({"mode": "full", "seed": 3, "betas": [0.7, 0.95]}) == "mode=full,seed=3,betas=0.7/0.95"
    assert member_entry({"mode": "full", "betas": "0.7 0.95", "raster_model": None}) == \
        "mode=full,betas=0.7/0.95,raster_model=none"
    with pytest.raises(ValueError, match="holds no ',' or '='; --pack 1 trains such runs alone"):
        member_entry({"mode": "full", "actor_init": "a,b"})


def test_pack_auto_is_twelve_on_gpu_runs_and_one_on_the_cpu(monkeypatch, capsys):
    assert SweepConfig(pack="auto").pack_size() == 1
    assert SweepConfig(pack="auto", gpus_per_run=0.25).pack_size() == 12
    assert SweepConfig(pack="3", gpus_per_run=1).pack_size() == 3
    for bad in ("0", "x", "-2", "1.5"):
        with pytest.raises(ValueError, match=rf"--pack must be auto or a positive whole number, got '{bad}'"):
            plan(SweepConfig(pack=bad, set=("iters=7",)))
    monkeypatch.setenv("COLUMNS", "200")
    with pytest.raises(SystemExit):
        main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    # the help says where the measurement behind auto's 12 is (the figure lives in BENCHMARKS.md, not the code)
    assert "--pack {auto,N}" in text and "auto: 12 on GPU runs" in text and "BENCHMARKS.md section 7" in text


def test_dry_run_lists_each_population_and_its_members(tmp_path, capsys):
    cfg = SweepConfig(out=tmp_path / "s", modes=("decoupled", "blind", "state"), seeds=(0, 1), set=("iters=7",),
                      pack="12")
    lines = dry_run(cfg)
    assert lines == [
        "start    cartpole_population0: ablate --task cartpole --iters 7 --member mode=decoupled,seed=0 "
        "mode=decoupled,seed=1 mode=blind,seed=0 mode=blind,seed=1",
        "           cartpole_decoupled_seed0 in runs/cartpole_population0/cartpole_decoupled_seed0",
        "           cartpole_decoupled_seed1 in runs/cartpole_population0/cartpole_decoupled_seed1",
        "           cartpole_blind_seed0 in runs/cartpole_population0/cartpole_blind_seed0",
        "           cartpole_blind_seed1 in runs/cartpole_population0/cartpole_blind_seed1",
        "start    cartpole_population1: ablate --task cartpole --iters 7 --member mode=state,seed=0 "
        "mode=state,seed=1",
        "           cartpole_state_seed0 in runs/cartpole_population1/cartpole_state_seed0",
        "           cartpole_state_seed1 in runs/cartpole_population1/cartpole_state_seed1",
        "6 runs in 2 processes (2 populations of at most 12, --pack 12); 1.0 CPU and 0.0 GPU each process"]
    assert capsys.readouterr().out.splitlines() == lines and not (tmp_path / "s").exists()


def test_a_rerun_keeps_every_run_that_has_a_folder_in_its_recorded_job(tmp_path):
    """Runs already started stay where they are whatever --pack says now (nothing trained is lost or repeated);
    runs without a folder are packed anew, into names not taken."""
    out = tmp_path / "s"
    first = SweepConfig(out=out, modes=("decoupled", "blind"), seeds=(0, 1), set=("iters=7",), pack="12")
    (job,) = plan_jobs(first, plan(first), None)
    manifest = {"runs": {r: {"job": job.job_id, "args": []} for r in job.run_ids},
                "jobs": {job.job_id: job.record()}}
    (out / "runs" / job.job_id).mkdir(parents=True)
    wider = SweepConfig(out=out, modes=("decoupled", "blind"), seeds=(0, 1, 2, 3), set=("iters=7",), pack="1")
    jobs = plan_jobs(wider, plan(wider), manifest)
    assert jobs[0] == job
    assert composition(jobs[1:]) == [("cartpole_decoupled_seed2",), ("cartpole_decoupled_seed3",),
                                     ("cartpole_blind_seed2",), ("cartpole_blind_seed3",)]
    packed = plan_jobs(SweepConfig(**{**vars(wider), "pack": "12"}), plan(wider), manifest)
    assert [j.job_id for j in packed] == ["cartpole_population0", "cartpole_population1"]
    assert composition(packed)[1] == ("cartpole_decoupled_seed2", "cartpole_decoupled_seed3",
                                      "cartpole_blind_seed2", "cartpole_blind_seed3")
    # A job recorded but never started (no folder) is packed anew, under the same name.
    (out / "runs" / job.job_id).rmdir()
    assert plan_jobs(first, plan(first), manifest) == [job]


# ---------------------------------------------------------------------------------------------------------
# Population folders as archives, the store, and what a rerun does with a job (no Ray)


def fake_population(home: Path, members: dict[str, list[int]]) -> Path:
    home.mkdir(parents=True)
    (home / POPULATION_RECORD).write_text(json.dumps({"members": list(members)}))
    for name, checkpoints in members.items():
        fake_run(home / name, iters=4, checkpoints=checkpoints)
    return home


def names_of(data: bytes) -> list[str]:
    return sorted(tarfile.open(fileobj=io.BytesIO(data)).getnames())


def test_a_population_folder_travels_with_each_members_newest_checkpoints(tmp_path):
    home = fake_population(tmp_path / "pop", {"a": [2, 4], "b": [2, 4]})
    names = names_of(pack_run(home))
    assert names == ["a/checkpoints/ckpt_000004.pt", "a/config.json", "a/metrics.jsonl", "a/videos/iter_000002.mp4",
                     "b/checkpoints/ckpt_000004.pt", "b/config.json", "b/metrics.jsonl", "b/videos/iter_000002.mp4",
                     POPULATION_RECORD]
    assert not [n for n in names_of(pack_run(home, checkpoints=0)) if "/checkpoints/" in n]
    dest = tmp_path / "dest"
    for name in ("a", "b"):  # 8: an abandoned timeline of each member (it resumed from an older checkpoint)
        (dest / name / "checkpoints").mkdir(parents=True)
        for it in (1, 8):
            (dest / name / "checkpoints" / f"ckpt_{it:06d}.pt").write_bytes(b"old")
    unpack_run(pack_run(home), dest)
    for name in ("a", "b"):
        assert sorted(p.name for p in (dest / name / "checkpoints").iterdir()) == ["ckpt_000001.pt",
                                                                                   "ckpt_000004.pt"]
        assert [r["iter"] for r in read_metrics(dest / name)] == [1, 2, 3, 4]  # the torn last line left out
    assert (dest / POPULATION_RECORD).read_text() == (home / POPULATION_RECORD).read_text()


def test_the_store_resumes_a_population_only_from_an_iteration_every_member_has(tmp_path):
    members = ("a", "b")
    fake_population(tmp_path / "runs" / "pop", {"a": [2, 4], "b": [2]})
    store = RunStore(str(tmp_path), {"pop": 1})
    attempt, pack = store.begin("pop", members)
    assert attempt == 2 and "b/checkpoints/ckpt_000002.pt" in names_of(pack)
    assert not [n for n in names_of(pack) if "videos" in n]  # a resume does not need them
    assert common_checkpoint([RunFolder(tmp_path / "runs" / "pop" / m) for m in members]) == 2
    assert job_state(tmp_path / "runs" / "pop", members, 4) == "resume"
    # no iteration in common, or no population record: nothing to resume, the folder moves aside
    fake_population(tmp_path / "runs" / "other", {"a": [4], "b": [2]})
    assert job_state(tmp_path / "runs" / "other", members, 4) == "start"
    assert store.begin("other", members) == (1, None)
    assert not (tmp_path / "runs" / "other").exists() and len(list((tmp_path / "discarded").iterdir())) == 1


# ---------------------------------------------------------------------------------------------------------
# Packed sweeps on a local Ray cluster


def record_program(log: Path, seconds: float) -> tuple[str, ...]:
    return (sys.executable, str(FAKE_ABLATE), "record", str(log), str(seconds), "--")


def spans(log: Path) -> list[dict]:
    return [json.loads(line) for line in log.read_text().splitlines()]


@pytest.mark.slow
@pytest.mark.usefixtures("ray_cluster")
def test_a_packed_sweep_writes_every_member_folder_once_and_its_command_reruns(tmp_path, monkeypatch, capsys):
    """Decoupled, blind and state x 2 seeds at --pack 12: two processes (the pixel population and the state
    one), each run's folder written once under its population's folder; the recorded command, run again as
    written, starts nothing and repeats nothing."""
    monkeypatch.chdir(tmp_path)
    log = tmp_path / "spans.jsonl"
    argv = ["--out", "s", "--modes", "decoupled", "blind", "state", "--seeds", "0", "1", "--set", "iters=6",
            "--pack", "12", "--no-progress"]
    main(argv, program=record_program(log, 2))
    manifest = load_manifest(tmp_path / "s")
    assert manifest["command"] == ["ablate-sweep", *argv] and manifest["sweep"]["pack_size"] == 12
    assert manifest["counts"]["done"] == 6
    runs = manifest["runs"]
    assert {r["job"] for r in runs.values()} == {"cartpole_population0", "cartpole_population1"}
    assert sorted(manifest["jobs"]["cartpole_population1"]["runs"]) == ["cartpole_state_seed0",
                                                                        "cartpole_state_seed1"]
    calls = spans(log)
    assert sorted(c["run"] for c in calls) == ["cartpole_population0", "cartpole_population1"]
    for run_id, rec in runs.items():
        assert rec["folder"].startswith(f"runs/{rec['job']}/") and rec["attempts"] == 1 and rec["iteration"] == 6
        rows = read_metrics(tmp_path / "s" / rec["folder"])
        assert [r["iter"] for r in rows] == list(range(1, 7)), run_id  # every iteration once
        assert len({r["pid"] for r in rows}) == 1
        # the final checkpoint and at most one older one (which older ones reached the folder depends on timing)
        kept = sorted((p.name for p in (tmp_path / "s" / rec["folder"] / "checkpoints").iterdir()), reverse=True)
        assert kept[0] == "ckpt_000006.pt" and len(kept) <= 2, kept
    assert {p.name for p in (tmp_path / "s" / "logs").iterdir()} == {"cartpole_population0.attempt1.log",
                                                                      "cartpole_population1.attempt1.log"}
    assert json.loads((tmp_path / "s" / "runs" / "cartpole_population0" / POPULATION_RECORD).read_text())[
        "members"] == ["cartpole_decoupled_seed0", "cartpole_decoupled_seed1", "cartpole_blind_seed0",
                       "cartpole_blind_seed1"]
    capsys.readouterr()

    main(shlex.split(shlex.join(manifest["command"]))[1:], program=record_program(log, 2))
    assert len(spans(log)) == 2  # nothing trained again
    again = load_manifest(tmp_path / "s")
    assert again["counts"]["done"] == 6 and again["jobs"] == manifest["jobs"]
    assert {k: r["attempts"] for k, r in again["runs"].items()} == {k: 1 for k in runs}


@pytest.mark.slow
@pytest.mark.usefixtures("ray_cluster")
def test_a_killed_population_worker_resumes_with_nothing_lost_or_repeated(tmp_path):
    """The real ablate training a population of three: its Ray worker is SIGKILLed once every member's first
    checkpoint has reached the sweep folder; the retry resumes the population folder from there, and every member
    holds each iteration once."""
    out = tmp_path / "sweep"
    cfg = SweepConfig(out=out, tasks=("cartpole",), modes=("decoupled", "blind"), seeds=(0, 1), set=TINY,
                      pack="3", progress=False)
    jobs = plan_jobs(cfg, plan(cfg), None)
    assert [len(j.run_ids) for j in jobs] == [2, 2]
    victim = jobs[0].job_id
    manifest = run_sweep(cfg, program=kill_worker_once(out, victim))
    assert manifest["counts"]["done"] == 4
    step = int((out / ".killed" / victim).read_text().split("_")[1].split(".")[0])
    assert 2 <= step < 12
    for rec in manifest["runs"].values():
        assert rec["status"] == "done" and rec["iteration"] == 12, rec
        assert_complete_run(out / rec["folder"], 12)
        killed = rec["job"] == victim
        assert rec["attempts"] == (2 if killed else 1) and rec["resumed"] is killed
        record = json.loads((out / rec["folder"] / "config.json").read_text())
        assert record["population"]["folder"] == rec["job"]
    # a killed worker sends no log: its attempt's output was in the node's scratch folder
    assert {p.name for p in (out / "logs").iterdir()} == {f"{victim}.attempt2.log",
                                                           f"{jobs[1].job_id}.attempt1.log"}


@pytest.mark.slow
@pytest.mark.usefixtures("ray_cluster")
def test_a_population_stopped_by_a_signal_is_retried_from_its_checkpoint(tmp_path):
    """The real ablate training a population stops on SIGTERM after every member's first checkpoint (summaries
    "interrupted", exit status 130): the worker ships the checkpoints and Ray retries the population, which
    resumes and repeats no iteration."""
    out = tmp_path / "sweep"
    cfg = SweepConfig(out=out, tasks=("cartpole",), modes=("decoupled", "blind"), seeds=(0,), set=TINY, pack="2",
                      progress=False)
    (job,) = plan_jobs(cfg, plan(cfg), None)
    program = (sys.executable, str(FAKE_ABLATE), "signal-once", str(out), job.job_id, "--")
    manifest = run_sweep(cfg, program=program)
    assert (out / ".signalled" / job.job_id).read_text() == "ckpt_000002.pt"
    for rec in manifest["runs"].values():
        assert rec["status"] == "done" and rec["attempts"] == 2 and rec["resumed"] is True, rec
        assert_complete_run(out / rec["folder"], 12)
    first = (out / "logs" / f"{job.job_id}.attempt1.log").read_text()
    assert "SIGTERM: stopping once this iteration has finished" in first and "Traceback" not in first


@pytest.mark.slow
@pytest.mark.usefixtures("ray_cluster")
def test_a_member_that_stops_alone_is_failed_and_the_others_done(tmp_path):
    """--vary abort-grad-norm (a member's own setting) puts both runs in one population; the member whose gradient
    passes its abort norm stops alone and is recorded failed with its summary's reason, the other finishes."""
    out = tmp_path / "sweep"
    cfg = SweepConfig(out=out, tasks=("cartpole",), modes=("decoupled",), seeds=(0,), set=TINY, pack="2",
                      vary=("abort-grad-norm=1e8,1e-12",), progress=False)
    (job,) = plan_jobs(cfg, plan(cfg), None)
    assert job.population
    runs = run_sweep(cfg, program=(sys.executable, "-m", "ablations", "ablate"))["runs"]
    ok = runs["cartpole_decoupled_seed0_abort-grad-norm1e8"]
    aborted = runs["cartpole_decoupled_seed0_abort-grad-norm1e-12"]
    assert ok["status"] == "done" and ok["error"] is None
    assert_complete_run(out / ok["folder"], 12)
    assert aborted["status"] == "failed" and aborted["summary_status"] == "nonfinite", aborted
    assert aborted["error"].startswith("nonfinite: ") and "abort" in aborted["error"], aborted["error"]


def test_the_attempt_gets_sigint_and_sigterm_back_from_a_worker_that_ignores_and_blocks_them():
    """A Ray worker ignores or blocks SIGINT; child.py resets both signals before it execs the attempt, so that
    ablate's own handlers (checkpoint, then stop) get the signal a sweep's stop sends."""
    import signal
    import subprocess
    import sys

    from ablations.sweep.worker import _CHILD

    code = ("import signal\n"
            "print(signal.getsignal(signal.SIGINT) == signal.default_int_handler,\n"
            "      signal.getsignal(signal.SIGTERM) == signal.SIG_DFL,\n"
            "      bool(signal.pthread_sigmask(signal.SIG_BLOCK, []) & {signal.SIGINT, signal.SIGTERM}))\n")

    def like_a_worker() -> None:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})

    worker = ("import os, subprocess, sys\n"  # the worker starts child.py with its own pid, as run_attempt does
              "sys.exit(subprocess.call([sys.argv[1], sys.argv[2], str(os.getpid()), *sys.argv[3:]]))\n")
    proc = subprocess.Popen([sys.executable, "-c", worker, sys.executable, str(_CHILD), sys.executable, "-c", code],
                            stdout=subprocess.PIPE, text=True, preexec_fn=like_a_worker)
    out, _ = proc.communicate(timeout=60)
    assert out.split() == ["True", "True", "False"], out
