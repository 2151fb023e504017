"""The start-up wing's compile cache folder (resolution, manifest, artifact files), compile statistics and compile
watch (CPU, tiny graphs)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from ablations.startup.cache import (
    CACHE_ENV_VAR,
    CompileCache,
    CompileCacheWarning,
    cache_versions,
    resolve_cache_root,
    start_compile_workers,
)
from ablations.startup.stats import CompileWatch, compile_phase_seconds, compiled_graphs

CPU = torch.device("cpu")


@pytest.fixture
def clean_env(monkeypatch):
    """The variables a cache sets, restored after the test (activate() writes them into os.environ)."""
    for name in ("TORCHINDUCTOR_CACHE_DIR", "TRITON_CACHE_DIR", CACHE_ENV_VAR):
        monkeypatch.delenv(name, raising=False)
    return monkeypatch


def test_root_is_the_flag_then_the_environment_then_the_default(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    env = {CACHE_ENV_VAR: str(tmp_path / "from-env")}
    assert resolve_cache_root(tmp_path / "flag", env=env) == (tmp_path / "flag").resolve()
    assert resolve_cache_root(None, env=env) == (tmp_path / "from-env").resolve()
    assert resolve_cache_root(None, env={}) == (tmp_path / "home" / ".cache/pixelgrad/compile").resolve()
    assert resolve_cache_root("~/c", env={}) == (tmp_path / "home" / "c").resolve()
    assert resolve_cache_root(None, env={CACHE_ENV_VAR: ""}) == (tmp_path / "home/.cache/pixelgrad/compile").resolve()
    for off in ("off", "OFF", "none", "0"):
        assert resolve_cache_root(off, env=env) is None
        assert resolve_cache_root(None, env={CACHE_ENV_VAR: off}) is None
    with pytest.raises(ValueError, match="compile cache folder is empty"):
        resolve_cache_root("  ", env={})


def test_folder_is_keyed_by_versions_and_points_inductor_and_triton_there(tmp_path, clean_env):
    cache = CompileCache(tmp_path, CPU)
    versions = cache_versions(CPU)
    assert cache.folder.parent == tmp_path
    assert torch.__version__ in cache.folder.name and cache.folder.name.endswith("-cpu")
    manifest = json.loads(cache.manifest_path.read_text())
    assert {k: manifest[k] for k in versions} == versions
    cache.activate("cartpole_decoupled")  # no artifact file yet: nothing loaded, no warning
    assert cache.loaded == {}
    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(cache.folder / "inductor")
    assert os.environ["TRITON_CACHE_DIR"] == str(cache.folder / "triton")
    import torch._functorch.config as functorch_config
    import torch._inductor.config as inductor_config

    assert inductor_config.fx_graph_cache and functorch_config.enable_autograd_cache
    # a second opening of a matching folder keeps it as it is
    (cache.folder / "inductor").mkdir()
    (cache.folder / "inductor" / "entry").write_text("kept")
    again = CompileCache(tmp_path, CPU)
    assert (again.folder / "inductor" / "entry").read_text() == "kept"


@pytest.mark.parametrize("manifest", ['{"format": 1, "torch": "1.0.0"}', "\x00 not json", "[1, 2]"])
def test_a_mismatched_or_unreadable_manifest_moves_the_folder_aside_with_one_warning(tmp_path, manifest):
    folder = CompileCache(tmp_path, CPU).folder
    (folder / "inductor").mkdir()
    (folder / "inductor" / "old-entry").write_text("from another torch")
    (folder / "manifest.json").write_text(manifest)
    with pytest.warns(CompileCacheWarning, match="moved aside") as record:
        cache = CompileCache(tmp_path, CPU)
    assert len(record) == 1
    assert "1.0.0" in str(record[0].message) or "cannot be read" in str(record[0].message)
    stale = folder.with_name(folder.name + ".stale")
    assert (stale / "inductor" / "old-entry").read_text() == "from another torch"
    assert not (cache.folder / "inductor").exists()  # rebuilt empty
    assert json.loads(cache.manifest_path.read_text())["torch"] == torch.__version__


def _compile_and_check(fn, *args):
    compiled = torch.compile(fn, dynamic=False)
    torch.testing.assert_close(compiled(*args), fn(*args))


def _poly(x):
    return (x.sin() * 3.0 + x.cos().pow(2)).sum(-1)


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["random", "flipped", "truncated"])
def test_a_damaged_artifact_file_is_moved_aside_with_one_warning_and_compiling_still_works(tmp_path, clean_env,
                                                                                          damage):
    cache = CompileCache(tmp_path, CPU)
    path = cache.artifact_path("tiny")
    path.parent.mkdir(parents=True)
    rng = torch.Generator().manual_seed(0)
    if damage == "random":
        data = bytes(torch.randint(0, 256, (4096,), generator=rng, dtype=torch.uint8).tolist())
    else:  # a real file, damaged after it was written
        _compile_and_check(_poly, torch.randn(3, 5))
        assert cache.save("tiny") == path
        data = bytearray(path.read_bytes())
        if damage == "flipped":
            data[-10] ^= 0xFF
        else:
            data = data[: len(data) // 2]
        data = bytes(data)
    path.write_bytes(data)
    with pytest.warns(CompileCacheWarning, match="unusable") as record:
        cache.activate("tiny")
    assert len(record) == 1
    assert not path.exists() and path.with_name(path.name + ".corrupt").read_bytes() == data
    assert cache.loaded == {}
    _compile_and_check(_poly, torch.randn(4, 6))


_WARM = textwrap.dedent("""
    import json, os, sys
    import torch
    from ablations.startup.cache import CompileCache
    from ablations.startup.stats import compile_counters

    SCALE = float(os.environ.get("BACKWARD_SCALE", "1"))

    class Square(torch.autograd.Function):  # a custom backward, as the simulator's
        @staticmethod
        def forward(ctx, x):
            ctx.save_for_backward(x)
            return x * x

        @staticmethod
        def backward(ctx, g):
            (x,) = ctx.saved_tensors
            return g * x * (2.0 * SCALE)

    def loss(x):
        return (Square.apply(x).sin() * 3.0 + x.cos()).sum()

    cache = CompileCache(sys.argv[1], torch.device("cpu"))
    cache.activate("tiny")
    x = torch.linspace(-1.0, 1.0, 7, dtype=torch.float64, requires_grad=True)
    value = torch.compile(loss, dynamic=False)(x)
    (grad,) = torch.autograd.grad(value, x)
    expected = torch.cos(x * x) * 3.0 * (2.0 * SCALE) * x - torch.sin(x)
    torch.testing.assert_close(grad, expected.detach())
    torch.testing.assert_close(value, loss(x))
    cache.save("tiny")
    print(json.dumps({"loaded": cache.loaded, **compile_counters()}))
