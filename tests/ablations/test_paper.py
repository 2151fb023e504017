"""ablate-paper: the arm table as a sweep (planned, not run), and its report from fixture run folders."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest

from ablations import paper
from ablations.paper import PaperConfig, main, sweep_config
from ablations.reports import paper as paper_report
from ablations.reports.paper import build_paper_report
from ablations.reports.paper_numbers import format_value, load_paper_numbers
from ablations.sweep import pack_runs, plan
from tests.ablations.conftest import write_run
from tests.ablations.test_report import write_sweep
from vocabulary import ARMS, DEFAULT_ARMS

#: Ten minutes of wall clock per iteration: twelve iterations span two hours, past the paper's 55-minute mark.
WALL = 600.0


def test_arms_expand_to_the_papers_sweep(monkeypatch):
    monkeypatch.setattr(paper, "cuda_gpus", lambda: 1)
    cfg = PaperConfig(out=Path("p"), time_limit_min=55.0, set=("cosine-every=5",))
    sweep, arms = sweep_config(cfg)
    specs = plan(sweep, arms=arms)
    assert cfg.tasks == ("cartpole-swingup", "hopper", "ant")
    assert len(specs) == 3 * len(DEFAULT_ARMS) * 3  # three tasks x six arms x seeds 0 1 2
    assert list(DEFAULT_ARMS) == ["decoupled", "full-hard", "full-hard-dva", "full-soft", "state", "blind"]
    assert set(DEFAULT_ARMS) < set(ARMS)
    by_id = {s.run_id: s for s in specs}
    hard = by_id["hopper_full-hard_seed2"]
    assert hard.mode == "full" and hard.arm == "full-hard"
    assert list(hard.args) == ["--task", "hopper", "--mode", "full", "--seed", "2", "--iters", "100000",
                               "--time-limit-min", "55", "--cosine-every", "5", "--preset", "shac-diffrender"]
    # the matched control: full-hard's estimator on the dva preset's schedule
    matched = by_id["hopper_full-hard-dva_seed2"]
    assert list(matched.args) == [*hard.args[:-2], "--raster-model", "hard"] and "--preset" not in matched.args
    soft = by_id["ant_full-soft_seed0"]
    assert soft.mode == "full" and "--preset" not in soft.args and "--raster-model" not in soft.args
    assert {by_id[f"ant_{m}_seed1"].mode for m in ("decoupled", "state", "blind")} == {"decoupled", "state", "blind"}
    # full-alpha (not a default arm) is the full estimator through coverage compositing
    alpha_sweep, alpha_arms = sweep_config(PaperConfig(out=Path("p"), tasks=("ant",), arms=("full-alpha",),
                                                       seeds=(0,)))
    (alpha,) = plan(alpha_sweep, arms=alpha_arms)
    assert alpha.mode == "full" and list(alpha.args[-2:]) == ["--raster-model", "alpha"]
    assert sweep.gpus_per_run == 1.0 and sweep.modes == ("decoupled", "full", "state", "blind")
    # On a GPU the arms pack (--pack auto): per task, the five pixel arms x 3 seeds in two populations (8 + 7),
    # the state runs in one of their own.
    assert cfg.pack == "auto" and sweep.pack_size() == 12
    jobs = pack_runs(specs, sweep.pack_size())
    assert [len(j.run_ids) for j in jobs] == [8, 7, 3] * 3
    assert all({by_id[r].mode for r in j.run_ids} == {"state"} for j in jobs[2::3])
    assert all(by_id[r].task == j.run_ids[0].split("_")[0] for j in jobs for r in j.run_ids)


def test_on_the_cpu_paper_runs_one_per_process(monkeypatch):
    monkeypatch.setattr(paper, "cuda_gpus", lambda: 0)
    sweep, arms = sweep_config(PaperConfig(out=Path("p"), tasks=("hopper",), seeds=(0,)))
    assert sweep.gpus_per_run == 0 and sweep.pack_size() == 1
    assert all(not j.population for j in pack_runs(plan(sweep, arms=arms), sweep.pack_size()))
    sweep, _ = sweep_config(PaperConfig(out=Path("p"), tasks=("hopper",), seeds=(0,), pack="3"))
    assert sweep.pack_size() == 3


def test_dry_run_lists_the_runs_and_starts_nothing(tmp_path, capsys):
    main(["--dry-run", "--out", str(tmp_path / "p"), "--tasks", "hopper", "--arms", "decoupled", "full-hard",
          "--seeds", "0", "--time-limit-min", "None", "--iters", "50", "--gpus-per-run", "0"])
    lines = capsys.readouterr().out.splitlines()
    assert lines == ["start    hopper_decoupled_seed0: ablate --task hopper --mode decoupled --seed 0 --iters 50",
                     "start    hopper_full-hard_seed0: ablate --task hopper --mode full --seed 0 --iters 50 "
                     "--preset shac-diffrender",
                     "2 runs; 1.0 CPU and 0.0 GPU each"]
    assert not (tmp_path / "p").exists()


def test_without_a_gpu_the_runs_go_to_the_cpu_and_dry_run_says_so(tmp_path, capsys, monkeypatch):
    argv = ["--dry-run", "--out", str(tmp_path / "p"), "--tasks", "hopper", "--arms", "state", "--seeds", "0"]
    monkeypatch.setattr(paper, "cuda_gpus", lambda: 0)
    main(argv)
    lines = capsys.readouterr().out.splitlines()
    assert lines[-2:] == ["1 runs; 1.0 CPU and 0.0 GPU each",
                          "no CUDA GPU on this machine: the runs train on the CPU (--gpus-per-run 0); on a GPU "
                          "machine each run gets one (--gpus-per-run 1)"]
    main([*argv, "--gpus-per-run", "0"])  # asked for: nothing to explain
    assert capsys.readouterr().out.splitlines()[-1] == "1 runs; 1.0 CPU and 0.0 GPU each"
    monkeypatch.setattr(paper, "cuda_gpus", lambda: 2)
    main(argv)
    assert capsys.readouterr().out.splitlines()[-1] == "1 runs; 1.0 CPU and 1.0 GPU each"
    # A cluster to join decides for itself what it has: one GPU per run unless told otherwise.
    monkeypatch.setattr(paper, "cuda_gpus", lambda: 0)
    assert paper.gpus_per_run(PaperConfig(address="auto")) == (1.0, None)


@pytest.mark.parametrize(("argv", "message"), [
    (["--arms", "full-medium"], "--arms full-medium: choose from decoupled, full-hard"),
    (["--arms", "state", "state"], "--arms lists an arm twice"),
    (["--set", "iters=5"], "--set iters=5: ablate-paper sets it; use --iters"),
    (["--set", "time-limit-min=5"], "use --time-limit-min"),
    (["--time-limit-min", "0"], "--time-limit-min must be positive"),
    (["--tasks", "hoper"], "--tasks hoper: choose from cartpole, cartpole-swingup, hopper, ant, humanoid, cheetah"),
])
def test_bad_options_are_one_line_errors(tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as e:
        main(["--dry-run", "--out", str(tmp_path / "p"), *argv])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err, err


def paper_sweep(folder: Path, *, seeds=(0, 1)) -> Path:
    """A finished ablate-paper folder: sweep.json and hopper runs of every arm (one run queued, no folder)."""
    arms = {n: {"mode": a.mode, "flags": a.flags, "about": a.about} for n, a in ARMS.items()}
    runs = {}
    for arm, spec in arms.items():
        for seed in seeds:
            run_id = f"hopper_{arm}_seed{seed}"
            runs[run_id] = {"task": "hopper", "mode": spec["mode"], "arm": arm, "seed": seed, "status": "done",
                            "folder": f"runs/{run_id}"}
            settings = {"preset": "shac-diffrender" if arm == "full-hard" else "dva",
                        "raster_model": "hard" if arm.startswith("full-hard") else "alpha"}
            write_run(folder / "runs", task="hopper", mode=spec["mode"], seed=seed, name=run_id,
                      bwd_ms=30.0 if arm == "full-hard" else 10.0, wall_per_iter=WALL, settings=settings,
                      probe_every=3 if spec["mode"] in ("full", "decoupled") else 0)
    runs["hopper_blind_seed9"] = {"task": "hopper", "mode": "blind", "arm": "blind", "seed": 9, "status": "queued",
                                  "folder": "runs/hopper_blind_seed9"}
    (folder / "sweep.json").write_text(json.dumps({
        "version": 1, "id": "abc", "created": "2026-05-01T10:00:00", "updated": "2026-05-01T12:00:00",
        "command": ["ablate-paper", "--tasks", "hopper"], "runs": runs,
        "sweep": {"tasks": ["hopper"], "modes": ["decoupled", "full", "state", "blind"], "seeds": list(seeds),
                  "set": {"iters": "100000", "time_limit_min": "120"}, "vary": {}, "arms": arms}}))
    return folder


@pytest.fixture
def floors(tmp_path):
    path = tmp_path / "floors.json"
    path.write_text(json.dumps({"tasks": {"hopper": {"zero": {"mean": 12.5, "std": 1.0, "episodes": 64},
                                                     "random": {"mean": 33.0, "std": 2.0, "episodes": 64}}}}))
    return path


def rows_of(text: str, prefix: str) -> list[list[str]]:
    return [[c.strip() for c in ln.strip("|").split("|")] for ln in text.splitlines() if ln.startswith(prefix)]


def test_report_of_a_sweep_folder(tmp_path, floors, monkeypatch):
    folder = paper_sweep(tmp_path / "p")
    seen = []
    real = paper_report.make_plots

    def spy(runs, out, **kw):
        res = real(runs, out, **kw)
        seen.append(res)
        return res

    monkeypatch.setattr(paper_report, "make_plots", spy)
    out = build_paper_report(folder, floors=floors, memory=(write_sweep(tmp_path / "mem"),))
    assert out == folder / "report" / "report.md"
    text = out.read_text()

    # Arms, with their flags and run counts; the queued run without a folder is named.
    assert rows_of(text, "| full-hard |")[0][:3] == ["full-hard", "full", "--preset shac-diffrender"]
    assert rows_of(text, "| blind |")[0][4] == "2 done, 1 queued"
    assert "hopper_blind_seed9" in text

    # Return curves with seed bands (two seeds per arm) and the floors, linked and drawn.
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    for name in ("return_vs_wall_clock.png", "return_vs_env_steps.png", "probe_grad_norms.png",
                 "cosine_vs_iter.png", "render_term_groups.png", "image_sensitivity.png", "memory_bwd.png"):
        link = next(lk for lk in links if lk.endswith(name))
        assert (out.parent / link).read_bytes()[:4] == b"\x89PNG", name
    assert "(n=2)" in text or "mean +- one sample standard deviation" in text.lower()
    (res,) = seen
    assert not res.warnings and "return_vs_wall_clock.png" in res.files
    assert "| hopper | 12.5 +- 1 | 33 +- 2 | 64 |" in text

    # Fig. 3 series: medians over every probe of both seeds (grad_norm_full = 2 + seed).
    fig3 = {r[1]: r for r in rows_of(text, "| hopper | ") if len(r) == 7 and r[2].isdigit()}
    assert set(fig3) == {"decoupled", "full-hard", "full-hard-dva", "full-soft", "full-alpha"}
    assert fig3["full-hard"][2:5] == ["8", "2.5", "1"]  # 4 probes x 2 seeds; medians of |g_full|, |g_decoupled|

    # Our numbers beside the paper's, each paper number with its citation.
    numbers = load_paper_numbers()
    comparison = rows_of(text, "| hopper | ")
    final = next(r for r in comparison if r[1] == "final return (ours: training return)" and r[2] == "decoupled")
    assert final[3].startswith("120.5 +- 0.7071 (n=2)") and final[4] == "~5k"
    assert numbers.cite("readme") in final[5] and "read off plots" in final[5]
    final_row = "final return (ours: training return)"
    assert next(r for r in comparison if r[1] == final_row and r[2] == "blind")[4:] == ["-", "-"]
    at55 = next(r for r in comparison if r[1] == "return at 55 min" and r[2] == "full-hard")
    # 55 min = 3300 s lies between iterations 5 (3000 s) and 6 (3600 s): returns 55 and 56 for seeds 0 and 1.
    assert at55[3] == "55.5 +- 0.7071 (n=2)" and at55[4] == "~3.8k"
    reach = next(r for r in comparison if r[1] == "minutes to return 4300" and r[2] == "decoupled")
    assert reach[3] == "not reached; 0/2 seeds reached it" and reach[4] == "~<= 55"
    bwd = next(r for r in comparison if r[1] == "backward per iteration" and r[2] == "full-hard")
    assert bwd[3].startswith("30 ms (runs") and bwd[4] == "510 ms" and numbers.cite("table1") in bwd[5]

    # Table 1 from the runs (no benchmark given): full-hard 30 ms against decoupled 10 ms.
    table1 = [r for r in rows_of(text, "| hopper | 10.0 |")]
    assert any(r[2:4] == ["30.0", "3.00x"] and "full-hard" in r[4] for r in table1)
    # Memory sweep and provenance.
    assert "## 7. Memory against scene complexity (Fig. 10)" in text and "| full | 8 | 64 |" in text
    assert "Sweep command: `ablate-paper --tasks hopper`" in text


@pytest.mark.slow
def test_report_uses_a_benchmark_for_table1(tmp_path, floors):
    folder = paper_sweep(tmp_path / "p", seeds=(0,))
    bench = tmp_path / "iteration.json"
    results = [{"task": "hopper", "mode": "decoupled", "bwd_ms": 4.0, "num_envs": 64, "horizon": 32,
                "image_size": 84, "status": "ok"},
               {"task": "hopper", "mode": "full", "bwd_ms": None, "status": "oom"}]
    bench.write_text(json.dumps({"date": "2026-05-02", "gpu": "NVIDIA H100",
                                 "command": "python benchmarks/iteration.py", "results": results}))
    out = build_paper_report(folder, floors=floors, benchmark=bench, out=tmp_path / "r" / "paper.md")
    text = out.read_text()
    rows = rows_of(text, "| hopper | 4 |")  # the benchmark's decoupled time wins over the runs' 10 ms
    assert rows and all("decoupled: 64x32 84px, NVIDIA H100, benchmark iteration.json (n=1)" in r[4] for r in rows)
    assert "python benchmarks/iteration.py" in text
    # Several files (e.g. one per process of tasks): the first that has a task and mode wins, later ones fill in;
    # a full time is set beside the decoupled time of its own file (a ratio of one measurement).
    more = tmp_path / "iteration_more.json"
    more.write_text(json.dumps({"date": "2026-05-03", "gpu": "NVIDIA H100", "command": "python more.py", "results": [
        {"task": "hopper", "mode": "decoupled", "bwd_ms": 99.0, "status": "ok"},
        {"task": "hopper", "mode": "full", "bwd_ms": 7.0, "status": "ok"}]}))
    text = build_paper_report(folder, floors=floors, benchmark=(bench, more), out=tmp_path / "r2" / "p.md").read_text()
    assert rows_of(text, "| hopper | 4 |")  # the runs' full arms beside the first file's decoupled time
    (paired,) = rows_of(text, "| hopper | 99")
    assert paired[1:4] == ["99.0", "7", "0.07x"] and paired[4] == ("decoupled: ?, NVIDIA H100, benchmark "
                                                                    "iteration_more.json (n=1); full: ?, NVIDIA H100, "
                                                                    "benchmark iteration_more.json (n=1)")
    assert "python more.py" in text


def test_missing_inputs_are_named(tmp_path, floors, capsys):
    with pytest.raises(ValueError, match="no such folder"):
        build_paper_report(tmp_path / "none")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"no sweep\.json there"):
        build_paper_report(tmp_path / "empty")
    folder = paper_sweep(tmp_path / "p", seeds=(0,))
    with pytest.raises(ValueError, match=r"--benchmark .*: no such file"):
        build_paper_report(folder, benchmark=tmp_path / "nope.json")
    with pytest.raises(ValueError, match=r"--memory .*: no memory\.csv"):
        build_paper_report(folder, memory=(tmp_path / "empty",))
    with pytest.raises(ValueError, match=r"--floors .*: no such file"):
        build_paper_report(folder, floors=tmp_path / "f.json")
    with pytest.raises(ValueError, match=r"ending in \.md"):
        build_paper_report(folder, out=tmp_path / "r.txt")
    with pytest.raises(SystemExit) as e:
        main(["--report-only", str(tmp_path / "empty")])
    assert e.value.code == 2 and "no sweep.json" in capsys.readouterr().err
    # A task without floors is named once, in the report and as a warning.
    flo = tmp_path / "other.json"
    flo.write_text(json.dumps({"tasks": {"ant": {"zero": {"mean": 1.0}}}}))
    with pytest.warns(UserWarning, match="no return floor for task 'hopper'"):
        text = build_paper_report(folder, floors=flo).read_text()
    assert text.count("**Warning:** no return floor for task 'hopper'") == 1


def test_report_only_regenerates_from_the_command_line(tmp_path, floors, capsys):
    folder = paper_sweep(tmp_path / "p", seeds=(0,))
    main(["--report-only", str(folder), "--floors", str(floors)])
    out = Path(capsys.readouterr().out.strip())
    assert out == folder / "report" / "report.md" and out.read_text().startswith("# D.Va paper experiments: hopper")


def test_wall_clock_helpers(tmp_path):
    run = paper_report.load_run(write_run(tmp_path, task="hopper", mode="decoupled", seed=1, wall_per_iter=WALL))
    assert paper_report._time_to(run, 50.0) == 5 * WALL  # return 10 * iter + 1 first reaches 50 at iteration 5
    assert paper_report._time_to(run, 1e6) is None
    assert paper_report._return_at(run, 3300.0) == pytest.approx(56.0)
    assert paper_report._return_at(run, 12 * WALL + 1) is None  # the run stopped before


def test_paper_numbers_say_where_they_come_from_and_how():
    numbers = load_paper_numbers()
    for table in (numbers.final_return, numbers.return_at_time, numbers.backward_s):
        for entry in table:
            assert numbers.cite(entry["source"])  # every number has a citation
    plot_read = [e for e in numbers.final_return if e["approx"]]
    assert {format_value(e) for e in plot_read} >= {"~5k", "~7.5-8k", "~1.8k"}
    stated = next(e for e in numbers.final_return if not e["approx"])
    assert format_value(stated) == "7475.77 +- 812.48" and "OpenReview" in numbers.cite(stated["source"])
    assert {e["task"]: e["minutes"] for e in numbers.return_at_time} == {"cartpole": 45, "hopper": 55, "ant": 360,
                                                                         "humanoid": 360}


def test_bad_paper_numbers_file_is_named(tmp_path):
    good = json.loads(load_paper_numbers().path.read_text())
    bad = dict(good, backward_s=[{"task": "ant", "dva": 0.2, "approx": False, "source": "blog"}])
    (tmp_path / "n.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"backward_s\[0\]: source 'blog' is not in 'sources'"):
        load_paper_numbers(tmp_path / "n.json")
    bad = dict(good, final_return=[{"task": "ant", "method": "dva", "approx": True, "source": "readme"}])
    (tmp_path / "n.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="needs a numeric value, or low and high"):
        load_paper_numbers(tmp_path / "n.json")


def test_recorded_command_reruns_as_written_and_the_report_holds_relative_paths(tmp_path, monkeypatch, capsys):
    """A sweep whose runs have all finished needs no Ray: ablate-paper records its command, writes the report, and
    that command, run again as written, does the same."""
    import shlex

    from tests.ablations.test_report import absolute_paths

    monkeypatch.chdir(tmp_path)
    argv = ["--out", "p", "--tasks", "hopper", "--arms", "decoupled", "state", "--seeds", "0", "--iters", "12",
            "--time-limit-min", "30", "--gpus-per-run", "0", "--no-progress"]
    for arm, mode in (("decoupled", "decoupled"), ("state", "state")):
        write_run(tmp_path / "p" / "runs", task="hopper", mode=mode, seed=0, name=f"hopper_{arm}_seed0",
                  probe_every=0)
    monkeypatch.setattr(sys, "argv", [str(tmp_path / "venv" / "bin" / "ablate-paper"), *argv])
    main(argv)
    report = Path(capsys.readouterr().out.strip())
    manifest = json.loads((tmp_path / "p" / "sweep.json").read_text())
    assert manifest["command"] == ["ablate-paper", *argv]
    assert manifest["counts"]["done"] == 2
    text = (tmp_path / report).read_text()
    recorded = re.search(r"Sweep command: `([^`]*)`", text).group(1)
    assert shlex.split(recorded) == manifest["command"]
    assert absolute_paths(text) == [] and str(tmp_path) not in text
    assert "Sweep folder `..`" in text and "| ../runs/hopper_state_seed0 |" in text

    main(shlex.split(recorded)[1:])  # the recorded command, run again as written
    assert json.loads((tmp_path / "p" / "sweep.json").read_text())["command"] == manifest["command"]


def packed_sweep(folder: Path) -> Path:
    """An ablate-paper folder whose hopper and cartpole runs trained packed: per task one population of the
    decoupled, full-hard and full-hard-dva arms (two seeds) and one of the state runs."""
    arms = {n: {"mode": ARMS[n].mode, "flags": ARMS[n].flags, "about": ARMS[n].about}
            for n in ("decoupled", "full-hard", "full-hard-dva", "state")}
    runs, jobs = {}, {}
    for task in ("cartpole", "hopper"):
        for k, names in enumerate((("decoupled", "full-hard", "full-hard-dva"), ("state",))):
            job = f"{task}_population{k}"
            ids = [f"{task}_{arm}_seed{seed}" for arm in names for seed in (0, 1)]
            jobs[job] = {"runs": ids, "members": ids, "args": [], "iters": 12, "folder": f"runs/{job}"}
            for arm in names:
                for seed in (0, 1):
                    run_id = f"{task}_{arm}_seed{seed}"
                    runs[run_id] = {"task": task, "mode": arms[arm]["mode"], "arm": arm, "seed": seed,
                                    "status": "done", "job": job, "folder": f"runs/{job}/{run_id}"}
                    run = write_run(folder / "runs" / job, task=task, mode=arms[arm]["mode"], seed=seed,
                                    name=run_id, wall_per_iter=WALL,
                                    settings={"raster_model": "hard" if arm.startswith("full-hard") else "softmax"})
                    record = json.loads((run / "config.json").read_text())
                    record["population"] = {"folder": job, "members": ids, "index": ids.index(run_id)}
                    (run / "config.json").write_text(json.dumps(record))
    (folder / "sweep.json").write_text(json.dumps({
        "version": 1, "id": "abc", "created": "2026-05-01T10:00:00", "updated": "2026-05-01T12:00:00",
        "command": ["ablate-paper", "--tasks", "cartpole", "hopper"], "runs": runs, "jobs": jobs,
        "sweep": {"tasks": ["cartpole", "hopper"], "modes": ["decoupled", "full", "state"], "seeds": [0, 1],
                  "set": {"iters": "12"}, "vary": {}, "arms": arms, "pack": "auto", "pack_size": 12,
                  "gpus_per_run": 1.0}}))
    return folder


@pytest.mark.slow
def test_report_of_packed_runs_sets_each_arms_time_alone_beside_its_populations(tmp_path):
    folder = packed_sweep(tmp_path / "p")
    floors = tmp_path / "floors.json"
    floors.write_text(json.dumps({"tasks": {"hopper": {"zero": {"mean": 156.5}, "random": {"mean": -40.6}},
                                            "cartpole": {"zero": {"mean": 2097.8}, "random": {"mean": 1987.1}}}}))
    iteration = tmp_path / "iteration.json"
    iteration.write_text(json.dumps({"gpu": "NVIDIA H100", "command": "benchmarks/iteration.py", "results": [
        {"task": "hopper", "mode": "decoupled", "raster_model": "softmax", "bwd_ms": 4.0, "iter_ms": 90.0},
        {"task": "hopper", "mode": "full", "raster_model": "hard", "bwd_ms": 9.0, "iter_ms": 120.0},
        {"task": "hopper", "mode": "full", "raster_model": "softmax", "bwd_ms": 8.0, "iter_ms": 150.0},
        {"task": "hopper", "mode": "state", "bwd_ms": None, "status": "oom"}]}))
    population = tmp_path / "population_hopper.json"
    population.write_text(json.dumps({"gpu": "NVIDIA H100", "command": "population.py --tasks hopper", "rows": [
        {"kind": "population", "task": "hopper", "members": 1, "iter_ms": 100.0, "status": "ok"},
        {"kind": "population", "task": "hopper", "members": 12, "iter_ms": 800.0, "status": "ok"},
        {"kind": "population", "task": "hopper", "members": 16, "status": "oom"},
        *({"kind": "separate", "task": "hopper", "members": 1, "arm": i % 4, "processes": 12, "iter_ms": ms,
           "status": "ok"} for i, ms in enumerate([1200.0] * 6 + [1400.0] * 6))]}))
    text = build_paper_report(folder, floors=floors, benchmark=(iteration, population)).read_text()

    # How the runs trained, and the marked task
    assert "The runs trained in 4 processes: 4 populations (of 6, 6, 2, 2 members) and 0 runs alone (--pack auto)" \
        in text
    assert "**cartpole:** D.Va's cartpole (with springs) ranks no arms: doing nothing already scores high (zero " \
           "action 2098, floors.json; the paper's final return ~1.8k)" in text
    assert rows_of(text, "| cartpole (does not rank arms) | final return (ours: training return) | decoupled |")
    # the paragraph once (section 2, beside the wall-clock figures), a pointer to it in section 4
    assert text.count("**Packed runs:** a population member's wall-clock is its population's") == 1
    assert "Packed runs' wall-clock times are their populations' (section 2 says why)." in text
    # Table 1 leaves the members out, and says so
    assert "16 run(s) trained as population members are left out" in text

    # Section 6: each arm alone (the first benchmark that times it) beside its population's time
    section = text[text.index("## 6. Iteration time"):text.index("## 7. Memory")]
    rows = {(r[0], r[1]): r[2:] for r in rows_of(section, "| hopper |") + rows_of(section, "| cartpole |")
            if len(r) == 6}
    assert rows[("hopper", "decoupled")] == ["90", "benchmark iteration.json, NVIDIA H100 (n=1)", "20",
                                             "in populations of 6"]
    assert rows[("hopper", "state")][2:] == ["20", "in populations of 2"]
    assert rows[("hopper", "full-hard")][:2] == ["120", "benchmark iteration.json, NVIDIA H100 (n=1)"]
    assert rows[("hopper", "full-hard-dva")][0] == "120"  # the same estimator and cost; only the schedule differs
    assert rows[("hopper", "state")][:2] == ["not measured", "-"]  # the oom row times nothing
    assert rows[("cartpole", "decoupled")][0] == "not measured"
    assert "No benchmark gives the iteration time alone of cartpole decoupled, cartpole full-hard, cartpole " \
           "full-hard-dva, cartpole state, hopper state: wall-clock comparisons of packed members are not an " \
           "arm's own time" in " ".join(section.split())
    # the population benchmark: 12 members against 12 separate processes (median 1300 ms each)
    assert rows_of(section, "| hopper | 12 |") == [["hopper", "12", "800", "66.67", "1300", "1.62x",
                                                     "benchmark population_hopper.json, NVIDIA H100"]]
    # Table 1 reads the iteration.py file only; provenance names both
    assert rows_of(text, "| hopper | 4 |")
    assert "### Benchmark ../../population_hopper.json" in text and "population.py --tasks hopper" in text
    # a population of one in benchmarks/population.py is a decoupled run alone
    text = build_paper_report(folder, floors=floors, benchmark=(population, iteration)).read_text()
    section = text[text.index("## 6. Iteration time"):text.index("## 7. Memory")]
    assert rows_of(section, "| hopper | decoupled |")[0][2:4] == [
        "100", "benchmark population_hopper.json, NVIDIA H100 (n=1)"]


def test_starting_ablate_paper_imports_no_statistics_stack():
    # ablate-paper and ablate-sweep train for hours before any statistic: a resampling library that cannot
    # import (arch under pandas 3) must not stop them at the start; the statistics need none of them at all
    import subprocess

    code = ("import sys; import ablations.paper as p, ablations.sweep; from ablations.cli import parse; "
            "parse(p.PaperConfig, ['--tasks', 'hopper', '--seeds', '0', '--dry-run'], prog='ablate-paper'); "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'rliable', 'arch', 'pandas'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
