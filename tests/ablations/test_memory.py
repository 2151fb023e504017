"""ablate-memory: the sweep's bookkeeping (one process per point, failure rows, restart, atomic CSV).

The per-point measurement is replaced through the documented seam (``sweep(cfg, measure=...)``) by
tests/ablations/fake_workers.py, which runs in the same fresh worker processes the real trainer would.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ablations import memory
from ablations.memory import COLUMNS, MemoryConfig, read_csv, sweep, worker
from tests.ablations.conftest import ROOT, calls

FAKE = "tests.ablations.fake_workers:fake"


def cfg_for(out: Path, **kw) -> MemoryConfig:
    base = dict(task="cartpole", modes=("decoupled", "full"), meshes=(0, 2), verts=(8,), num_envs=2, horizon=4,
                image_size=16, warmup_iters=1, iters=2, device="cpu", out=out, timeout_s=60.0, progress=False)
    base.update(kw)
    return MemoryConfig(**base)


def by_point(rows: list[dict]) -> dict[str, dict]:
    return {f"{r['mode']}_m{r['meshes']}_v{r['verts_per_mesh']}": r for r in rows}


def test_sweep_writes_rows_for_both_modes(tmp_path, fake_env):
    out = tmp_path / "sweep"
    log = fake_env({}, out)
    rows = sweep(cfg_for(out), measure=FAKE)

    # Points: the robot alone once per mode (verts 0), then 2 meshes x 8 verts per mode, cheap first.
    assert [c["point"] for c in calls(log)] == ["full_m0_v0", "decoupled_m0_v0", "full_m2_v8", "decoupled_m2_v8"]
    # One fresh process per point.
    assert len({c["pid"] for c in calls(log)}) == 4
    # Every worker saw a complete memory.csv with the rows of the points before it.
    assert [c["csv_rows"] for c in calls(log)] == [0, 1, 2, 3]

    on_disk = read_csv(out / "memory.csv")
    assert on_disk == [{k: r.get(k) for k in COLUMNS} for r in rows]
    pts = by_point(on_disk)
    assert set(pts) == {"full_m0_v0", "decoupled_m0_v0", "full_m2_v8", "decoupled_m2_v8"}
    assert all(r["status"] == "ok" and r["error"] is None for r in on_disk)
    # Values are the worker's (the fake's formulas), the fixed settings the sweep's.
    assert pts["full_m2_v8"]["scene_faces"] == 100 + 2 * 16
    assert pts["full_m2_v8"]["bwd_ms"] == pytest.approx(3 * (1 + 1.32))
    assert pts["decoupled_m2_v8"]["bwd_ms"] == pytest.approx(1 + 1.32)
    assert pts["full_m2_v8"]["saved_mb"] == pytest.approx(13.2 * 4)
    for r in on_disk:
        assert (r["task"], r["num_envs"], r["horizon"], r["image_size"], r["device"]) == ("cartpole", 2, 4, 16, "cpu")
        assert r["point_s"] > 0 and (out / r["log"]).exists()

    meta = json.loads((out / "memory.json").read_text())
    assert meta["config"]["task"] == "cartpole" and len(meta["rows"]) == 4 and meta["commands"]
    for png in ("memory_peak.png", "memory_bwd.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list((out / ".points").iterdir()), "per-point result files are cleaned up"


def test_failures_are_rows_and_the_sweep_goes_on(tmp_path, fake_env):
    out = tmp_path / "sweep"
    log = fake_env({
        "full_m0_v0": "error",            # a Python exception in the trainer
        "decoupled_m2_v8": "kill",        # SIGKILL, as the kernel's OOM killer does
        "full_m2_v8": "oom",              # torch.OutOfMemoryError
        "decoupled_m3_v8": "exit_oom_log",  # a native abort after CUDA's out-of-memory message
        "full_m3_v8": "exit",             # a native crash with another message
        "full_m4_v8": "cpu_oom",          # the CPU allocator's RuntimeError
    }, out)
    rows = sweep(cfg_for(out, meshes=(0, 2, 3, 4)), measure=FAKE)
    pts = by_point(rows)
    assert len(calls(log)) == 8 and len(rows) == 8
    assert pts["decoupled_m0_v0"]["status"] == "ok"
    assert pts["full_m0_v0"]["status"] == "error"
    assert pts["full_m0_v0"]["error"] == "ValueError: boom: the renderer disliked this point"
    assert pts["decoupled_m2_v8"]["status"] == "oom"
    assert "SIGKILL" in pts["decoupled_m2_v8"]["error"]
    assert pts["full_m2_v8"]["status"] == "oom"
    assert pts["full_m2_v8"]["error"].startswith("OutOfMemoryError: CUDA out of memory")
    assert pts["decoupled_m3_v8"]["status"] == "oom"
    assert pts["full_m3_v8"]["status"] == "error"
    assert "exited with code 3" in pts["full_m3_v8"]["error"] and "native library" in pts["full_m3_v8"]["error"]
    assert pts["full_m4_v8"]["status"] == "oom"
    assert pts["decoupled_m4_v8"]["status"] == "ok", "points after failures still run"
    # The scene size reported before the failure is kept, even for the killed worker: its x on the plots.
    assert pts["decoupled_m2_v8"]["scene_faces"] == 132
    # A failed point has no timings (they would not be measurements).
    assert all(pts[p]["bwd_ms"] is None for p in pts if pts[p]["status"] != "ok")
    assert read_csv(out / "memory.csv") == [{k: r.get(k) for k in COLUMNS} for r in rows]
    assert "Traceback" in (out / pts["full_m0_v0"]["log"]).read_text()


def test_timeout_kills_the_point_and_the_sweep_goes_on(tmp_path, fake_env):
    out = tmp_path / "sweep"
    log = fake_env({"full_m0_v0": "hang"}, out)
    t0 = time.perf_counter()
    rows = sweep(cfg_for(out, meshes=(0,), timeout_s=3.0), measure=FAKE)
    assert time.perf_counter() - t0 < 40
    pts = by_point(rows)
    assert pts["full_m0_v0"]["status"] == "timeout" and "3 s" in pts["full_m0_v0"]["error"]
    assert pts["decoupled_m0_v0"]["status"] == "ok"
    hung = next(c["pid"] for c in calls(log) if c["point"] == "full_m0_v0")
    with pytest.raises(ProcessLookupError):
        os.kill(hung, 0)  # the worker is gone, not left running


def test_restart_skips_finished_points(tmp_path, fake_env):
    out = tmp_path / "sweep"
    log = fake_env({"full_m0_v0": "error", "decoupled_m0_v0": "oom"}, out)
    sweep(cfg_for(out, meshes=(0,)), measure=FAKE)
    assert len(calls(log)) == 2

    # Extending the sweep runs only the new points; the error and oom rows are kept as they are.
    fake_env({}, out)
    with open(out / "memory.csv") as held:  # a reader that opened the CSV before the sweep went on
        before = (out / "memory.csv").read_text()
        rows = sweep(cfg_for(out, meshes=(0, 2)), measure=FAKE)
        # The CSV was replaced by a rename, never rewritten in place: the reader still sees the whole old file.
        assert held.read() == before
    assert (out / "memory.csv").read_text() != before
    assert [c["point"] for c in calls(log)][2:] == ["full_m2_v8", "decoupled_m2_v8"]
    assert by_point(rows)["full_m0_v0"]["status"] == "error"

    # Nothing left: no worker runs at all.
    sweep(cfg_for(out, meshes=(0, 2)), measure=FAKE)
    assert len(calls(log)) == 4

    # --retry-failed re-runs the error row only (an oom row is a result, not a failure).
    rows = sweep(cfg_for(out, meshes=(0, 2), retry_failed=True), measure=FAKE)
    assert [c["point"] for c in calls(log)][4:] == ["full_m0_v0"]
    assert by_point(rows)["full_m0_v0"]["status"] == "ok"
    assert by_point(rows)["decoupled_m0_v0"]["status"] == "oom"
    assert len(rows) == 4
    assert len(json.loads((out / "memory.json").read_text())["commands"]) == 4


def test_restart_with_other_settings_is_refused(tmp_path, fake_env):
    out = tmp_path / "sweep"
    fake_env({}, out)
    sweep(cfg_for(out, meshes=(0,), modes=("full",)), measure=FAKE)
    with pytest.raises(ValueError, match="num_envs: 2 there vs 3 now"):
        sweep(cfg_for(out, meshes=(0,), num_envs=3), measure=FAKE)


def test_killed_sweep_leaves_a_whole_csv_and_resumes(tmp_path, fake_env):
    """SIGKILL the sweep itself mid-point: memory.csv holds exactly the finished rows; a restart completes."""
    out = tmp_path / "sweep"
    log = fake_env({"full_m2_v8": "hang"}, out)
    script = ("import sys; from pathlib import Path; from tests.ablations.test_memory import cfg_for, FAKE; "
              "from ablations.memory import sweep; sweep(cfg_for(Path(sys.argv[1])), measure=FAKE)")
    proc = subprocess.Popen([sys.executable, "-c", script, str(out)], cwd=ROOT)
    deadline = time.time() + 60
    while not any(c["point"] == "full_m2_v8" for c in calls(log)):
        assert time.time() < deadline and proc.poll() is None, "the sweep did not reach the third point"
        time.sleep(0.1)
    proc.kill()
    proc.wait()
    # The worker (in its own session, so the kill did not reach it) notices its sweep is gone and ends itself.
    hung = next(c["pid"] for c in calls(log) if c["point"] == "full_m2_v8")
    deadline = time.time() + 15
    while _alive(hung) and time.time() < deadline:
        time.sleep(0.1)
    if _alive(hung):
        os.kill(hung, signal.SIGKILL)
        pytest.fail("the worker outlived its sweep")

    rows = read_csv(out / "memory.csv")
    assert sorted(by_point(rows)) == ["decoupled_m0_v0", "full_m0_v0"]
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")], "no temp file left beside the CSV"

    fake_env({}, out)
    rows = sweep(cfg_for(out), measure=FAKE)
    assert [c["point"] for c in calls(log)][3:] == ["full_m2_v8", "decoupled_m2_v8"]
    assert all(r["status"] == "ok" for r in rows) and len(rows) == 4


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie (dead, not yet reaped by init) counts as gone.
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def test_worker_classifies_exceptions_in_process(tmp_path, monkeypatch):
    """The worker entry itself (no subprocess): every failure becomes a result file, never an exit."""
    point = {"task": "cartpole", "mode": "full", "meshes": 1, "verts_per_mesh": 8, "horizon": 4}
    for behaviour, status in (("ok", "ok"), ("oom", "oom"), ("cpu_oom", "oom"), ("error", "error")):
        monkeypatch.setenv("FAKE_BEHAVIOUR", json.dumps({"full_m1_v8": behaviour}))
        result = tmp_path / f"{behaviour}.json"
        assert worker.main(["--point", json.dumps(point), "--result", str(result), "--measure", FAKE]) == 0
        got = worker.read_result(result)
        assert got["status"] == status, behaviour
        assert got["scene_faces"] == 116


def test_points_and_validation(tmp_path):
    cfg = cfg_for(tmp_path, meshes=(4, 0), verts=(16, 8), modes=("full", "decoupled", "full"))
    pts = [(p["mode"], p["meshes"], p["verts_per_mesh"]) for p in cfg.points("cpu")]
    assert pts == [("full", 0, 0), ("decoupled", 0, 0), ("full", 4, 8), ("decoupled", 4, 8), ("full", 4, 16),
                   ("decoupled", 4, 16)]
    # every error starts with the flag it is about
    for bad, match in ((dict(task="walker"), "--task: unknown task 'walker'; valid tasks: cartpole, cartpole-swingup"),
                       (dict(verts=(5,)), "--verts"), (dict(meshes=(-1,)), "--meshes"), (dict(modes=()), "--modes"),
                       (dict(modes=("state",)), "--modes: mode 'state' cannot be swept"),
                       (dict(num_envs=0), "--num-envs"), (dict(image_size=8), "--image-size"),
                       (dict(timeout_s=0), "--timeout-s"), (dict(renderer="nvdiffrast"), "--renderer: unknown")):
        with pytest.raises(ValueError, match=f"^{match}"):
            cfg_for(tmp_path, **bad).validate()


def test_every_task_and_renderer_can_be_swept(tmp_path):
    """The task and renderer lists are those of the rest of the toolkit (tasks.TASKS, tasks.vision.RENDERERS)."""
    import tasks
    from tasks.vision import RENDERERS

    for task in tasks.TASKS:
        cfg_for(tmp_path, task=task).validate()
    for renderer in RENDERERS:
        cfg_for(tmp_path, renderer=renderer, modes=("decoupled",)).validate()
    assert "cartpole-swingup" in tasks.TASKS


def test_cli_reports_bad_input_in_one_line(tmp_path, capsys):
    from ablations.cli import memory_main

    with pytest.raises(SystemExit) as e:
        memory_main(["--verts", "2", "--out", str(tmp_path / "x"), "--device", "cpu"])
    assert e.value.code == 2
    assert "error: --verts must be integers >= 6" in capsys.readouterr().err
    assert not (tmp_path / "x").exists(), "bad input fails before any work"


def test_plot_sweep_marks_failures(tmp_path):
    rows = []
    for mode in ("full", "decoupled"):
        for m, v, status in ((0, 0, "ok"), (2, 8, "ok"), (4, 8, "ok" if mode == "decoupled" else "oom"),
                             (2, 32, "ok"), (4, 32, "timeout")):
            rows.append({"task": "ant", "mode": mode, "meshes": m, "verts_per_mesh": v, "status": status,
                         "scene_faces": 100 + m * v if status != "timeout" else None, "bwd_ms": 1.0 + m * v,
                         "saved_mb": 2.0 + m * v, "max_rss_mb": 300.0, "peak_alloc_mb": None, "num_envs": 2,
                         "horizon": 4, "image_size": 16, "device": "cpu", "gpu": None})
    files = memory.plot_sweep(rows, tmp_path)
    assert [f.name for f in files] == ["memory_peak.png", "memory_bwd.png"]
    assert memory.plot_sweep([dict(rows[0], status="oom")], tmp_path / "none") == []

    import matplotlib.pyplot as plt
    from matplotlib.colors import to_rgb

    figures = memory.sweep_figures(rows)
    try:
        for name, fig in figures.items():
            fig.canvas.draw()
            ax = fig.axes[0]
            lines = [ln for ln in ax.lines if ln.get_label() not in ("oom", "timeout")]
            # one line per (mode, vertices per mesh), none alike: the mode's line style, the vertices' marker
            assert [ln.get_label() for ln in lines] == [f"{m}, {v} verts/mesh" for m in ("full", "decoupled")
                                                         for v in (8, 32)], name
            assert len({(to_rgb(ln.get_color()), ln.get_linestyle(), ln.get_marker()) for ln in lines}) == 4
            assert {ln.get_linestyle() for ln in lines} == {"-", "--"} and len({ln.get_marker() for ln in lines}) == 2
            crosses = {ln.get_label(): ln for ln in ax.lines if ln.get_label() in ("oom", "timeout")}
            assert set(crosses) == {"oom"}, "the timed-out point has no scene size: named in a note instead"
            assert any("oom/timeout, size unknown" in t.get_text() for t in ax.texts)
            # the legend right of the panels, over none of them
            assert len(fig.legends) == 1 and all(a.get_legend() is None for a in fig.axes)
            legend = fig.legends[0].get_window_extent()
            assert not any(legend.overlaps(a.get_window_extent()) for a in fig.axes), name
    finally:
        for fig in figures.values():
            plt.close(fig)


def test_worker_result_lines_merge_and_a_torn_line_is_ignored(tmp_path):
    """A worker killed mid-write leaves a torn last line: what was written before it still counts."""
    path = tmp_path / "p.jsonl"
    path.write_text('{"status": "running", "scene_faces": 132}\n{"status": "ok", "bwd_ms": 1.5, "scene_f')
    assert worker.read_result(path) == {"status": "running", "scene_faces": 132}
    path.write_text('{"status": "running", "scene_faces": 132}\n{"status": "ok", "bwd_ms": 1.5}\n')
    assert worker.read_result(path) == {"status": "ok", "scene_faces": 132, "bwd_ms": 1.5}
    assert worker.read_result(tmp_path / "missing.jsonl") == {}


def test_renderer_is_a_setting_of_the_sweep(tmp_path, fake_env):
    """--renderer warp: decoupled points only (full is refused up front), the renderer in every row and in
    the worker's point, the points' log names; one renderer per folder; a CSV from before the column reads as
    the soft renderer's."""
    for bad, match in ((dict(renderer="warp"), "--renderer warp renders without gradient, so --modes full"),
                       (dict(renderer="nvdiffrast"), "unknown renderer 'nvdiffrast'")):
        with pytest.raises(ValueError, match=match):
            cfg_for(tmp_path, **bad).validate()
    cfg = cfg_for(tmp_path / "warp", renderer="warp", modes=("decoupled",))
    assert {p["renderer"] for p in cfg.points("cpu")} == {"warp"}
    assert memory.point_id(cfg.points("cpu")[1]) == "cartpole_decoupled_warp_m2_v8"
    assert memory.point_id(cfg_for(tmp_path).points("cpu")[0]) == "cartpole_full_m0_v0"

    out = tmp_path / "warp"
    fake_env({}, out)
    rows = sweep(cfg, measure=FAKE)
    assert [(r["mode"], r["renderer"], r["status"]) for r in rows] == [("decoupled", "warp", "ok")] * 2
    assert {r["renderer"] for r in read_csv(out / "memory.csv")} == {"warp"}
    assert sorted(p.name for p in (out / "logs").iterdir()) == ["cartpole_decoupled_warp_m0_v0.log",
                                                                "cartpole_decoupled_warp_m2_v8.log"]
    with pytest.raises(ValueError, match="renderer: 'warp' there vs 'soft' now"):
        sweep(cfg_for(out, modes=("decoupled",)), measure=FAKE)

    old = tmp_path / "old.csv"
    text = memory.csv_text([dict(rows[0], renderer=None)])
    old.write_text(text)
    assert read_csv(old)[0]["renderer"] == "soft"


