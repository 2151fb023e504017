"""``ablate-sweep``: the grid, its checks, run folders as archives, the driver's store, and real sweeps on a local
Ray cluster (a worker killed mid-run, a failed run, a rerun that skips and resumes, how many runs train at once)."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from pathlib import Path

import pytest

from ablations.run_folder import read_metrics
from ablations.sweep import (
    KEPT_CHECKPOINTS,
    RunStore,
    SweepConfig,
    attempt_command,
    dry_run,
    load_manifest,
    main,
    pack_run,
    parse_args,
    plan,
    run_slots,
    run_sweep,
    unpack_run,
)
from gradlab.config import MODES
from tasks import TASKS

ROOT = Path(__file__).resolve().parents[2]
#: Stand-ins for ablate that a sweep's workers start instead (the sweep's ``program`` seam).
FAKE_ABLATE = Path(__file__).with_name("fake_ablate.py")


def kill_worker_once(out: Path, *run_ids: str) -> tuple[str, ...]:
    """The real ablate, but the named runs' Ray workers are SIGKILLed once each, right after the run's first
    checkpoint has reached the sweep folder (tests/ablations/fake_ablate.py)."""
    return (sys.executable, str(FAKE_ABLATE), "kill-worker-once", str(out), ",".join(run_ids), "--")
#: A run of a few seconds on one CPU core: 12 iterations, a checkpoint every 2.
TINY = ("iters=12", "num-envs=2", "horizon=3", "image-size=24", "critic-iterations=1", "critic-batches=1",
        "checkpoint-every=2", "video-every=0", "cosine-every=0", "device=cpu")


def tiny_sweep(out: Path, **kw) -> SweepConfig:
    kw.setdefault("modes", ("decoupled", "state"))
    kw.setdefault("progress", False)
    return SweepConfig(out=out, tasks=("cartpole",), set=TINY, **kw)


# ---------------------------------------------------------------------------------------------------------
# The grid and its checks (no Ray)


def test_plan_is_the_product_of_the_axes_with_stable_names_and_flags():
    cfg = SweepConfig(tasks=("cartpole", "ant"), modes=("full", "state"), seeds=(0, 1),
                      set=("iters=7", "compile=false", "actor-hidden=32 16"), vary=("image-size=24,32",))
    specs = plan(cfg)
    assert len(specs) == 2 * 2 * 2 * 2
    assert len({s.run_id for s in specs}) == len(specs)
    first = specs[0]
    assert first.run_id == "cartpole_full_seed0_image-size24"
    assert first.flags == {"image_size": "24"} and first.iters == 7
    args = list(first.args)
    assert args[:6] == ["--task", "cartpole", "--mode", "full", "--seed", "0"]
    assert "--no-compile" in args and args[args.index("--actor-hidden") + 1:][:2] == ["32", "16"]
    assert args[-2:] == ["--image-size", "24"]
    assert {s.run_id for s in specs if s.task == "ant" and s.seed == 1} == {
        "ant_full_seed1_image-size24", "ant_full_seed1_image-size32",
        "ant_state_seed1_image-size24", "ant_state_seed1_image-size32"}


def test_arms_replace_the_modes_axis_with_named_flag_sets(tmp_path, capsys):
    arms = {"full-hard": {"mode": "full", "flags": {"raster-model": "hard", "lr_decay_iters": 2000}},
            "full-soft": {"mode": "full"}, "blind": {"mode": "blind", "flags": {}}}
    cfg = SweepConfig(out=tmp_path / "s", tasks=("hopper", "ant"), modes=("full", "blind"), seeds=(0, 1),
                      set=("iters=7",), vary=("image-size=24,32",))
    specs = plan(cfg, arms=arms)
    assert len(specs) == 2 * 3 * 2 * 2
    first = specs[0]
    assert first.run_id == "hopper_full-hard_seed0_image-size24" and first.arm == "full-hard"
    assert first.mode == "full" and first.iters == 7
    assert list(first.args) == ["--task", "hopper", "--mode", "full", "--seed", "0", "--iters", "7",
                                "--raster-model", "hard", "--lr-decay-iters", "2000", "--image-size", "24"]
    soft = next(s for s in specs if s.arm == "full-soft")
    assert "--raster-model" not in soft.args and soft.run_id == "hopper_full-soft_seed0_image-size24"
    assert {s.mode for s in specs if s.arm == "blind"} == {"blind"}
    lines = dry_run(cfg, arms=arms)
    assert lines[0].startswith("start    hopper_full-hard_seed0_image-size24: ablate --task hopper --mode full")
    assert lines[-1] == "24 runs; 1.0 CPU and 0.0 GPU each" and capsys.readouterr().out.splitlines() == lines


@pytest.mark.parametrize(("arms", "message"), [
    ({}, "give at least one arm"),
    ({"a/b": {"mode": "full"}}, "names are letters, digits"),
    ({"a": {"flags": {}}}, "arm a: needs a 'mode'"),
    ({"a": {"mode": "full", "colour": 1}}, r"arm a: unknown keys \['colour'\]"),
    ({"a": {"mode": "full", "flags": {"mode": "state"}}}, "the sweep sets --mode itself"),
    ({"a": {"mode": "full", "flags": {"iters": 3}}}, "arm a: iters is set by the arm and also by --set/--vary"),
    ({"a": {"mode": "fll"}}, "run cartpole_a_seed0: ablate rejects its flags"),
])
def test_bad_arms_are_refused(arms, message):
    with pytest.raises(ValueError, match=message):
        plan(SweepConfig(set=("iters=7",)), arms=arms)


@pytest.mark.parametrize(("kw", "message"), [
    (dict(set=("tsk=3",)), "--set tsk=3: ablate has no flag --tsk"),
    (dict(set=("seed=3",)), "the sweep sets --seed itself; use --seeds"),
    (dict(vary=("name=a,b",)), "the sweep sets --name itself"),
    (dict(set=("compile-helper=true",)), "the sweep sets --compile-helper itself"),  # its runs fill the cores
    (dict(set=("iters",)), "expected FLAG=VALUE"),
    (dict(set=("compile=maybe",)), "--compile: expected true or false, got 'maybe'"),
    (dict(set=("no-compile=true",)), "write compile=false instead"),
    (dict(vary=("horizon=4,,8",)), "an empty value"),
    (dict(vary=("horizon=4,4",)), "values repeat"),
    (dict(set=("horizon=4",), vary=("horizon=8,16",)), "horizon: given in both --set and --vary"),
    (dict(tasks=("cartpol",)), "--tasks cartpol: choose from cartpole, cartpole-swingup, hopper"),
    (dict(modes=("full", "blnd")), "--modes blnd: choose from full, decoupled, state, blind"),
    (dict(seeds=(1, 1)), "--seeds lists a value twice"),
    (dict(modes=()), "--modes needs at least one value"),
    (dict(set=("num-envs=0",)), "run cartpole_full_seed0: --num-envs must be a positive integer"),
    (dict(cpus_per_run=0), "--cpus-per-run must be positive"),
    (dict(gpus_per_run=1.5), "--gpus-per-run above 1 must be a whole number"),
    (dict(address="ray://head:10001"), "Ray Client is not supported"),
    (dict(address="auto", num_cpus=2), "cannot be used with --address"),
])
def test_bad_grid_is_refused_naming_the_flag(kw, message):
    with pytest.raises(ValueError) as info:
        plan(SweepConfig(**kw))
    assert message in str(info.value)


def test_every_task_and_mode_is_a_grid_value(monkeypatch, capsys):
    """The axes take the lists every command shares (tasks.TASKS, gradlab.config.MODES), and --help names them."""
    # a distill student needs its expert, which the other modes refuse: a grid of its own
    others = tuple(m for m in MODES if m != "distill")
    specs = plan(SweepConfig(tasks=TASKS, modes=others, set=("iters=7",)))
    specs += plan(SweepConfig(tasks=TASKS, modes=("distill",), set=("iters=7", "expert=runs/expert")))
    assert {(s.task, s.mode) for s in specs} == {(t, m) for t in TASKS for m in MODES}
    assert "blind" in MODES and "cartpole-swingup" in TASKS
    monkeypatch.setenv("COLUMNS", "200")
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "--tasks {" + ",".join(TASKS) + "}" in text and "--modes {" + ",".join(MODES) + "}" in text


def test_progress_of_a_time_limited_run_is_its_time_budget():
    """ablate-paper's runs end on --time-limit-min with --iters a ceiling: their progress is time, not 31/100000."""
    from ablations.sweep.table import progress_text

    rec = {"iteration": 31, "iters": 100000, "wall_s": 192.0}
    assert progress_text({**rec, "args": ["--task", "hopper"]}) == "it 31/100000"
    assert progress_text({**rec, "args": ["--time-limit-min", "60", "--iters", "100000"]}) == \
        "time 3.2/60 min (it 31)"


