"""A population's critics fitted in one pass (``fit_critics``) against each member's own ``fit_critic``.

In float64 the two differ only in the rounding of the batched kernels (batched against single matrix products,
and each member's gradient norm reduced over its stacked slice rather than tensor by tensor), so losses,
parameters and Adam state agree to a few ulps; a member's gradient, zeroing, clipping or learning rate leaking
into another member would show at the first step.
"""

import copy
import dataclasses

import pytest
import torch

from gradlab.config import SHACConfig
from gradlab.critic import fit_critic, fit_critics
from gradlab.networks import Critic, MemberStack
from gradlab.shac import SHAC

OBS_DIM, HIDDEN, ROWS = 5, (8, 8), 38  # 38 rows in 3 minibatches: slices of 13, 13 and 12 rows
ITERATIONS, BATCHES = 3, 3
TOL = dict(rtol=1e-10, atol=1e-12)


pytestmark = pytest.mark.usefixtures("single_thread")


def _members(lrs: list[float], *, warm: bool = True) -> tuple[list[Critic], list[torch.optim.Adam]]:
    """Critics in float64 (each its own initialisation) with Adam; ``warm``: after one step, so that the Adam
    state is not zero (a fit then starts mid-run)."""
    critics, optimizers = [], []
    for m, lr in enumerate(lrs):
        torch.manual_seed(100 + m)
        critic = Critic(OBS_DIM, HIDDEN).double()
        optimizer = torch.optim.Adam(critic.parameters(), lr=lr, betas=(0.7, 0.95))
        if warm:
            critic(torch.randn(7, OBS_DIM, dtype=torch.float64)).square().mean().backward()
            optimizer.step()
        critics.append(critic)
        optimizers.append(optimizer)
    return critics, optimizers


def _data(n: int, seed: int = 0, scale: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """(n, ROWS, OBS_DIM) states and (n, ROWS) targets."""
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(n, ROWS, OBS_DIM, generator=g, dtype=torch.float64),
            scale * torch.randn(n, ROWS, generator=g, dtype=torch.float64))


def _alone(critics, optimizers, obs, targets, grad_clip) -> torch.Tensor:
    """Each member's fit_critic on its own rows: the reference. Returns (N,) losses."""
    clips = grad_clip if isinstance(grad_clip, list) else [grad_clip] * len(critics)
    return torch.stack([fit_critic(c, o, x, y, iterations=ITERATIONS, batches=BATCHES, grad_clip=clip)
                        for c, o, x, y, clip in zip(critics, optimizers, obs, targets, clips)])


def _together(critics, optimizers, obs, targets, grad_clip) -> torch.Tensor:
    clip = torch.tensor(grad_clip, dtype=torch.float64) if isinstance(grad_clip, list) else grad_clip
    return fit_critics(MemberStack(critics), optimizers, obs, targets, iterations=ITERATIONS, batches=BATCHES,
                       grad_clip=clip)


def _both(lrs, obs, targets, grad_clip, *, warm=True):
    """(losses, critics, optimizers) of the batched fit and of the members alone, from the same states."""
    critics, optimizers = _members(lrs, warm=warm)
    ref_critics, ref_optimizers = copy.deepcopy((critics, optimizers))
    together = _together(critics, optimizers, obs, targets, grad_clip)
    alone = _alone(ref_critics, ref_optimizers, obs, targets, grad_clip)
    return (together, critics, optimizers), (alone, ref_critics, ref_optimizers)


def _assert_member_equal(a, b, m: int, **tol) -> None:
    """Member m's loss, parameters and Adam state (step, moments) of the fits a and b agree within tol."""
    (loss_a, critics_a, opts_a), (loss_b, critics_b, opts_b) = a, b
    torch.testing.assert_close(loss_a[m], loss_b[m], equal_nan=True, **tol)
    for p, q in zip(critics_a[m].parameters(), critics_b[m].parameters()):
        torch.testing.assert_close(p, q, **tol)
        sp, sq = opts_a[m].state[p], opts_b[m].state[q]
        assert sp.keys() == sq.keys() == {"step", "exp_avg", "exp_avg_sq"}
        for k in sp:
            torch.testing.assert_close(sp[k], sq[k], **tol)


