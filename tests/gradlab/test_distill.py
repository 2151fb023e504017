"""State-to-visual distillation (``--mode distill``, gradlab/distill.py): the reference's constants, the FIFO buffer,
the segments that resume, the student's own actions, the MSE target, the schedule, early stopping, resume,
populations and the refusals. Sources: HaoxiangYou/D.VA ``01b2be4``."""

from __future__ import annotations

import dataclasses
import re

import pytest
import torch
import torch.nn.functional as F

from gradlab import SHAC, SHACConfig, resolve_config
from gradlab.checkpoint import save_checkpoint
from gradlab.config import check_as_given
from gradlab.distill import Distill, ReplayBuffer, load_expert, to_uint8
from gradlab.networks import StateActor
from gradlab.normalizer import RunningMeanStd
from vocabulary import TASKS


@pytest.fixture(scope="module")
def expert(tmp_path_factory):
    """A tiny cartpole state expert's checkpoint (one iteration of the teacher preset)."""
    torch.set_num_threads(1)
    trainer = SHAC([SHACConfig(task="cartpole", mode="state", preset="teacher", iters=1, num_envs=2, horizon=4,
                               critic_iterations=1, critic_batches=1, seed=5)], device="cpu")
    trainer.train_iteration()
    path = tmp_path_factory.mktemp("expert") / "ckpt_000001.pt"
    (state,) = trainer.state_dict()  # a run folder's checkpoint: one run's state
    save_checkpoint(path, state)
    return path


def tiny(expert, **kw) -> SHACConfig:
    """A cartpole student of 2 environments, 4-step segments (8 samples an iteration), a 20-sample buffer whose
    updates start at 16 samples (the third iteration), 3 Adam steps of batch 4 at most; 12-step episodes."""
    base = dict(task="cartpole", mode="distill", expert=None if expert is None else str(expert), num_envs=2,
                horizon=4, image_size=24, seed=1, eval_envs=2, episode_length=12, distill_buffer=20,
                distill_starts=16, distill_updates=3, distill_batch=4)
    base.update(kw)
    return SHACConfig(**base)


# ---------------------------------------------------------------------------------------------- constants
def test_student_settings_are_the_references():
    """examples/cfg/teacher_student/<task>.yaml: num_actors 64, steps_num 32, actor_learning_rate 2e-3, betas
    [0.7, 0.95], max_replay_buffer_size 100000, learning_starts 32000, num_update_per_epoch 2000, batch_size 128,
    supervised_loss_threshold 0.1, 84x84 images (3 frames: models/actor.py's 9 channels); actor_mlp units
    [128, 64, 32] (cartpole [64, 64]), the encoder's output its first width (models/actor.py); max_epochs 10000
    (humanoid 40000) as the decay length (algorithms/dagger.py:231-234)."""
    for task, hidden, decay in (("cartpole", (64, 64), 10000), ("hopper", (128, 64, 32), 10000),
                                ("ant", (128, 64, 32), 10000), ("humanoid", (128, 64, 32), 40000),
                                ("cheetah", (128, 64, 32), 10000)):
        c = resolve_config(SHACConfig(task=task, mode="distill", expert="x"))
        assert (c.actor_hidden, c.trunk_dim, c.lr_decay_iters, c.actor_lr, c.num_envs) == (
            hidden, hidden[0], decay, 2e-3, 64)
        assert (c.horizon, c.betas, c.image_size, c.frames) == (32, (0.7, 0.95), 84, 3)
        assert (c.distill_buffer, c.distill_starts, c.distill_updates, c.distill_batch, c.distill_loss_threshold) \
            == (100_000, 32_000, 2000, 128, 0.1)
    # a deviation is a flag: D.Va's own humanoid actor (dva/humanoid.yaml: [256, 128], the trunk its first width)
    c = resolve_config(SHACConfig(task="humanoid", mode="distill", expert="x", actor_hidden=(256, 128),
                                  trunk_dim=256))
    assert c.actor_hidden == (256, 128) and c.trunk_dim == 256


