"""Gradients of rollout returns: autograd against central finite differences (float64), and finiteness."""

from __future__ import annotations

import pytest
import torch

import tasks
from tests.tasks.helpers import directional_fd_check, rollout_return


@pytest.mark.parametrize("name", ["cartpole", "cartpole-swingup"])
def test_cartpole_16_steps_matches_finite_differences(name):
    """d(return)/d(actions) and d(return)/d(initial qpos, qvel) over 16 control steps (64 substeps), with the
    joint springs (cartpole) and without (cartpole-swingup)."""
    env = tasks.make(name, 3, dtype=torch.float64, early_termination=False)
    gen = torch.Generator().manual_seed(0)
    # away from th = +-pi, where the wrapped angle in the reward has a kink
    qpos0 = torch.tensor([[0.1, -2.0], [-0.3, 1.0], [0.0, 0.3]], dtype=torch.float64)
    qvel0 = torch.tensor([[0.5, 1.0], [-0.2, -2.0], [0.1, 0.0]], dtype=torch.float64)
    actions = torch.tanh(torch.randn(16, 3, 1, generator=gen, dtype=torch.float64))

    def f(a, q, v):
        return rollout_return(env, q, v, a)

    pairs = directional_fd_check(f, [actions, qpos0, qvel0], n_dirs=4, eps=1e-6, rtol=1e-6)
    assert any(abs(ad) > 1.0 for ad, _ in pairs)  # the check is not vacuous


def _ant_in_contact(num_envs: int):
    """Float64 ants 13 steps after the start: they fell 0.2 m and landed, all four foot tips in the ground."""
    env = tasks.make("ant", num_envs, dtype=torch.float64, early_termination=False, reset_noise=False)
    env.reset()
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for _ in range(13):
            env.step(0.3 * torch.tanh(torch.randn(num_envs, 8, generator=gen, dtype=torch.float64)))
    return env


def test_ant_8_steps_through_contact_matches_finite_differences():
    """d(return)/d(actions, initial qpos, initial qvel) over 8 control steps (128 substeps) with the feet in
    ground contact, so the gradient flows through the contact normal, damping and friction forces."""
    env = _ant_in_contact(2)
    qpos0, qvel0 = env.qpos.clone(), env.qvel.clone()
    fr = env.sim.frames(qpos0)
    vb = torch.einsum("bn,xnk->xbk", env.sim._body_dof_anc, fr.S * qvel0[..., None])
    f_contact = env.sim._contact_forces(fr, vb)
    feet = torch.tensor([4, 7, 10, 13]) - 1  # the foot bodies carry the contact
    assert (f_contact[:, feet, 5] > 50).all(), "the ants must stand on their feet for this test"
    gen = torch.Generator().manual_seed(4)
    actions = torch.tanh(0.7 * torch.randn(8, 2, 8, generator=gen, dtype=torch.float64))

    def f(a, q, v):
        return rollout_return(env, q, v, a)

    pairs = directional_fd_check(f, [actions, qpos0, qvel0], n_dirs=3, eps=1e-6, rtol=1e-5, seed=1)
    assert any(abs(ad) > 1e-2 for ad, _ in pairs)


def test_step_gradient_reaches_action_and_state():
    env = tasks.make("cartpole", 2, dtype=torch.float64)
    env.reset()
    q = env.qpos.clone().requires_grad_(True)
    v = env.qvel.clone().requires_grad_(True)
    a = torch.full((2, 1), 0.3, dtype=torch.float64, requires_grad=True)
    env.qpos, env.qvel = q, v
    _obs, r, _done, info = env.step(a)
    gq, gv, ga = torch.autograd.grad(r.sum() + info["obs_before_reset"].sum(), (q, v, a))
    assert gq.abs().sum() > 0 and gv.abs().sum() > 0 and ga.abs().sum() > 0


def test_cheetah_through_contact_and_the_ffoot_limit_matches_finite_differences():
    """d(return)/d(actions, initial qpos, initial qvel) over 2 control steps (32 substeps) of two float64
    cheetahs: one with its back foot pressed into the ground (contact normal, damping and friction), one at the
    reference's start pose, ffoot 0.3 rad past its upper limit (the limit penalty's gradient)."""
    env = tasks.make("cheetah", 2, dtype=torch.float64, reset_noise=False)
    qpos0 = torch.tensor([[0.0, -0.44, -0.05, 0.2, -0.3, 0.1, -0.2, 0.1, -0.6], [0.0, -0.2] + [0.0] * 7],
                         dtype=torch.float64)
    qvel0 = torch.tensor([[-0.3, -0.2, 0.1, 0.0, 0.0, 1.0, 0.0, -1.0, 0.0], [0.0] * 9], dtype=torch.float64)
    fr = env.sim.frames(qpos0)
    vb = torch.einsum("bn,xnk->xbk", env.sim._body_dof_anc, fr.S * qvel0[..., None])
    normal = env.sim._contact_forces(fr, vb)[..., 5]
    assert normal[0, 3] > 100 and normal[1].abs().sum() == 0  # bfoot on the ground; the other in the air
    limit = env.sim.passive_force(qpos0, qvel0, limits=True) - env.sim.passive_force(qpos0, qvel0, limits=False)
    assert limit[1, 8].item() == pytest.approx(-300.0)
    gen = torch.Generator().manual_seed(4)
    actions = torch.tanh(0.7 * torch.randn(2, 2, 6, generator=gen, dtype=torch.float64))

    def f(a, q, v):
        return rollout_return(env, q, v, a)

    pairs = directional_fd_check(f, [actions, qpos0, qvel0], n_dirs=2, eps=1e-6, rtol=1e-6, seed=1)
    assert any(abs(ad) > 1e-1 for ad, _ in pairs)