def test_attempt_command_names_no_folder_of_the_worker_node():
    """An attempt runs in its scratch folder with relative paths, so the run's config.json records none of the
    node's folders (reports show the recorded command)."""
    (spec,) = plan(SweepConfig(modes=("state",), set=("iters=3",)))
    fresh = attempt_command(spec.args, spec.run_id, resume=False)
    assert fresh == [sys.executable, "-m", "ablations", "ablate", *spec.args, "--out", ".", "--name", spec.run_id,
                     "--no-progress", "--no-compile-helper", "--threads", "1"]
    # the run's torch threads are the CPUs it was given, on a fresh start and a resume alike
    assert attempt_command(spec.args, spec.run_id, resume=True, program=["fake"], threads=2) == [
        "fake", "--resume", spec.run_id, "--restart", "--no-progress", "--no-compile-helper", "--threads", "2"]
    with pytest.raises(ValueError, match="the sweep sets --threads itself; use --cpus-per-run"):
        plan(SweepConfig(modes=("state",), set=("threads=4",)))


def test_tyro_rejection_names_the_run(capsys):
    with pytest.raises(ValueError, match=r"run cartpole_full_seed0: ablate rejects its flags: .*--num-envs abc"):
        plan(SweepConfig(set=("num-envs=abc",)))