""")


def _fresh_process(root: Path, **env_vars: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("TORCHINDUCTOR_CACHE_DIR", "TRITON_CACHE_DIR")}
    out = subprocess.run([sys.executable, "-c", _WARM, str(root)], capture_output=True, text=True,
                         env={**env, **env_vars}, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_the_artifact_file_alone_makes_another_machines_first_compile_a_cache_hit(tmp_path):
    cold = _fresh_process(tmp_path / "machine-a")
    assert cold["fxgraph_cache_hit"] == 0 and cold["fxgraph_cache_miss"] >= 1 and cold["loaded"] == {}
    assert cold["autograd_cache_miss"] >= 1 and cold["autograd_cache_bypass"] == 0
    # another machine: an empty root that is given only the artifact file
    src = CompileCache(tmp_path / "machine-a", CPU).artifact_path("tiny")
    dst = CompileCache(tmp_path / "machine-b", CPU).artifact_path("tiny")
    dst.parent.mkdir(parents=True)
    dst.write_bytes(src.read_bytes())
    warm = _fresh_process(tmp_path / "machine-b")
    assert warm["loaded"].get("inductor", 0) >= 1 and warm["loaded"].get("aot_autograd", 0) >= 1
    assert warm["fxgraph_cache_hit"] >= 1 and warm["fxgraph_cache_miss"] == 0
    assert warm["autograd_cache_hit"] >= 1 and warm["autograd_cache_miss"] == 0
    # an edited custom backward is a miss, never the cached gradient (the script checks the gradient's value)
    edited = _fresh_process(tmp_path / "machine-b", BACKWARD_SCALE="3")
    assert edited["autograd_cache_miss"] >= 1


def test_the_watch_names_the_part_that_compiles_and_counts_recompiles():
    shown = []
    watch = CompileWatch(on_change=shown.append)
    assert watch.available

    def step(x):
        return x * 2.0 + 1.0

    compiled = watch.labelled("physics step", torch.compile(step, backend="eager", dynamic=False))
    compiled(torch.ones(3))
    compiled(torch.ones(3))  # no compilation: nothing new to say
    assert shown == ["compiling physics step (0 done)"]
    assert (watch.compiles, watch.recompiles) == (1, 0)
    compiled(torch.ones(3, requires_grad=True))  # a guard fails: dynamo compiles the frame again
    assert shown[-1] == "compiling physics step (1 done)"
    assert (watch.compiles, watch.recompiles) == (2, 1)
    assert watch.compile_s > 0
    watch.announce("capturing CUDA graphs (window 1/2)")
    watch.announce(None)
    watch.announce(None)  # said once
    assert shown[-2:] == ["capturing CUDA graphs (window 1/2)", None]
    summary = watch.summary()
    assert summary["compiles"] == 2 and summary["recompiles"] == 1
    # the seconds by part: all of them the physics step's, a compilation outside any part is the model's
    assert set(summary["compile_s_by_part"]) == {"physics step"}
    assert summary["compile_s_by_part"]["physics step"] == pytest.approx(watch.compile_s, abs=2e-3)
    torch.compile(lambda x: x - 1.0, backend="eager", dynamic=False)(torch.ones(2))
    assert set(watch.summary()["compile_s_by_part"]) == {"physics step", "model"}


def test_a_backward_graph_is_named_after_the_part_that_compiled_its_forward():
    """The lazily compiled backward of a labelled part is that part's ("physics step backward"), whichever label
    the backward pass itself runs under; compiled_graphs lists forward and backward by function, slowest first."""
    shown = []
    watch = CompileWatch(on_change=shown.append)

    def wobble(x):
        return (x.sin() * 2.0).cos()

    compiled = watch.labelled("physics step", torch.compile(wobble, backend="aot_eager", dynamic=False))
    y = compiled(torch.randn(5, requires_grad=True))
    with watch.part("backward pass"):
        y.sum().backward()
    assert shown == ["compiling physics step (0 done)", "compiling physics step backward (1 done)"]
    assert (watch.compiles, watch.backward_compiles) == (1, 1)
    assert set(watch.summary()["compile_s_by_part"]) == {"physics step", "physics step backward"}
    mine = [g for g in compiled_graphs() if g["name"] == "wobble"]
    assert sorted(g["kind"] for g in mine) == ["backward", "forward"]
    assert len({g["compile_id"] for g in mine}) == 1  # the backward carries its forward's id
    forward = next(g for g in mine if g["kind"] == "forward")
    assert forward["nodes"] >= 3 and forward["s"] > 0
    assert forward["inductor_s"] is None and forward["cache_miss"] is None  # not inductor: nothing to say
    every = [g["s"] or g["inductor_s"] or 0.0 for g in compiled_graphs()]
    assert every == sorted(every, reverse=True)


def test_the_watch_counts_triton_kernels_compiled_in_this_process(tmp_path, monkeypatch):
    """Triton's compilation listener: a kernel built here is a compile with its seconds, the same kernel again
    is a hit in Triton's on-disk cache. Built for an sm_90 target offline, so no GPU is needed."""
    triton = pytest.importorskip("triton")
    import triton.language as tl
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    monkeypatch.setenv("TRITON_CACHE_DIR", str(tmp_path / "triton"))

    @triton.jit
    def double(x_ptr, n, BLOCK: tl.constexpr):
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        tl.store(x_ptr + i, tl.load(x_ptr + i, mask=i < n) * 2.0, mask=i < n)

    watch = CompileWatch()
    source = ASTSource(fn=double, signature={"x_ptr": "*fp32", "n": "i32", "BLOCK": "constexpr"},
                       constexprs={(2,): 64})
    try:
        triton.compile(source, target=GPUTarget("cuda", 90, 32))
    except Exception as e:  # a Triton without its NVIDIA backend or ptxas cannot build offline
        pytest.skip(f"Triton cannot build for sm_90 here: {e}")
    summary = watch.summary()
    assert (summary["triton_compiles"], summary["triton_cache_hits"]) == (1, 0)
    assert summary["triton_compile_s"] > 0
    triton.compile(source, target=GPUTarget("cuda", 90, 32))
    assert (watch.triton_compiles, watch.triton_cache_hits) == (1, 1)


