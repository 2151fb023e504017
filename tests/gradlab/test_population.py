"""Populations: several runs trained in one process as one batched simulation, each member a run of its own.

The arithmetic of every member is that of its run alone except where its networks run as batched kernels: with
``batching="modules"`` (each member's own modules) a member must equal its standalone run bit for bit; with the
batched kernels (``"grouped"``) to float32 rounding, whose differences the window's chaotic dynamics then grow.
"""

import copy
import dataclasses
import math

import pytest
import torch

from gradlab.config import SHACConfig
from gradlab.probes import NonFiniteError
from gradlab.shac import SHAC, check_population

# Keys whose values depend on the clock or the process, not on the run's arithmetic.
_UNCOMPARED = {"wall_s", "fwd_ms", "bwd_ms", "critic_ms", "iter_ms", "peak_alloc_mb", "peak_reserved_mb", "saved_mb"}

BASE = SHACConfig(task="cartpole", num_envs=3, horizon=4, image_size=16, iters=5, cosine_every=2, episode_length=6,
                  critic_iterations=2)
MIXED = [dataclasses.replace(BASE, mode=mode, seed=seed) for seed in (0, 1) for mode in ("decoupled", "full", "blind")]


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the same reduction order in every run of this module
    yield
    torch.set_num_threads(threads)


def _train(trainer: SHAC, iters: int) -> list[list]:
    return [trainer.train_iteration() for _ in range(iters)]


def _alone(cfg: SHACConfig, iters: int) -> list[dict]:
    """A run alone's metrics of ``iters`` iterations."""
    return [row for (row,) in _train(SHAC([cfg], device="cpu"), iters)]


def _same(a: dict, b: dict) -> bool:
    def eq(x, y):
        return x == y or (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y))

    return a.keys() == b.keys() and all(eq(a[k], b[k]) for k in a if k not in _UNCOMPARED)


#: What a run alone of ``replace(BASE, mode="full", seed=4)`` computes in its first three iterations on the CPU,
#: recorded: a population of one is a run alone (its noise from torch's default generator, its own modules, its
#: critic fitted alone), so it must compute exactly this.
RUN_ALONE = [
    {"actor_loss": 10.400460243225098, "critic_loss": 1026.7991943359375, "grad_norm": 39.249176025390625,
     "grad_norm_clipped": 1.0000000487658953, "return_mean": None, "action_std": 0.3671444356441498,
     "cos_full_decoupled": 0.9999999160245047},
    {"actor_loss": 11.019866943359375, "critic_loss": 399.8023681640625, "grad_norm": 1.1216527223587036,
     "grad_norm_clipped": 0.9999991572230721, "return_mean": -78.85268910725911, "action_std": 0.3664630055427551},
    {"actor_loss": 14.297259330749512, "critic_loss": 1460.8367919921875, "grad_norm": 0.3886815011501312,
     "grad_norm_clipped": 0.3886815036270615, "return_mean": -71.88369051615398, "action_std": 0.3658272624015808,
     "cos_full_decoupled": 0.9999999999995888},
]


def test_a_population_of_one_computes_what_a_run_alone_computed():
    rows = _alone(dataclasses.replace(BASE, mode="full", seed=4), 3)
    for row, recorded in zip(rows, RUN_ALONE, strict=True):
        assert ("cos_full_decoupled" in row) == ("cos_full_decoupled" in recorded) == row["probed"]
        # to float rounding: another CPU may round its kernels differently (on this one they are equal)
        assert {k: row[k] for k in recorded} == {k: v if v is None else pytest.approx(v, rel=1e-4)
                                                 for k, v in recorded.items()}


def test_each_member_of_a_mixed_population_is_its_run_alone_bit_for_bit():
    population = SHAC(MIXED, device="cpu", batching="modules")
    together = _train(population, 5)
    assert [m.cfg.mode for m in population.members] == ["full", "full", "decoupled", "decoupled", "blind", "blind"]
    for m in population.members:
        alone = _alone(m.cfg, 5)
        for it in range(5):
            assert _same(alone[it], together[it][m.index]), (m.cfg.mode, m.cfg.seed, it)
        probed = [row for row in alone if row["probed"]]
        assert len(probed) == (3 if m.plan.probes else 0)
        if m.plan.grad_through_images:
            assert "cos_hard_soft" in probed[0] and "cos_full_decoupled" in probed[0]


def test_batched_networks_follow_the_members_runs_to_float_rounding():
    population = SHAC(MIXED, device="cpu", batching="grouped")
    (together,) = _train(population, 1)
    for m in population.members:
        (alone,) = _alone(m.cfg, 1)
        mine = together[m.index]
        for key in ("actor_loss", "critic_loss", "grad_norm", "grad_norm_clipped", "grad_norm_full",
                    "grad_norm_decoupled", "cos_full_decoupled", "image_sensitivity_f2", "action_std"):
            if key in alone:
                assert mine[key] == pytest.approx(alone[key], rel=1e-4, abs=1e-6), (m.cfg.mode, key)