def test_toml_file_and_command_line_merge_key_by_key(tmp_path):
    toml = tmp_path / "sweep.toml"
    toml.write_text('tasks = ["cartpole"]\nmodes = ["state"]\nseeds = [0, 1, 2]\nout = "from-file"\n'
                    'gpus-per-run = 0.25\n[set]\niters = 9\nnum_envs = 4\ncompile = false\nactor_hidden = [32, 32]\n'
                    '[vary]\nimage-size = [24, 32]\n')
    cfg, set_table, vary_table = parse_args(["--config", str(toml), "--seeds", "5", "--set", "num-envs=8",
                                             "--vary", "horizon=3,4"])
    assert cfg.seeds == (5,) and cfg.modes == ("state",) and cfg.out == Path("from-file")
    assert cfg.gpus_per_run == 0.25
    assert set_table == {"iters": 9, "num_envs": "8", "compile": False, "actor_hidden": [32, 32]}
    assert vary_table == {"image_size": [24, 32], "horizon": ["3", "4"]}
    specs = plan(cfg, set_table, vary_table)
    assert len(specs) == 4
    assert specs[0].run_id == "cartpole_state_seed5_image-size24_horizon3"
    args = list(specs[0].args)
    assert args[args.index("--num-envs") + 1] == "8" and "--no-compile" in args
    assert args[args.index("--actor-hidden") + 1:][:2] == ["32", "32"]


@pytest.mark.parametrize(("text", "message"), [
    ("tasks = [", "not valid TOML"),
    ("colour = 3\n", "unknown key 'colour'"),
    ("[vary]\nhorizon = 3\n", "[vary] must be a table of flag = [value, ...]"),
    ("[set]\nbogus = 1\n", "ablate has no flag --bogus"),
])
def test_bad_toml_is_refused(tmp_path, text, message):
    toml = tmp_path / "sweep.toml"
    toml.write_text(text)
    with pytest.raises(ValueError) as info:
        parse_args(["--config", str(toml)])
    assert message in str(info.value)


def test_main_reports_bad_input_in_one_line_before_starting_ray(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["--out", str(tmp_path / "s"), "--set", "tsk=3"])
    assert info.value.code == 2
    assert capsys.readouterr().err.strip() == "error: --set tsk=3: ablate has no flag --tsk (see ablate --help)"
    assert not (tmp_path / "s").exists()


def field_docs() -> dict[str, str]:
    """SweepConfig's attribute docstrings (what tyro shows as each flag's help), from the source."""
    import ast

    tree = ast.parse((ROOT / "ablations" / "sweep" / "config.py").read_text())
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "SweepConfig")
    docs = {}
    for a, b in zip(cls.body, cls.body[1:]):
        if isinstance(a, ast.AnnAssign) and isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant):
            docs[a.target.id] = b.value.value
    return docs


def test_help_explains_every_flag(monkeypatch, capsys):
    import dataclasses

    docs = field_docs()
    assert set(docs) == {f.name for f in dataclasses.fields(SweepConfig)}
    monkeypatch.setenv("COLUMNS", "200")
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    text = capsys.readouterr().out
    for name, doc in docs.items():
        assert "--" + name.replace("_", "-") in text, name
        assert " ".join(doc.split()[:3]) in text, name


def test_dry_run_lists_runs_without_ray(tmp_path, capsys):
    main(["--dry-run", "--out", str(tmp_path / "s"), "--modes", "state", "--seeds", "0", "1", "--set", *TINY])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("start    cartpole_state_seed0: ablate --task cartpole --mode state --seed 0")
    assert lines[-1] == "2 runs; 1.0 CPU and 0.0 GPU each"


# ---------------------------------------------------------------------------------------------------------
# Run folders as archives, and the driver's store (no Ray: the store is a plain class underneath)


def fake_run(folder: Path, *, iters: int, checkpoints: list[int]) -> Path:
    (folder / "checkpoints").mkdir(parents=True)
    (folder / "config.json").write_text('{"config": {}}')
    (folder / "metrics.jsonl").write_text("".join(json.dumps({"iter": i}) + "\n" for i in range(1, iters + 1))
                                          + '{"iter": 99, "torn')
    for it in checkpoints:
        (folder / "checkpoints" / f"ckpt_{it:06d}.pt").write_bytes(b"state %d" % it)
    (folder / "checkpoints" / ".ckpt_000009.pt.abc.tmp").write_bytes(b"half written")
    (folder / "videos").mkdir()
    (folder / "videos" / "iter_000002.mp4").write_bytes(b"\x00" * 10)
    return folder


