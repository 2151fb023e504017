"""The GPU experiments shipped under docs/ are what their READMEs say: the reports' inputs, readable as run folders."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest

from ablations.reports.arms import arm_label, arm_names, iteration_times
from ablations.run_folder import COMPACTED, CONFIG, METRICS, SUMMARY, evaluation_of, find_runs

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
#: The arms of the shipped runs (names from vocabulary.ARMS).
SHIPPED_ARMS = {"decoupled", "full-soft", "full-hard-dva", "blind"}


def _last_evaluated_iteration(run) -> int:
    return max(r["iter"] for r in run.metrics if evaluation_of(r) is not None)


def test_the_hopper_population_is_twelve_members_of_one_process_that_finished_2000_iterations():
    # decoupled, full, full with the hard raster model and blind, seeds 0-2, one compiled GPU run
    runs = find_runs([DOCS / "hopper_population_h100" / "runs"])
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


def test_the_ant_populations_hold_the_four_arms_with_three_seeds_each_past_2000_iterations():
    # the seeded experiment: ant, the four arms, 3 seeds, at least 2000 iterations in one continuous GPU run
    runs = find_runs([DOCS / "seeded_h100" / "runs"])
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
def test_the_seeded_populations_hold_the_four_arms_with_five_seeds_each_at_3000_iterations(task, folders):
    # the seeded experiment: hopper and cartpole-swingup, the four arms, 5 seeds, at least 3000 iterations;
    # compiled GPU populations
    runs = [r for r in find_runs([DOCS / "seeded_h100" / "runs"]) if r.task == task]
    assert len(runs) == 20  # no (arm, seed) twice
    arms = arm_names(runs)
    assert {(arms[r.path], r.seed) for r in runs} == {(a, s) for a in SHIPPED_ARMS for s in range(5)}
    assert {(r.summary["status"], r.summary["iterations"]) for r in runs} == {("finished", 3000)}
    assert {_last_evaluated_iteration(r) for r in runs} == {3000}
    assert all(r.config["compile"] and r.environment["device"] == "cuda" for r in runs)
    assert {r.population["folder"] for r in runs} == folders


def test_every_arm_of_the_seeded_experiment_has_its_iteration_time_measured_alone():
    # the equal-wall-clock view needs each arm's iteration time measured alone; the README's report command passes
    # this benchmark, whose rows must match every arm's settings (sizes, raster, compile)
    runs = find_runs([DOCS / "seeded_h100" / "runs"])
    bench = ROOT / "benchmarks" / "results" / "iteration_arms_alone_h100_20261127.json"
    times = iteration_times(runs, arm_label(runs), [bench])
    assert set(times) == {"ant", "hopper", "cartpole-swingup"}
    for task, t in times.items():
        assert t.ms is not None and set(t.ms) == SHIPPED_ARMS, (task, t.why)
        assert {a.source for a in t.found.values()} == {f"benchmark {bench.name}"}
        # blind renders nothing, decoupled renders without a backward through the image, full does both
        assert t.ms["blind"] < t.ms["decoupled"] < min(t.ms["full-soft"], t.ms["full-hard-dva"])


def test_every_shipped_run_folder_is_compacted():
    # The run data is most of what a clone checks out; plain metrics and summaries would make it six times larger
    # (docs/design.md, "Shipped run data"). Each folder keeps both, compacted, and nothing plain beside them.
    folders = sorted(p.parent for p in DOCS.glob(f"*/runs/**/{CONFIG}"))
    assert folders
    for folder in folders:
        names = {p.name for p in folder.iterdir()}
        assert {METRICS + COMPACTED, SUMMARY + COMPACTED} <= names and not names & {METRICS, SUMMARY}, folder