def test_one_members_loss_reaches_no_other_members_parameters():
    population = SHAC(MIXED, device="cpu", batching="grouped")
    population._start()
    loss, _ = population._rollout(render_grad=[True] * population.n)
    population.gate.set_route(("image",) * 4 + (None, None))  # every seeing member's image path open
    target = population.members[2]
    loss[target.index].backward()
    for m in population.members:
        grads = [p.grad for p in m.params]
        if m is target:
            assert any(g is not None and torch.count_nonzero(g) > 0 for g in grads)
        else:
            assert all(g is None or torch.count_nonzero(g) == 0 for g in grads), m.cfg.mode


def test_a_member_that_goes_non_finite_stops_alone():
    population = SHAC(MIXED, device="cpu", batching="modules")
    _train(population, 1)
    broken = population.members[2]
    with torch.no_grad():
        next(broken.actor.parameters()).fill_(float("nan"))
    rows = _train(population, 3)
    assert rows[0][broken.index] is None and broken.failed is not None
    # the second iteration (one trained before the NaN), counted from 1 as metrics.jsonl counts
    assert broken.failed.startswith("iteration 2: ") and "non-finite" in broken.failed
    # the others trained on, as they would have alone
    for m in population.members:
        if m is broken:
            continue
        alone = _alone(m.cfg, 4)
        assert all(_same(alone[it + 1], rows[it][m.index]) for it in range(3)), (m.cfg.mode, m.cfg.seed)


def test_every_member_stopped_stops_the_run():
    population = SHAC(MIXED[:2], device="cpu", batching="modules")
    for m in population.members:
        with torch.no_grad():
            next(m.actor.parameters()).fill_(float("nan"))
    with pytest.raises(NonFiniteError, match="every member"):
        population.train_iteration()


def test_a_resumed_population_continues_as_if_uninterrupted():
    uninterrupted = SHAC(MIXED, device="cpu", batching="modules")
    straight = _train(uninterrupted, 5)
    first = SHAC(MIXED, device="cpu", batching="modules")
    _train(first, 3)
    states = first.state_dict()
    assert len(states) == 6 and all(s["iteration"] == 3 for s in states)
    assert all(s["task"]["qpos"].shape[0] == BASE.num_envs for s in states)  # a member's rows, a run's format
    resumed = SHAC(MIXED[::-1], device="cpu", batching="modules")  # members matched by their settings
    resumed.load_state_dict(states[::-1])
    rest = _train(resumed, 2)
    index = {(m.cfg.mode, m.cfg.seed): m.index for m in uninterrupted.members}
    for it in range(2):
        for m in resumed.members:
            assert _same(straight[3 + it][index[m.cfg.mode, m.cfg.seed]], rest[it][m.index])


def test_a_member_of_several_does_not_resume_as_a_run_alone_nor_the_reverse():
    """A member of several draws its noise from a generator of its own, a run alone from torch's default one:
    either checkpoint would resume the other inexactly, so it is refused."""
    pair = SHAC(MIXED[:2], device="cpu", batching="modules")
    _train(pair, 1)
    member = copy.deepcopy(pair.state_dict()[0])
    alone = SHAC([pair.members[0].cfg], device="cpu")
    with pytest.raises(ValueError, match="checkpoint of a member of a population cannot resume exactly as a run "
                                         "alone"):
        alone.load_state_dict([member])
    _train(alone, 1)
    with pytest.raises(ValueError, match="checkpoint of a run alone cannot resume exactly as a member of a "
                                         "population of 2"):
        SHAC(MIXED[:2], device="cpu").load_state_dict([copy.deepcopy(alone.state_dict()[0]),
                                                        pair.state_dict()[1]])


def test_members_that_cannot_share_a_process_are_refused_naming_the_flag():
    resolved = [dataclasses.replace(SHAC([c], device="cpu").cfg) for c in (BASE, dataclasses.replace(BASE, seed=1))]
    with pytest.raises(ValueError, match="appears twice"):
        check_population([resolved[0], resolved[0]])
    with pytest.raises(ValueError, match="--num-envs"):
        SHAC([BASE, dataclasses.replace(BASE, num_envs=5, seed=1)], device="cpu")
    with pytest.raises(ValueError, match="--mode state"):
        SHAC([BASE, dataclasses.replace(BASE, mode="state", seed=1)], device="cpu")


def test_evaluation_is_deterministic_and_leaves_training_untouched():
    cfg = dataclasses.replace(BASE, mode="decoupled", seed=1, eval_envs=2)
    # one trainer after the other: single runs share torch's default generator
    expected = _alone(cfg, 2)[1]
    a = SHAC([cfg], device="cpu")
    _train(a, 1)
    (first,) = a.evaluate(video_steps=3)
    (again,) = a.evaluate()
    stats = ("eval_return_mean", "eval_return_std", "eval_length_mean")
    assert [first[k] for k in stats] == [again[k] for k in stats]  # the same seed, the same episodes
    assert len(first["frames"]) == 3 and first["frames"][0].dtype.name == "uint8" and again["frames"] == []
    assert 1 <= first["eval_length_mean"] <= cfg.episode_length
    # evaluating changed nothing of the training run
    assert _same(a.train_iteration()[0], expected)
    # a population's member is evaluated as its run alone
    population = SHAC([cfg, dataclasses.replace(cfg, seed=5)], device="cpu", batching="modules")
    _train(population, 1)
    member = next(m for m in population.members if m.cfg.seed == 1)
    evaluated = population.evaluate()[member.index]
    assert [evaluated[k] for k in stats] == [first[k] for k in stats]