@pytest.mark.parametrize("name", [pytest.param(t, marks=pytest.mark.slow) if t in ("humanoid", "cheetah", "ant") else t
                                  for t in tasks.TASKS])
def test_gradients_finite_short_windows(name):
    """CI variant of the 1000-step check: 64 steps of random actions in windows of 32 (SHAC-style, detach at
    window starts) on 8 envs, resets included; every window's action gradient is finite and non-zero."""
    env = tasks.make(name, 8, seed=1)
    env.reset()
    gen = torch.Generator().manual_seed(0)
    for _ in range(2):
        env.detach()
        acts = torch.tanh(torch.randn(32, 8, env.num_act, generator=gen)).requires_grad_(True)
        total = sum(env.step(a)[1].sum() for a in acts)
        (g,) = torch.autograd.grad(total, acts)
        assert torch.isfinite(g).all(), f"{name}: non-finite action gradient"
        assert g.abs().sum() > 0


@pytest.mark.slow
@pytest.mark.parametrize("name", tasks.TASKS)
def test_gradients_finite_1000_steps_64_envs(name):
    """The full check: 1000 steps of random actions on 64 envs, backprop windows of 32 steps."""
    env = tasks.make(name, 64, seed=2)
    env.reset()
    gen = torch.Generator().manual_seed(0)
    for _ in range(1000 // 32 + 1):
        env.detach()
        acts = torch.tanh(torch.randn(32, 64, env.num_act, generator=gen)).requires_grad_(True)
        total = sum(env.step(a)[1].sum() for a in acts)
        (g,) = torch.autograd.grad(total, acts)
        assert torch.isfinite(g).all(), f"{name}: non-finite action gradient"


def test_chained_substep_copies_give_the_fan_out_gradients():
    """The compiled path hands tau and the cached mass matrix from substep to substep as copies (so that their
    gradient sums happen inside each compiled backward); without compiling, that chain must give the plain
    fan-out's return and action gradients (float64, the ant through contact, mass matrix cached over 4
    substeps so that M is both handed on and refactorised)."""
    import functools

    results = []
    for copy in (False, True):
        task = tasks.make("ant", 3, dtype=torch.float64, seed=5, substeps=8, mass_matrix_every=4)
        task.reset()
        task._substep = functools.partial(task._chained_substep, copy=copy)
        acts = torch.linspace(-0.9, 0.9, 4 * 3 * task.num_act, dtype=torch.float64).reshape(4, 3, task.num_act)
        acts.requires_grad_(True)
        total = sum(task.step(a)[1].sum() for a in acts)
        (g,) = torch.autograd.grad(total, acts)
        results.append((total.detach(), g))
    assert torch.equal(results[0][0], results[1][0])
    torch.testing.assert_close(results[1][1], results[0][1], rtol=1e-12, atol=1e-12)
    assert results[0][1].abs().max() > 0


@pytest.mark.slow
@pytest.mark.parametrize("name", ["cartpole", "ant"])
def test_compiled_step_matches_eager(name):
    """Task.compile() (fullgraph, no graph breaks) gives the eager observations, rewards, resets and action
    gradients (float32 tolerances; the compiled kernels reassociate sums)."""
    eager = tasks.make(name, 4, seed=3, episode_length=3)
    compiled = tasks.make(name, 4, seed=3, episode_length=3).compile(fullgraph=True)
    gen = torch.Generator().manual_seed(0)
    acts = torch.tanh(torch.randn(5, 4, eager.num_act, generator=gen))
    results = []
    for env in (eager, compiled):
        env.reset()
        a = acts.clone().requires_grad_(True)
        out = [env.step(x) for x in a]
        total = sum(o[1].sum() for o in out)
        (g,) = torch.autograd.grad(total, a)
        results.append((torch.stack([o[0] for o in out]), torch.stack([o[2] for o in out]), total, g))
    (o1, d1, r1, g1), (o2, d2, r2, g2) = results
    assert torch.equal(d1, d2) and d1.any()  # the same resets (episode_length 3), through the compiled reset
    assert torch.allclose(o1, o2, rtol=1e-4, atol=1e-4)
    assert torch.allclose(r1, r2, rtol=1e-5)
    assert torch.allclose(g1, g2, rtol=1e-3, atol=1e-3 * g1.abs().max())


def test_row_gather_backward_is_the_scatter_sum_as_a_gather():
    """RowGather's compiled-path backward (for each source row, a gather and sum of the output rows that came
    from it) equals indexing's scatter-add; a no-grad row gets none; float64 gradcheck; and it compiles."""
    from tasks.spatial import RowGather, _GatherRows

    idx = [2, 0, 2, 3, 2, 0]  # row 2 feeds three outputs, rows 1 and 4 none
    take = RowGather(idx, 5, device=torch.device("cpu"), no_grad_rows=(3,))
    assert take.width == 3
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(2, 5, 3, dtype=torch.float64, generator=gen, requires_grad=True)
    w = torch.randn(2, 6, 3, dtype=torch.float64, generator=gen)
    (expected,) = torch.autograd.grad((x[:, take.idx] * w).sum(), x)
    expected[:, 3] = 0.0  # the no-grad row
    out = _GatherRows.apply(x, take.idx, take.inv)
    assert torch.equal(out, x[:, take.idx])
    (got,) = torch.autograd.grad((out * w).sum(), x)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-14)
    assert got[:, 2].abs().sum() > 0 and got[:, 1].abs().sum() == 0
    full = RowGather(idx, 5, device=torch.device("cpu"))
    assert torch.autograd.gradcheck(lambda y: _GatherRows.apply(y, full.idx, full.inv) * w, (x,))
    compiled = torch.compile(lambda y: (full(y) * w).square().sum(), fullgraph=True, dynamic=False)
    (g_compiled,) = torch.autograd.grad(compiled(x), x)
    (g_eager,) = torch.autograd.grad((x[:, full.idx] * w).square().sum(), x)
    torch.testing.assert_close(g_compiled, g_eager, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="indices must lie in"):
        RowGather([0, 5], 5, device=torch.device("cpu"))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["hopper", "humanoid"])