def _first_grad_norm(critic: Critic, obs: torch.Tensor, targets: torch.Tensor) -> float:
    """The total gradient norm of the first minibatch step (before clipping)."""
    critic = copy.deepcopy(critic)
    size = -(-ROWS // BATCHES)
    (critic(obs[:size]) - targets[:size]).square().mean().backward()
    return torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in critic.parameters()])).item()


@pytest.mark.parametrize("warm", [False, True], ids=["fresh-adam", "warm-adam"])
def test_the_batched_fit_is_each_members_own_fit(warm):
    obs, targets = _data(4)
    together, alone = _both([1e-3] * 4, obs, targets, 1.0, warm=warm)
    assert together[0].shape == (4,)
    for m in range(4):
        _assert_member_equal(together, alone, m, **TOL)
    assert not torch.equal(together[1][0].net[0].weight, _members([1e-3])[0][0].net[0].weight)  # it trained


def test_each_member_steps_with_its_own_learning_rate():
    lrs = [1e-4, 3e-3, 1e-4, 2e-2]
    obs, targets = _data(4, seed=1)
    together, alone = _both(lrs, obs, targets, 1.0)
    for m in range(4):
        _assert_member_equal(together, alone, m, **TOL)
    # the rates matter here: member 3 on member 0's rate ends elsewhere
    (_, same_rate, _), _ = _both([1e-4] * 4, obs, targets, 1.0)
    assert (same_rate[3].net[0].weight - together[1][3].net[0].weight).abs().max() > 1e-4


@pytest.mark.parametrize("per_member_bound", [False, True], ids=["one-bound", "bound-per-member"])
def test_each_member_is_clipped_by_its_own_gradient_norm(per_member_bound):
    obs, targets = _data(3, seed=2)
    targets[0] *= 1e3  # a large gradient: clipped
    critics, _ = _members([1e-3] * 3)
    with torch.no_grad():
        targets[1] = critics[1](obs[1]) + 1e-4 * targets[1]  # nearly fitted: a small gradient, not clipped
    grad_clip = [1.0, 1.0, 0.05] if per_member_bound else 1.0
    clips = grad_clip if per_member_bound else [grad_clip] * 3
    assert _first_grad_norm(critics[0], obs[0], targets[0]) > 100 * clips[0]
    assert _first_grad_norm(critics[1], obs[1], targets[1]) < clips[1] / 100
    together, alone = _both([1e-3] * 3, obs, targets, grad_clip)
    for m in range(3):
        _assert_member_equal(together, alone, m, **TOL)


@pytest.mark.parametrize("where", ["targets", "obs"])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")], ids=["nan", "inf", "-inf"])
def test_a_non_finite_input_of_one_member_leaves_the_others_untouched(where, value):
    obs, targets = _data(3, seed=3)
    poisoned_obs, poisoned_targets = obs.clone(), targets.clone()
    if where == "targets":
        poisoned_targets[1, 17] = value
    else:
        poisoned_obs[1, 17, 2] = value
    clean, _ = _both([1e-3] * 3, obs, targets, 1.0)
    poisoned, alone = _both([1e-3] * 3, poisoned_obs, poisoned_targets, 1.0)
    for m in (0, 2):  # bit for bit: no kernel mixes members
        _assert_member_equal(poisoned, clean, m, rtol=0, atol=0)
    assert not torch.isfinite(poisoned[0][1])  # its loss shows the bad sample
    _assert_member_equal(poisoned, alone, 1, **TOL)  # and it updated as fit_critic does on the same input
    assert all(torch.isfinite(p).all() for p in poisoned[1][1].parameters())