def test_compile_workers_start_early_for_a_gpu_only_and_never_fail_a_run(monkeypatch):
    """start_compile_workers: inductor's worker pool is started for a CUDA device (its Triton kernels), not for
    the CPU (C++ there); a torch whose private pool function fails or is missing costs the head start only."""
    import torch._inductor.async_compile as async_compile

    started = []
    monkeypatch.setattr(async_compile, "maybe_warm_pool", lambda: started.append(True))
    assert start_compile_workers("cpu") is False and started == []
    assert start_compile_workers(torch.device("cuda", 0)) is True and started == [True]

    def broken():
        raise RuntimeError("no pool in this torch")

    monkeypatch.setattr(async_compile, "maybe_warm_pool", broken)
    assert start_compile_workers("cuda") is False
    monkeypatch.delattr(async_compile, "maybe_warm_pool")
    assert start_compile_workers("cuda") is False


def test_the_compile_phases_say_where_compiling_went(monkeypatch):
    """compile_phase_seconds: torch's own phase times of this process, in seconds; nested phases are within the
    ones that contain them; a torch without the table gives an empty breakdown, not an error."""
    torch.compile(lambda x: x.sin() * 3.0, backend="eager", dynamic=False)(torch.ones(4))
    phases = compile_phase_seconds()
    assert phases["_compile.compile_inner"] > 0
    assert 0 < phases["bytecode_tracing"] <= phases["_compile.compile_inner"]
    assert all(isinstance(v, float) for v in phases.values())

    import torch._dynamo.utils as dynamo_utils

    def gone(*args, **kwargs):
        raise AttributeError("no compile_times in this torch")

    monkeypatch.setattr(dynamo_utils, "compile_times", gone)
    assert compile_phase_seconds() == {}


