"""Every refusal of a command is one ``error:`` line naming the flag as typed (choices included), exit status 2,
and nothing is created: bad choices and numbers (which tyro would answer with a box), flags given twice, flags a
resume would ignore, settings that mean nothing for the mode, names that are paths, more threads than cores."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ablations.cli import ablate_main
from tasks import command_line

ROOT = Path(__file__).resolve().parents[2]


def refusal(err: str) -> str:
    """The one line of a refusal (asserted to be exactly one ``error:`` line, no traceback)."""
    assert err.startswith("error: ") and err.count("\n") == 1, err
    return err.strip()


@pytest.fixture
def two_cores(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})


CASES = [
    # tyro's boxes, as one line
    (["--mode", "fulll"], "--mode 'fulll' is not one of full, decoupled, state, blind"),
    (["--mode", "full", "fulll"], "--mode 'fulll' is not one of full, decoupled, state, blind"),
    (["--preset", "nope"], "--preset 'nope' is not one of dva, shac-diffrender"),
    (["--raster-model", "blurry"], "--raster-model 'blurry' is not one of hard, softmax, alpha"),
    (["--renderer", "pbr"], "--renderer 'pbr' is not one of soft, warp"),
    (["--num-envs", "1.5"], "--num-envs must be an integer, got '1.5'"),
    (["--seed", "0", "one"], "--seed must be an integer, got 'one'"),
    (["--gamma", "high"], "--gamma must be a number, got 'high'"),
    (["--betas", "0.9"], "--betas takes 2 values, got 1: 0.9"),
    (["--iters"], "--iters needs a value"),
    (["--iters", "3", "4"], "--iters takes one value, got 2: 3 4"),
    (["--modes", "full"], "--modes: no such flag (did you mean --mode?); ablate --help lists them"),
    (["--compile=yes"], "--compile is a switch and takes no value (--compile or --no-compile)"),
    # a flag twice: the last would win without a word
    (["--iters", "3", "--iters", "4"], "--iters is given twice: give it once"),
    (["--num_envs", "3", "--num-envs", "4"], "--num-envs and --num_envs are both given: give one"),
    (["--seed", "0", "--seed", "1"], "--seed is given twice: give it once (several values after one flag)"),
    (["--compile", "--no-compile"], "--no-compile and --compile are both given: give one"),
    # a member's own settings are named as the member entry gives them
    (["--member", "mode=bogus"], "--member 'mode=bogus': mode: unknown mode 'bogus'; valid modes: full, "
                                 "decoupled, state, blind"),
    (["--member", "mode=full,actor_lr=-1"], "--member 'mode=full,actor_lr=-1': actor_lr must be in (0, inf), "
                                            "got -1"),
    (["--member", "mode=state,raster_model=hard"], "--member 'mode=state,raster_model=hard': raster_model=hard "
                                                   "means nothing with mode=state"),
    # a setting that means nothing for the mode is refused, not recorded as if it had acted
    (["--mode", "state", "--raster-model", "hard"], "--raster-model hard means nothing with --mode state"),
    (["--mode", "blind", "--raster-model", "softmax"], "--raster-model softmax means nothing with --mode blind"),
    (["--mode", "full", "state", "--raster-model", "hard"], "--raster-model hard means nothing with --mode state"),
    # distill needs a state expert; an expert or the teacher preset mean nothing elsewhere
    (["--mode", "distill"], "--expert: --mode distill needs a state expert"),
    (["--mode", "decoupled", "--expert", "runs/x"], "--expert means nothing with --mode decoupled"),
    (["--mode", "full", "--preset", "teacher"], "--preset teacher trains the state experts of --mode distill"),
    # the run folder stays inside --out
    (["--name", "../escape"], "--name '../escape': the run folder's name inside --out, not a path"),
    (["--name", "a/b"], "--name 'a/b': the run folder's name inside --out, not a path"),
    (["--name", ".."], "--name '..': the run folder's name inside --out, not a path"),
    # more threads than cores (two_cores) only wait
    (["--threads", "3"], "--threads 3 is more than the 2 cores this process may use (its CPU affinity)"),
    # a member's values are typed and checked before the trainer is built
    (["--member", "mode=decoupled,seed=abc"], "--member 'mode=decoupled,seed=abc': seed must be an integer, got "
                                              "'abc'"),
    (["--member", "mode=decoupled,seed=1.5"], "--member 'mode=decoupled,seed=1.5': seed must be an integer, got "
                                              "'1.5'"),
    (["--member", "mode=decoupled,betas=0.7"], "--member 'mode=decoupled,betas=0.7': betas takes 2 values "
                                               "separated by '/', got 1: 0.7"),
    (["--member", "mode=decoupled,mode=full"], "--member 'mode=decoupled,mode=full': mode is given twice"),
    (["--seed", "99999999999999999999"], "--seed must be an integer in [-2**63, 2**63 - 1] (torch's 64-bit seed), "
                                         "got 99999999999999999999"),
    (["--member", f"mode=full,seed={2**64}"], f"--member 'mode=full,seed={2**64}': seed must be an integer in "
                                              "[-2**63, 2**63 - 1]"),
    # a flag given where it means nothing (check_given_flags)
    (["--video-steps", "50", "--video-every", "0"], "--video-steps 50 means nothing with --video-every 0"),
    (["--mode", "state", "--cosine-every", "1"], "--cosine-every 1 means nothing with --mode state"),
    (["--mode", "state", "--sigma", "2.0"], "--sigma 2.0 means nothing with --mode state"),
    (["--mode", "state", "--render-gamma", "0.5"], "--render-gamma 0.5 means nothing with --mode state"),
    (["--eval-every", "0", "--video-every", "0", "--eval-envs", "64"], "--eval-envs 64 means nothing with "
                                                                     "--eval-every 0 --video-every 0"),
    # values out of range, each naming its flag as typed
    (["--num-envs", "0"], "--num-envs must be a positive integer, got 0"),
    (["--horizon", "-2"], "--horizon must be a positive integer"),
    (["--iters", "0"], "--iters must be a positive integer"),
    (["--raster-model", "blurry"], "--raster-model"),
    (["--actor-lr", "nan"], "--actor-lr must be in (0, inf), got nan"),
    (["--critic-lr", "-1"], "--critic-lr must be in (0, inf), got -1.0"),
    (["--sigma", "-1"], "--sigma must be in (0, inf), got -1.0"),
    (["--render-gamma", "-1"], "--render-gamma must be in (0, inf), got -1.0"),
    (["--gamma", "nan"], "--gamma must be in (0, 1], got nan"),
    (["--threads", "0"], "--threads must be a positive integer, got 0"),
    (["--time-limit-min", "nan"], "--time-limit-min must be in (0, inf), got nan"),
]


@pytest.mark.parametrize(("args", "message"), CASES, ids=[" ".join(a) for a, _ in CASES])
def test_ablate_refuses_in_one_line_naming_the_flag(tmp_path, capsys, two_cores, args, message):
    out = tmp_path / "runs"
    with pytest.raises(SystemExit) as e:
        ablate_main([*args, "--out", str(out), "--device", "cpu", "--no-progress"])
    line = refusal(capsys.readouterr().err)
    assert e.value.code == 2 and message in line, line
    assert not out.exists() and list(tmp_path.iterdir()) == []  # no run folder, here or beside --out


def test_a_resume_refuses_the_flags_it_would_ignore_and_takes_the_ones_it_uses(tmp_path, capsys, two_cores):
    run = tmp_path / "run"
    with pytest.raises(SystemExit) as e:
        ablate_main(["--resume", str(run), "--task", "hopper", "--mode", "full", "--iters", "9"])
    line = refusal(capsys.readouterr().err)
    assert e.value.code == 2
    assert f"--resume continues {run} with the settings its config.json records, so --task, --mode would be " \
           "ignored: drop them (a resume takes --device, --iters, --time-limit-min, --compile-cache, --threads, " \
           "--compile-helper)" in line
    # what a resume takes gets as far as the folder (which is no run folder here)
    with pytest.raises(SystemExit):
        ablate_main(["--resume", str(run), "--iters", "9", "--threads", "1", "--device", "cpu", "--no-progress",
                     "--no-compile-helper", "--time-limit-min", "5", "--compile-cache", "off"])
    assert f"{run}: no such folder" in refusal(capsys.readouterr().err) and not run.exists()


def test_a_resume_of_a_tensor_core_run_on_the_cpu_says_it_needs_cuda(tmp_path, capsys, two_cores):
    """A run trained at --precision bf16 resumed with --device cpu: one line saying the run needs a CUDA device
    (its precision is the run's own; a resume cannot change it)."""
    ablate_main(["--task", "cartpole", "--num-envs", "2", "--horizon", "3", "--image-size", "16", "--iters", "1",
                 "--critic-iterations", "1", "--critic-batches", "1", "--eval-envs", "2", "--episode-length", "12",
                 "--threads", "1", "--device", "cpu", "--no-progress", "--out", str(tmp_path), "--name", "run"])
    config = tmp_path / "run" / "config.json"
    record = json.loads(config.read_text())
    record["config"]["precision"] = "bf16"  # as a GPU run records it
    config.write_text(json.dumps(record))
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        ablate_main(["--resume", str(tmp_path / "run"), "--iters", "2", "--device", "cpu", "--no-progress"])
    line = refusal(capsys.readouterr().err)
    assert e.value.code == 2 and "trains at --precision bf16, which needs a CUDA device" in line


@pytest.mark.parametrize("argv", [["--mode", "fulll"], ["--name", "../escape"]])
def test_the_console_command_refuses_in_one_line(tmp_path, argv):
    """The real command, in a process of its own: one line on stderr, nothing on stdout, status 2."""
    r = subprocess.run([sys.executable, "-m", "ablations", "ablate", *argv, "--out", "runs"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert r.returncode == 2 and r.stdout == ""
    assert argv[0] in refusal(r.stderr)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("command", "args", "message"), [
    ("plot", ["runs", "--out"], "--out needs a value"),
    ("report", ["runs", "--reps", "many"], "--reps must be an integer, got 'many'"),
    ("memory", ["--device", "tpu"], "--device 'tpu' is not one of auto, cpu, cuda"),
    ("memory", ["--modes", "state"], "--modes 'state' is not one of full, decoupled"),
    ("sweep", ["--seeds", "0", "--seeds", "1"], "--seeds is given twice"),
    ("paper", ["--dry-run", "--dry-run"], "--dry-run is given twice"),
])
def test_every_ablations_command_refuses_in_one_line(tmp_path, capsys, command, args, message):
    from importlib import import_module

    from ablations.__main__ import COMMANDS

    module, function = COMMANDS[command].split(":")
    with pytest.raises(SystemExit) as e:
        getattr(import_module(module), function)(args)
    assert e.value.code == 2 and message in refusal(capsys.readouterr().err)


def test_what_only_tyro_refuses_is_folded_into_one_line(capsys):
    from ablations.cli import parse
    from ablations.run_config import RunConfig

    with pytest.raises(SystemExit) as e:
        parse(RunConfig, ["stray"], prog="ablate")  # a positional where there is none: tyro's box
    line = refusal(capsys.readouterr().err)
    assert e.value.code == 2 and "stray" in line and "│" not in line and "ablate --help" in line


def test_help_still_reaches_stdout(capsys):
    with pytest.raises(SystemExit) as e:
        command_line.cli(command_line.Given, ["--help"], prog="given")
    assert e.value.code == 0 and "--spelling" in capsys.readouterr().out


def test_scan_reads_flags_values_and_inline_values():
    given = command_line.scan(["pos", "--a", "1", "2", "--b=x", "--no-c", "--", "--d"])
    assert [(g.spelling, g.values, g.inline) for g in given] == [("--a", ("1", "2"), False), ("--b", ("x",), True),
                                                                ("--no-c", (), False)]


@pytest.mark.parametrize("box", [
    "╭─ Invalid choice ───╮\n│ invalid choice 'x' │\n│ for '--mode'.      │\n│ ────────────────── │\n"
    "│ For full helptext, run ablate --help │\n╰────╯\n",
    " Invalid choice      \n -------------------- \n  invalid choice 'x'  \n  for '--mode'.  \n  ----------  \n"
    "  For full helptext, run ablate --help  \n", # tyro's ASCII box, where the output takes no line characters
])
def test_one_line_keeps_what_went_wrong_from_either_box(box):
    assert command_line.one_line("\x1b[31m" + box + "\x1b[0m") == "invalid choice 'x' for '--mode'."


@pytest.mark.parametrize(("set_", "message"), [
    (("num-envs=1.5",), "ablate rejects its flags: --task cartpole --mode state --seed 0 --num-envs 1.5 "
                        "(--num-envs must be an integer, got '1.5')"),
    (("raster-model=hard",), "run cartpole_state_seed0: --raster-model hard means nothing with --mode state"),
])
def test_a_sweeps_runs_are_checked_as_ablate_checks_them(capsys, set_, message):
    from ablations.sweep import SweepConfig, plan

    with pytest.raises(ValueError) as e:
        plan(SweepConfig(modes=("state",), set=set_))
    assert message in str(e.value) and capsys.readouterr().err == ""  # no box from tyro


@pytest.mark.skipif(not (ROOT / ".git").exists(), reason="not a git checkout")
def test_no_console_scripts_default_output_is_a_shipped_file():
    """Every console script of pyproject.toml writes by default where nothing is tracked and everything is
    git-ignored: a shipped file (docs/floors.json, docs/robots, a shipped report) changes only where named."""
    import tomllib

    from ablations.memory import MemoryConfig
    from ablations.paper import PaperConfig
    from ablations.reports import PlotConfig, ReportConfig
    from ablations.run_config import RunConfig
    from ablations.sweep import SweepConfig
    from tasks.floors import FloorsConfig
    from tasks.snapshots import SnapshotsConfig

    configs = {"ablate": RunConfig, "ablate-memory": MemoryConfig, "ablate-plot": PlotConfig,
               "ablate-report": ReportConfig, "ablate-sweep": SweepConfig, "ablate-paper": PaperConfig,
               "robot-snapshots": SnapshotsConfig, "task-floors": FloorsConfig}
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    # ablate-plan prints; it writes only with --pin, into the registration it must be given (no default)
    assert set(scripts) == set(configs) | {"ablate-plan"}, "a new console script: add its config here"
    for script, config in configs.items():
        out = config().out
        tracked = subprocess.run(["git", "ls-files", "--", str(out)], cwd=ROOT, capture_output=True, text=True)
        assert tracked.stdout == "", f"{script}'s default --out {out} is tracked"
        path = str(out) if out.suffix else f"{out}/x"
        assert subprocess.run(["git", "check-ignore", "-q", path], cwd=ROOT).returncode == 0, (script, out)


def test_ablate_memory_ctrl_c_is_one_line_not_a_traceback(tmp_path, capsys, monkeypatch):
    import ablations.memory
    from ablations.cli import memory_main

    def interrupted(cfg):
        raise KeyboardInterrupt

    monkeypatch.setattr(ablations.memory, "sweep", interrupted)
    with pytest.raises(SystemExit) as e:
        memory_main(["--device", "cpu", "--out", str(tmp_path / "sweep")])
    err = capsys.readouterr().err
    assert e.value.code == 130 and err.count("\n") == 1 and err.startswith("interrupted: the points measured")


def test_an_unknown_device_is_named_as_the_flag(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        ablate_main(["--device", "tpu", "--out", str(tmp_path / "runs"), "--no-progress"])
    assert e.value.code == 2
    assert refusal(capsys.readouterr().err) == "error: --device: unknown device 'tpu': use auto, cpu or cuda[:N]"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("state", [{}, {"wall_s": 1.0, "config": {}}, "other mode"])
def test_a_checkpoint_that_is_not_this_runs_is_one_line_and_the_folder_stays(tmp_path, capsys, state):
    """A checkpoint without an iteration, or one of another run (its recorded config's mode differs from
    config.json's), counts as damaged: with no other checkpoint the resume is refused in one line, nothing renamed."""
    import dataclasses

    from ablations.run_config import RunConfig
    from gradlab.checkpoint import atomic_write_json, checkpoint_path, save_checkpoint

    run = tmp_path / "run"
    cfg = dataclasses.asdict(RunConfig(task="cartpole", mode="decoupled", device="cpu", out=tmp_path, iters=9))
    del cfg["restart"]
    atomic_write_json(run / "config.json", {"config": cfg})
    if state == "other mode":
        state = {"iteration": 2, "wall_s": 1.0, "config": dict(cfg, mode="state")}
    path = checkpoint_path(run / "checkpoints", 2)
    save_checkpoint(path, state)
    before = sorted(p.name for p in run.rglob("*"))
    with pytest.raises(SystemExit) as e:
        ablate_main(["--resume", str(run), "--no-progress"])
    line = refusal(capsys.readouterr().err)
    assert e.value.code == 2 and f"no readable checkpoint of one iteration in common in {run / 'checkpoints'}: " \
        f"{path} (" in line
    assert ("its mode is 'state', config.json's 'decoupled'" if state.get("config") else
            "holds no 'iteration' entry") in line
    assert sorted(p.name for p in run.rglob("*")) == before


def test_ablate_plot_out_pointed_at_a_file_is_one_line(tmp_path, capsys):
    from ablations.cli import plot_main
    from tests.ablations.conftest import write_run

    write_run(tmp_path / "runs", task="cartpole", mode="decoupled", seed=0, iters=3)
    (tmp_path / "figs").write_text("a file")
    with pytest.raises(SystemExit) as e:
        plot_main([str(tmp_path / "runs"), "--out", str(tmp_path / "figs")])
    assert e.value.code == 2
    assert refusal(capsys.readouterr().err) == f"error: --out {tmp_path / 'figs'} is a file: give the folder the " \
        f"figures go in"


def test_population_and_sweep_wide_flags_stay_exempt(monkeypatch):
    """A population-wide flag that acts for some member is kept (--cosine-every over decoupled and blind members);
    a sweep's ablate (its flags the grid's, for every run) is not checked for them."""
    from ablations.cli import _checked_members, parse
    from ablations.run_config import SWEEP_WIDE, AblateConfig

    argv = ["--mode", "decoupled", "blind", "--cosine-every", "1", "--sigma", "2.0", "--device", "cpu"]
    assert len(_checked_members(parse(AblateConfig, argv), argv)[0]) == 2
    argv = ["--mode", "state", "--cosine-every", "1", "--device", "cpu"]
    with pytest.raises(ValueError, match="--cosine-every 1 means nothing with --mode state"):
        _checked_members(parse(AblateConfig, argv), argv)
    monkeypatch.setenv(SWEEP_WIDE, "1")
    assert len(_checked_members(parse(AblateConfig, argv), argv)[0]) == 1