def test_dry_run_refuses_what_the_real_run_refuses(tmp_path, capsys):
    """A grid changed under an existing sweep.json, and more GPUs a run than this machine has, are refused by
    --dry-run as by the real run (it used to list the runs as done, and accept the GPUs)."""
    out = tmp_path / "s"
    dry_run(tiny_sweep(out, modes=("state",), seeds=(0,)))
    specs = plan(tiny_sweep(out, modes=("state",), seeds=(0,)))
    out.mkdir()
    (out / "sweep.json").write_text(json.dumps({"version": 1, "id": "x", "runs": {
        specs[0].run_id: {"args": [*specs[0].args[:-1], "changed"], "status": "done"}}}))
    with pytest.raises(ValueError, match=f"run {specs[0].run_id} was made with the flags"):
        dry_run(tiny_sweep(out, modes=("state",), seeds=(0,)))
    with pytest.raises(ValueError, match=r"--gpus-per-run 1.0: this machine has 0 GPU\(s\)"):
        dry_run(tiny_sweep(tmp_path / "t", modes=("state",), seeds=(0,), gpus_per_run=1.0, num_gpus=0))


def test_pack_keeps_the_newest_checkpoint_and_whole_metrics_lines(tmp_path):
    run = fake_run(tmp_path / "run", iters=4, checkpoints=[2, 4])
    names = tarfile.open(fileobj=io.BytesIO(pack_run(run))).getnames()
    assert sorted(names) == ["checkpoints/ckpt_000004.pt", "config.json", "metrics.jsonl", "videos/iter_000002.mp4"]
    assert "checkpoints/ckpt_000004.pt" not in tarfile.open(
        fileobj=io.BytesIO(pack_run(run, checkpoints=0))).getnames()
    both = tarfile.open(fileobj=io.BytesIO(pack_run(run, checkpoints=2))).getnames()
    assert {"checkpoints/ckpt_000002.pt", "checkpoints/ckpt_000004.pt"} <= set(both)

    dest = tmp_path / "dest"
    (dest / "checkpoints").mkdir(parents=True)
    (dest / "checkpoints" / "ckpt_000002.pt").write_bytes(b"older")
    (dest / "summary.json").write_text("{}")
    unpack_run(pack_run(run), dest)
    assert [r["iter"] for r in read_metrics(dest)] == [1, 2, 3, 4]
    assert (dest / "metrics.jsonl").read_text().endswith("\n")
    # The previous checkpoint stays beside the new one: a resume falls back to it if the newest is damaged.
    assert KEPT_CHECKPOINTS == 2
    assert sorted(p.name for p in (dest / "checkpoints").iterdir()) == ["ckpt_000002.pt", "ckpt_000004.pt"]
    assert (dest / "checkpoints" / "ckpt_000004.pt").read_bytes() == b"state 4"
    assert (dest / "checkpoints" / "ckpt_000002.pt").read_bytes() == b"older"
    assert (dest / "summary.json").exists()  # files the archive does not carry stay


def test_unpack_keeps_two_checkpoints_and_drops_an_abandoned_timeline(tmp_path):
    dest = tmp_path / "dest"
    (dest / "checkpoints").mkdir(parents=True)
    for it in (2, 4, 8):  # 8: written before the run resumed from 4 (its newer checkpoint was damaged)
        (dest / "checkpoints" / f"ckpt_{it:06d}.pt").write_bytes(b"old %d" % it)
    run = fake_run(tmp_path / "run", iters=6, checkpoints=[6])
    unpack_run(pack_run(run), dest)
    assert sorted(p.name for p in (dest / "checkpoints").iterdir()) == ["ckpt_000004.pt", "ckpt_000006.pt"]
    # An archive without checkpoints leaves them alone.
    unpack_run(pack_run(run, checkpoints=0), dest)
    assert sorted(p.name for p in (dest / "checkpoints").iterdir()) == ["ckpt_000004.pt", "ckpt_000006.pt"]


def test_unpack_refuses_paths_outside_the_run_folder(tmp_path):
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        info = tarfile.TarInfo("../evil.txt")
        info.size = 1
        tar.addfile(info, io.BytesIO(b"x"))
    with pytest.raises(ValueError, match=r"refusing member '\.\./evil\.txt'"):
        unpack_run(buf.getvalue(), tmp_path / "run")
    assert not (tmp_path / "evil.txt").exists()


