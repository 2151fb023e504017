"""Training presets: the reference code's per-task hyperparameters, flags that override them, and the trainer
options they set (decay length, actor init, observation clipping, bootstrapping, renderer)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from gradlab import SHAC, SHACConfig, preset_record, preset_values, resolve_config
from gradlab.normalizer import RunningMeanStd
from gradlab.presets import PRESET_FIELDS, PRESETS


def tiny(task="cartpole", mode="decoupled", **kw) -> SHACConfig:
    base = dict(task=task, mode=mode, iters=4, num_envs=3, horizon=4, image_size=24, critic_iterations=2,
                critic_batches=2, cosine_every=0, seed=3)
    base.update(kw)
    return SHACConfig(**base)


@pytest.mark.parametrize("preset", PRESETS)
@pytest.mark.parametrize("task", ["cartpole", "cartpole-swingup", "hopper", "ant", "humanoid", "cheetah"])
@pytest.mark.parametrize("mode", ["full", "decoupled", "state", "blind"])
def test_every_preset_sets_every_field(preset, task, mode):
    values = preset_values(preset, task, mode)
    assert set(values) == set(PRESET_FIELDS)
    resolved = resolve_config(SHACConfig(task=task, mode=mode, preset=preset))
    assert all(getattr(resolved, k) is not None for k in PRESET_FIELDS)


def test_dva_preset_is_dvas_configs():
    """D.Va examples/cfg/dva/<task>.yaml: actor 2e-3 everywhere; critic 2e-4 cartpole/hopper, 2e-3 ant, 5e-4
    humanoid; target_critic_alpha 0.2 (humanoid 0.995); actor_mlp units [64,64] / [128,64,32] / [256,128];
    critic [64,64] ([128,128] humanoid); max_epochs 4000 / 30000 / 30000 / 60000; num_actors 64. The trunk is
    the first actor width (models/actor.py: Encoder(output_dim=units[0]))."""
    expect = {
        "cartpole": (2e-4, 0.2, (64, 64), (64, 64), 4000),
        "hopper": (2e-4, 0.2, (128, 64, 32), (64, 64), 30000),
        "ant": (2e-3, 0.2, (128, 64, 32), (64, 64), 30000),
        "humanoid": (5e-4, 0.995, (256, 128), (128, 128), 60000),
    }
    for task, (critic_lr, alpha, actor, critic, decay) in expect.items():
        c = resolve_config(SHACConfig(task=task, mode="decoupled"))
        assert (c.actor_lr, c.critic_lr, c.target_alpha, c.actor_hidden, c.critic_hidden, c.lr_decay_iters) == (
            2e-3, critic_lr, alpha, actor, critic, decay)
        assert c.num_envs == 64 and c.trunk_dim == actor[0]
        # utils/running_mean_std.py normalises without clipping; ActorStochasticMLP keeps nn.Linear's init;
        # algorithms/dva.py bootstraps an episode that reached its length.
        assert (c.obs_clip, c.actor_init, c.bootstrap_last_step) == (0.0, "default", True)


def test_cheetah_presets_are_the_references():
    """D.Va examples/cfg/dva/cheetah.yaml: actor lr 2e-3, critic lr 2e-3, target_critic_alpha 0.2, actor_mlp
    [128, 64, 32], critic_mlp [64, 64], max_epochs 30000, num_actors 64; dva/diff_render_cheetah.yaml (and
    shac/cheetah_vis.yaml): max_epochs 2000; DiffRL examples/cfg/shac/cheetah.yaml (state SHAC): the same values
    with max_epochs 2000 and num_actors 64."""
    c = resolve_config(SHACConfig(task="cheetah", mode="decoupled"))
    assert (c.actor_lr, c.critic_lr, c.target_alpha, c.actor_hidden, c.critic_hidden, c.lr_decay_iters) == (
        2e-3, 2e-3, 0.2, (128, 64, 32), (64, 64), 30000)
    assert (c.num_envs, c.trunk_dim) == (64, 128)
    c = resolve_config(SHACConfig(task="cheetah", mode="full", preset="shac-diffrender"))
    assert (c.critic_lr, c.lr_decay_iters, c.raster_model) == (2e-3, 2000, "hard")
    c = resolve_config(SHACConfig(task="cheetah", mode="state"))
    assert (c.actor_lr, c.critic_lr, c.target_alpha, c.num_envs, c.lr_decay_iters) == (2e-3, 2e-3, 0.2, 64, 2000)


def test_shac_diffrender_preset_is_the_papers_baseline():
    """D.Va examples/cfg/dva/diff_render_<task>.yaml: max_epochs 800 (cartpole), 2000 (others); the renderer
    is PyTorch3D's MeshRasterizer at blur_radius 0, faces_per_pixel 1: our hard raster model."""
    for task, decay in (("cartpole", 800), ("hopper", 2000), ("ant", 2000), ("humanoid", 2000)):
        c = resolve_config(SHACConfig(task=task, mode="full", preset="shac-diffrender"))
        assert (c.lr_decay_iters, c.raster_model) == (decay, "hard")


