"""The compile helpers: processes that fill the compile cache while the run compiles its own share.

The fast tests check that a helper that fails or hangs costs the run nothing but a warning, and how the work is
shared; the slow one checks the point of it on the CPU: the run finds the helpers' graphs in the shared cache (FX
graph cache hits for everything but its own share) and trains to the same numbers as a run without helpers.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import pytest
import torch

from ablations.startup import Startup
from ablations.startup.helpers import HELPER_SHARES, RUN_SHARE, CompileHelper, CompileHelpers, helper_shares
from gradlab.config import SHACConfig, resolve_config

CPU = torch.device("cpu")


def _cfg(**kw):
    return resolve_config(SHACConfig(task="cartpole", mode="decoupled", num_envs=2, image_size=16, horizon=4,
                                     compile=True, **kw))


def _start(cache_root, log, *, parts, command):
    """A stand-in helper (``command``) spawned and given its share, as the run does; None where that failed."""
    helper = CompileHelper.spawn(command=command)
    return helper if helper is not None and helper.assign([_cfg()], CPU, cache_root, log, parts=parts) else None


def test_a_helper_that_fails_warns_once_and_the_run_goes_on(tmp_path):
    helper = _start(tmp_path / "cache", tmp_path / "run" / "compile_helper.log",
                                 parts=("networks",),
                                 command=[sys.executable, "-c", "import sys; print('broken'); sys.exit(3)"])
    with pytest.warns(RuntimeWarning, match=r"exited with code 3.*compile_helper.log") as record:
        assert helper.wait(timeout=30) is False
    assert len(record) == 1
    assert "broken" in (tmp_path / "run" / "compile_helper.log").read_text()  # its output is kept
    assert not helper._early_log.exists()  # what it printed before it had a log went into its log
    helper.stop()  # already ended: nothing to do, no error


def test_a_helper_that_hangs_is_waited_for_only_until_the_timeout_then_stopped(tmp_path):
    helper = _start(tmp_path / "cache", tmp_path / "compile_helper.log",
                                 parts=("networks",), command=[sys.executable, "-c", "import time; time.sleep(60)"])
    told = []
    with pytest.warns(RuntimeWarning, match="still compiling after 0 s of waiting; stopped"):
        assert helper.wait(timeout=0.3, on_wait=lambda: told.append(True)) is False
    assert told == [True]  # the run says what it waits for
    assert helper.process.poll() is not None  # stopped: it would compete with the run's own iterations
    helper.stop()  # again: nothing to do


def test_a_helper_that_cannot_start_or_be_given_its_share_is_a_warning_not_an_error(tmp_path):
    with pytest.warns(RuntimeWarning, match="could not start"):
        assert CompileHelper.spawn(command=[str(tmp_path / "no-such-program")]) is None
    (tmp_path / "run").write_text("a file where the run folder should be")
    with pytest.warns(RuntimeWarning, match="could not be given its share") as record:
        helper = _start(tmp_path / "cache", tmp_path / "run" / "compile_helper.log",
                                     parts=("networks",), command=[sys.executable, "-c", _READS_STDIN])
    assert helper is None and len(record) == 1


#: a stand-in helper that, like the real one on standby, ends when its stdin closes
_READS_STDIN = "import sys; sys.stdin.buffer.read()"


def _helper(tmp_path, *args: str) -> subprocess.CompletedProcess:
    early = tmp_path / "early.log"
    early.write_text("")
    return subprocess.run([sys.executable, "-X", "importtime", "-m", "ablations.startup.helpers", str(early), *args],
                          input=b"", capture_output=True, timeout=300)


def test_a_helper_on_standby_that_is_let_go_or_whose_run_is_gone_does_nothing(tmp_path):
    """The real helper: dismissed (its stdin closed without a share) it exits cleanly, removing its early log and
    never touching a cache; let go before its head start began, it imports none of torch (on a warm start it
    takes no CPU from the run); one whose run is gone before it started does the same."""
    out = _helper(tmp_path, str(os.getpid()))  # this test's process stands in for the run
    assert out.returncode == 0, out.stderr.decode()[-2000:]
    assert not (tmp_path / "early.log").exists()
    imported = out.stderr.decode()  # -X importtime lists every module imported
    assert "torch._dynamo" not in imported and "gradlab.shac" not in imported
    if sys.platform.startswith("linux"):
        out = _helper(tmp_path, "1")  # its parent is not process 1
        assert out.returncode == 0 and not (tmp_path / "early.log").exists()


def test_helpers_on_standby_are_started_only_for_command_lines_that_may_want_them(monkeypatch):
    from ablations.startup import helpers as compile_helper

    spawned = []
    monkeypatch.setattr(CompileHelpers, "spawn", classmethod(lambda cls, n=3: spawned.append(n) or cls([])))
    monkeypatch.setattr(compile_helper, "cores", lambda: compile_helper.MIN_CORES)
    wants = [["--task", "ant", "--compile"], ["--compile", "--device", "cuda"], ["--compile", "--device=cuda:1"]]
    never = [["--task", "ant"], ["--compile", "--device", "cpu"], ["--compile", "--device=cpu"],
             ["--compile", "--no-compile-helper"], ["--compile", "--resume", "runs/a"], ["--compile", "--help"]]
    for argv in wants:
        assert CompileHelpers.standby_for(argv) is not None, argv
    for argv in never:
        assert CompileHelpers.standby_for(argv) is None, argv
    assert spawned == [len(HELPER_SHARES)] * len(wants)
    monkeypatch.setattr(compile_helper, "cores", lambda: compile_helper.MIN_CORES - 1)  # too few to share
    assert CompileHelpers.standby_for(wants[0]) is None and len(spawned) == len(wants)


def test_a_run_that_wants_no_helpers_lets_those_on_standby_go(tmp_path):
    """A run that turns out not to want helpers (here: on the CPU) dismisses them before it trains."""
    from ablations import runs

    standby = CompileHelpers.spawn(command=[sys.executable, "-c", _READS_STDIN])
    processes = [h.process for h in standby.helpers]
    cfg = runs.RunConfig(task="cartpole", mode="state", num_envs=2, horizon=4, iters=1, device="cpu",
                         out=tmp_path / "runs", name="r", progress=False, video_every=0)
    runs.run(cfg, startup=Startup(standby))
    assert len(processes) == len(HELPER_SHARES)
    assert [p.wait(timeout=30) for p in processes] == [0] * len(processes)  # ended by themselves: let go
    assert not list((tmp_path / "runs" / "r").glob("compile_helper*"))


def _failing_run(tmp_path, monkeypatch, where: str):
    """A --compile run on the CPU made to start its helpers (sleeping stand-ins), failing ``where``."""
    from ablations import runs
    from ablations.startup import ahead, wing
    from ablations.startup import helpers as compile_helper

    helpers = []
    spawn = CompileHelper.spawn

    def spawn_sleeper(*args, **kwargs):
        helpers.append(spawn(*args, **{**kwargs, "command": [sys.executable, "-c", "import time; time.sleep(120)"]}))
        return helpers[-1]

    def boom(*args, **kwargs):
        raise KeyboardInterrupt if where == "compiling ahead" else RuntimeError("the trainer cannot be built")

    monkeypatch.setattr(wing, "wants_helpers", lambda *a, **k: True)
    monkeypatch.setattr(compile_helper.CompileHelper, "spawn", spawn_sleeper)
    import gradlab.shac

    if where == "compiling ahead":
        monkeypatch.setattr(ahead, "compile_physics_ahead", boom)
    else:
        monkeypatch.setattr(gradlab.shac.SHAC, "__init__", boom)
    cfg = runs.RunConfig(task="cartpole", mode="decoupled", num_envs=2, image_size=16, horizon=4, iters=1,
                         compile=True, device="cpu", out=tmp_path / "runs", name="r", progress=False,
                         compile_cache=str(tmp_path / "cache"), video_every=0)
    if where == "compiling ahead":
        runs.run(cfg)  # an interrupt inside the run's bookkeeping ends the run as interrupted
    else:
        with pytest.raises(RuntimeError, match="the trainer cannot be built"):
            runs.run(cfg)
    return helpers, tmp_path / "runs" / "r"


def test_a_population_gives_its_helpers_every_member_in_the_rosters_order(tmp_path, monkeypatch):
    """A population's graphs have the population's shapes (every member's batch, its members in render order):
    its helpers build a trainer of the same members, in the roster's order, not of its first member's."""
    from ablations import runs
    from ablations.startup import helpers as compile_helper
    from ablations.startup import wing
    from gradlab.roster import Roster

    given = []
    monkeypatch.setattr(wing, "wants_helpers", lambda *a, **k: True)
    monkeypatch.setattr(compile_helper.CompileHelpers, "spawn", classmethod(lambda cls, *a, **k: cls([])))
    monkeypatch.setattr(compile_helper.CompileHelpers, "assign",
                        lambda self, cfgs, *a, **k: given.append(list(cfgs)) or self)
    cfg = runs.RunConfig(task="cartpole", num_envs=2, image_size=16, horizon=4, iters=1, compile=True, device="cpu",
                         out=tmp_path / "runs", name="p", progress=False, compile_cache=str(tmp_path / "cache"),
                         video_every=0)
    members = [runs.RunConfig(**{**vars(cfg), "mode": mode, "seed": seed})
               for mode, seed in [("blind", 0), ("decoupled", 1), ("blind", 2)]]
    import gradlab.shac

    def built(*args, **kwargs):  # the helpers have their shares before the trainer is built: no need to train
        raise RuntimeError("stop after the start-up")

    monkeypatch.setattr(gradlab.shac.SHAC, "__init__", built)
    with pytest.raises(RuntimeError, match="stop after the start-up"):
        runs.run(members)
    roster = Roster.of([resolve_config(SHACConfig(task="cartpole", mode=m.mode, seed=m.seed, num_envs=2, image_size=16,
                                                  horizon=4, compile=True)) for m in members])
    assert len(given) == 1
    assert [(c.mode, c.seed) for c in given[0]] == [(c.mode, c.seed) for c in roster.cfgs]


@pytest.mark.parametrize("where", ["building the trainer", "compiling ahead"])
def test_a_run_that_fails_stops_its_helpers(tmp_path, monkeypatch, where):
    helpers, run_dir = _failing_run(tmp_path, monkeypatch, where)
    assert [h.parts for h in helpers] == list(HELPER_SHARES)  # a rendering mode: one helper per share
    for helper in helpers:
        assert helper.process.poll() is not None  # not left compiling (or sleeping) after the run
        assert not helper._early_log.exists()
        assert (run_dir / f"compile_helper_{'_'.join(helper.parts)}.log").exists()
    if where == "compiling ahead":  # inside the run's bookkeeping: the summary says what happened
        summary = json.loads((run_dir / "summary.json").read_text())
        assert summary["status"] == "interrupted"
        records = summary["compile"]["helpers"]
        assert [r["parts"] for r in records] == [list(share) for share in HELPER_SHARES]
        assert all(r["returncode"] is not None for r in records)


def test_helpers_are_waited_for_within_one_deadline_and_told_what_still_compiles(tmp_path):
    """The wait is one deadline for all of them; the run is told which parts are still being compiled."""
    quick = _start(tmp_path, tmp_path / "quick.log", parts=("networks",),
                                command=[sys.executable, "-c", "pass"])
    slow = [_start(tmp_path, tmp_path / f"slow{i}.log", parts=share,
                                command=[sys.executable, "-c", "import time; time.sleep(60)"])
            for i, share in enumerate([("factorize", "finish"), ("renderer",)])]
    quick.process.wait(timeout=30)
    helpers = CompileHelpers([quick, *slow])
    told = []
    began = time.monotonic()
    with pytest.warns(RuntimeWarning, match="still compiling") as record:
        assert helpers.wait(timeout=1.0, on_wait=told.append) is False
    assert time.monotonic() - began < 5  # not 1 s per helper: at most one deadline (and the stops)
    assert len(record) == 2  # one warning per helper that did not finish
    # before each wait, what is still compiling: never the finished one
    assert told == ["factorize, finish, renderer", "renderer"]
    assert [r["returncode"] for r in helpers.record()] == [0, -15, -15]  # the slow ones stopped (SIGTERM)


def test_the_work_is_shared_by_what_the_mode_compiles():
    """The run keeps the physics substep; a helper per other share, none for a renderer that never runs; between
    them every part of a --compile trainer, each once."""
    from gradlab.shac import COMPILE_PARTS

    state = resolve_config(SHACConfig(task="cartpole", mode="state", compile=True))
    assert helper_shares([_cfg()]) == list(HELPER_SHARES)
    assert helper_shares([state]) == [share for share in HELPER_SHARES if share != ("renderer",)]
    blind = resolve_config(SHACConfig(task="cartpole", mode="blind", compile=True))
    assert helper_shares([blind, _cfg()]) == list(HELPER_SHARES)  # a population renders if one member does
    parts = [*RUN_SHARE, *(p for share in HELPER_SHARES for p in share)]
    assert sorted(parts) == sorted(COMPILE_PARTS)


def test_a_helper_that_finished_is_not_announced(tmp_path):
    helper = _start(tmp_path / "cache", tmp_path / "compile_helper.log",
                                 parts=("networks",), command=[sys.executable, "-c", "pass"])
    helper.process.wait(timeout=30)
    told = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert helper.wait(on_wait=lambda: told.append(True)) is True
    assert told == []


def test_a_run_starts_helpers_only_where_it_pays(tmp_path, monkeypatch):
    """On a GPU of a machine with enough cores, fresh, with a cache and no artifact file for the settings: yes;
    otherwise no."""
    from ablations.run_config import RunConfig
    from ablations.startup import helpers as compile_helper
    from ablations.startup.cache import CompileCache
    from ablations.startup.wing import wants_helpers

    cache = CompileCache(tmp_path, CPU)  # the folder's device kind does not matter to the decision
    cfg = RunConfig(task="cartpole", compile=True)
    gpu = torch.device("cuda", 0)
    monkeypatch.setattr(compile_helper, "cores", lambda: compile_helper.MIN_CORES)
    assert wants_helpers(cfg, gpu, cache, "cartpole_x", resuming=False)
    monkeypatch.setattr(compile_helper, "cores", lambda: compile_helper.MIN_CORES - 1)
    assert not wants_helpers(cfg, gpu, cache, "cartpole_x", resuming=False)  # too few cores to share
    monkeypatch.setattr(compile_helper, "cores", lambda: compile_helper.MIN_CORES)
    assert not wants_helpers(cfg, CPU, cache, "cartpole_x", resuming=False)
    assert not wants_helpers(cfg, gpu, None, "cartpole_x", resuming=False)  # --compile-cache off
    assert not wants_helpers(cfg, gpu, cache, "cartpole_x", resuming=True)
    assert not wants_helpers(RunConfig(task="cartpole", compile=True, compile_helper=False), gpu, cache,
                                     "cartpole_x", resuming=False)
    assert not wants_helpers(RunConfig(task="cartpole"), gpu, cache, "cartpole_x", resuming=False)
    cache.artifact_path("cartpole_x").parent.mkdir(parents=True, exist_ok=True)
    cache.artifact_path("cartpole_x").write_bytes(b"compiled before")  # a warm start: nothing to gain
    assert not wants_helpers(cfg, gpu, cache, "cartpole_x", resuming=False)


_RUN = textwrap.dedent("""
    import json, sys
    import torch
    from pathlib import Path
    from ablations.startup.ahead import compile_physics_ahead
    from ablations.startup.cache import CompileCache
    from ablations.startup.helpers import RUN_SHARE, CompileHelpers
    from ablations.startup.stats import CompileWatch, compile_counters
    from gradlab.config import SHACConfig, resolve_config
    from gradlab.shac import SHAC

    root, with_helper, seeds = Path(sys.argv[1]), sys.argv[2] == "1", [int(s) for s in sys.argv[3].split(",")]
    cfgs = [resolve_config(SHACConfig(task="cartpole", mode="decoupled", num_envs=2, image_size=16, horizon=4,
                                      compile=True, seed=seed)) for seed in seeds]
    CompileCache(root, torch.device("cpu")).activate()
    helpers = CompileHelpers.spawn().assign(cfgs, torch.device("cpu"), root, root) if with_helper else None
    trainer = SHAC(cfgs, device="cpu")
    trainer.compile()
    watch = CompileWatch()
    if helpers is not None:
        compile_physics_ahead(trainer, RUN_SHARE)
        assert helpers.wait(timeout=900), [Path(h.log).read_text()[-3000:] for h in helpers.helpers]
    metrics = [row for rows in (trainer.train_iteration() for _ in range(2)) for row in rows]
    print(json.dumps({"losses": [m["actor_loss"] for m in metrics], "critic": [m["critic_loss"] for m in metrics],
                      "compiles": watch.compiles, "recompiles": watch.recompiles, **compile_counters()}))
""")


def _run(root: Path, with_helper: bool, seeds: str) -> dict:
    out = subprocess.run([sys.executable, "-c", _RUN, str(root), "1" if with_helper else "0", seeds],
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.slow
@pytest.mark.parametrize("seeds", ["3", "3,4"], ids=["run-alone", "population"])
def test_the_run_finds_the_helpers_graphs_in_the_cache_and_trains_to_the_same_numbers(tmp_path, seeds):
    alone = _run(tmp_path / "alone", with_helper=False, seeds=seeds)
    helped = _run(tmp_path / "helped", with_helper=True, seeds=seeds)
    # everything but the substep came from the helpers: the run compiled (missed) only the substep's two graphs
    # (forward, backward); the other physics parts' graphs and the networks' were hits
    assert helped["fxgraph_cache_miss"] == 2, helped
    assert helped["fxgraph_cache_hit"] + helped["fxgraph_cache_miss"] >= alone["fxgraph_cache_miss"]
    for share in helper_shares([resolve_config(SHACConfig(task="cartpole", mode="decoupled", compile=True))]):
        log = (tmp_path / "helped" / f"compile_helper_{'_'.join(share)}.log").read_text()
        assert f"compile helper ({', '.join(share)}): imports" in log  # where its time went
    # compiling ahead used the training windows' guards: no graph more, no recompile more
    assert (helped["compiles"], helped["recompiles"]) == (alone["compiles"], alone["recompiles"])
    # compiling ahead restored the task's state and reset noise: the same training, to the bit on the CPU
    assert helped["losses"] == alone["losses"] and helped["critic"] == alone["critic"]
