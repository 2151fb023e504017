"""ablate-report: Table 1 with our numbers and the paper's, "not run" gaps, figures, sweep, provenance."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest

from ablations.memory import COLUMNS, csv_text
from ablations.reports.report import PAPER_TABLE1_MS, ReportConfig, build_report, load_benchmark
from tests.ablations.conftest import write_run


def absolute_paths(text: str) -> list[str]:
    """Words of a report that start like an absolute path: at a line start, or after a space, quote, backtick,
    bracket or table bar."""
    return re.findall(r"(?:^|[\s`'\"(\[|=])(/[\w.~/-]+)", text, flags=re.MULTILINE)


def table_row(text: str, task: str) -> list[str]:
    line = next(ln for ln in text.splitlines() if ln.startswith(f"| {task} |"))
    return [c.strip() for c in line.strip("|").split("|")]


def write_sweep(folder: Path) -> Path:
    folder.mkdir(parents=True)
    rows = []
    for mode in ("full", "decoupled"):
        for m, v in ((0, 0), (2, 64)):
            rows.append({**{k: None for k in COLUMNS}, "task": "cartpole", "mode": mode, "meshes": m,
                         "verts_per_mesh": v, "status": "ok", "scene_faces": 100 + 2 * m * v, "bwd_ms": 5.0 + m,
                         "fwd_ms": 4.0, "saved_mb": 10.0 + m * v, "num_envs": 2, "horizon": 4, "image_size": 16,
                         "warmup_iters": 1, "iters": 2, "device": "cpu", "seed": 0})
    rows.append({**rows[-1], "mode": "full", "meshes": 8, "status": "oom", "bwd_ms": None,
                 "error": "OutOfMemoryError: CUDA out of memory"})
    (folder / "memory.csv").write_text(csv_text(rows))
    (folder / "memory.json").write_text(json.dumps({
        "started": "2026-01-01T10:00:00+00:00", "updated": "2026-01-01T11:00:00+00:00",
        "environment": {"device": "cpu", "torch": "2.13.0+cpu", "python": "3.11.7"},
        "commands": [{"argv": ["ablate-memory", "--task", "cartpole"], "started": "2026-01-01T10:00:00+00:00"}]}))
    return folder


@pytest.fixture
def inputs(tmp_path):
    runs = tmp_path / "runs"
    for seed, (dec, full) in enumerate(((10.0, 30.0), (12.0, 34.0))):
        write_run(runs, task="cartpole", mode="decoupled", seed=seed, bwd_ms=dec)
        write_run(runs, task="cartpole", mode="full", seed=seed, bwd_ms=full)
    # hopper: only decoupled ran, and without summary.json (killed): recomputed from metrics.jsonl.
    write_run(runs, task="hopper", mode="decoupled", seed=0, bwd_ms=20.0, summary=False)
    return runs, write_sweep(tmp_path / "sweep")


def test_report_has_our_table_the_papers_and_not_run(inputs, tmp_path):
    runs, sweep = inputs
    out = build_report(ReportConfig(runs=(runs,), memory=(sweep,), out=tmp_path / "rep" / "report.md"))
    text = out.read_text()

    cart = table_row(text, "cartpole")
    assert cart[1:4] == ["11.0", "32.0", "2.91x"]  # medians over 2 seeds; ratio full / decoupled
    assert cart[5:8] == ["110", "360", "3.27x"]  # the paper's, in ms
    hopper = table_row(text, "hopper")
    # Warm-up (+1000 ms) and probe iterations (+1000 ms) excluded when recomputing from metrics.jsonl.
    assert hopper[1:4] == ["20.0", "not run", "not run"]
    for task in ("ant", "humanoid"):
        row = table_row(text, task)
        assert row[1:5] == ["not run"] * 4
        assert row[5:7] == [f"{PAPER_TABLE1_MS[task][0]:.0f}", f"{PAPER_TABLE1_MS[task][1]:.0f}"]
    assert "paper (RTX 4080): D.Va [ms]" in text and "quoted for comparison and not measured here" in text

    # Figures: relative links that resolve.
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    assert any(link.endswith("return_vs_env_steps.png") for link in links)
    assert any(link.endswith("memory_bwd.png") for link in links)
    for link in links:
        assert not Path(link).is_absolute() and (out.parent / link).read_bytes()[:4] == b"\x89PNG"

    # Seed statistics: these runs predate deterministic evaluation, and say so; their probes all look (the
    # image sensitivity stays at its first value).
    assert "## 3. Seed statistics" in text and "No run logged a deterministic evaluation" in text
    assert "## 4. Gradient probes where the policy looks" in text
    assert "| cartpole | decoupled | 8/8 (s0: 4/4, s1: 4/4) |" in text
    assert "## 5. Memory sweep" in text and "## 6. Provenance" in text

    # Memory sweep table and provenance.
    assert "| full | 8 | 64 |" in text and "oom: OutOfMemoryError" in text
    assert "`ablate-memory --task cartpole`" in text
    assert "`ablate --task cartpole --mode full --seed 1`" in text
    assert "torch 2.13.0+cpu" in text and "0123456789ab" in text


@pytest.mark.slow
def test_benchmark_json_wins_and_differing_settings_give_no_ratio(inputs, tmp_path):
    runs, _ = inputs
    bench = tmp_path / "bench.json"
    bench.write_text(json.dumps({"date": "2026-02-02", "gpu": "NVIDIA H100", "command": "python -m benchmarks.bwd",
                                 "results": [{"task": "ant", "mode": "decoupled", "bwd_ms": 50.0, "num_envs": 64,
                                              "horizon": 32, "image_size": 84},
                                             {"task": "ant", "mode": "full", "bwd_ms": 150.0, "num_envs": 64,
                                              "horizon": 32, "image_size": 84},
                                             {"task": "cartpole", "mode": "full", "median_bwd_ms": 99.0,
                                              "num_envs": 64, "horizon": 32, "image_size": 84}]}))
    text = build_report(ReportConfig(runs=(runs,), benchmark=(bench,), out=tmp_path / "r.md")).read_text()
    ant = table_row(text, "ant")
    assert ant[1:4] == ["50.0", "150", "3.00x"] and "benchmark bench.json" in ant[4] and "NVIDIA H100" in ant[4]
    cart = table_row(text, "cartpole")
    # full from the benchmark (64x32), decoupled from the runs (4x8): not comparable, so no ratio.
    assert cart[1:4] == ["11.0", "99.0", "n/a (settings differ)"]
    assert "No memory sweep was given" in text and "python -m benchmarks.bwd" in text
    # Same setting but measured apart (a benchmark alone on its GPU against runs): no ratio either.
    bench.write_text(json.dumps({"gpu": "NVIDIA H100", "results": [
        {"task": "cartpole", "mode": "full", "bwd_ms": 99.0, "num_envs": 4, "horizon": 8, "image_size": 32}]}))
    text = build_report(ReportConfig(runs=(runs,), benchmark=(bench,), out=tmp_path / "r2.md")).read_text()
    assert table_row(text, "cartpole")[1:4] == ["11.0", "99.0", "n/a (measured apart)"]


def test_report_from_a_benchmark_alone(tmp_path):
    bench = tmp_path / "b.json"
    bench.write_text(json.dumps([{"task": "humanoid", "mode": "full", "bwd_ms": 1234.0}]))
    text = build_report(ReportConfig(benchmark=(bench,), out=tmp_path / "r.md")).read_text()
    assert table_row(text, "humanoid")[1:3] == ["not run", "1234"]
    assert "No training runs were given." in text


def test_bad_input_errors(tmp_path, capsys):
    from ablations.cli import report_main

    with pytest.raises(ValueError, match="nothing to report"):
        build_report(ReportConfig(out=tmp_path / "r.md"))
    (tmp_path / "notarun").mkdir()
    with pytest.raises(ValueError, match=r"no config\.json"):
        build_report(ReportConfig(runs=(tmp_path / "notarun",), out=tmp_path / "r.md"))
    with pytest.raises(ValueError, match=r"no memory\.csv"):
        build_report(ReportConfig(memory=(tmp_path / "notarun",), out=tmp_path / "r.md"))
    (tmp_path / "b.json").write_text(json.dumps({"results": [{"task": "ant"}]}))
    with pytest.raises(ValueError, match="needs task, mode and a numeric bwd_ms"):
        load_benchmark(tmp_path / "b.json")
    with pytest.raises(ValueError, match="no such file"):
        load_benchmark(tmp_path / "none.json")
    run = write_run(tmp_path / "runs", task="ant", mode="full", seed=0)
    with pytest.raises(ValueError, match=r"ending in \.md"):
        build_report(ReportConfig(runs=(run,), out=tmp_path / "report.txt"))
    with pytest.raises(ValueError, match="--reps must be a positive number"):
        build_report(ReportConfig(runs=(run,), reps=0, out=tmp_path / "r.md"))
    with pytest.raises(ValueError, match="--at-iteration: at_iteration must be a positive number of iterations, got 0"):
        build_report(ReportConfig(runs=(run,), at_iteration=0, out=tmp_path / "r.md"))
    assert not (tmp_path / "r.md").exists()

    with pytest.raises(SystemExit) as e:
        report_main(["--out", str(tmp_path / "r.md")])
    assert e.value.code == 2 and "nothing to report" in capsys.readouterr().err


def test_cli_builds_the_report(inputs, tmp_path, capsys):
    from ablations.cli import report_main

    runs, sweep = inputs
    out = tmp_path / "cli" / "report.md"
    report_main([str(runs), "--memory", str(sweep), "--out", str(out)])
    assert capsys.readouterr().out.strip() == str(out)
    assert out.read_text().startswith("# Policy gradients through pixels")


@pytest.mark.slow
def test_report_lists_floors_dates_and_variants(tmp_path):
    runs = tmp_path / "runs"
    write_run(runs, task="hopper", mode="decoupled", seed=0, bwd_ms=20.0, settings={"raster_model": "alpha"},
              started_utc="2026-03-01T10:00:00+00:00", ended_utc="2026-03-01T11:30:00+00:00")
    write_run(runs, task="hopper", mode="full", seed=0, bwd_ms=50.0, name="hard",
              settings={"raster_model": "hard"})
    write_run(runs, task="hopper", mode="full", seed=0, bwd_ms=40.0, name="alpha",
              settings={"raster_model": "alpha"})
    write_run(runs, task="humanoid", mode="blind", seed=0, bwd_ms=7.0, probe_every=0)
    floors = tmp_path / "floors.json"
    floors.write_text(json.dumps({"tasks": {"hopper": {"zero": {"mean": -12.5, "std": 3.0, "episodes": 64},
                                                       "random": {"mean": 40.25, "std": 9.0, "episodes": 64}}}}))
    with pytest.warns(UserWarning, match="no return floor for task 'humanoid'"):
        text = build_report(ReportConfig(runs=(runs,), floors=floors, out=tmp_path / "r.md")).read_text()

    # One Table 1 row per full variant, each against the decoupled runs.
    rows = [[c.strip() for c in ln.strip("|").split("|")] for ln in text.splitlines() if ln.startswith("| hopper |")]
    assert [r[1:4] for r in rows[:2]] == [["20.0", "40.0", "2.00x"], ["20.0", "50.0", "2.50x"]]
    assert "full (alpha): 4x8" in rows[0][4] and "full (hard): 4x8" in rows[1][4]
    assert "humanoid blind 7 ms" in text
    # Floors: a table with their source, and the task without one named.
    assert "from `floors.json`" in text  # relative to the report's folder
    assert table_row(text, "hopper")[0] == "hopper"
    assert "| hopper | -12.5 +- 3 | 40.25 +- 9 | 64 |" in text
    assert "| humanoid | no entry | no entry | - |" in text
    assert "**Warning:** no return floor for task 'humanoid'" in text
    assert "| alpha | hopper | full (alpha) | 0 |" in text
    # Recorded start and end; file times marked as such where a run recorded none.
    assert "| 2026-03-01T10:00:00+00:00 | 2026-03-01T11:30:00+00:00 |" in text
    assert text.count("(file time)") == 3 * 2


def test_benchmark_points_that_failed_are_left_out(tmp_path):
    bench = tmp_path / "b.json"
    bench.write_text(json.dumps({"results": [
        {"task": "ant", "mode": "full", "status": "oom", "bwd_ms": None, "error": "CUDA out of memory"},
        {"task": "ant", "mode": "decoupled", "status": "ok", "bwd_ms": 12.0}]}))
    _, results = load_benchmark(bench)
    assert [(r["task"], r["mode"]) for r in results] == [("ant", "decoupled")]


def test_paper_numbers_come_from_the_cited_file():
    from ablations.reports.paper_numbers import load_paper_numbers

    numbers = load_paper_numbers()
    assert PAPER_TABLE1_MS == {r["task"]: (1000 * r["dva"], 1000 * r["shac-diffrender"]) for r in numbers.backward_s}
    assert PAPER_TABLE1_MS["hopper"] == pytest.approx((190.0, 510.0))
    assert "Table 1" in numbers.cite("table1") and "RTX 4080" in numbers.cite("table1")


def test_benchmark_rows_of_several_raster_models_stay_apart(tmp_path):
    bench = tmp_path / "b.json"
    rows = [{"task": "ant", "mode": "decoupled", "bwd_ms": 10.0, "raster_model": "alpha", "renderer": "soft"},
            {"task": "ant", "mode": "full", "bwd_ms": 30.0, "raster_model": "hard", "renderer": "soft"},
            {"task": "ant", "mode": "full", "bwd_ms": 50.0, "raster_model": "alpha", "renderer": "soft"}]
    bench.write_text(json.dumps({"results": rows}))
    text = build_report(ReportConfig(benchmark=(bench,), out=tmp_path / "r.md")).read_text()
    ant = [[c.strip() for c in ln.strip("|").split("|")] for ln in text.splitlines() if ln.startswith("| ant |")]
    assert [r[1:4] for r in ant] == [["10.0", "50.0", "5.00x"], ["10.0", "30.0", "3.00x"]]
    assert "full (alpha):" in ant[0][4] and "full (hard):" in ant[1][4]


@pytest.mark.slow
def test_report_names_no_absolute_path(inputs, tmp_path, monkeypatch):
    """Inputs given as absolute paths, a run recorded by `python -m ablations ablate`, the report's own command run
    through a console script: the report names them relative to its folder, and programs by name."""
    runs, sweep = inputs
    run = next(runs.iterdir())
    record = json.loads((run / "config.json").read_text())
    record["command"] = [str(tmp_path / "site-packages" / "ablations" / "__main__.py"), "ablate", "--task", "hopper"]
    (run / "config.json").write_text(json.dumps(record))
    bench = tmp_path / "bench" / "b.json"
    bench.parent.mkdir()
    bench.write_text(json.dumps({"command": "python benchmarks/iteration.py", "results": [
        {"task": "ant", "mode": "full", "bwd_ms": 10.0}]}))
    floors = tmp_path / "floors.json"
    floors.write_text(json.dumps({"tasks": {t: {"zero": {"mean": 1.0}} for t in ("cartpole", "hopper")}}))
    monkeypatch.setattr(sys, "argv", [str(tmp_path / "venv" / "bin" / "ablate-report"), "--out", "rep/report.md"])
    out = build_report(ReportConfig(runs=(runs.resolve(),), memory=(sweep.resolve(),), benchmark=(bench,),
                                    floors=floors, out=tmp_path / "rep" / "report.md"))
    text = out.read_text()
    assert absolute_paths(text) == [] and str(tmp_path) not in text
    assert "by `ablate-report --out rep/report.md`" in text
    assert "`python -m ablations ablate --task hopper`" in text
    assert f"| ../runs/{run.name} |" in text and "### Benchmark ../bench/b.json" in text
    assert "### Memory sweep ../sweep" in text and "from `../floors.json`" in text
    # The default floors file of this checkout, too.
    text = build_report(ReportConfig(runs=(runs,), out=tmp_path / "rep2" / "report.md")).read_text()
    assert absolute_paths(text) == [] and "floors.json`" in text
    assert absolute_paths("a `/home/x` b\n/tmp/y | /z |") == ["/home/x", "/tmp/y", "/z"]


def test_report_of_evaluated_seeds_and_a_population_benchmark(tmp_path):
    """Runs with deterministic evaluations: the seed statistics per arm, the evaluation and profile figures, and
    a benchmarks/population.py file read for iteration times (not for Table 1)."""
    runs = tmp_path / "runs"
    for seed in (0, 1, 2):
        for mode, base in (("decoupled", 500.0), ("blind", 100.0)):
            run = write_run(runs, task="hopper", mode=mode, seed=seed, settings={"preset": "dva",
                                                                               "raster_model": "softmax"})
            lines = [json.loads(ln) for ln in (run / "metrics.jsonl").read_text().splitlines()]
            for m in lines:
                if m["iter"] % 4 == 0:
                    m.update(eval_return_mean=base + 10.0 * seed + m["iter"], eval_return_std=1.0)
            (run / "metrics.jsonl").write_text("".join(json.dumps(m) + "\n" for m in lines))
    bench = tmp_path / "population.json"
    bench.write_text(json.dumps({"device": "cuda", "gpu": "NVIDIA H100", "command": "population.py --num-envs 4",
                                 "rows": [{"kind": "population", "task": "hopper", "members": 1, "status": "ok",
                                           "iter_ms": 93.0, "bwd_ms": 45.0}]}))
    text = build_report(ReportConfig(runs=(runs,), benchmark=(bench,), reps=20, out=tmp_path / "r" / "r.md")
                        ).read_text()
    assert table_row(text, "hopper")[1:3] == ["10.0", "not run"]  # Table 1: the runs' own, not the population's
    # decoupled minus blind is 400 on every seed: 3 of 3 agree, which a quarter of all seed triples would do by
    # chance (sign-flip p = 0.25; Holm over the two views' comparisons: 0.5), so nothing is ranked
    assert ("**Verdict (equal iterations, 12):** decoupled is not shown to beat blind after Holm correction: "
            "decoupled minus blind 400 [400, 400], 3 of 3 seeds agree in sign, sign-flip p = 0.25, Holm-adjusted "
            "p = 0.5 (2 comparisons) > 0.05") in text
    # the final return is the mean of the evaluations at 4, 8, 12, the same iterations for every run
    assert "| decoupled | 3 | 12 | 3 | 4, 8, 12 | 518 [" in text and "| s0: 508, s1: 518, s2: 528 |" in text
    assert "| blind | 3 | 12 | 3 | 4, 8, 12 |" in text and "| -400 [-400, -400] (the range of the 3 seeds) |" in text
    # the benchmark times decoupled alone but not blind: both arms' times come from their single runs instead
    assert "**Verdict (equal wall-clock, 0.24 s):**" in text and "(decoupled 20 ms, blind 20 ms per" in text
    assert "iteration times measured alone from runs on cpu" in text
    for png in ("performance_profile_hopper.png", "eval_return_vs_iter.png"):
        assert f"](figures/{png})" in text and (tmp_path / "r" / "figures" / png).exists()


def test_population_members_times_are_not_their_arms(tmp_path):
    """A member's logged times are its whole population's: Table 1 leaves members out and says so."""
    from ablations.reports.report import collect_bwd, runs_table, table1_section
    from ablations.run_folder import find_runs

    runs = tmp_path / "runs"
    write_run(runs, task="hopper", mode="decoupled", seed=0, bwd_ms=20.0)  # a single run
    for mode in ("decoupled", "full"):
        run = write_run(runs, task="hopper", mode=mode, seed=1, bwd_ms=300.0)
        record = json.loads((run / "config.json").read_text())
        record["population"] = {"folder": "pop", "index": 0, "members": ["a", "b"]}
        (run / "config.json").write_text(json.dumps(record))
    loaded = find_runs([runs])
    cells = collect_bwd(loaded, [])
    assert cells[("hopper", "decoupled")].ms == 20.0 and cells[("hopper", "decoupled")].n == 1
    assert ("hopper", "full") not in cells
    text = "\n".join(table1_section(cells, members_left_out=2))
    assert table_row(text, "hopper")[1:3] == ["20.0", "not run"]
    assert "2 run(s) trained as population members are left out" in text
    assert "2 run(s) trained as population members: their times and memory" in "\n".join(runs_table(loaded))


def test_table1_sets_each_full_time_beside_the_decoupled_time_measured_with_it():
    """A ratio needs both times from one measurement: where one file times decoupled with each raster model
    (labels "decoupled (hard)", "decoupled (softmax)") and another plain "decoupled", a full row of the first
    is set beside the first's decoupled time, D.Va's softmax image model's, not the other file's."""
    from ablations.reports.report import collect_bwd, table1_section

    def row(mode, raster, bwd, renderer="soft"):
        return {"task": "hopper", "mode": mode, "raster_model": raster, "renderer": renderer, "bwd_ms": bwd,
                "num_envs": 64, "horizon": 32, "image_size": 84, "status": "ok"}

    h100 = (Path("h100.json"), {"gpu": "H100"}, [row("decoupled", "softmax", 45.0), row("blind", None, 40.0)])
    h200 = (Path("h200.json"), {"gpu": "H200"}, [row("decoupled", "hard", 41.0), row("decoupled", "softmax", 44.0),
                                                  row("full", "hard", 63.0), row("full", "softmax", 66.0)])
    text = "\n".join(table1_section(collect_bwd([], [h100, h200])))
    rows = [r for r in text.splitlines() if r.startswith("| hopper |")]
    assert [r.split(" | ")[1:4] for r in rows] == [["44.0", "63.0", "1.43x"], ["44.0", "66.0", "1.50x"]]
    assert all("decoupled (softmax): 64x32 84px, H200, benchmark h200.json" in r for r in rows)
    # the same label in both files (the first file's cell is the table's), and a ray-traced decoupled row (labels
    # "decoupled (None, warp)" and "decoupled (softmax, soft)"): still the second file's rasterized softmax row
    h100 = (Path("h100.json"), {"gpu": "H100"}, [row("decoupled", "softmax", 45.0)])
    h200 = (Path("h200.json"), {"gpu": "H200"}, [row("decoupled", None, 30.0, "warp"), row("decoupled", "hard", 41.0),
                                                  row("decoupled", "softmax", 44.0), row("full", "hard", 63.0)])
    text = "\n".join(table1_section(collect_bwd([], [h100, h200])))
    rows = [r for r in text.splitlines() if r.startswith("| hopper |")]
    assert [r.split(" | ")[1:4] for r in rows] == [["44.0", "63.0", "1.43x"]]
    assert "decoupled (softmax, soft): 64x32 84px, H200" in rows[0]
    one = (Path("one.json"), {"gpu": "H200"}, [row("decoupled", "softmax", 44.0), row("full", "softmax", 66.0)])
    rows = [r for r in "\n".join(table1_section(collect_bwd([], [h100, one]))).splitlines() if r.startswith("| hop")]
    assert [r.split(" | ")[1:4] for r in rows] == [["44.0", "66.0", "1.50x"]]
    # a file without decoupled rows: its full row is set beside the table's decoupled cell, and the ratio refused
    alone = (Path("alone.json"), {"gpu": "H200"}, [row("full", "softmax", 66.0)])
    rows = [r for r in "\n".join(table1_section(collect_bwd([], [h100, alone]))).splitlines() if r.startswith("| hop")]
    assert [r.split(" | ")[1:4] for r in rows] == [["45.0", "66.0", "n/a (measured apart)"]]
