"""The evaluation schedule: every --eval-every-th iteration, denser from --eval-final-from on
(--eval-final-every), and the last; recorded in config.json."""

from __future__ import annotations

import json

import pytest

from ablations.cli import ablate_main
from ablations.run_config import RunConfig
from ablations.run_folder import read_metrics


def evaluated(cfg: RunConfig, iters: int) -> list[int]:
    return [it for it in range(1, iters + 1) if cfg.evaluates_at(it, ended=it == iters)]


def test_the_schedule_is_every_kth_plus_the_final_window():
    assert evaluated(RunConfig(eval_every=250), 1000) == [250, 500, 750, 1000]
    dense = RunConfig(eval_every=250, eval_final_every=50, eval_final_from=1500)
    assert evaluated(dense, 2000) == [250, 500, 750, 1000, 1250, 1500, 1550, 1600, 1650, 1700, 1750, 1800, 1850,
                                      1900, 1950, 2000]
    # the last iteration is evaluated where either schedule is on, off the grid too
    assert evaluated(RunConfig(eval_every=0, eval_final_every=3, eval_final_from=5), 9) == [5, 8, 9]
    assert evaluated(RunConfig(eval_every=0), 9) == []


@pytest.mark.parametrize(("flags", "message"), [
    ({"eval_final_every": 5}, "--eval-final-every and --eval-final-from go together"),
    ({"eval_final_from": 5}, "--eval-final-every and --eval-final-from go together"),
    ({"eval_final_every": -1, "eval_final_from": 5}, "--eval-final-every"),
    ({"eval_final_every": 5, "eval_final_from": 0}, "--eval-final-from"),
])
def test_bad_windows_are_refused_naming_the_flag(flags, message):
    with pytest.raises(ValueError, match=message):
        RunConfig(**flags).validate()


@pytest.mark.slow
def test_a_run_evaluates_on_the_schedule_and_records_it(tmp_path):
    ablate_main(["--task", "cartpole", "--mode", "decoupled", "--iters", "6", "--eval-every", "4", "--eval-final-every",
                 "1", "--eval-final-from", "5", "--video-every", "0", "--cosine-every", "0", "--eval-envs", "1",
                 "--num-envs", "2", "--horizon", "3", "--image-size", "24", "--critic-iterations", "1",
                 "--critic-batches", "1", "--device", "cpu", "--no-progress", "--out", str(tmp_path), "--name", "r"])
    rows = read_metrics(tmp_path / "r")
    assert [r["iter"] for r in rows if "eval_return_mean" in r] == [4, 5, 6]
    config = json.loads((tmp_path / "r" / "config.json").read_text())["config"]
    assert (config["eval_every"], config["eval_final_every"], config["eval_final_from"]) == (4, 1, 5)