def test_store_hands_out_resume_state_and_refuses_stale_attempts(tmp_path):
    store = RunStore(str(tmp_path), {"b": 3})
    assert store.begin("a") == (1, None)
    worker = fake_run(tmp_path / "worker" / "a", iters=3, checkpoints=[2])
    assert store.save("a", 1, pack_run(worker))
    attempt, pack = store.begin("a")  # a retry
    assert attempt == 2
    names = tarfile.open(fileobj=io.BytesIO(pack)).getnames()
    assert "checkpoints/ckpt_000002.pt" in names and "metrics.jsonl" in names
    assert not any(n.startswith("videos/") for n in names)  # a resume does not need them
    assert not store.save("a", 1, pack_run(worker))  # the dead attempt's late message
    assert store.snapshot()["a"]["attempts"] == 2
    # A run folder without a checkpoint cannot be resumed; ablate needs it empty: it moves to discarded/.
    (tmp_path / "runs" / "b").mkdir(parents=True)
    (tmp_path / "runs" / "b" / "config.json").write_text("{}")
    assert store.begin("b") == (4, None)
    assert not (tmp_path / "runs" / "b").exists()
    assert [p.name.split(".")[:2] for p in (tmp_path / "discarded").iterdir()] == [["b", "attempt3"]]


def test_rerun_with_other_flags_in_the_same_folder_is_refused(tmp_path):
    out = tmp_path / "s"
    out.mkdir()
    spec = plan(tiny_sweep(out, modes=("state",)))[0]
    (out / "sweep.json").write_text(json.dumps({"version": 1, "id": "x", "runs": {
        spec.run_id: {"args": [*spec.args[:-2]], "status": "done"}}}))
    with pytest.raises(ValueError, match=r"was made with the flags .*use another --out"):
        run_sweep(tiny_sweep(out, modes=("state",)))


# ---------------------------------------------------------------------------------------------------------
# Real sweeps on a local Ray cluster


@pytest.fixture(scope="module")
def ray_cluster():
    """One local cluster for the module (starting one takes seconds); run_sweep uses this connection."""
    ray = pytest.importorskip("ray")
    import logging

    ray.init(address="local", num_cpus=2, include_dashboard=False, logging_level=logging.WARNING,
             log_to_driver=False)
    yield ray
    ray.shutdown()


def assert_complete_run(run: Path, iters: int, *, checkpoint: bool = True) -> None:
    """Every iteration once, in order; finished; the files ablate writes, gathered in the sweep folder."""
    assert [r["iter"] for r in read_metrics(run)] == list(range(1, iters + 1))
    summary = json.loads((run / "summary.json").read_text())
    assert summary["status"] == "finished" and summary["iterations"] == iters
    assert (run / "config.json").exists() and (run / "git.txt").exists()
    if checkpoint:
        # The final checkpoint and at most one older one (which older ones reached the folder depends on timing).
        names = sorted((p.name for p in (run / "checkpoints").iterdir()), reverse=True)
        assert names[0] == f"ckpt_{iters:06d}.pt" and 1 <= len(names) <= KEPT_CHECKPOINTS, names
    else:
        assert not (run / "checkpoints").exists()


def killed_at(out: Path, run_id: str) -> int:
    """The iteration of the checkpoint the run had shipped when its worker was killed (fake_ablate.py's note)."""
    return int((out / ".killed" / run_id).read_text().split("_")[1].split(".")[0])


@pytest.mark.slow
def test_sweep_recovers_a_killed_worker_then_a_rerun_skips_everything(ray_cluster, tmp_path):
    out = tmp_path / "sweep"
    killed = "cartpole_decoupled_seed0"
    program = kill_worker_once(out, killed)
    manifest = run_sweep(tiny_sweep(out, progress=True), program=program)  # the live table too
    runs = manifest["runs"]
    assert set(runs) == {killed, "cartpole_state_seed0"}
    assert manifest["counts"] == {"queued": 0, "running": 0, "done": 2, "failed": 0, "interrupted": 0}
    assert load_manifest(out) == manifest
    for run_id, rec in runs.items():
        assert rec["status"] == "done" and rec["error"] is None and rec["iteration"] == 12, (run_id, rec)
        assert rec["folder"] == f"runs/{run_id}"
        assert_complete_run(out / rec["folder"], 12)
        # The recorded command names no folder of the worker node (the run trained in a scratch folder there).
        command = json.loads((out / rec["folder"] / "config.json").read_text())["command"]
        assert command[command.index("--out") + 1] == "." and command[command.index("--name") + 1] == run_id
        assert not any(tempfile.gettempdir() in arg for arg in command[1:]), command
    # The worker died after shipping an early checkpoint; Ray retried it and the retry resumed from there.
    assert 2 <= killed_at(out, killed) < 12
    assert runs[killed]["attempts"] == 2 and runs[killed]["resumed"] is True
    assert runs["cartpole_state_seed0"]["attempts"] == 1 and runs["cartpole_state_seed0"]["resumed"] is False
    # A killed worker sends no log: its attempt's output was in the node's scratch folder.
    logs = {f"{killed}.attempt2.log", "cartpole_state_seed0.attempt1.log"}
    assert {p.name for p in (out / "logs").iterdir()} == logs

    again = run_sweep(tiny_sweep(out), program=program)
    assert {k: (r["status"], r["attempts"]) for k, r in again["runs"].items()} == {
        killed: ("done", 2), "cartpole_state_seed0": ("done", 1)}
    assert {p.name for p in (out / "logs").iterdir()} == logs