def test_world_frames_backward_by_subtree_sums_equals_the_tree_walk(name):
    """_WorldFrames (depth-round products forward, subtree-sum backward) against plain autograd through the
    leaf-to-root recursion X_e = X_parent(e) P_e, float64, on the robot's real tree (entries: bodies, then
    pre-joint frames) with random rigid local frames; plus gradcheck. Compiled, it gives the same gradient."""
    from tasks.dynamics import _WorldFrames
    from tasks.spatial import quat_to_mat

    sim = tasks.make(name, 1, dtype=torch.float64).sim
    chain, parent, subtree = sim._chain, sim._entry_parent, sim._subtree
    E = chain.shape[1]
    gen = torch.Generator().manual_seed(1)
    B = 2

    def world(P):
        return _WorldFrames.apply(P, chain, parent, subtree, sim._eye4)

    def rigid(n):
        T = torch.eye(4, dtype=torch.float64).repeat(B, n, 1, 1)
        T[..., :3, :3] = quat_to_mat(torch.randn(B, n, 4, generator=gen, dtype=torch.float64))
        T[..., :3, 3] = torch.randn(B, n, 3, generator=gen, dtype=torch.float64)
        return T

    P = rigid(E).requires_grad_(True)
    w = torch.randn(B, E, 4, 4, generator=gen, dtype=torch.float64)

    def reference(P):
        X = [None] * E
        for e in sorted(range(E), key=lambda e: int((chain[:, e] < E).sum())):  # parents before children
            p = int(parent[e])
            X[e] = P[:, e] if p == E else X[p] @ P[:, e]
        return torch.stack(X, dim=1)

    X_ref = reference(P)
    X = world(P)
    torch.testing.assert_close(X, X_ref, rtol=1e-12, atol=1e-12)
    (g_ref,) = torch.autograd.grad((X_ref * w).sum(), P)
    (g,) = torch.autograd.grad((X * w).sum(), P)
    torch.testing.assert_close(g, g_ref, rtol=1e-10, atol=1e-10)
    assert int((chain < E).sum(0).max()) >= 4  # a tree deep enough for the subtree sums to matter
    P0 = rigid(E).requires_grad_(True)  # gradcheck's Jacobian is taken at a rigid point
    assert torch.autograd.gradcheck(world, (P0,))
    compiled = torch.compile(lambda p: (world(p) * w).sum(), dynamic=False)
    (g_compiled,) = torch.autograd.grad(compiled(P), P)
    torch.testing.assert_close(g_compiled, g_ref, rtol=1e-10, atol=1e-10)
