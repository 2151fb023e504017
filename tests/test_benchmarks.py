"""The benchmark scripts' helpers (kernel configs, provenance, timing, results files) and their command lines on
the CPU."""

import json
import re
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _benchmarks_importable(monkeypatch):
    """The scripts import their shared module as a sibling, as ``python benchmarks/X.py`` lets them."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))


def _autotuner(name: str, src: str, *configs: str):
    from torch._inductor.runtime.triton_heuristics import CachingAutotuner

    k = CachingAutotuner.__new__(CachingAutotuner)  # no compilation: only the attributes the helper reads
    k.fn = SimpleNamespace(src=src)
    k.inductor_meta = {"kernel_name": name}
    k.launchers = [SimpleNamespace(config=c) for c in configs]
    return k


def test_kernel_configs_names_each_kernel_by_its_source_and_records_the_kept_config(benchmark_script):
    sim = benchmark_script("sim")
    found = sim.kernel_configs([
        _autotuner("triton_poi_fused_0", "def k(): a", "XBLOCK: 128"),
        _autotuner("triton_poi_fused_0", "def k(): b", "XBLOCK: 256"),
        _autotuner("triton_poi_fused_0", "def k(): a", "XBLOCK: 256"),
        object(),  # not a kernel
    ])
    assert len(found) == 3
    assert {k["name"] for k in found} == {"triton_poi_fused_0"}
    by_source = {}
    for k in found:
        by_source.setdefault(k["source"], []).append(k["chosen"])
    assert sorted(map(len, by_source.values())) == [1, 2]  # equal sources hash equally, different ones do not
    assert sorted(k["chosen"] for k in found) == [["XBLOCK: 128"], ["XBLOCK: 256"], ["XBLOCK: 256"]]


def test_config_diff_lists_only_kernels_whose_configs_differ(tmp_path, capsys, benchmark_script):
    cd = benchmark_script("config_diff")
    a = [{"name": "k0", "source": "s0", "chosen": ["X: 128"]}, {"name": "k1", "source": "s1", "chosen": ["X: 64"]},
         {"name": "k2", "source": "s2", "chosen": ["X: 64"]}, {"name": "k2", "source": "s2", "chosen": ["X: 128"]}]
    b = [{"name": "k0", "source": "s0", "chosen": ["X: 256"]}, {"name": "k1", "source": "s1", "chosen": ["X: 64"]},
         {"name": "k2", "source": "s2", "chosen": ["X: 128"]}, {"name": "k2", "source": "s2", "chosen": ["X: 64"]},
         {"name": "k3", "source": "s3", "chosen": ["X: 64"]}]
    n_common, rows = cd.diff(a, b)
    assert n_common == 3
    assert [(r[0], r[1]) for r in rows] == [("k0", "s0")]  # k2's two instances match as a multiset; k3 is b's only
    for path, kernels, ms in ((tmp_path / "a.json", a, 38.3), (tmp_path / "b.json", b, 47.7)):
        row = {"task": "ant", "num_envs": 64, "ms": ms, "kernel_configs": kernels}
        path.write_text(json.dumps({"rows": [{"task": "ant", "num_envs": 4096}, row]}))
    cd.main([str(tmp_path / "a.json"), str(tmp_path / "b.json"), "--task", "ant", "--num-envs", "64"])
    out = capsys.readouterr().out
    assert "3 kernels in both, 1 with different configs" in out and "k0 [s0]" in out and "k1" not in out
    with pytest.raises(SystemExit, match="no row with kernel_configs for num_envs=1024"):
        cd.main([str(tmp_path / "a.json"), str(tmp_path / "b.json"), "--num-envs", "1024"])


@pytest.mark.slow
def test_startup_runs_cold_then_warm_and_the_warm_run_hits_the_compile_cache(tmp_path, benchmark_script):
    startup = benchmark_script("startup")
    out = tmp_path / "startup.json"
    doc = startup.main(["--device", "cpu", "--tasks", "cartpole", "--modes", "state", "--num-envs", "2",
                        "--work", str(tmp_path / "work"), "--out", str(out), "--horizon", "2",
                        "--critic-iterations", "1"])
    assert json.loads(out.read_text()) == doc
    assert {"device", "date", "command", "commit", "torch"} <= set(doc["meta"])
    cold, warm = doc["rows"]
    assert (cold["phase"], warm["phase"]) == ("cold", "warm")
    for row in (cold, warm):
        assert row["status"] == "finished", row
        assert 0 < row["first_iter_s"] < row["process_s"]
        assert len(row["iter_ms"]) == 2 and row["compiles"] >= 1 and row["recompiles"] >= 0
        assert 0 < row["before_first_iter_s"] < row["first_iter_s"]
        assert sum(row["compile_s_by_part"].values()) == pytest.approx(row["compile_s"], abs=0.05)
        assert row["phase_s"]["_compile.compile_inner"] > 0  # torch's own phase times of the run's compiling
        assert row["startup_s"]["first_iteration"] == pytest.approx(row["iter_ms"][0] / 1e3)
        assert (tmp_path / "work" / "runs" / f"cartpole_state_{row['phase']}" / "stderr.log").is_file()
    # cold: an empty folder, every graph compiled; warm: every graph inductor compiles comes from the cache
    assert cold["fxgraph_cache_miss"] >= 1 and cold["artifacts_loaded"] == {}
    assert warm["fxgraph_cache_hit"] >= 1 and warm["fxgraph_cache_miss"] == 0
    assert warm["artifacts_loaded"].get("inductor", 0) >= 1
    assert warm["actor_loss"] == cold["actor_loss"]  # the cached kernels compute what the compiled ones did (CPU)
    assert "--compile-cache" in cold["command"] and "--horizon 2" in cold["command"]


def test_startup_runs_each_pair_with_and_without_the_compile_helper_in_its_own_cache(
        tmp_path, monkeypatch, benchmark_script):
    """--compile-helper on off: the same cold/warm pair twice, the second with ablate --no-compile-helper and a
    cache folder of its own (a shared one would make the second pair warm)."""
    startup = benchmark_script("startup")
    seen = []

    def fake_run(cmd, run_dir, *, timeout):
        seen.append(cmd)
        return {"status": "error", "error": "not run", "process_s": 0.0, "returncode": 1}

    monkeypatch.setattr(startup, "run_once", fake_run)
    monkeypatch.setattr(startup, "meta", lambda args, argv: {})
    doc = startup.main(["--device", "cpu", "--tasks", "cartpole", "--compile-helper", "on", "off",
                        "--work", str(tmp_path), "--out", str(tmp_path / "s.json")])
    assert [r["compile_helper"] for r in doc["rows"]] == [True, False]  # an error ends a pair after its cold run
    with_helper, without = seen
    assert "--no-compile-helper" not in with_helper and without[-1] == "--no-compile-helper"
    cache = [c[c.index("--compile-cache") + 1] for c in seen]
    assert cache[0] != cache[1]
    assert startup.run_label(doc["rows"][1]) == "cold no-helper"


def test_startup_keeps_each_compile_helpers_own_account_of_its_seconds(tmp_path, monkeypatch, capsys, benchmark_script):
    """A run's summary names its helpers' logs; each row keeps the last line each helper printed (where its
    seconds went), and the printout lists them with the run's wait, so a reader sees which process was slowest."""
    startup = benchmark_script("startup")
    run_dir = tmp_path / "runs" / "ant_decoupled_cold"
    run_dir.mkdir(parents=True)
    log = run_dir / "compile_helper_renderer.log"
    log.write_text("a warning first\ncompile helper (renderer): imports 10.4 s, ...; done after 47.9 s\n")
    helpers = [{"parts": ["renderer"], "returncode": 0, "log": str(log)},
               {"parts": ["networks"], "returncode": -9, "log": str(run_dir / "never_written.log")}]
    (run_dir / "summary.json").write_text(json.dumps({
        "status": "finished", "first_iter_s": 60.0, "startup_s": {"imports": 6.0},
        "compile": {"helpers": helpers, "helpers_wait_s": 4.9}}))
    (run_dir / "metrics.jsonl").write_text(json.dumps({"iter_ms": 7500.0, "actor_loss": -1.5}) + "\n")
    monkeypatch.setattr(startup.subprocess, "run",
                        lambda *a, **k: subprocess.CompletedProcess(a, 0, stdout="", stderr=""))
    row = startup.run_once(["python", "-m", "ablations"], run_dir, timeout=10)
    assert row["helpers_wait_s"] == 4.9
    assert [h["report"] for h in row["helpers"]] == [
        "compile helper (renderer): imports 10.4 s, ...; done after 47.9 s", None]
    monkeypatch.setattr(startup, "run_once", lambda cmd, run_dir, *, timeout: dict(row))
    monkeypatch.setattr(startup, "meta", lambda args, argv: {})
    startup.main(["--device", "cpu", "--tasks", "ant", "--iters", "1", "--work", str(tmp_path / "w"),
                  "--out", str(tmp_path / "s.json")])
    out = capsys.readouterr().out
    assert ("ant decoupled cold: the run waited 4.9 s for them | compile helper (renderer): imports 10.4 s, ...; "
            "done after 47.9 s; (networks: exit -9, no report)") in out


