"""The GPU experiments shipped under docs/ are what their READMEs say: the reports' inputs, readable as run folders."""

from __future__ import annotations

import json
import shutil
import tarfile
from collections import Counter
from pathlib import Path

import pytest

from ablations.reports.arms import arm_label, arm_names, iteration_times
from ablations.run_folder import CONFIG, evaluation_of, find_runs

ROOT = Path(__file__).resolve().parents[2]
#: The experiments whose run folders ship as docs/<experiment>/runs.tar.xz.
EXPERIMENTS = ("seeded", "hopper_population_h100", "hopper_diagnosis_h100", "precision_h200", "humanoid_h200",
               "sim_backends_h200", "confirmatory")
#: The arms of the shipped runs (names from vocabulary.ARMS).
SHIPPED_ARMS = {"decoupled", "full-soft", "full-hard-dva", "blind"}


@pytest.fixture(scope="module")
def shipped(tmp_path_factory) -> Path:
    """The shipped archives unpacked as their READMEs unpack them: <experiment>/runs/ under a temporary folder."""
    root = tmp_path_factory.mktemp("docs")
    for name in EXPERIMENTS:
        with tarfile.open(ROOT / "docs" / name / "runs.tar.xz") as archive:
            archive.extractall(root / name, filter="data")
    return root


def _last_evaluated_iteration(run) -> int:
    return max(r["iter"] for r in run.metrics if evaluation_of(r) is not None)


def test_the_hopper_population_is_twelve_members_of_one_process_that_finished_2000_iterations(shipped):
    # decoupled, full, full with the hard raster model and blind, seeds 0-2, one compiled GPU run
    runs = find_runs([shipped / "hopper_population_h100" / "runs"])
    assert len(runs) == 12
    assert {r.population["folder"] for r in runs} == {"hopper_population12"}
    assert all(len(r.population["members"]) == 12 for r in runs)
    assert {(r.summary["status"], r.summary["iterations"]) for r in runs} == {("finished", 2000)}
    assert all(r.config["compile"] and r.task == "hopper" for r in runs)
    assert all(r.environment["device"] == "cuda" for r in runs)
    arms = arm_names(runs)
    assert Counter(arms.values()) == {a: 3 for a in SHIPPED_ARMS}
    assert {(arms[r.path], r.seed) for r in runs} == {(a, s) for a in SHIPPED_ARMS for s in range(3)}
    assert {_last_evaluated_iteration(r) for r in runs} == {2000}


def test_the_ant_populations_hold_the_four_arms_with_three_seeds_each_past_2000_iterations(shipped):
    # the seeded experiment: ant, the four arms, 3 seeds, at least 2000 iterations in one continuous GPU run
    runs = find_runs([shipped / "seeded" / "runs"])
    ant = [r for r in runs if r.task == "ant"]
    assert len(ant) == 12  # no (arm, seed) twice
    arms = arm_names(ant)
    assert {(arms[r.path], r.seed) for r in ant} == {(a, s) for a in SHIPPED_ARMS for s in range(3)}
    assert all(r.summary["status"] in ("finished", "time_limit") and r.summary["iterations"] >= 2000 for r in ant)
    assert all(_last_evaluated_iteration(r) == r.summary["iterations"] for r in ant)


@pytest.mark.parametrize(("task", "folders"), [
    ("hopper", {f"hopper_population_{p}" for p in "abc"}),
    ("cartpole-swingup", {f"cartpole_swingup_population_{p}" for p in "abcd"}),
])
def test_the_seeded_populations_hold_the_four_arms_with_five_seeds_each_at_3000_iterations(shipped, task, folders):
    # the seeded experiment: hopper and cartpole-swingup, the four arms, 5 seeds, at least 3000 iterations;
    # compiled GPU populations
    runs = [r for r in find_runs([shipped / "seeded" / "runs"]) if r.task == task and r.population["folder"] in folders]
    assert len(runs) == 20  # no (arm, seed) twice
    arms = arm_names(runs)
    assert {(arms[r.path], r.seed) for r in runs} == {(a, s) for a in SHIPPED_ARMS for s in range(5)}
    assert {(r.summary["status"], r.summary["iterations"]) for r in runs} == {("finished", 3000)}
    assert {_last_evaluated_iteration(r) for r in runs} == {3000}
    assert all(r.config["compile"] and r.environment["device"] == "cuda" for r in runs)
    assert {r.population["folder"] for r in runs} == folders


