"""The registered analysis and ``ablate-plan`` on synthetic runs whose answers are known: planted paired
differences come back exactly, Holm across looks rejects what it should, the power is 1 for huge effects and at
most about alpha for none, and the command prints the table or pins the hash."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ablations import registration as rg
from ablations.cli import plan_main
from ablations.reports import confirmatory as cf
from ablations.tree_hash import tree_hash
from vocabulary import ARMS


def small_registration(**over) -> dict:
    window = {"kind": "window", "from": 10, "to": 20}
    data = {
        "name": "small", "tree_hash": None, "correction": "holm",
        "looks": [{"seeds": list(range(6)), "alpha": 0.02}, {"seeds": list(range(10)), "alpha": 0.03}],
        "iterations": 20, "budget_axis": "iterations", "tasks": ["hopper"],
        "arms": ["decoupled", "full-soft", "blind"],
        "hypotheses": [
            {"id": "G", "task": "hopper", "arm": "decoupled", "reference": "blind", "alternative": "greater",
             "statistic": window, "role": "gate", "smallest_effect": 50},
            {"id": "C", "task": "hopper", "arm": "full-soft", "reference": "decoupled", "alternative": "two-sided",
             "statistic": window, "role": "comparison", "smallest_effect": 5, "equivalence_margin": 5},
        ],
        "settings": {"iters": 20}, "must_equal": ["iters", "mode"], "may_differ": ["name"],
        "incomplete_looks": "waits",
    }
    data.update(over)
    return data


HASH = "sha256:" + "c" * 64


def write_run(root, arm, seed, returns_at, tree=HASH):
    """A run folder of ``arm`` with evaluations ``returns_at`` (iteration -> return), trained in tree ``tree``."""
    run = root / f"{arm}_{seed}"
    run.mkdir(parents=True)
    a = ARMS[arm]
    config = {"task": "hopper", "mode": a.mode, "raster_model": a.raster_model, "preset": a.preset, "seed": seed,
              "iters": 20}
    (run / "config.json").write_text(json.dumps({"config": config, "environment": {}, "tree_hash": tree}))
    lines = [{"iter": it, **({"eval_return_mean": returns_at[it]} if it in returns_at else {})}
             for it in range(1, 21)]
    (run / "metrics.jsonl").write_text("\n".join(map(json.dumps, lines)) + "\n")


def write_pilot(root, seeds=range(6), full_minus=-3.0):
    for s in seeds:
        base = 100.0 + 7 * s
        write_run(root, "blind", s, {5: 0.0, 10: 1.0, 20: 3.0})
        write_run(root, "decoupled", s, {5: 50.0, 10: base, 15: base + 2, 20: base + 4})
        write_run(root, "full-soft", s, {10: base + full_minus + s, 20: base + 4 + full_minus + s})


def test_planted_paired_differences_come_back(tmp_path):
    write_pilot(tmp_path)
    reg = rg.parse_registration(small_registration())
    from ablations.run_folder import find_runs
    pairs = cf.hypothesis_pairs(reg, find_runs([tmp_path]))
    # decoupled's window mean is base + 2 (10, 15, 20), blind's 2 (10, 20): +base; full-soft's base + 2 - 3 + s
    assert pairs["G"] == pytest.approx({s: 100.0 + 7 * s for s in range(6)})
    assert pairs["C"] == pytest.approx({s: -3.0 + s for s in range(6)})
    assert cf.hypothesis_pairs(reg, find_runs([tmp_path]), seeds=[1, 2])["C"] == pytest.approx({1: -2.0, 2: -1.0})


def test_holm_across_looks_and_the_control_rule():
    reg = rg.parse_registration(small_registration())
    assert cf.holm_rejects({"a": 0.001, "b": 0.02, "c": 0.5}, 0.05) == {"a", "b"}  # 0.001 <= 0.05/3, 0.02 <= 0.025
    assert cf.holm_rejects({"a": 0.001, "b": float("nan")}, 0.0015) == set()  # NaN counts in m: 0.001 > 0.00075
    # look 1 rejects the gate (0.01 <= 0.02 / 2); look 2 tests C alone at 0.03
    assert cf.sequential_holm(reg, [{"G": 0.01, "C": 0.2}, {"G": 0.9, "C": 0.025}]) == [{"G"}, {"G", "C"}]
    # a comparison without its gate does not stand
    assert cf.sequential_holm(reg, [{"G": 0.5, "C": 0.001}]) == [set()]


def test_tost_is_the_larger_one_sided_p():
    assert cf.tost_p([0.1] * 8, margin=10) == 1 / 2 ** 8
    # by hand: d + 0.05 = (0.15, -0.15, 0.35) reaches its sum 0.35 in 3 of 8 sign patterns; d - 0.05 =
    # (0.05, -0.25, 0.25) is at or below its sum 0.05 in 6 of 8
    assert cf.tost_p([0.1, -0.2, 0.3], margin=0.05) == 6 / 8
    assert np.isnan(cf.tost_p([], margin=1))


def test_power_is_one_for_huge_effects_and_about_alpha_for_none():
    reg = rg.parse_registration(small_registration())
    huge = cf.simulate_power(reg, {"G": (10.0, 1.0), "C": (-10.0, 1.0)}, sims=30)
    assert huge["G"].by_last == huge["C"].by_last == 1.0
    # 6 seeds at look 1 cannot reject: the smallest one-sided p, 1/64, is above Holm's first bound 0.02 / 2
    assert huge["G"].at_first == huge["C"].at_first == 0.0
    none = cf.simulate_power(reg, {"G": (0.0, 1.0), "C": (0.0, 1.0)}, sims=400, seed=1)
    assert none["G"].by_last <= 0.05 + 0.035  # family-wise 0.05; 3.2 binomial SDs of 400 draws
    # margin 5 at SD 1 over 10 seeds: every d + 5 > 0 and d - 5 < 0 (short of a 5-SD draw), p = 2^-10 <= 0.03
    assert none["C"].tost == 1.0
    with pytest.raises(ValueError, match="sims"):
        cf.simulate_power(reg, {}, sims=0)


def test_ablate_plan_prints_the_table_and_pins(tmp_path, capsys):
    write_pilot(tmp_path / "pilot")
    path = tmp_path / "preregistration.json"
    path.write_text(json.dumps(small_registration()))
    plan_main([str(tmp_path / "pilot"), "--registration", str(path), "--sims", "20"])
    out = capsys.readouterr().out
    # G: 100 + 7 s over seeds 0-5, mean 117.5, SD 7 x 1.8708 = 13.1; look 1's 6 seeds cannot reject (1/64 > 0.01)
    assert "| G | window 10-20, greater | 6 | +117.5, 13.1 | 1.00 (0.00) | 50 |" in out
    # C: -3 + s, mean -0.5, SD 1.9; at 5 (the smallest effect) power 1; TOST at +-5 with no difference: 1
    assert "| C | window 10-20, two-sided | 6 | -0.5, 1.9 |" in out and "| 5 | 1.00 (0.00) | 5 | 1.00 |" in out
    plan_main(["--pin", "--registration", str(path)])
    assert capsys.readouterr().out.strip() == f"{path}: tree_hash {tree_hash().value}"
    assert rg.load_registration(path).tree_hash == tree_hash().value


def test_ablate_plan_refuses_in_one_line(tmp_path, capsys):
    path = tmp_path / "preregistration.json"
    path.write_text(json.dumps(small_registration()))
    for argv, message in (([ "--registration", str(path)], "give pilot run folders"),
                          ([str(tmp_path), "--registration", str(tmp_path / "none.json")], "no such registration")):
        with pytest.raises(SystemExit) as e:
            plan_main(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2 and err.startswith("error: ") and message in err and err.count("\n") == 1


def test_the_registered_analysis_reads_the_latest_complete_look(tmp_path):
    from ablations.run_folder import find_runs
    write_pilot(tmp_path / "runs")
    looks = [{"seeds": list(range(6)), "alpha": 0.04}, {"seeds": list(range(10)), "alpha": 0.01}]
    reg = rg.parse_registration(small_registration(tree_hash=HASH, looks=looks))
    assert cf.latest_complete_look(reg, find_runs([tmp_path / "runs"])) == 0  # seeds 6-9 have no runs
    assert "| hopper | blind | 0-5 | - |" in cf.look_progress(reg, find_runs([tmp_path / "runs"]), 0)
    second = cf.look_progress(reg, find_runs([tmp_path / "runs"]), 1)
    assert second[0].startswith("Look 2: 18 of 30 registered runs done") and "| hopper | blind | 0-5 | 6-9 |" in second
    text = "\n".join(cf.registered_section(reg, find_runs([tmp_path / "runs"])))
    assert "Look 1 of 2 is the latest complete one (6 seeds, alpha 0.04)" in text
    # G: every seed agrees, one-sided p = 1/64 <= 0.04 / 2; C: -3 + s, p well above
    assert "| G | decoupled - blind | greater | 6 | +117.5 [" in text and "| 6 of 6 | 0.0156 | rejected at look 1 |" \
        in text
    assert "| C | full-soft - decoupled | two-sided | 6 | -0.5 [" in text and "not rejected (not equivalence)" in text


def test_the_registered_analysis_refuses_runs_that_differ_naming_them(tmp_path):
    from ablations.run_folder import find_runs
    write_pilot(tmp_path / "runs", seeds=range(5))
    write_run(tmp_path / "runs", "blind", 5, {10: 1.0, 20: 3.0}, tree="sha256:" + "d" * 64)
    reg = rg.parse_registration(small_registration(tree_hash=HASH))
    with pytest.raises(ValueError, match=r"1 run\(s\) differ") as e:
        cf.registered_section(reg, find_runs([tmp_path / "runs"]))
    assert f"{tmp_path / 'runs' / 'blind_5'}: tree hash sha256:ddd" in str(e.value)
    with pytest.raises(rg.RegistrationError, match="not pinned"):
        cf.registered_section(rg.parse_registration(small_registration()), find_runs([tmp_path / "runs"]))
    # look 1 needs seeds 0-5 of every arm: without blind seed 5 nothing is tested
    (tmp_path / "runs" / "blind_5" / "config.json").unlink()
    (tmp_path / "runs" / "blind_5").rename(tmp_path / "elsewhere")
    text = "\n".join(cf.registered_section(reg, find_runs([tmp_path / "runs"])))
    assert "Look 1 (6 seeds) is not complete" in text
    # what is left to run, by task and arm; no statistic of a hypothesis before its look is complete
    assert "Look 1: 15 of 18 registered runs done" in text
    assert "| hopper | blind | 0-4 | 5 |" in text and "| hopper | decoupled | 0-4 | 5 |" in text
    assert "| G |" not in text and "exact p" not in text


def test_seed_ranges_name_runs_of_consecutive_seeds():
    assert cf._seed_ranges([105, 100, 101, 102, 107, 108]) == "100-102, 105, 107-108"
    assert cf._seed_ranges([]) == "" and cf._seed_ranges([3]) == "3"


@pytest.mark.slow
def test_ablate_report_with_a_registration_opens_with_it_and_reads_nothing_else(tmp_path):
    from ablations.cli import report_main
    write_pilot(tmp_path / "runs")
    looks = [{"seeds": list(range(6)), "alpha": 0.04}, {"seeds": list(range(10)), "alpha": 0.01}]
    (tmp_path / "reg.json").write_text(json.dumps(small_registration(tree_hash=HASH, looks=looks)))
    report_main([str(tmp_path / "runs"), "--out", str(tmp_path / "rep" / "report.md"), "--registration",
                 str(tmp_path / "reg.json"), "--reps", "20"])
    text = (tmp_path / "rep" / "report.md").read_text()
    assert text.index("## The registered analysis") < text.index("## 1.")
    assert "| G | decoupled - blind | greater | 6 |" in text and "**Verdict" not in text
    assert "| blind | 6 |" in text and text.count("| exploratory |") == 2  # full-soft and blind, no reading