def test_a_sweep_the_cluster_cannot_run_is_refused_leaving_no_sweep_json(ray_cluster, tmp_path):
    """A refused start writes nothing: no sweep.json, and no sweep folder made for it."""
    out = tmp_path / "sweep"
    with pytest.raises(ValueError, match="no node of the cluster has that many GPUs"):
        run_sweep(tiny_sweep(out, gpus_per_run=1.0), program=["unused"])
    assert not out.exists()


@pytest.mark.slow
def test_failed_run_is_recorded_and_a_rerun_resumes_it(ray_cluster, tmp_path):
    out = tmp_path / "sweep"
    killed = "cartpole_state_seed1"
    program = kill_worker_once(out, killed)
    manifest = run_sweep(tiny_sweep(out, modes=("state",), seeds=(1,), max_retries=0), program=program)
    rec = manifest["runs"][killed]
    assert rec["status"] == "failed" and manifest["counts"]["failed"] == 1
    assert "Worker" in rec["error"] or "worker" in rec["error"], rec["error"]
    step = killed_at(out, killed)
    # The sweep folder holds the run up to the checkpoint it shipped, and nothing past it.
    assert [r["iter"] for r in read_metrics(out / rec["folder"])][:step] == list(range(1, step + 1))
    assert (out / rec["folder"] / "checkpoints" / f"ckpt_{step:06d}.pt").exists()

    manifest = run_sweep(tiny_sweep(out, modes=("state",), seeds=(1,), keep_checkpoints=False), program=program)
    rec = manifest["runs"][killed]
    assert rec["status"] == "done" and rec["error"] is None and rec["resumed"] is True and rec["attempts"] == 2
    assert_complete_run(out / rec["folder"], 12, checkpoint=False)


def max_overlap(spans: list[dict]) -> int:
    """The most intervals [start, end] open at one moment."""
    events = sorted([(s["start"], 1) for s in spans] + [(s["end"], -1) for s in spans])
    most = now = 0
    for _, step in events:  # at equal times an end (-1) sorts first: touching intervals do not overlap
        now += step
        most = max(most, now)
    return most


@pytest.mark.slow
def test_sweep_trains_at_most_cpus_over_cpus_per_run_runs_at_once(ray_cluster, tmp_path):
    """Two CPUs, one per run: six runs, never more than two training at once (each run records when it trained)."""
    log = tmp_path / "spans.jsonl"
    cfg = SweepConfig(out=tmp_path / "sweep", tasks=("cartpole",), modes=("decoupled", "state"), seeds=(0, 1, 2),
                      set=("iters=8",), cpus_per_run=1.0, progress=False)
    assert run_slots(cfg) == 2
    manifest = run_sweep(cfg, program=(sys.executable, str(FAKE_ABLATE), "record", str(log), "4", "--"))
    assert manifest["counts"]["done"] == 6
    spans = [json.loads(line) for line in log.read_text().splitlines()]
    assert sorted(s["run"] for s in spans) == sorted(manifest["runs"])
    assert max_overlap(spans) == 2
    assert {s["threads"] for s in spans} == {"1"}  # ablate --threads: the run's --cpus-per-run


@pytest.mark.slow
def test_a_run_stopped_by_a_signal_is_retried_from_its_checkpoint(ray_cluster, tmp_path):
    """ablate stops on SIGTERM after checkpointing (summary "interrupted", exit status 130): the worker ships that
    checkpoint and Ray retries the run, which resumes from it and repeats no iteration."""
    out = tmp_path / "sweep"
    victim = "cartpole_state_seed0"
    program = (sys.executable, str(FAKE_ABLATE), "signal-once", str(out), victim, "--")
    manifest = run_sweep(tiny_sweep(out, modes=("state",)), program=program)
    rec = manifest["runs"][victim]
    assert rec["status"] == "done" and rec["attempts"] == 2 and rec["resumed"] is True, rec
    assert (out / ".signalled" / victim).read_text() == "ckpt_000002.pt"
    assert_complete_run(out / rec["folder"], 12)
    first = (out / "logs" / f"{victim}.attempt1.log").read_text()
    assert "SIGTERM: stopping once this iteration has finished" in first and "Traceback" not in first