@pytest.mark.parametrize(("task", "sweep_file"), [("cartpole-swingup", "ablate_paper_cartpole_swingup.sweep.json"),
                                                 ("hopper", "ablate_paper_hopper.sweep.json")])
def test_the_tasks_have_the_six_arms_the_papers_baseline_and_state_from_ablate_paper_on_one_h200(shipped, task,
                                                                                                   sweep_file):
    # issue "six arms on every task": full-hard (--preset shac-diffrender) and state x 5 seeds x 3000 iterations,
    # launched by ablate-paper (--pack 5) on a one-GPU H200 machine; its sweep.json records where each run trained
    runs = [r for r in find_runs([shipped / "seeded" / "runs"]) if r.task == task]
    arms = arm_names(runs)
    assert Counter(arms.values()) == {a: 5 for a in (*SHIPPED_ARMS, "full-hard", "state")}
    added = [r for r in runs if arms[r.path] in ("full-hard", "state")]
    assert {r.population["folder"] for r in added} == {f"{task}_population0", f"{task}_population1"}
    assert all(r.config["preset"] == "shac-diffrender" and r.config["raster_model"] == "hard"
               for r in added if arms[r.path] == "full-hard")
    # the state arm trains with SHAC's state-based settings (gradlab.presets: the hopper's 256 environments)
    assert {r.config["num_envs"] for r in added if arms[r.path] == "state"} == {256 if task == "hopper" else 64}
    assert {(r.summary["status"], r.summary["iterations"]) for r in added} == {("finished", 3000)}
    assert {_last_evaluated_iteration(r) for r in added} == {3000}
    assert all(r.config["compile"] and r.environment["device"] == "cuda" for r in added)
    sweep = json.loads((ROOT / "docs" / "seeded" / sweep_file).read_text())
    assert sweep["command"][0] == "ablate-paper" and sweep["counts"]["done"] == 10
    assert {(r["arm"], r["seed"]) for r in sweep["runs"].values()} == {
        (a, s) for a in ("full-hard", "state") for s in range(5)}
    assert {tuple(r["gpus"]) for r in sweep["runs"].values()} == {("0",)}


def test_every_arm_of_the_seeded_experiment_has_its_iteration_time_measured_alone(shipped):
    # the equal-wall-clock view needs each arm's iteration time measured alone, all of a task's on one device;
    # the README's report command passes these benchmarks, the first file with an arm's row giving its time. The
    # hopper's state arm was timed at 64 environments, not its runs' 256: it alone is left out of that view.
    runs = find_runs([shipped / "seeded" / "runs"])
    results = ROOT / "benchmarks" / "results"
    cartpole = results / "iteration_arms_alone_cartpole_h200_20261128.json"
    hopper = results / "iteration_arms_alone_hopper_h200_20261129.json"
    h100 = results / "iteration_arms_alone_h100_20261127.json"
    times = iteration_times(runs, arm_label(runs), [cartpole, hopper, h100])
    assert set(times) == {"ant", "hopper", "cartpole-swingup"}
    bench = {"cartpole-swingup": cartpole, "hopper": hopper, "ant": h100}
    timed = {"cartpole-swingup": SHIPPED_ARMS | {"full-hard", "state"}, "hopper": SHIPPED_ARMS | {"full-hard"},
             "ant": SHIPPED_ARMS}
    for task, t in times.items():
        assert t.ms is not None and set(t.ms) == timed[task], (task, t.why)
        assert t.untimed == (("state",) if task == "hopper" else ())
        assert {t.found[a].source for a in t.ms} == {f"benchmark {bench[task].name}"}
        # blind renders nothing, decoupled renders without a backward through the image, full does both
        assert t.ms["blind"] < t.ms["decoupled"] < min(t.ms["full-soft"], t.ms["full-hard-dva"])
        if task != "ant":  # full-hard costs full-hard-dva's (the preset changes the schedule, not the work)
            assert t.ms["full-hard"] == t.ms["full-hard-dva"]
    assert times["cartpole-swingup"].ms["state"] < times["cartpole-swingup"].ms["blind"]


