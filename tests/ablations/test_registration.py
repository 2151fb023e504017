"""ablations.registration: the shipped docs/confirmatory/preregistration.json is valid and says what its page says;
bad files are refused naming the key; runs that differ from it are named; pinning writes the tree hash."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from ablations import registration as rg
from ablations.run_folder import Run
from ablations.tree_hash import tree_hash
from vocabulary import ARMS

SHIPPED = Path(__file__).resolve().parents[2] / "docs" / "confirmatory" / "preregistration.json"


def shipped() -> dict:
    return json.loads(SHIPPED.read_text())


def test_the_shipped_registration_is_the_issues_design():
    reg = rg.load_registration(SHIPPED)
    # pinned before any registered run: the runs train that tree (docs/confirmatory/README.md, "Running a look")
    assert reg.tree_hash is not None and reg.tree_hash.startswith("sha256:")
    assert [h.role for h in reg.hypotheses].count("gate") == 2 and len(reg.hypotheses) == 6
    gates = {(h.task, h.arm, h.reference, h.alternative) for h in reg.hypotheses if h.role == "gate"}
    assert gates == {(t, "decoupled", "blind", "greater") for t in ("hopper", "cartpole-swingup")}
    comparisons = {(h.task, h.arm, h.reference) for h in reg.hypotheses if h.role == "comparison"}
    assert comparisons == {(t, a, "decoupled") for t in ("hopper", "cartpole-swingup") for a in ("full-soft",
                                                                                               "full-hard")}
    assert [(len(lk.seeds), lk.alpha) for lk in reg.looks] == [(12, 0.01), (24, 0.04)]
    assert reg.looks[-1].seeds == tuple(range(100, 124)) and reg.iterations == 2000
    assert {"name", "out", "device", "threads", "compile_cache"} <= set(reg.may_differ)
    assert {"eval_every", "eval_envs", "eval_final_every", "eval_final_from", "iters"} <= set(reg.must_equal)


def bad(mutate):
    data = copy.deepcopy(shipped())
    mutate(data)
    return data


@pytest.mark.parametrize(("mutate", "message"), [
    (lambda d: d.pop("looks"), "missing key"),
    (lambda d: d["looks"][1].update(alpha=0.045), "sum to 0.055"),
    (lambda d: d["looks"][1].update(seeds=list(range(100, 110))), "every earlier look's seeds"),
    (lambda d: d["hypotheses"][0].update(alternative="bigger"), "hypothesis G-hopper: alternative"),
    (lambda d: d["hypotheses"][2].update(arm="full-alpha"), "arm 'full-alpha' is not among arms"),
    (lambda d: d["hypotheses"][2]["statistic"].update(to=2500), "window 1500-2500"),
    (lambda d: d["hypotheses"][3].update(id="G-hopper"), "a name of its own"),
    (lambda d: d.update(tree_hash="abc"), "tree_hash must be null"),
    (lambda d: d["may_differ"].append("iters"), "both in must_equal and may_differ: iters"),
    (lambda d: d["arms"].append("fancy"), "unknown arm"),
])
def test_bad_registrations_are_refused_naming_the_key(mutate, message):
    with pytest.raises(rg.RegistrationError, match=message) as e:
        rg.parse_registration(bad(mutate), "x/preregistration.json")
    assert str(e.value).startswith("x/preregistration.json: ")


def test_unreadable_files_name_the_file(tmp_path):
    with pytest.raises(rg.RegistrationError, match="no such registration file"):
        rg.load_registration(tmp_path / "none.json")
    (tmp_path / "torn.json").write_text("{")
    with pytest.raises(rg.RegistrationError, match=r"torn\.json: not readable JSON"):
        rg.load_registration(tmp_path / "torn.json")


def test_pin_writes_this_trees_hash_once(tmp_path):
    path = tmp_path / "preregistration.json"
    path.write_text(json.dumps(dict(shipped(), tree_hash=None), indent=2))  # as it was before its pin
    assert rg.pin(path) == tree_hash().value == rg.load_registration(path).tree_hash
    assert list(json.loads(path.read_text())) == list(shipped())  # the keys keep their order
    with pytest.raises(rg.RegistrationError, match="already pinned"):
        rg.pin(path, "sha256:" + "0" * 64)


def run(tmp_path, name, *, seed=100, arm_mode="decoupled", tree="sha256:" + "a" * 64, **config):
    reg = rg.load_registration(SHIPPED)
    cfg = dict(reg.settings, task="hopper", mode=arm_mode, raster_model=ARMS[arm_mode].raster_model,
               preset="dva", seed=seed, name=name, device="cuda", num_envs=64)
    cfg.update(config)
    return Run(path=tmp_path / name, config=cfg, environment={}, command=None, summary=None, metrics=[],
               tree_hash=tree)


def test_runs_that_differ_from_the_registration_are_named(tmp_path):
    reg = rg.parse_registration(dict(shipped(), tree_hash="sha256:" + "a" * 64))
    good = [run(tmp_path, "a"), run(tmp_path, "b", seed=101, device="cpu", threads=3)]
    assert rg.check_runs(reg, good) == []
    problems = rg.check_runs(reg, [*good, run(tmp_path, "c", seed=102, eval_every=100),
                                   run(tmp_path, "d", seed=103, tree="sha256:" + "b" * 64),
                                   run(tmp_path, "e", seed=104, num_envs=32), run(tmp_path, "f", seed=7)])
    assert len(problems) == 4
    assert f"{tmp_path / 'c'}: eval_every is 100, registered 250" in problems
    assert any(p.startswith(f"{tmp_path / 'd'}: tree hash sha256:bbb") for p in problems)
    assert any(p.startswith(f"{tmp_path / 'e'}: num_envs is 32, but {tmp_path / 'a'}") for p in problems)
    assert any(p.startswith(f"{tmp_path / 'f'}: task 'hopper', arm 'decoupled', seed 7 is not registered")
               for p in problems)
    with pytest.raises(rg.RegistrationError, match="not pinned"):
        rg.check_runs(rg.parse_registration(dict(shipped(), tree_hash=None)), good)