def ctrl_c_after(out: Path, run_ids: list[str], lines: int) -> threading.Thread:
    """A thread that presses Ctrl-C (a SIGINT to this process: KeyboardInterrupt in the driver) once each run's
    attempt has written ``lines`` metrics lines in its worker's scratch folder."""
    import _thread

    def press() -> None:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:
            manifest = out / "sweep.json"
            if manifest.exists():
                base = Path(tempfile.gettempdir()) / "ablate-sweep" / json.loads(manifest.read_text())["id"]
                counts = [sum(len(p.read_text().splitlines()) for p in base.glob(f"{r}.attempt*/{r}/metrics.jsonl"))
                          for r in run_ids]
                if all(n >= lines for n in counts):
                    _thread.interrupt_main()
                    return
            time.sleep(0.05)

    thread = threading.Thread(target=press, daemon=True)
    thread.start()
    return thread


@pytest.mark.parametrize("stage", ["first", pytest.param("second", marks=pytest.mark.slow)])
def test_ctrl_c_keeps_each_runs_last_finished_iteration_and_a_rerun_resumes_there(ray_cluster, tmp_path,
                                                                                 monkeypatch, capsys, stage):
    """Ctrl-C on the driver: each worker sends its ablate SIGINT (first: it finishes the iteration it is in and
    checkpoints it; second, after a short grace with long iterations: a second SIGINT stops it at once, keeping
    the last finished one), sends the folder and returns "interrupted", not retried. sweep.json records the kept
    iteration, the driver prints it, and a rerun resumes from it (no periodic checkpoint in between)."""
    import ablations.sweep.driver as driver

    log = tmp_path / "spans.jsonl"
    out = tmp_path / "sweep"
    # 0.4 s an iteration, Ctrl-C after 2; or 4 s, after 1 (the second SIGINT comes well inside iteration 2)
    seconds, lines = {"first": (8.0, 2), "second": (80.0, 1)}[stage]
    if stage == "second":
        monkeypatch.setattr(driver, "STOP_GRACE_S", 0.2)
    cfg = SweepConfig(out=out, tasks=("cartpole",), modes=("decoupled", "state"), seeds=(0,),
                      set=("iters=20", "checkpoint-every=100"), cpus_per_run=1.0, progress=False)
    program = (sys.executable, str(FAKE_ABLATE), "record", str(log), str(seconds), "--")
    run_ids = [s.run_id for s in plan(cfg)]
    ctrl_c_after(out, run_ids, lines)
    with pytest.raises(KeyboardInterrupt):
        run_sweep(cfg, program=program)
    printed = capsys.readouterr()
    err = printed.err
    manifest = load_manifest(out)
    spans = {s["run"]: s for s in map(json.loads, log.read_text().splitlines())}
    for run_id in run_ids:
        rec = manifest["runs"][run_id]
        kept = spans[run_id]["interrupted"]
        assert rec["status"] == "interrupted" and rec["attempts"] == 1 and rec["checkpoint"] == kept, rec
        assert lines <= kept < 20
        if stage == "second":
            assert kept == 1  # the iteration under way when the SIGINTs came is lost, not waited for
        run = out / rec["folder"]
        assert [r["iter"] for r in read_metrics(run)] == list(range(1, kept + 1))
        assert [p.name for p in (run / "checkpoints").iterdir()] == [f"ckpt_{kept:06d}.pt"]
        assert json.loads((run / "summary.json").read_text())["status"] == "interrupted"
        assert f"interrupted {run_id}: kept iteration {kept} of 20 (runs/{run_id})" in err
        assert f"it {kept}/20 ckpt {kept}" in printed.out  # the status line: progress, the checkpoint beside it
    assert manifest["counts"]["interrupted"] == 2 and not (out / "discarded").exists()
    if stage == "second":
        return
    again = run_sweep(cfg, program=(sys.executable, str(FAKE_ABLATE), "record", str(log), "1", "--"))
    resumed = {s["run"]: s["resumed_from"] for s in map(json.loads, log.read_text().splitlines()[2:])}
    assert resumed == {r: spans[r]["interrupted"] for r in run_ids}
    for run_id in run_ids:
        rec = again["runs"][run_id]
        assert rec["status"] == "done" and rec["attempts"] == 2 and rec["resumed"] is True, rec
        assert [r["iter"] for r in read_metrics(out / rec["folder"])] == list(range(1, 21))