def test_the_humanoid_from_pixels_is_three_decoupled_seeds_of_one_population_and_its_readme_quotes_them(shipped):
    # docs/humanoid_h200: decoupled x seeds 0-2, one compiled population on one H200, stopped by its 19-minute budget
    from ablations.reports.stats.estimates import iqm_estimate

    runs = find_runs([shipped / "humanoid_h200" / "runs"])
    assert sorted(r.seed for r in runs) == [0, 1, 2]
    assert {(r.task, r.mode, r.setting("preset")) for r in runs} == {("humanoid", "decoupled", "dva")}
    assert {(r.summary["status"], r.summary["iterations"]) for r in runs} == {("time_limit", 2461)}
    assert all(r.config["compile"] and r.environment["gpu"] == "NVIDIA H200" for r in runs)
    assert {r.population["folder"] for r in runs} == {"humanoid_decoupled_pop3"}
    final = {}
    for r in runs:
        evals = {row["iter"]: evaluation_of(row)[0] for row in r.metrics if evaluation_of(row) is not None}
        assert sorted(evals)[-3:] == [2000, 2250, 2461]
        final[r.seed] = sum(evals[i] for i in (2000, 2250, 2461)) / 3
    readme = (ROOT / "docs" / "humanoid_h200" / "README.md").read_text()
    assert f"IQM {iqm_estimate(list(final.values())).value:.1f}" in readme
    assert f"per seed {final[0]:.0f}, {final[1]:.0f} and {final[2]:.0f}" in readme
    assert round(runs[0].summary["median_iter_ms"], 1) == 410.6 and "410.6 ms" in readme


def test_the_registered_runs_pass_the_registration_and_the_readme_lists_them(shipped):
    # docs/confirmatory: look 1's populations so far, each trained from the pinned tree; every run passes the
    # registration's checks (tree hash, registered fields) and the page's table is what the folders hold
    from ablations.registration import check_runs, load_registration
    from ablations.reports.confirmatory import in_family, latest_complete_look, look_progress

    reg = load_registration(ROOT / "docs" / "confirmatory" / "preregistration.json")
    runs = find_runs([shipped / "confirmatory" / "runs"])
    assert runs and all(in_family(reg, r) for r in runs) and check_runs(reg, runs) == []
    assert {r.tree_hash for r in runs} == {reg.tree_hash}
    assert {(r.summary["status"], r.summary["iterations"]) for r in runs} == {("finished", 2000)}
    assert {_last_evaluated_iteration(r) for r in runs} == {2000}
    readme = (ROOT / "docs" / "confirmatory" / "README.md").read_text()
    for folder in {r.population["folder"] for r in runs}:
        members = [r for r in runs if r.population["folder"] == folder]
        assert len(members) == 12 and len({r.task for r in members}) == 1
        seeds, arms = sorted({r.seed for r in members}), arm_names(members)
        assert {(arms[r.path], r.seed) for r in members} == {(a, s) for a in reg.arms for s in seeds}
        first = members[0].summary
        row = (f"| `{folder}` | {members[0].task} | {seeds[0]}-{seeds[-1]}, four arms | H200, ")
        assert row in readme and f"| {first['wall_s']:.0f} s | {first['median_iter_ms']:.1f} ms |" in readme, folder
    done = look_progress(reg, runs)[0]
    assert done.startswith(f"Look 1: {len(runs)} of 96 registered runs done") and f"({len(runs)} of its 96" in \
        (ROOT / "README.md").read_text().replace("\n", " ")
    assert latest_complete_look(reg, runs) is None or len(runs) >= 96


def test_every_experiment_ships_its_run_folders_as_one_archive(shipped):
    # The run data is most of what a clone checks out: one xz stream an experiment shares its dictionary across the
    # similar runs and leaves no file per run (docs/design.md, "Shipped run data"). Nothing of runs/ is tracked.
    for name in EXPERIMENTS:
        assert (ROOT / "docs" / name / "runs.tar.xz").is_file()
        assert sorted(p.parent for p in (shipped / name).glob(f"runs/**/{CONFIG}")), name