@pytest.mark.slow
def test_real_sweep_with_the_ray_tracer(tmp_path):
    """The real trainer with --renderer warp (Warp's CPU device), decoupled, the robot alone and with two
    extra meshes: both points measured, the scene counted, decoupled's saved bytes flat in the scene."""
    pytest.importorskip("warp")
    out = tmp_path / "sweep"
    cfg = MemoryConfig(task="cartpole", modes=("decoupled",), renderer="warp", meshes=(0, 2), verts=(14,),
                       num_envs=2, horizon=2, image_size=16, warmup_iters=1, iters=1, device="cpu", out=out,
                       timeout_s=300.0, progress=False)
    rows = sweep(cfg)
    pts = {r["meshes"]: r for r in rows}
    for m, r in pts.items():
        assert r["status"] == "ok", f"{m}: {r['error']}\n{(out / r['log']).read_text()[-3000:]}"
        assert r["renderer"] == "warp" and r["fwd_ms"] > 0 and r["bwd_ms"] > 0 and r["iter_ms"] > 0
    assert pts[2]["scene_faces"] > pts[0]["scene_faces"]
    assert pts[2]["saved_mb"] == pytest.approx(pts[0]["saved_mb"], abs=1e-6)


@pytest.mark.slow
def test_jobs_run_points_at_once_with_the_rows_of_a_sequential_sweep(tmp_path, fake_env):
    """--jobs 3: points overlap in time (each in its own process), failures and timeouts are still rows, and the
    CSV holds what a one-at-a-time sweep writes, in the same order."""
    behaviour = {"full_m2_v8": "oom", "decoupled_m3_v8": "error", "full_m3_v8": "hang"}
    seq, par = tmp_path / "seq", tmp_path / "par"
    fake_env(behaviour, seq)
    sweep(cfg_for(seq, meshes=(0, 2, 3), timeout_s=4.0), measure=FAKE)
    log = fake_env(behaviour, par)
    t0 = time.perf_counter()
    rows = sweep(cfg_for(par, meshes=(0, 2, 3), timeout_s=4.0, jobs=3), measure=FAKE)
    assert time.perf_counter() - t0 < 30
    assert len({c["pid"] for c in calls(log)[6:]}) == 6  # one fresh process per point (after the first sweep's 6)

    def comparable(rs):
        return [{k: v for k, v in r.items() if k not in ("started", "point_s")} for r in rs]

    assert comparable(read_csv(par / "memory.csv")) == comparable(read_csv(seq / "memory.csv"))
    assert by_point(rows)["full_m3_v8"]["status"] == "timeout"
    # the point after the hung one started while it hung (one at a time, it would wait the 4 s timeout)
    from datetime import datetime

    def started(rs, point):
        return datetime.fromisoformat(by_point(rs)[point]["started"])

    assert (started(rows, "decoupled_m3_v8") - started(rows, "full_m3_v8")).total_seconds() < 4
    seq_rows = read_csv(seq / "memory.csv")
    assert (started(seq_rows, "decoupled_m3_v8") - started(seq_rows, "full_m3_v8")).total_seconds() >= 4
    assert json.loads((par / "memory.json").read_text())["config"]["jobs"] == 3
    assert not list((par / ".points").iterdir())


def test_jobs_must_be_positive(tmp_path):
    with pytest.raises(ValueError, match="--jobs must be a positive integer"):
        cfg_for(tmp_path, jobs=0).validate()