def test_teacher_preset_is_the_references():
    """examples/cfg/teacher_student/teacher/<task>.yaml: num_actors 64 (the hopper too: DiffRL's state hopper has
    256), max_epochs 4000 cartpole, 2000 others; cartpole actor 1e-2 / critic 1e-3; hopper [128, 64, 32] /
    [64, 64], critic 2e-4, alpha 0.2; ant critic 2e-3; humanoid [256, 128] / [128, 128], critic 5e-4, alpha
    0.995; cheetah (teacher/cheetah.yaml, max_epochs 2000) critic 2e-3 as dva/cheetah.yaml; actor 2e-3 elsewhere."""
    expect = {"cartpole": (1e-2, 1e-3, 0.2, (64, 64), (64, 64), 4000),
              "hopper": (2e-3, 2e-4, 0.2, (128, 64, 32), (64, 64), 2000),
              "ant": (2e-3, 2e-3, 0.2, (128, 64, 32), (64, 64), 2000),
              "humanoid": (2e-3, 5e-4, 0.995, (256, 128), (128, 128), 2000),
              "cheetah": (2e-3, 2e-3, 0.2, (128, 64, 32), (64, 64), 2000)}
    assert set(expect) | {"cartpole-swingup"} == set(TASKS)  # every task has a teacher and a student
    for task, values in expect.items():
        c = resolve_config(SHACConfig(task=task, mode="state", preset="teacher"))
        assert (c.actor_lr, c.critic_lr, c.target_alpha, c.actor_hidden, c.critic_hidden, c.lr_decay_iters) == values
        assert c.num_envs == 64 and (c.horizon, c.critic_iterations, c.critic_batches, c.lam, c.gamma) == (
            32, 16, 4, 0.95, 0.99)


def test_the_distillation_loss_gradient_is_the_finite_differences_one():
    """The student's MSE loss against labels, differentiated in its head's parameters, in float64 (gradcheck)."""
    from torch.func import functional_call

    from gradlab.distill import Student

    torch.manual_seed(0)
    student = Student(9, 16, 16, 2, 5, (4, 3)).double()
    frames, labels = torch.rand(3, 9, 16, 16, dtype=torch.float64), torch.randn(3, 2, dtype=torch.float64)
    names = [n for n, _ in student.mu.named_parameters()]
    with torch.no_grad():
        features = student.encoder(frames)

    def loss(*head):
        return F.mse_loss(functional_call(student.mu, dict(zip(names, head)), (features,)), labels)

    head = [p.detach().clone().requires_grad_(True) for p in student.mu.parameters()]
    assert torch.autograd.gradcheck(loss, tuple(head))


# ---------------------------------------------------------------------------------------------- the buffer
def test_buffer_is_a_fifo_that_drops_the_overflow_at_the_wrap():
    """utils/dataset.py ExpertReplayBuffer.append: a batch that runs past the end is cut there, the next starts at
    0 over the oldest samples."""
    buf = ReplayBuffer(10, (1, 1, 1), 1, torch.device("cpu"))
    batch = lambda start, n: (torch.arange(start, start + n, dtype=torch.uint8).view(n, 1, 1, 1),  # noqa: E731
                              torch.arange(start, start + n, dtype=torch.float32).view(n, 1))
    for start in (0, 4, 8):
        buf.append(*batch(start, 4))
    assert (len(buf), buf.pos) == (10, 0)  # samples 10, 11 dropped
    assert buf.actions.view(-1).tolist() == list(range(10))
    buf.append(*batch(20, 3))
    assert buf.actions.view(-1).tolist() == [20, 21, 22, *range(3, 10)] and buf.images.dtype == torch.uint8
    frames, labels = buf.sample(10, torch.Generator().manual_seed(0))
    assert sorted(labels.view(-1).tolist()) == sorted(buf.actions.view(-1).tolist())  # without replacement
    assert torch.equal(frames.view(-1) * 255, labels.view(-1).round() % 256)


# ---------------------------------------------------------------------------------------------- the loop
def test_segments_resume_from_the_previous_end_with_the_students_own_actions(expert):
    d = Distill([tiny(expert)], device="cpu")
    d.train_iteration()
    state, frames = d.task.get_state(), d.frames.state_dict()
    start_obs = d.task.state_obs().clone()
    lengths = d.episode_length.clone()
    images, states = d._segment()
    # no reset between segments: the next segment starts where the last ended, episodes go on
    assert torch.equal(states[0], start_obs) and bool((d.episode_length == lengths + 4).all())
    # the first step of it was the student's deterministic action on the uint8 frames, no expert and no noise
    d.task.set_state(state)
    d.frames.load_state_dict(frames)
    assert torch.equal(to_uint8(d.frames.stacked()), images[0])
    with torch.no_grad():
        obs, *_ = d.task.step(torch.tanh(d.members[0].actor.mean(images[0].float() / 255.0)))
    assert torch.equal(obs, states[1])