@pytest.mark.parametrize("warm", [False, True], ids=["fresh-adam", "warm-adam"])
def test_adam_steps_taken_together_are_each_members_own_bit_for_bit(warm):
    """Members of equal Adam settings step in one call of torch's Adam; the others on their own."""
    lrs = [1e-3, 1e-3, 5e-3, 1e-3]
    obs, targets = _data(4, seed=4)
    critics, optimizers = _members(lrs, warm=warm)
    own_critics, own_optimizers = copy.deepcopy((critics, optimizers))
    kwargs = dict(iterations=ITERATIONS, batches=BATCHES, grad_clip=1.0)
    together = fit_critics(MemberStack(critics), optimizers, obs, targets, adam_groups=[[0, 1, 3], [2]], **kwargs)
    own = fit_critics(MemberStack(own_critics), own_optimizers, obs, targets, **kwargs)
    for m in range(4):
        _assert_member_equal((together, critics, optimizers), (own, own_critics, own_optimizers), m, rtol=0,
                             atol=0)


def test_adam_groups_that_cannot_step_as_one_are_refused():
    critics, optimizers = _members([1e-3, 2e-3, 1e-3])
    obs, targets = _data(3)
    for groups, match in (([[0, 1], [2]], "differ"), ([[0, 2]], "each of the 3 members once"),
                          ([[0, 2], [1], [2]], "each of the 3 members once")):
        with pytest.raises(ValueError, match=match):
            fit_critics(MemberStack(critics), optimizers, obs, targets, iterations=1, batches=1, grad_clip=1.0,
                        adam_groups=groups)
    optimizers[2].param_groups[0]["eps"] = 1e-6
    with pytest.raises(ValueError, match="differ"):
        fit_critics(MemberStack(critics), optimizers, obs, targets, iterations=1, batches=1, grad_clip=1.0,
                    adam_groups=[[0, 2], [1]])


def test_fit_critics_refuses_what_it_cannot_batch():
    critics, optimizers = _members([1e-3, 1e-3])
    obs, targets = _data(2)
    for stack in (MemberStack(critics[:1]), MemberStack(critics, batching="modules")):
        with pytest.raises(ValueError, match="fit_critic per member"):
            fit_critics(stack, optimizers, obs, targets, iterations=1, batches=1, grad_clip=1.0)


BASE = SHACConfig(task="cartpole", mode="state", num_envs=4, horizon=5, episode_length=8, critic_iterations=3)


def _window(trainer: SHAC) -> dict:
    """Random buffers of one window of the trainer's shape (what the critic fit reads)."""
    g = torch.Generator().manual_seed(7)
    T, rows, d = trainer.cfg.horizon, trainer.n * trainer.cfg.num_envs, trainer.task.num_obs
    dones = torch.rand(T, rows, generator=g) < 0.2
    dones[-1] = True
    return dict(critic_obs=torch.randn(T, rows, d, generator=g), rewards=torch.randn(T, rows, generator=g),
                next_values=torch.randn(T, rows, generator=g), dones=dones)