def test_evaluation_renders_each_raster_model_once_a_step_with_each_members_own_images():
    """One renderer call per run of adjacent members of one raster model (a call a member cost a 12-member
    population most of its evaluation time on a GPU), and every member's rows the image its own call renders."""
    cfgs = [dataclasses.replace(BASE, mode=mode, raster_model=raster, seed=seed, eval_envs=2)
            for seed in (0, 1) for mode, raster in (("decoupled", None), ("full", "hard"), ("full", None),
                                                     ("blind", None))]
    trainer = SHAC(cfgs, device="cpu")
    evaluation = trainer.evaluator.build()
    task, renderers = evaluation.task, evaluation.renderers
    task.reset()
    # every member starts from the same evaluation states: a distinct pose a row, so that no row passes for another
    task.qpos = task.qpos + 0.1 * torch.arange(task.qpos.shape[0], dtype=task.qpos.dtype).unsqueeze(1)
    calls = []
    for raster, renderer in renderers.items():
        renderer_call = renderer.__call__
        renderers[raster] = lambda q, r=raster, f=renderer_call: (calls.append((r, q.shape[0])), f(q))[1]
    images = trainer.evaluator.images(task, renderers)
    # population order puts members of one raster model side by side: softmax, hard, then the blind ones
    assert sorted(calls) == sorted({(raster, 2 * sum(m.cfg.raster_model == raster and m.plan.renders
                                                     for m in trainer.members)) for raster, _ in calls})
    assert len(calls) == len(renderers)
    for m in trainer.members:
        rows = slice(2 * m.index, 2 * m.index + 2)
        own = (renderers[m.cfg.raster_model](task.qpos[rows]) if m.plan.renders
               else torch.zeros_like(images[rows]))
        assert torch.equal(images[rows], own), (m.cfg.mode, m.cfg.raster_model)


def test_a_population_too_large_for_the_devices_memory_is_refused(monkeypatch):
    import gradlab.members as members

    need = members.window_bytes(MIXED)
    assert need == sum(members.window_bytes([c]) for c in MIXED)
    full, decoupled = (members.window_bytes([c]) for c in MIXED[1::-1])
    assert full > decoupled  # a full member also keeps the rasterizer's state
    monkeypatch.setattr(members, "_memory_of", lambda device: need - 1)
    with pytest.raises(ValueError, match="fewer --seed/--mode values"):
        SHAC(MIXED, device="cpu")
    monkeypatch.setattr(members, "_memory_of", lambda device: need)
    SHAC(MIXED, device="cpu")
    # what fewer members per process cannot mend is not refused: a run alone, or a member too large alone too
    monkeypatch.setattr(members, "_memory_of", lambda device: full - 1)
    SHAC([MIXED[1]], device="cpu")
    SHAC(MIXED, device="cpu")


def test_the_window_estimate_is_the_bulk_of_what_a_window_keeps():
    from gradlab.timing import SavedTensorMeter

    cfg = dataclasses.replace(BASE, mode="full", image_size=32, num_envs=2)
    trainer = SHAC([cfg], device="cpu")
    trainer._start()
    with SavedTensorMeter() as saved:
        trainer._rollout(render_grad=[True])
    from gradlab.shac import window_bytes

    assert 0.5 * saved.bytes < window_bytes([trainer.cfg]) < 2.0 * saved.bytes


def test_blind_phase_options_scale_the_encoder_and_ramp_the_actors_learning_rate():
    cfg = dataclasses.replace(BASE, mode="decoupled", encoder_lr_scale=0.1, lr_warmup_iters=4, lr_decay_iters=100)
    trainer = SHAC([cfg], device="cpu")
    (member,) = trainer.members
    encoder, head = member.actor_opt.param_groups
    assert {id(p) for p in encoder["params"]} == {id(p) for p in member.actor.encoder.parameters()}
    base = member.cfg.actor_lr
    rows = [row for (row,) in _train(trainer, 4)]
    decay = [base + (1e-5 - base) * i / 100 for i in range(4)]
    assert [r["actor_lr"] for r in rows] == pytest.approx([decay[i] * (i + 1) / 4 for i in range(4)])
    assert encoder["lr"] == pytest.approx(0.1 * head["lr"])
    plain = SHAC([dataclasses.replace(BASE, mode="decoupled")], device="cpu")
    # the reference's single group (its checkpoints load as before)
    assert len(plain.members[0].actor_opt.param_groups) == 1