def test_labels_are_the_experts_deterministic_action_and_the_loss_is_their_mse(expert):
    d = Distill([tiny(expert, distill_updates=1, distill_loss_threshold=0.0)], device="cpu")
    d.train_iteration()
    _, states = d._segment()  # what the next iteration would store: label it as the reference does
    ckpt = torch.load(expert, weights_only=False)
    actor = StateActor(d.task.num_obs, d.task.num_act, ckpt["config"]["actor_hidden"])
    actor.load_state_dict(ckpt["actor"])
    rms = RunningMeanStd(d.task.num_obs)
    rms.load_state_dict(ckpt["obs_rms"])
    flat = states.flatten(0, 1)
    with torch.no_grad():
        want = actor.mean(RunningMeanStd.apply(flat, rms.snapshot(), 0.0))  # pre-tanh: the teacher's output
    assert torch.allclose(d.members[0].expert(flat), want, atol=1e-6)
    # the buffer holds those labels for what it stored, and an update's loss is the MSE against them
    buf = d.members[0].buffer
    d.train_iteration()
    assert len(buf) == 16
    gen = d.members[0].generator.get_state()
    d.members[0].generator.set_state(gen)
    frames, labels = buf.sample(4, d.members[0].generator)
    with torch.no_grad():
        expected = float(F.mse_loss(d.members[0].actor.mean(frames), labels))
    d.members[0].generator.set_state(gen)
    loss, _, steps = d._update(d.members[0])
    assert steps == 1 and loss == pytest.approx(expected, rel=1e-6)


def test_updates_start_at_distill_starts_and_stop_at_the_threshold(expert):
    d = Distill([tiny(expert, distill_loss_threshold=0.0)], device="cpu")
    rows = [row for (row,) in (d.train_iteration() for _ in range(3))]
    assert [r["buffer_size"] for r in rows] == [8, 16, 20] and [r["updates"] for r in rows] == [0, 3, 3]
    assert rows[0]["actor_loss"] is None and rows[0]["grad_norm"] is None and rows[1]["actor_loss"] is not None
    # linear decay per Adam step over lr_decay_iters x distill_updates steps (algorithms/dagger.py:231-234)
    c = d.members[0].cfg
    assert rows[2]["actor_lr"] == pytest.approx(2e-3 + (1e-5 - 2e-3) * 5 / (c.lr_decay_iters * 3))
    d = Distill([tiny(expert, distill_loss_threshold=1e9)], device="cpu")  # the first minibatch is below it
    assert [d.train_iteration()[0]["updates"] for _ in range(3)] == [0, 1, 1]


def test_expert_time_and_steps_are_charged(expert):
    d = Distill([tiny(expert)], device="cpu")
    (row,) = d.train_iteration()
    ckpt = torch.load(expert, weights_only=False)
    assert row["expert_wall_s"] == ckpt["wall_s"] > 0 and row["expert_env_steps"] == 1 * 4 * 2
    assert row["wall_s"] == pytest.approx(ckpt["wall_s"] + row["student_wall_s"])
    assert row["env_steps"] == 8 + 8 and row["student_env_steps"] == 8


def test_resume_restores_everything_but_the_buffer(expert):
    a = Distill([tiny(expert)], device="cpu")
    for _ in range(3):
        a.train_iteration()
    state = a.state_dict()
    b = Distill([tiny(expert)], device="cpu")
    b.load_state_dict(state)
    assert len(b.members[0].buffer) == 0 and b.members[0].updates == a.members[0].updates > 0
    (ra,), (rb,) = a.train_iteration(), b.train_iteration()
    # the same segment (student, task, frames restored; a's third one was cut at the wrap, so its fourth starts at
    # 0), and b refills its buffer before updating again
    assert torch.equal(a.members[0].buffer.images[:8], b.members[0].buffer.images[:8])
    assert torch.equal(a.members[0].buffer.actions[:8], b.members[0].buffer.actions[:8])
    assert (ra["buffer_size"], rb["buffer_size"], rb["updates"]) == (20, 8, 0)