def test_results_record_the_commit_or_the_one_the_caller_names(monkeypatch, benchmark_script):
    common = benchmark_script("_common")
    monkeypatch.delenv("PIXELGRAD_COMMIT", raising=False)
    head = common.commit()
    assert head == "unknown" or re.fullmatch(r"[0-9a-f]{7,40}(\+dirty)?", head), head
    monkeypatch.setenv("PIXELGRAD_COMMIT", "abc1234")
    assert common.commit() == "abc1234"


def test_timing_skips_the_warm_up_and_times_each_call(benchmark_script):
    """Every script times through one helper: ``warmup`` untimed calls, then one time [ms] per timed call, and the
    last call's result. Call k sleeps 5 k ms, so a timed warm-up call would show as a time under its bound."""
    common = benchmark_script("_common")
    calls = []

    def fn():
        calls.append(None)
        time.sleep(0.005 * len(calls))
        return len(calls)

    times, last = common.time_ms(fn, "cpu", warmup=2, repeats=3)
    assert len(calls) == 5 and last == 5
    assert len(times) == 3 and all(t >= bound for t, bound in zip(times, (15.0, 20.0, 25.0))), times
    calls.clear()
    assert common.median_ms(fn, "cpu", repeats=3) >= 10.0


def test_results_files_are_replaced_whole(tmp_path, benchmark_script):
    """A results file is written beside and renamed over the old one: a reader never sees half a file, and no
    temporary file is left."""
    common = benchmark_script("_common")
    out = tmp_path / "new" / "r.json"
    common.write_json(out, {"rows": [1]})
    common.write_json(out, {"rows": [1, 2]}, indent=2)
    assert json.loads(out.read_text()) == {"rows": [1, 2]}
    assert [p.name for p in out.parent.iterdir()] == ["r.json"]