def test_state_mode_takes_shacs_state_configs_where_they_differ():
    """DiffRL examples/cfg/shac/cartpole_swing_up.yaml: actor 1e-2, critic 1e-3, max_epochs 500;
    hopper.yaml: num_actors 256, max_epochs 2000; ant.yaml and humanoid.yaml: max_epochs 2000."""
    c = resolve_config(SHACConfig(task="cartpole", mode="state"))
    assert (c.actor_lr, c.critic_lr, c.lr_decay_iters) == (1e-2, 1e-3, 500)
    c = resolve_config(SHACConfig(task="hopper", mode="state"))
    assert (c.num_envs, c.lr_decay_iters) == (256, 2000)
    assert resolve_config(SHACConfig(task="humanoid", mode="state")).lr_decay_iters == 2000
    assert resolve_config(SHACConfig(task="hopper", mode="blind")).num_envs == 64  # visual modes: D.Va's


def test_explicit_flags_override_the_preset_and_the_record_holds_both():
    given = SHACConfig(task="ant", preset="shac-diffrender", mode="full", raster_model="alpha", critic_lr=1e-3)
    resolved = resolve_config(given)
    assert (resolved.raster_model, resolved.critic_lr, resolved.lr_decay_iters) == ("alpha", 1e-3, 2000)
    record = preset_record(given, resolved)
    assert record["name"] == "shac-diffrender"
    assert record["overridden"]["raster_model"] == {"flag": "alpha", "preset": "hard"}
    assert record["overridden"]["critic_lr"] == {"flag": 1e-3, "preset": 2e-3}
    assert record["supplied"]["lr_decay_iters"] == 2000 and "raster_model" not in record["supplied"]


def test_presets_are_the_references_and_every_other_choice_is_a_flag():
    """The presets are the reference code's (the --preset choices are PRESETS); the trainer's other choices are flags
    over one: orthogonal init with a small last layer, clipped observations, no last-step bootstrap, the decay over
    the run's own length."""
    from typing import get_args, get_type_hints

    assert get_args(get_type_hints(SHACConfig)["preset"]) == PRESETS == ("dva", "shac-diffrender", "teacher")
    c = resolve_config(SHACConfig(task="hopper", iters=123, lr_decay_iters=123, obs_clip=5.0, actor_init="orthogonal",
                                  bootstrap_last_step=False))
    assert (c.lr_decay_iters, c.obs_clip, c.actor_init, c.bootstrap_last_step) == (123, 5.0, "orthogonal", False)
    assert (c.critic_lr, c.actor_hidden) == (2e-4, (128, 64, 32))  # the rest from the dva preset
    with pytest.raises(ValueError, match="unknown preset 'project'; valid presets: dva, shac-diffrender"):
        resolve_config(SHACConfig(task="hopper", preset="project"))


@pytest.mark.parametrize(("field", "value", "message"), [
    ("preset", "paper", "unknown preset 'paper'; valid presets: dva, shac-diffrender"),
    ("raster_model", "blurry", "--raster-model: unknown raster model 'blurry'"),
    ("renderer", "opengl", "unknown renderer 'opengl'"),
    ("sim_backend", "jax", "--sim-backend: unknown simulator backend 'jax'; valid: torch, warp"),
    ("lr_decay_iters", 0, "--lr-decay-iters must be a positive integer"),
    ("obs_clip", -1.0, r"--obs-clip must be in \[0, inf\)"),
])
def test_bad_values_are_named(field, value, message):
    with pytest.raises(ValueError, match=message):
        SHACConfig(task="ant", **{field: value}).validate()