def test_the_precision_comparison_is_four_hopper_populations_and_its_readme_quotes_its_statistics(
        shipped, benchmark_script):
    # docs/precision_h200: decoupled and full (softmax) x fp32 and bf16 x seeds 0-4, 2000 iterations, one
    # compiled population each; the README's paired numbers are what benchmarks/precision_seeded.py computes
    runs = find_runs([shipped / "precision_h200" / "runs"])
    assert len(runs) == 20
    assert {(r.config["mode"], r.config["precision"], r.seed) for r in runs} == {
        (m, p, s) for m in ("decoupled", "full") for p in ("fp32", "bf16") for s in range(5)}
    assert {(r.summary["status"], r.summary["iterations"]) for r in runs} == {("finished", 2000)}
    assert all(r.config["compile"] and r.environment["device"] == "cuda" for r in runs)
    doc = benchmark_script("precision_seeded").compare_precisions([shipped / "precision_h200" / "runs"])
    rows = {r["arm"]: r for r in doc["rows"]}
    assert set(rows) == {"decoupled", "full-soft"} and doc["family"] == 2
    assert all(r["window"] == [1500, 1750, 2000] for r in rows.values())
    readme = (ROOT / "docs" / "precision_h200" / "README.md").read_text()
    for r in rows.values():
        quoted = (f"{r['mean']:+.0f} [{r['ci'][0]:+.0f}, {r['ci'][1]:+.0f}], {r['agree']} of 5 seeds, "
                  f"sign-flip p = {r['p']:.3f}, Holm {r['p_holm']:.3f}")
        assert quoted in readme, quoted
    assert not any(r["differs"] for r in rows.values())  # 5 paired seeds cannot differ under Holm over 2


def test_the_simulator_backends_seeded_check_is_two_hopper_populations_and_its_readme_quotes_them(
        shipped, benchmark_script):
    # docs/sim_backends_h200: decoupled hopper x seeds 0-2 x --sim-backend torch and warp, 1000 iterations, one
    # compiled population each; the README's table and paired numbers are what precision_seeded.py computes
    runs = find_runs([shipped / "sim_backends_h200" / "runs"])
    assert {(r.config["mode"], r.config.get("sim_backend") or "torch", r.seed) for r in runs} == {
        ("decoupled", b, s) for b in ("torch", "warp") for s in range(3)}
    assert len(runs) == 6 and {(r.summary["status"], r.summary["iterations"]) for r in runs} == {("finished", 1000)}
    assert all(r.config["compile"] and r.environment["device"] == "cuda" for r in runs)
    doc = benchmark_script("precision_seeded").compare_precisions([shipped / "sim_backends_h200" / "runs"],
                                                                  setting="sim_backend")
    (row,) = doc["rows"]
    assert (row["arm"], row["sim_backend"], row["reference"]) == ("decoupled", "warp", "torch")
    assert row["window"] == [800, 900, 1000]
    readme = (ROOT / "docs" / "sim_backends_h200" / "README.md").read_text()
    for seed in range(3):
        ref, cand = row["reference_returns"][seed], row["candidate"][seed]
        assert f"| {seed} | {ref:.0f} | {cand:.0f} | {cand - ref:+.0f} |" in readme, seed
    quoted = (f"Mean difference {row['mean']:+.0f} [{row['ci'][0]:+.0f}, {row['ci'][1]:+.0f}], {row['agree']} of 3 "
              f"seeds above, sign-flip p = {row['p']:.3f}")
    assert quoted in readme, quoted


def test_the_precision_comparison_refuses_a_seed_twice_in_one_arm_and_precision(shipped, tmp_path, benchmark_script):
    # a second copy of a run would count its seed twice (or silently replace it): named instead
    runs = shipped / "precision_h200" / "runs"
    shutil.copytree(runs, tmp_path / "a")
    shutil.copytree(runs / "hopper_full_bf16" / "hopper_full_seed0", tmp_path / "b" / "hopper_full_seed0")
    with pytest.raises(ValueError, match="has two runs"):
        benchmark_script("precision_seeded").compare_precisions([tmp_path])