def test_render_anchor_runs_the_anchor_time_part_with_this_commands_choices(monkeypatch, tmp_path, benchmark_script):
    """``render.py --anchor`` is anchor.py's comparison with nvdiffrast (one process): its models, repeats,
    warm-up, compiled-and-eager choice and output pass through."""
    render = benchmark_script("render")
    seen = []
    monkeypatch.setattr(render.anchor, "main", lambda argv: seen.append(argv) or 0)
    out = tmp_path / "a.json"
    assert render.main(["--anchor", "--models", "softmax", "--repeats", "5", "--compile", "--out", str(out)]) == 0
    argv = seen[0]
    assert argv[:3] == ["--parts", "time", "--no-warp"]
    assert argv[argv.index("--out") + 1] == str(out)
    assert argv[argv.index("--models") + 1:argv.index("--repeats")] == ["softmax"]
    assert argv[argv.index("--repeats") + 1] == "5" and "--warmup" not in argv
    assert argv[argv.index("--compile") + 1:] == ["off", "on"]
    seen.clear()
    render.main(["--anchor", "--out", str(out)])
    assert "--compile" not in seen[0] and "--repeats" not in seen[0]


def test_iteration_times_each_critic_placement_in_one_process(tmp_path, monkeypatch, benchmark_script):
    """``iteration.py --overlap-critic on off``: one row per placement, each with the phases' medians and whether
    the fit ran alongside the backward (never on the CPU, where nothing is replayed)."""
    iteration = benchmark_script("iteration")
    out = tmp_path / "iter.json"
    monkeypatch.setattr(sys, "argv", ["iteration.py", "--device", "cpu", "--tasks", "cartpole", "--modes", "decoupled",
                                      "--num-envs", "2", "--horizon", "2", "--image-size", "32", "--warmup", "1",
                                      "--iters", "1", "--probe-every", "0", "--overlap-critic", "on", "off",
                                      "--out", str(out)])
    iteration.main()
    rows = json.loads(out.read_text())["results"]
    assert [(r["overlap_critic"], r["status"]) for r in rows] == [(True, "ok"), (False, "ok")], rows
    for r in rows:
        assert r["critic_overlapped"] is False and r["critic_ms"] > 0 and r["iter_ms"] > r["fwd_ms"] > 0


