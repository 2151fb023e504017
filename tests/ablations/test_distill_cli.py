"""``ablate --mode distill`` end to end: a tiny state expert trained with the teacher preset, a student that
imitates it in a run folder of the usual kind (config.json with the expert and its charged cost, metrics,
summary, checkpoints), its resume (the buffer refilled), a population of students, the arms the reports give
them, and the refusals of bad experts."""

from __future__ import annotations

import json

import pytest

from ablations.cli import ablate_main
from ablations.reports.arms import arm_names
from ablations.run_folder import find_runs, read_metrics
from ablations.runs import REQUIRED_KEYS

TINY = ["--task", "cartpole", "--num-envs", "2", "--horizon", "4", "--episode-length", "12", "--eval-envs", "2",
        "--video-every", "0", "--device", "cpu", "--no-progress"]
STUDENT = ["--mode", "distill", "--image-size", "24", "--distill-buffer", "20", "--distill-starts", "16",
           "--distill-updates", "3", "--distill-batch", "4"]


@pytest.mark.slow
def test_ablate_distill_end_to_end(tmp_path, capsys):
    ablate_main([*TINY, "--mode", "state", "--preset", "teacher", "--iters", "2", "--critic-iterations", "1",
                 "--critic-batches", "1", "--out", str(tmp_path), "--name", "expert"])
    expert = tmp_path / "expert"
    ablate_main([*TINY, *STUDENT, "--expert", str(expert), "--iters", "3", "--eval-every", "3",
                 "--out", str(tmp_path), "--name", "student"])
    student = tmp_path / "student"
    record = json.loads((student / "config.json").read_text())
    expert_summary = json.loads((expert / "summary.json").read_text())
    assert record["config"]["mode"] == "distill" and record["config"]["expert"] == str(expert)
    assert record["expert"]["source"].startswith(str(expert / "checkpoints"))
    assert record["expert"]["wall_s"] == pytest.approx(expert_summary["wall_s"])
    assert record["expert"]["env_steps"] == expert_summary["env_steps"] == 2 * 4 * 2
    rows = read_metrics(student)
    assert [r["iter"] for r in rows] == [1, 2, 3] and all(set(REQUIRED_KEYS) <= set(r) for r in rows)
    assert [r["buffer_size"] for r in rows] == [8, 16, 20] and rows[0]["updates"] == 0 < rows[1]["updates"]
    assert all(r["wall_s"] == pytest.approx(r["expert_wall_s"] + r["student_wall_s"]) for r in rows)
    summary = json.loads((student / "summary.json").read_text())
    assert summary["status"] == "finished" and summary["final_eval_return"] is not None
    assert summary["wall_s"] > expert_summary["wall_s"] and (student / "checkpoints").is_dir()
    # the reports name the arms (the tiny sizes set the student apart from its expert's defaults, in brackets)
    runs = find_runs([expert, student])
    assert sorted(name.split(" (")[0] for name in arm_names(runs).values()) == ["distill", "expert"]

    # a resume goes on from the checkpoint and refills the buffer before it updates again
    ablate_main(["--resume", str(student), "--iters", "4", "--no-progress"])
    last = read_metrics(student)[-1]
    assert (last["iter"], last["buffer_size"], last["updates"]) == (4, 8, 0)

    # students of one expert each form a population
    members = [f"mode=distill,seed={s},expert={expert}" for s in (0, 1)]
    ablate_main([*TINY, *STUDENT, "--member", *members, "--iters", "1",
                 "--out", str(tmp_path), "--name", "population"])
    folders = sorted(p.name for p in (tmp_path / "population").iterdir() if p.is_dir())
    assert folders == ["cartpole_distill_seed0", "cartpole_distill_seed1"]

    # bad experts: one error line naming the flag, and no run folder left behind
    capsys.readouterr()
    for expert_flag, message in ((str(tmp_path / "nothing"), "no such file or folder"),
                                 (str(student), "a --mode distill run, not a state run")):
        with pytest.raises(SystemExit):
            ablate_main([*TINY, *STUDENT, "--expert", expert_flag, "--iters", "1", "--out", str(tmp_path),
                         "--name", "refused"])
        err = capsys.readouterr().err
        assert err.startswith(f"error: --expert {expert_flag}: {message}") and err.count("\n") == 1, err
        assert not (tmp_path / "refused").exists()


def test_ablate_distill_writes_the_usual_run_folder(tmp_path):
    """The fast path of the test above: an expert's checkpoint made by the trainer directly, one student run."""
    import torch

    from gradlab import SHAC, SHACConfig
    from gradlab.checkpoint import checkpoint_path, save_checkpoint

    torch.set_num_threads(1)
    trainer = SHAC([SHACConfig(task="cartpole", mode="state", iters=1, num_envs=2, horizon=4, critic_iterations=1,
                               critic_batches=1)], device="cpu")
    trainer.train_iteration()
    (tmp_path / "expert" / "checkpoints").mkdir(parents=True)
    save_checkpoint(checkpoint_path(tmp_path / "expert" / "checkpoints", 1), trainer.state_dict()[0])
    tiny = [a for i, a in enumerate(TINY) if a != "--eval-envs" and (i == 0 or TINY[i - 1] != "--eval-envs")]
    ablate_main([*tiny, *STUDENT, "--expert", str(tmp_path / "expert"), "--iters", "2", "--eval-every", "0",
                 "--out", str(tmp_path), "--name", "student"])  # nothing evaluated: --eval-envs would be refused
    record = json.loads((tmp_path / "student" / "config.json").read_text())
    assert record["expert"]["env_steps"] == 8 and record["expert"]["iterations"] == 1
    rows = read_metrics(tmp_path / "student")
    assert [r["env_steps"] for r in rows] == [8 + 8, 8 + 16] and rows[-1]["buffer_size"] == 16
    assert json.loads((tmp_path / "student" / "summary.json").read_text())["status"] == "finished"
    assert (tmp_path / "student" / "checkpoints" / "ckpt_000002.pt").exists()


def test_ablate_paper_trains_the_experts_first(tmp_path):
    """ablate-paper with the distill arm: one sweep per task of its experts (the teacher preset, the teacher's
    max_epochs iterations: 4000 cartpole, 2000 others), then the experiment set, each distill run's --expert the
    folder its task's and seed's expert trains in; distill runs pack only with each other."""
    from ablations.paper import PaperConfig, phases
    from ablations.sweep import plan
    from ablations.sweep.packing import pack_runs

    cfg = PaperConfig(out=tmp_path, tasks=("cartpole-swingup", "hopper"), arms=("decoupled", "distill"),
                      seeds=(0, 1), gpus_per_run=0)
    planned = phases(cfg)
    assert len(planned) == 3
    for (sweep, arms), task, iters in zip(planned, ("cartpole-swingup", "hopper"), (4000, 2000)):
        specs = plan(sweep, arms=arms)
        assert sweep.out == tmp_path / "experts" / task and list(arms) == ["expert"]
        assert [(s.run_id, s.iters) for s in specs] == [(f"{task}_expert_seed{k}", iters) for k in (0, 1)]
        assert all("--preset" in s.args and "teacher" in s.args for s in specs)
    specs = plan(planned[-1][0], arms=planned[-1][1])
    distill = {s.run_id: s for s in specs if s.mode == "distill"}
    assert distill["hopper_distill_seed1"].own["expert"] == str(
        tmp_path / "experts" / "hopper" / "runs" / "hopper_expert_seed1")
    for job in pack_runs(specs, 12):
        assert len({"distill" in r for r in job.run_ids}) == 1