@pytest.mark.slow
def test_ctrl_c_on_a_sweep_of_the_real_ablate_keeps_its_last_finished_iteration(ray_cluster, tmp_path, capsys):
    """The real ablate (cartpole, 4 environments, no video, the default --checkpoint-every 50): Ctrl-C after its
    third iteration leaves a checkpoint of an iteration from 3 on in the sweep folder, which a rerun resumes."""
    out = tmp_path / "sweep"
    cfg = SweepConfig(out=out, tasks=("cartpole",), modes=("decoupled",), seeds=(0,),
                      set=("iters=12", "num-envs=4", "video-every=0", "eval-every=0", "device=cpu"),
                      cpus_per_run=1.0, progress=False)
    (run_id,) = [s.run_id for s in plan(cfg)]
    ctrl_c_after(out, [run_id], 3)
    with pytest.raises(KeyboardInterrupt):
        run_sweep(cfg)
    rec = load_manifest(out)["runs"][run_id]
    kept = rec["checkpoint"]
    assert rec["status"] == "interrupted" and rec["attempts"] == 1 and 3 <= kept < 12, rec
    run = out / rec["folder"]
    assert (run / "checkpoints" / f"ckpt_{kept:06d}.pt").exists()
    assert [r["iter"] for r in read_metrics(run)] == list(range(1, kept + 1))
    assert json.loads((run / "summary.json").read_text())["status"] == "interrupted"
    assert f"kept iteration {kept} of 12" in capsys.readouterr().err
    again = run_sweep(cfg)["runs"][run_id]
    assert again["status"] == "done" and again["resumed"] is True and again["attempts"] == 2, again
    assert_complete_run(run, 12)


def test_run_slots_divide_each_node_by_what_a_run_takes(monkeypatch):
    ray = pytest.importorskip("ray")
    nodes = [{"Alive": True, "Resources": {"CPU": 16.0, "GPU": 1.0}},
             {"Alive": True, "Resources": {"CPU": 3.0}},
             {"Alive": False, "Resources": {"CPU": 64.0, "GPU": 8.0}}]
    monkeypatch.setattr(ray, "nodes", lambda: nodes)
    assert run_slots(SweepConfig(cpus_per_run=1.0)) == 16 + 3
    assert run_slots(SweepConfig(cpus_per_run=1.5)) == 10 + 2
    assert run_slots(SweepConfig(cpus_per_run=0.5, gpus_per_run=0.25)) == 4  # the GPU node's four quarters
    assert run_slots(SweepConfig(cpus_per_run=0.1)) == 160 + 30  # 3.0 / 0.1 is 29.999999999999996 in floats
    assert run_slots(SweepConfig(cpus_per_run=32.0)) == 1  # never none (_check_resources refuses such a sweep)


def test_rays_token_notice_is_left_out_and_its_warning_kept():
    pytest.importorskip("ray")
    import logging

    from ray._private.authentication import authentication_token_setup as auth

    from ablations.sweep.driver import quiet_token_notice

    seen: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: seen.append(record.getMessage())
    logger = logging.getLogger(auth.__name__)
    logger.addHandler(handler)
    try:
        quiet_token_notice()
        auth._warn_token_auth_enabled()  # what Ray logs on every ray.init that starts a local cluster
        auth._warn_token_auth_disabled()
    finally:
        logger.removeHandler(handler)
    assert len(seen) == 1 and seen[0].startswith("Token authentication is disabled"), seen


@pytest.mark.slow
def test_a_local_cluster_starts_without_rays_token_notice(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("RAY_AUTH_MODE", "RAY_ADDRESS")}
    code = ("import ray\nfrom ablations.sweep import SweepConfig\nfrom ablations.sweep.driver import _ray_init\n"
            "assert _ray_init(SweepConfig(num_cpus=1))\nray.shutdown()\n")
    proc = subprocess.run([sys.executable, "-c", code], env=env, cwd=tmp_path, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "Token authentication" not in proc.stderr + proc.stdout


@pytest.mark.slow
def test_grid_of_two_modes_and_two_seeds_with_a_kill_and_failing_runs(ray_cluster, tmp_path, capsys):
    """The grid of the issue: decoupled and state, 2 seeds; one worker killed; a --vary point whose runs fail."""
    out = tmp_path / "sweep"
    killed = "cartpole_decoupled_seed1_abort-grad-norm1e8"
    with pytest.raises(SystemExit) as info:
        main(["--out", str(out), "--modes", "decoupled", "state", "--seeds", "0", "1", "--set", *TINY,
              "--vary", "abort-grad-norm=1e8,1e-12", "--no-progress"], program=kill_worker_once(out, killed))
    assert info.value.code == 1  # some runs failed
    manifest = load_manifest(out)
    assert len(manifest["runs"]) == 8
    assert manifest["command"][:3] == ["ablate-sweep", "--out", str(out)]
    for run_id, rec in manifest["runs"].items():
        if run_id.endswith("1e-12"):
            assert rec["status"] == "failed" and "abort_grad_norm" in rec["error"], rec
        else:
            assert rec["status"] == "done", rec
            assert_complete_run(out / rec["folder"], 12)
    assert manifest["runs"][killed]["attempts"] == 2
    err = capsys.readouterr().err
    assert err.count("failed cartpole_") == 4