def test_iteration_times_each_fused_variant_in_one_process(tmp_path, monkeypatch, benchmark_script):
    """``--fused-variants default FWD_BIN=1,...``: a row per variant for a rendering mode, named by it, the tuning
    constants restored after; a mode that renders nothing is timed once; a malformed variant is refused by name."""
    from diffrender.raster.fused import tuning

    iteration = benchmark_script("iteration")
    out = tmp_path / "iter.json"
    argv = ["iteration.py", "--device", "cpu", "--tasks", "cartpole", "--modes", "decoupled", "blind",
            "--num-envs", "2", "--horizon", "2", "--image-size", "16", "--warmup", "0", "--iters", "1",
            "--probe-every", "0", "--fused-variants", "default", "FWD_BIN=1,BIN_CAPACITY=64", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", argv)
    iteration.main()
    rows = json.loads(out.read_text())["results"]
    assert [(r["mode"], r["fused_variant"], r["status"]) for r in rows] == [
        ("decoupled", "default", "ok"), ("decoupled", "FWD_BIN=1,BIN_CAPACITY=64", "ok"), ("blind", "default", "ok")]
    assert tuning.FWD_BIN is False  # the last row's variant is the default
    monkeypatch.setattr(sys, "argv", [*argv[:-4], "NO_SUCH=1", "--out", str(out)])
    with pytest.raises(SystemExit):
        iteration.main()


def test_iteration_times_every_arm_alone_for_the_equal_wall_clock_view(tmp_path, monkeypatch, benchmark_script):
    """``--modes decoupled full blind --raster-model softmax hard``: every rendering mode with each raster model and
    blind once, each row naming its raster model, so that a report finds each arm's time alone in the file."""
    from ablations.reports.arms import benchmark_iteration_rows

    iteration = benchmark_script("iteration")
    out = tmp_path / "iter.json"
    monkeypatch.setattr(sys, "argv", ["iteration.py", "--device", "cpu", "--tasks", "cartpole", "--modes", "decoupled",
                                      "full", "blind", "--raster-model", "softmax", "hard", "--num-envs", "2",
                                      "--horizon", "2", "--image-size", "32", "--warmup", "1", "--iters", "1",
                                      "--probe-every", "0", "--out", str(out)])
    iteration.main()
    rows = json.loads(out.read_text())["results"]
    assert [(r["mode"], r.get("raster_model"), r["status"]) for r in rows] == [
        ("decoupled", "softmax", "ok"), ("decoupled", "hard", "ok"), ("full", "softmax", "ok"), ("full", "hard", "ok"),
        ("blind", None, "ok")], rows
    _, timed = benchmark_iteration_rows(out)
    assert [(r["mode"], r["raster_model"]) for r in timed] == [(r["mode"], r.get("raster_model")) for r in rows]
    assert all(r["iter_ms"] > 0 and r["num_envs"] == 2 and r["compile"] is False for r in timed)


def test_iteration_times_each_arm_at_the_size_ablate_trains_it(tmp_path, monkeypatch, benchmark_script):
    """Without ``--num-envs`` each row takes its preset's environments: 64 for the hopper's pixel arms, SHAC's 256
    (gradlab.presets, DiffRL's hopper.yaml) for its state arm; ``--num-envs`` still sets every row."""
    iteration = benchmark_script("iteration")
    out = tmp_path / "iter.json"
    argv = ["iteration.py", "--device", "cpu", "--tasks", "hopper", "--modes", "state", "blind", "--horizon", "2",
            "--image-size", "16", "--warmup", "0", "--iters", "1", "--probe-every", "0", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", argv)
    iteration.main()
    rows = json.loads(out.read_text())["results"]
    assert [(r["mode"], r["num_envs"], r["status"]) for r in rows] == [("state", 256, "ok"), ("blind", 64, "ok")]
    monkeypatch.setattr(sys, "argv", [*argv, "--num-envs", "3", "--modes", "state"])
    iteration.main()
    assert [r["num_envs"] for r in json.loads(out.read_text())["results"]] == [3]
    # a setting the config refuses is that row's error, not the script's end
    monkeypatch.setattr(sys, "argv", [*argv, "--num-envs", "1", "--modes", "state"])
    iteration.main()
    (row,) = json.loads(out.read_text())["results"]
    assert row["status"] == "error" and row["num_envs"] == 1 and "ValueError" in row["error"], row


def test_startup_records_how_much_bytecode_a_run_found(tmp_path, monkeypatch, benchmark_script):
    """Where Python writes no bytecode beside the sources, a row says how many modules' bytecode ablate's folder
    held before the run (0: the run compiled all its Python too); elsewhere there is no such folder to count."""
    startup = benchmark_script("startup")
    monkeypatch.setattr(startup.subprocess, "run",
                        lambda *a, **k: subprocess.CompletedProcess(a, 1, stdout="", stderr="stopped"))
    folder = tmp_path / "bytecode"
    for name in ("a", "b"):
        path = folder / "usr" / "lib" / f"{name}.cpython-311.pyc"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"")
    monkeypatch.setenv("PIXELGRAD_BYTECODE_CACHE", str(folder))
    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
    assert startup.run_once(["python"], tmp_path / "run", timeout=10)["bytecode_pyc_before"] == 2
    monkeypatch.delenv("PYTHONDONTWRITEBYTECODE")
    assert startup.run_once(["python"], tmp_path / "run", timeout=10)["bytecode_pyc_before"] is None


def test_evaluation_times_each_variant_and_compares_its_episodes_with_the_first(
        tmp_path, monkeypatch, benchmark_script):
    """``evaluation.py``: per population, the first evaluation, then the captured and the eager steps (the same
    path on the CPU, where nothing is captured: equal episodes), each with its time per evaluation step."""
    evaluation = benchmark_script("evaluation")
    out = tmp_path / "evaluation.json"
    monkeypatch.setattr(sys, "argv", ["evaluation.py", "--device", "cpu", "--tasks", "cartpole", "--members", "2",
                                      "--num-envs", "2", "--eval-envs", "2", "--image-size", "16", "--repeats", "1",
                                      "--out", str(out)])
    evaluation.main()
    doc = json.loads(out.read_text())
    assert doc["complete"] and [r["variant"] for r in doc["rows"]] == [
        "first evaluation (compiling, capturing)", "captured", "eager (same compiled kernels)"]
    for r in doc["rows"][1:]:
        assert r["max_rel_diff"] == 0 and r["steps"] > 0 and r["ms_per_step"] > 0


def test_run_progress_says_where_each_run_stands_and_thins_copies_with_the_population_record(tmp_path, monkeypatch,
                                                                                         capsys, benchmark_script):
    from ablations.run_folder import RunFolder, read_metrics

    progress = benchmark_script("run_progress")
    home = tmp_path / "runs" / "pop"
    home.mkdir(parents=True)
    (home / "population.json").write_text('{"members": ["a"]}')
    folder = RunFolder.create(home, "a")
    (folder.path / "config.json").write_text('{"config": {"task": "cartpole", "mode": "decoupled"}}')
    for it in range(1, 31):
        row = {"iter": it, "iter_ms": 100.0 + it % 2, "return_mean": 5.0}
        if it == 20:
            row.update(eval_return_mean=42.0, eval_return_std=1.0)
        folder.append_metrics(row)
    (tmp_path / "runs" / "pop.log").write_text("step\nTraceback (most recent call last):\nValueError: boom\n")
    monkeypatch.setattr(sys, "argv", ["run_progress.py", str(tmp_path / "runs"), "--thin", str(tmp_path / "keep"),
                                      "--every", "10"])
    progress.main()
    out = capsys.readouterr().out
    assert "pop/a: iter 30, 100 ms/it, train return 5, eval 42 at 20, running" in out
    assert "--- pop.log (last lines)" in out and "ValueError: boom" in out
    assert (tmp_path / "keep" / "pop" / "population.json").read_text() == '{"members": ["a"]}'
    assert [r["iter"] for r in read_metrics(tmp_path / "keep" / "pop" / "a")] == [10, 20, 30]


def test_precision_compares_each_candidate_with_the_float32_run_from_the_same_state(tmp_path, capsys, benchmark_script):
    """``precision.py``: at each point the candidates start from the float32 run's state; a second float32 trainer
    reproduces its gradient exactly on the CPU (so the snapshot carries parameters, states and noise), bf16 is close
    but not equal, and the output says that the CPU measures nothing."""
    precision = benchmark_script("precision")
    out = tmp_path / "precision.json"
    try:
        doc = precision.main(["--device", "cpu", "--tasks", "cartpole", "--modes", "full", "--iters", "2",
                              "--candidates", "fp32", "bf16", "--num-envs", "2", "--horizon", "2", "--image-size", "16",
                              "--parts", "agreement", "--out", str(out)])
    finally:
        from gradlab import precision as process_precision

        process_precision.use("fp32", "cpu")
    assert json.loads(out.read_text()) == doc and doc["complete"] and doc["points"] == [0, 1, 2]
    rows = {(r["iteration"], r["candidate"]): r for r in doc["agreement"]}
    assert set(rows) == {(i, c) for i in (0, 1, 2) for c in ("fp32", "bf16")}
    for i in (0, 1, 2):
        same, bf16 = rows[i, "fp32"], rows[i, "bf16"]
        assert same["status"] == bf16["status"] == "ok"
        assert same["norm_ratio"] == 1.0 and same["loss_rel_diff"] == 0.0 and same["cos"] > 1 - 1e-12
        assert 0.99 < bf16["cos"] < 1 and bf16["cos_encoder"] > 0.99 and bf16["norm_ratio"] != 1.0
    assert [s["candidate"] for s in doc["agreement_summary"]] == ["fp32", "bf16"]
    printed = capsys.readouterr().out
    assert "NOTE on the CPU: no TF32" in printed and "median cos" in printed


def test_precision_compares_the_warp_simulator_with_the_pytorch_one_from_the_same_state(tmp_path, benchmark_script):
    """``precision.py --candidates fp32-warp-sim``: the Warp simulator loads the PyTorch simulator's run state and
    its float32 gradient agrees (issue 56's learning check; on the CPU both are float32 on the same numbers)."""
    precision = benchmark_script("precision")
    doc = precision.main(["--device", "cpu", "--tasks", "hopper", "--modes", "decoupled", "--iters", "2",
                          "--candidates", "fp32-warp-sim", "--num-envs", "2", "--horizon", "4", "--image-size", "16",
                          "--parts", "agreement", "--out", str(tmp_path / "p.json")])
    rows = doc["agreement"]
    assert [(r["iteration"], r["candidate"], r["status"]) for r in rows] == [
        (i, "fp32-warp-sim", "ok") for i in (0, 1, 2)], rows
    assert all(r["cos"] > 1 - 1e-9 and abs(r["norm_ratio"] - 1) < 1e-4 for r in rows), rows
    assert precision.candidate_config(precision.SHACConfig(task="hopper"), "fp32-warp-sim").sim_backend == "warp"


@pytest.mark.slow
def test_precision_times_each_precision_in_a_process_of_its_own(tmp_path, benchmark_script):
    precision = benchmark_script("precision")
    doc = precision.main(["--device", "cpu", "--tasks", "cartpole", "--modes", "decoupled", "--candidates", "bf16",
                          "--num-envs", "2", "--horizon", "2", "--image-size", "16", "--parts", "time",
                          "--time-warmup", "1", "--time-iters", "1", "--out", str(tmp_path / "p.json")])
    assert [(r["precision"], r["status"]) for r in doc["time"]] == [("fp32", "ok"), ("bf16", "ok")], doc["time"]
    assert all(r["iter_ms"] > 0 for r in doc["time"])


def test_forward_walk_counts_fewer_pairs_for_finer_chunks_down_to_the_bound(tmp_path, capsys, benchmark_script):
    """The compacted walk's pair count falls with its chunk size, between the block-wise walk's and the bound;
    chunks of one face are the bound itself (every face whose box reaches a tile, each once). The backward's
    packed lanes walk fewer lane-pixels than the block's."""
    fw = benchmark_script("forward_walk")
    out = tmp_path / "walk.json"
    assert fw.main(["--batch", "2", "--res", "24", "--chunks", "64", "16", "4", "1", "--out", str(out)]) == 0
    (row,) = json.loads(out.read_text())["rows"]
    assert row["faces"] == 1856 and row["tiles"] == 36
    assert row["block"] >= row["compact_64"] > row["compact_16"] > row["compact_4"] > row["bound"] > 0
    assert row["compact_1"] == row["bound"]
    # the backward: packed lanes walk no more than the block's, and a sub-block of the whole block is the same
    assert row["bwd_compact_64"] == row["bwd_block_64"] >= row["bwd_block_32"] >= row["bwd_compact_32"] > 0
    assert "| 1,856 |" in capsys.readouterr().out


def test_the_profile_counts_every_renderer_kernel_as_the_renderers(benchmark_script):
    # names as torch.profiler reports them (BENCHMARKS section 7's profile): the rasterizer's per-pixel and merge
    # kernels were once counted as generic element-wise work, the setup's too
    prof = benchmark_script("profile_iteration")
    for name in ("_fused_forward", "_fused_backward", "_pixel_backward", "_merge_forward"):
        assert prof.category(name) == "rasterizer (fused triton)", name
    for name in ("_setup_forward", "_setup_backward", "_floor_forward", "_floor_backward"):
        assert prof.category(name) == "renderer setup (triton)", name
    assert prof.category("triton_poi_fused_clone_sub_0") == "inductor triton (sim, elementwise)"
    assert prof.category("void cudnn::engines_precompiled::convertTensor_kernel<float>") == "cudnn conv"
    assert prof.category("void at::native::elementwise_kernel<128, 2>") == "aten elementwise/other"


@pytest.mark.slow
def test_sim_times_both_backends_after_checking_warp(tmp_path, benchmark_script):
    """``sim.py --backends torch warp``: a row per backend in one JSON, the Warp row carrying its check against the
    float64 torch simulator (CPU, tiny sizes)."""
    pytest.importorskip("warp")
    sim = benchmark_script("sim")
    out = tmp_path / "sim.json"
    sim.main(["--device", "cpu", "--tasks", "cartpole", "--num-envs", "2", "--horizon", "1", "--modes", "eager",
              "--backends", "torch", "warp", "--check-horizon", "2", "--iters", "1", "--warmup", "1",
              "--settle-s", "0", "--out", str(out)])
    rows = json.loads(out.read_text())["rows"]
    assert [(r["backend"], r["status"]) for r in rows] == [("torch", "ok"), ("warp", "ok")]
    warp = rows[1]
    assert warp["check_ok"] and warp["check_grad_cos"] > 0.999 and warp["ms"] > 0
    assert warp["check_state_err"] <= 4 * warp["check_torch32_spread"] + 1e-5
    assert abs(rows[0]["loss"] - warp["loss"]) <= 1e-4 * abs(rows[0]["loss"])  # the same rollout, either backend