def test_a_population_member_trains_as_it_would_alone(expert):
    alone = Distill([tiny(expert, seed=2)], device="cpu")
    pop = Distill([tiny(expert, seed=1), tiny(expert, seed=2)], device="cpu")
    for _ in range(3):
        (r_alone,), (_, r_pop) = alone.train_iteration(), pop.train_iteration()
    assert r_alone["actor_loss"] == r_pop["actor_loss"] and r_alone["buffer_size"] == r_pop["buffer_size"]
    assert torch.equal(alone.members[0].buffer.actions, pop.members[1].buffer.actions)
    evaluated = pop.evaluate()
    assert len(evaluated) == 2 and all(e["eval_steps"] > 0 for e in evaluated)


def test_compile_compiles_the_rollouts_physics_and_renderer_once(expert):
    d = Distill([tiny(expert)], device="cpu")
    with pytest.raises(ValueError, match="compile parts are some of"):
        d.compile(parts=("networks",))
    d.compile()
    assert d.compiled == Distill.COMPILE_PARTS and set(d.COMPILE_SITES) == {"physics step", "renderer"}
    with pytest.raises(RuntimeError, match=r"compiled .* already"):
        d.compile()


@pytest.mark.slow  # inductor's C++ compile of the cartpole substep and reward on the CPU
def test_a_compiled_student_trains_as_the_eager_one(expert):
    eager, compiled = Distill([tiny(expert)], device="cpu"), Distill([tiny(expert, compile=True)], device="cpu")
    for _ in range(3):  # the third iteration updates the student
        (re,), (rc,) = eager.train_iteration(), compiled.train_iteration()
    assert compiled.compiled == Distill.COMPILE_PARTS
    assert rc["updates"] == re["updates"] > 0 and rc["actor_loss"] == pytest.approx(re["actor_loss"], rel=1e-4)
    torch.testing.assert_close(compiled.members[0].buffer.actions, eager.members[0].buffer.actions, rtol=1e-4,
                               atol=1e-5)


# ---------------------------------------------------------------------------------------------- bad input
def test_bad_experts_are_refused_naming_the_flag(expert, tmp_path):
    task = Distill([tiny(expert)], device="cpu").task
    ckpt = torch.load(expert, weights_only=False)
    for config, message in ((dict(mode="decoupled"), "a --mode decoupled run, not a state run"),
                            (dict(task="hopper"), "an expert of task hopper, not --task cartpole")):
        path = tmp_path / f"{next(iter(config.values()))}.pt"
        save_checkpoint(path, {**ckpt, "config": {**ckpt["config"], **config}})
        with pytest.raises(ValueError, match="^" + re.escape(f"--expert {path}: {message}")):
            load_expert(tiny(path), task, torch.device("cpu"))
    with pytest.raises(ValueError, match=r"^--expert: --mode distill needs a state expert"):
        load_expert(tiny(None), task, torch.device("cpu"))
    with pytest.raises(ValueError, match="no such file or folder"):
        load_expert(tiny(tmp_path / "nothing"), task, torch.device("cpu"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="holds no readable checkpoint"):
        load_expert(tiny(tmp_path / "empty"), task, torch.device("cpu"))


def test_settings_that_mean_nothing_are_refused():
    for cfg, message in ((SHACConfig(mode="distill"), r"^--expert: --mode distill needs a state expert"),
                         (SHACConfig(mode="decoupled", expert="x"), r"^--expert means nothing with --mode decoupled"),
                         (SHACConfig(mode="full", preset="teacher"), r"^--preset teacher trains the state experts")):
        with pytest.raises(ValueError, match=message):
            check_as_given(cfg)
    with pytest.raises(ValueError, match=r"^--distill-starts 5 must lie between --distill-batch 8"):
        SHACConfig(mode="distill", expert="x", distill_starts=5, distill_batch=8).validate()
    with pytest.raises(ValueError, match="cannot share a population with the other modes"):
        Distill([SHACConfig(mode="distill", expert="x"), dataclasses.replace(SHACConfig(), seed=1)])
    with pytest.raises(ValueError, match=r"trained by gradlab.Distill, not SHAC"):
        SHAC([SHACConfig(mode="distill", expert="x")])
