"""SHAC / D.Va trainer: the switch, the probes, determinism, the NaN guard (CPU, tiny sizes)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import tasks
from gradlab import SHAC, SHACConfig
from gradlab.networks import VisualActor
from gradlab.probes import NonFiniteError, cosine, flat_grad

TIMING = ("wall_s", "fwd_ms", "bwd_ms", "critic_ms", "iter_ms", "peak_alloc_mb", "peak_reserved_mb")


def tiny(task="cartpole", mode="decoupled", **kw) -> SHACConfig:
    base = dict(task=task, mode=mode, iters=4, num_envs=3, horizon=4, image_size=24, critic_iterations=2,
                critic_batches=2, cosine_every=0, seed=3)
    base.update(kw)
    return SHACConfig(**base)


def actor_grad(trainer: SHAC, *, render_grad: bool, gate_open: bool) -> torch.Tensor:
    trainer._start()
    loss, _ = trainer._rollout(render_grad=[render_grad])
    trainer.members[0].actor.zero_grad(set_to_none=True)
    trainer.gate.open = gate_open
    loss.backward()
    return flat_grad(trainer.members[0].actor.parameters())


def test_decoupled_gradient_equals_explicit_detach():
    # Decoupled training renders without grad (the image is a constant); the probe renders with grad behind a
    # closed gate. Both must be the gradient with the image explicitly detached.
    g_nograd = actor_grad(SHAC([tiny()], device="cpu"), render_grad=False, gate_open=False)
    g_gated = actor_grad(SHAC([tiny()], device="cpu"), render_grad=True, gate_open=False)
    torch.testing.assert_close(g_gated, g_nograd, rtol=1e-6, atol=1e-9)
    assert float(g_nograd.norm()) > 0


def test_full_and_decoupled_differ_through_the_renderer():
    # Same seed -> the same rollout; with the gate open the image path adds gradient through the renderer.
    # Over a few 1/60 s steps the cart barely moves, so the image term is small (~1e-6 relative) but real: the
    # noise floor is exactly zero because the same computation repeats bit for bit on the CPU.
    cfg = tiny(mode="full", horizon=6)
    g_full = actor_grad(SHAC([cfg], device="cpu"), render_grad=True, gate_open=True)
    g_dec = actor_grad(SHAC([cfg], device="cpu"), render_grad=True, gate_open=False)
    g_dec_again = actor_grad(SHAC([cfg], device="cpu"), render_grad=True, gate_open=False)
    assert torch.equal(g_dec, g_dec_again)
    diff = float((g_full - g_dec).norm())
    assert diff > 1e-8 * float(g_dec.norm()), diff
    assert float(cosine(g_full, g_dec)) < 1.0


def test_state_mode_has_no_image_path():
    g_open = actor_grad(SHAC([tiny(mode="state")], device="cpu"), render_grad=False, gate_open=True)
    g_closed = actor_grad(SHAC([tiny(mode="state")], device="cpu"), render_grad=False, gate_open=False)
    assert torch.equal(g_open, g_closed)


def test_probe_reports_both_gradients_of_one_rollout_and_trains_with_the_mode():
    trainer = SHAC([tiny(mode="decoupled", cosine_every=1)], device="cpu")
    m = trainer.train_iteration()[0]
    for k in ("grad_norm_full", "grad_norm_decoupled", "cos_full_decoupled", "grad_norm_render_term"):
        assert k in m
    # The applied (pre-clip) gradient is the decoupled one.
    assert m["grad_norm"] == pytest.approx(m["grad_norm_decoupled"], rel=1e-5)
    assert -1.0 <= m["cos_full_decoupled"] <= 1.0
    full = SHAC([tiny(mode="full", cosine_every=1)], device="cpu").train_iteration()[0]
    assert full["grad_norm"] == pytest.approx(full["grad_norm_full"], rel=1e-5)
    # Same seed, same rollout: both runs measured the same pair of gradients.
    assert full["grad_norm_decoupled"] == pytest.approx(m["grad_norm_decoupled"], rel=1e-5)
    assert full["cos_full_decoupled"] == pytest.approx(m["cos_full_decoupled"], abs=1e-5)


def test_same_seed_same_metrics():
    def metrics():
        tr = SHAC([tiny(mode="decoupled", cosine_every=2)], device="cpu")
        return [{k: v for k, v in tr.train_iteration()[0].items() if k not in TIMING} for _ in range(3)]

    assert metrics() == metrics()


def test_metrics_keys_and_types():
    m = SHAC([tiny(mode="state")], device="cpu").train_iteration()[0]
    for k in ("iter", "env_steps", "wall_s", "return_mean", "actor_loss", "critic_loss", "grad_norm",
              "grad_norm_clipped", "fwd_ms", "bwd_ms", "peak_alloc_mb", "peak_reserved_mb", "saved_mb"):
        assert k in m
    assert m["iter"] == 1 and m["env_steps"] == 3 * 4
    assert m["grad_norm_clipped"] <= 1.0 + 1e-6
    assert m["peak_alloc_mb"] is None  # CPU: torch keeps no peak statistics


def test_binned_renders_overflowing_tiles_are_in_the_iterations_metrics_only_when_there_are(monkeypatch):
    import diffrender

    trainer = SHAC([tiny()], device="cpu")
    counts = iter([0, 7])
    monkeypatch.setattr(diffrender, "bin_overflows", lambda: next(counts))
    first, second = trainer.train_iteration()[0], trainer.train_iteration()[0]
    assert "bin_overflows" not in first and second["bin_overflows"] == 7


def test_full_mode_saves_more_for_backward_than_decoupled():
    full = SHAC([tiny(mode="full")], device="cpu").train_iteration()[0]
    dec = SHAC([tiny(mode="decoupled")], device="cpu").train_iteration()[0]
    assert full["saved_mb"] > dec["saved_mb"]


def test_nan_guard_names_iteration_step_and_tensor(monkeypatch):
    trainer = SHAC([tiny(mode="state")], device="cpu")
    trainer.train_iteration()
    real_step = trainer.task.step
    calls = {"n": 0}

    def poisoned(action):
        obs, reward, done, info = real_step(action)
        calls["n"] += 1
        if calls["n"] == 3:  # horizon step 2 of the second iteration
            reward = reward * float("nan")
        return obs, reward, done, info

    monkeypatch.setattr(trainer.task, "step", poisoned)
    # iterations counted from 1, as metrics.jsonl and ablate's lines count them
    with pytest.raises(NonFiniteError, match=r"iteration 2: non-finite forward value at horizon step 2 in reward"):
        trainer.train_iteration()


def test_evaluate_and_video_frames():
    trainer = SHAC([dataclasses.replace(tiny(mode="decoupled"), eval_envs=2)], device="cpu")
    evaluated = trainer.evaluate(video_steps=3, video_size=32)[0]
    assert isinstance(evaluated["eval_return_mean"], float) and len(evaluated["frames"]) == 3
    assert evaluated["frames"][0].shape == (32, 32, 3) and evaluated["frames"][0].dtype.name == "uint8"


def test_config_errors_are_clear():
    with pytest.raises(ValueError, match="unknown task 'cartpol'; valid tasks: cartpole"):
        SHAC([tiny(task="cartpol")], device="cpu")
    with pytest.raises(ValueError, match="unknown mode 'ful'; valid modes: full, decoupled, state"):
        SHAC([tiny(mode="ful")], device="cpu")
    with pytest.raises(ValueError, match="--num-envs must be a positive integer"):
        SHAC([tiny(num_envs=0)], device="cpu")
    with pytest.raises(ValueError, match="horizon must be a positive integer"):
        SHAC([tiny(horizon=-1)], device="cpu")
    trainer = SHAC([tiny(compile=True)], device="cpu")
    with pytest.raises(ValueError, match=r"compile parts are some of \('substep', 'factorize', 'finish', "
                                         r"'renderer', 'networks'\), got \('renderer', 'critic'\)"):
        trainer.compile(parts=("renderer", "critic"))
    with pytest.raises(ValueError, match="compile parts are some of"):
        trainer.compile(parts="networks")  # a string, not a collection of parts
    trainer.compile(parts=("networks",))
    with pytest.raises(RuntimeError, match=r"compiled \('networks',\) already"):
        trainer.compile()
    assert "ant" in tasks.TASKS


@pytest.mark.parametrize("mode", ["full", "blind"])
def test_compile_table_and_sites_name_what_the_trainer_calls(mode):
    """Every part of COMPILE_PARTS has an entry (the renderer's empty where nothing is rendered), each entry can
    compile; every compile site is an attribute path to a callable the trainer calls. Compiling a part puts a
    compiled callable where the trainer calls it, lazily: nothing is compiled before the first call."""
    from gradlab.shac import COMPILE_PARTS

    trainer = SHAC([tiny(mode=mode, compile=True)], device="cpu")
    table = trainer.compile_table()
    assert tuple(table) == COMPILE_PARTS
    assert (len(table["renderer"]) == 0) == (mode == "blind")
    assert all(callable(entry.compile) for entries in table.values() for entry in entries)
    for path in trainer.COMPILE_SITES.values():
        holder = trainer
        for name in path.split("."):
            holder = getattr(holder, name)
        assert callable(holder), path
    eager_mean = trainer._actor_mean
    trainer.compile(parts=("networks",))
    assert trainer.compiled == ("networks",) and trainer._actor_mean is not eager_mean
    assert trainer.task._substep == trainer.task._chained_substep  # not compiled: the physics stays eager


def test_raster_model_option_reaches_the_renderer():
    def trained_with(cfg):  # the renderer of the raster model the run trains on (the probe's other one beside)
        trainer = SHAC([cfg], device="cpu")
        return trainer, trainer.renderers[trainer.members[0].cfg.raster_model].settings

    trainer, settings = trained_with(tiny(mode="full", raster_model="alpha"))
    assert settings.raster_model == "alpha" and not settings.cull_backfaces
    assert trained_with(tiny(mode="full", raster_model="softmax"))[1].raster_model == "softmax"
    assert trained_with(tiny(mode="full", preset="shac-diffrender"))[1].raster_model == "hard"
    assert trainer.train_iteration()[0]["grad_norm"] > 0


@pytest.mark.skipif(not (__import__("shutil").which("g++") or __import__("shutil").which("c++")),
                    reason="torch.compile on the CPU needs a C++ compiler")
@pytest.mark.slow
def test_compile_matches_eager_on_cpu():
    from gradlab.shac import COMPILE_PARTS

    # --compile's non-graph part (torch.compile'd physics substep and reward/reset; CUDA graphs need a GPU and
    # are tested in tests/test_cuda.py) gives the eager numbers within float tolerance, probes included.
    # Compiled, each window starts from a leaf that requires grad (one guard set for every control step;
    # tests/tasks/test_tasks.py counts the graphs), eagerly from a plain detached state.
    def run(compile_: bool):
        trainer = SHAC([tiny(mode="decoupled", cosine_every=2, compile=compile_)], device="cpu")
        cut, starts = trainer.task.detach, []

        def detach(**kw):
            cut(**kw)
            starts.append(trainer.task.qpos.requires_grad and trainer.task.qvel.requires_grad)

        trainer.task.detach = detach
        out = [trainer.train_iteration()[0] for _ in range(3)]
        assert starts == [compile_] * len(starts) and len(starts) >= 3
        assert trainer.compiled == (COMPILE_PARTS if compile_ else None)  # compiled at its first iteration
        return out

    eager, compiled = run(False), run(True)
    for a, b in zip(eager, compiled):
        for k in ("actor_loss", "grad_norm", "critic_loss", "grad_norm_full", "cos_full_decoupled"):
            if k in a:
                assert b[k] == pytest.approx(a[k], rel=1e-4, abs=1e-6), (k, a[k], b[k])
        assert not b["graph"]


def test_probe_explains_the_render_term_by_group_and_frame():
    trainer = SHAC([tiny(mode="decoupled", cosine_every=1)], device="cpu")
    trainer._start()
    loss, _ = trainer._window_forward(True)
    out = {k: float(v) for (_, k), v in trainer._backward(loss, True).items()}  # the only member's
    groups = ("encoder", "mlp", "log_std")
    total_sq = sum(out[f"grad_norm_render_term_{g}"] ** 2 for g in groups)
    assert total_sq == pytest.approx(out["grad_norm_render_term"] ** 2, rel=1e-9)
    assert out["grad_norm_render_term_encoder"] > 0
    # The sensitivity is the actor's input gradient on the stack the window ended in, by hand (the parameters
    # are still the rollout's: no optimiser step yet).
    x = trainer.frames.stacked().detach().requires_grad_(True)
    (g,) = torch.autograd.grad(trainer.members[0].actor.mean(x).sum(), x)
    for i in range(3):
        want = g[:, 3 * i:3 * i + 3].flatten(1).norm(dim=1).mean()
        assert out[f"image_sensitivity_f{i}"] == pytest.approx(float(want), rel=1e-5)
        assert out[f"image_sensitivity_f{i}"] > 0
    # The same keys reach the metrics of a probe iteration.
    m = SHAC([tiny(mode="full", cosine_every=1)], device="cpu").train_iteration()[0]
    assert {f"grad_norm_render_term_{g}" for g in groups} | {"image_sensitivity_f0", "image_sensitivity_f2"} <= set(m)


@pytest.mark.parametrize("mode", ["blind", "state"])
def test_modes_without_images_run_no_probes(mode):
    m = SHAC([tiny(mode=mode, cosine_every=1)], device="cpu").train_iteration()[0]
    assert not m["probed"]
    assert not [k for k in m if k.startswith(("grad_norm_render_term", "image_sensitivity", "cos_", "grad_norm_f"))]


def test_blind_actor_sees_one_constant_image_and_renders_nothing(monkeypatch):
    trainer = SHAC([tiny(mode="blind")], device="cpu")
    assert trainer.renderers == {} and isinstance(trainer.members[0].actor, VisualActor)  # decoupled's actor
    seen = []
    real_mean = trainer._actor_mean
    monkeypatch.setattr(trainer, "_actor_mean",
                        lambda params, x: (seen.append((x, real_mean(params, x))), seen[-1][1])[1])
    m = trainer.train_iteration()[0]
    assert m["grad_norm"] > 0 and len(seen) == 4
    for x, mu in seen:
        assert x.shape == (3, 9, 24, 24) and not x.any()
        # Different environments (different states: random resets) get the same mean action (to float
        # rounding: a batched GEMM need not round identical rows identically).
        torch.testing.assert_close(mu, mu[:1].expand_as(mu), rtol=1e-6, atol=1e-7)
    assert not torch.equal(trainer.task.qpos[0], trainer.task.qpos[1])  # the environments' states differ
    assert not trainer.frames.frames  # nothing was rendered into the stack

    # evaluate() feeds the same constant image.
    inputs = []
    real_mean = trainer.members[0].actor.mean
    monkeypatch.setattr(trainer.members[0].actor, "mean", lambda x: (inputs.append(x), real_mean(x))[1])
    trainer.cfg.eval_envs = 2
    evaluated = trainer.evaluate()[0]
    # (episodes' ends are read every 16 steps, so a few steps may follow the last end)
    assert isinstance(evaluated["eval_return_mean"], float) and len(inputs) >= evaluated["eval_length_mean"]
    assert all(x.shape == (2, 9, 24, 24) and not x.any() for x in inputs)


@pytest.mark.parametrize("mode", ["blind", "decoupled"])
def test_resume_from_state_dict_equals_uninterrupted(mode):
    import io

    cfg = tiny(mode=mode, cosine_every=2)
    straight = SHAC([cfg], device="cpu")
    want = [straight.train_iteration()[0] for _ in range(3)][-1]
    first = SHAC([cfg], device="cpu")
    first.train_iteration(), first.train_iteration()
    buf = io.BytesIO()
    torch.save(first.state_dict(), buf)
    resumed = SHAC([cfg], device="cpu")
    resumed.load_state_dict(torch.load(io.BytesIO(buf.getvalue()), weights_only=False))
    got = resumed.train_iteration()[0]
    assert {k: v for k, v in got.items() if k not in TIMING} == {k: v for k, v in want.items() if k not in TIMING}