def test_a_population_fits_its_critics_as_its_members_alone():
    """Members that differ in critic learning rate and decay, gradient bound, iterations and minibatches: those
    that share iterations and minibatches fit together (those of one learning-rate schedule stepping their Adam
    as one), a member alone in its group as it would alone; all equal the exact member-by-member fit
    (``"modules"``) to float32 rounding."""
    cfgs = [dataclasses.replace(BASE, seed=0), dataclasses.replace(BASE, seed=1, critic_lr=3e-3, grad_clip=0.01),
            dataclasses.replace(BASE, seed=2, lr_decay_iters=2),
            dataclasses.replace(BASE, seed=3, critic_iterations=2, critic_batches=2), dataclasses.replace(BASE, seed=4)]
    batched, exact = SHAC(cfgs, device="cpu"), SHAC(cfgs, device="cpu", batching="modules")
    assert sorted(len(g.members) for g in batched._critic_groups) == [1, 4]
    (together,) = [g for g in batched._critic_groups if g.stack is not None]
    assert sorted(len(a) for a in together.adam_groups) == [1, 1, 2]  # seeds 0 and 4 step their Adam as one
    for trainer in (batched, exact):
        trainer.iteration = 1  # the decay under way: member 2's critic rate is half its base
        trainer._set_learning_rates()
    buf = _window(batched)
    losses = batched._fit_critic(buf)
    exact_losses = exact._fit_critic(buf)
    assert losses.shape == (5,)
    torch.testing.assert_close(losses, exact_losses, rtol=1e-5, atol=1e-7)
    for m, e in zip(batched.members, exact.members):
        assert m.cfg == e.cfg
        for p, q in zip(m.critic.parameters(), e.critic.parameters()):
            torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(m.critic_opt.state[p]["exp_avg_sq"], e.critic_opt.state[q]["exp_avg_sq"],
                                       rtol=1e-4, atol=1e-10)
    alone = batched.members[3]  # alone in its group: fit_critic's own arithmetic, bit for bit
    for p, q in zip(alone.critic.parameters(), exact.members[3].critic.parameters()):
        assert torch.equal(p, q)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_the_batched_fit_replays_from_a_cuda_graph_as_it_runs_eagerly():
    """The fit as the trainer runs it with --compile on a GPU: capturable Adam with tensor learning rates, the
    members of one rate stepping as one (multi-tensor kernels: bit for bit their own steps), captured once
    (``GraphedCriticPhase``) and replayed on new inputs, against the same fits run eagerly."""
    from gradlab.graphs import GraphedCriticPhase

    device = torch.device("cuda")
    lrs = [1e-3, 1e-3, 4e-3, 1e-3]
    critics, optimizers = [], []
    for m, lr in enumerate(lrs):
        torch.manual_seed(100 + m)
        critics.append(Critic(11, (64, 64)).to(device))
        optimizers.append(torch.optim.Adam(critics[-1].parameters(), lr=torch.tensor(lr, device=device),
                                           betas=(0.7, 0.95), capturable=True))
    fits = {name: copy.deepcopy((critics, optimizers)) for name in ("graphed", "eager", "eager-own-steps")}
    grad_clip = torch.tensor([1.0, 0.5, 1.0, 1.0], device=device)  # made before the capture: no copy inside

    def phase(name: str, groups):
        critics, optimizers = fits[name]
        stack = MemberStack(critics)
        return lambda buf: fit_critics(stack, optimizers, buf["critic_obs"], buf["rewards"], iterations=4, batches=3,
                                       grad_clip=grad_clip, adam_groups=groups)

    groups = [[0, 1, 3], [2]]
    graphed = GraphedCriticPhase(phase("graphed", groups), torch.nn.ModuleList(fits["graphed"][0]), device)
    eager, own_steps = phase("eager", groups), phase("eager-own-steps", None)
    g = torch.Generator(device=device).manual_seed(0)
    for _ in range(4):  # an eager fit and the capture, then three replays
        buf = dict(critic_obs=torch.randn(4, 64, 11, device=device, generator=g),
                   rewards=torch.randn(4, 64, device=device, generator=g), next_values=torch.zeros(1, device=device),
                   dones=torch.zeros(1, device=device))
        losses = {"graphed": graphed(buf).clone(), "eager": eager(buf), "eager-own-steps": own_steps(buf)}
        torch.testing.assert_close(losses["eager"], losses["eager-own-steps"], rtol=0, atol=0)
        # a replay runs the kernels it captured: equal but for cuBLAS picking other kernels on the side stream
        torch.testing.assert_close(losses["graphed"], losses["eager"], rtol=1e-5, atol=1e-6)
    assert graphed.graph is not None
    for m in range(4):
        params = {name: list(fits[name][0][m].parameters()) for name in fits}
        for p, q, r in zip(params["graphed"], params["eager"], params["eager-own-steps"]):
            assert torch.equal(q, r)
            torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6)