def test_full_mode_refuses_the_ray_tracer():
    with pytest.raises(ValueError, match=r"--renderer warp renders without gradient.*--mode full"):
        SHACConfig(task="ant", mode="full", renderer="warp").validate()
    for mode in ("decoupled", "blind", "state"):
        SHACConfig(task="ant", mode=mode, renderer="warp").validate()


def test_learning_rate_decays_over_lr_decay_iters_not_iters():
    trainer = SHAC([tiny(mode="state", iters=4, lr_decay_iters=8, actor_lr=1e-3)], device="cpu")
    lrs = [trainer.train_iteration()[0]["actor_lr"] for _ in range(4)]
    expected = [1e-3 + (1e-5 - 1e-3) * i / 8 for i in range(4)]
    assert lrs == pytest.approx(expected)


def test_actor_init_option():
    default = SHAC([tiny(mode="state", actor_init="default")], device="cpu").members[0].actor
    ortho = SHAC([tiny(mode="state", actor_init="orthogonal")], device="cpu").members[0].actor
    last_default, last_ortho = default.mu[-1].weight.detach(), ortho.mu[-1].weight.detach()
    # orthogonal: the last layer scaled to 0.01 (mean actions near 0); nn.Linear's init: U(-1/sqrt(in), ..)
    assert float(last_ortho.abs().max()) < 0.02 < float(last_default.abs().max())
    w = ortho.mu[0].weight.detach()  # (64, 5): orthonormal columns times the gain sqrt(2)
    torch.testing.assert_close(w.T @ w, 2.0 * torch.eye(w.shape[1]), atol=1e-5, rtol=0)


def test_observation_clip_zero_disables_clipping():
    stats = (torch.zeros(2), torch.ones(2))
    x = torch.tensor([[10.0, -0.5]])
    assert RunningMeanStd.apply(x, stats, 0.0).tolist() == [[10.0, -0.5]]
    assert RunningMeanStd.apply(x, stats, 5.0).tolist() == [[5.0, -0.5]]


def test_bootstrap_last_step_zeroes_only_early_terminations():
    trainer = SHAC([tiny()], device="cpu")
    f, t = torch.tensor(False), torch.tensor(True)
    # (terminated, invalid, time_limit) -> zero value with / without bootstrapping the last step
    cases = [((t, f, f), True, True), ((t, f, t), False, True), ((t, t, t), True, True), ((f, f, t), False, False)]
    for (term, inv, limit), zero_boot, zero_plain in cases:
        info = {"terminated": term, "invalid": inv, "time_limit": limit}
        trainer.cfg = dataclasses.replace(trainer.cfg, bootstrap_last_step=True)
        assert bool(trainer._ends_without_value(info)) is zero_boot
        trainer.cfg = dataclasses.replace(trainer.cfg, bootstrap_last_step=False)
        assert bool(trainer._ends_without_value(info)) is zero_plain


def test_decoupled_trains_on_ray_traced_images_and_probes_with_the_rasterizer(monkeypatch):
    trainer = SHAC([tiny(renderer="warp", cosine_every=2)], device="cpu")
    calls = {"warp": 0, "soft": 0}
    renderer = type(trainer.renderers[trainer.members[0].cfg.raster_model])
    real_call, real_soft = renderer.__call__, renderer.soft

    def traced(self, qpos):
        calls["warp"] += 1
        return real_call(self, qpos)

    def soft(self, qpos):
        calls["soft"] += 1
        return real_soft(self, qpos)
    monkeypatch.setattr(renderer, "__call__", traced)
    monkeypatch.setattr(renderer, "soft", soft)
    (probe,) = trainer.train_iteration()  # iteration 0 is a probe: every frame through the rasterizer
    assert probe["probed"] and calls["soft"] == 4 and calls["warp"] == 1  # + the first frame at start
    assert probe["grad_norm_full"] > 0
    (plain,) = trainer.train_iteration()
    assert not plain["probed"] and calls["warp"] == 5 and calls["soft"] == 4
    assert plain["grad_norm"] > 0