def test_a_run_summary_has_its_time_to_the_first_iteration(tmp_path, monkeypatch):
    import time

    from ablations import run_log, runs

    assert 0.0 <= time.time() - run_log.process_started() < 24 * 3600  # the real start time is plausible
    before = time.time()
    monkeypatch.setattr(run_log, "process_started", lambda: before - 100.0)  # as if the process began 100 s earlier
    cfg = runs.RunConfig(task="cartpole", mode="state", iters=2, num_envs=2, horizon=2, critic_iterations=1,
                         device="cpu", out=tmp_path, name="r", video_every=0, progress=False)
    summary = json.loads((runs.run(cfg) / "summary.json").read_text())
    assert 100.0 < summary["first_iter_s"] < 100.0 + (time.time() - before)
    # where those seconds went: the parts are each non-negative, the imports hold the 100 s, and together they
    # make up the time to the first iteration, to within the few statements between the timers (a part
    # counted twice, or one left out, would be off by its whole length)
    parts = summary["startup_s"]
    assert set(parts) == {"imports", "run_folder", "compile_cache", "trainer", "first_reset_render",
                          "first_iteration"}
    assert all(v >= 0.0 for v in parts.values()) and parts["imports"] >= 100.0
    assert sum(parts.values()) == pytest.approx(summary["first_iter_s"], abs=0.02)
    assert summary["compile"] is None  # not a --compile run
    with pytest.raises(ValueError, match="--compile-cache is empty"):
        runs.RunConfig(compile_cache=" ").validate()


def test_the_watch_labels_the_callables_an_owner_calls_its_compiled_parts_through():
    """label_sites wraps each attribute path (``task.step``, ``window.backward``) with the watch's label, so that
    what compiles inside is named so; calls still return what the callable returns."""
    from types import SimpleNamespace

    shown = []
    watch = CompileWatch(on_change=shown.append)
    compiled = torch.compile(lambda x: x * 3.0 - 1.0, backend="eager", dynamic=False)
    owner = SimpleNamespace(task=SimpleNamespace(step=compiled), window=SimpleNamespace(backward=lambda x: x))
    watch.label_sites(owner, {"physics step": "task.step", "backward pass": "window.backward"})
    assert torch.equal(owner.task.step(torch.ones(2)), torch.full((2,), 2.0))
    assert shown == ["compiling physics step (0 done)"]
    assert owner.window.backward(5) == 5
