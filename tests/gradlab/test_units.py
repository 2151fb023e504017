"""Unit tests of gradlab's parts that need no simulator: targets, normaliser, gate, guards, checkpoints."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from gradlab.checkpoint import atomic_write_json, latest_checkpoint, load_checkpoint, save_checkpoint
from gradlab.critic import fit_critic, polyak_update, td_lambda_targets
from gradlab.networks import Critic, StateActor, VisualActor
from gradlab.normalizer import RunningMeanStd
from gradlab.probes import FiniteFlags, ImageGate, NonFiniteError, cosine, flat_grad, group_norms, image_sensitivity


def lambda_return_reference(r, v, d, gamma, lam):
    """Brute force: G^lambda_t = (1-lam) sum_{n<N} lam^(n-1) G^(n) + lam^(N-1) G^(N), N = steps to the end."""
    T, B = r.shape
    out = np.zeros((T, B))
    for b in range(B):
        for t in range(T):
            e = t
            while not d[e, b]:
                e += 1
            N = e - t + 1

            def G(n, t=t, b=b):
                return sum(gamma**k * r[t + k, b] for k in range(n)) + gamma**n * v[t + n - 1, b]

            out[t, b] = (1 - lam) * sum(lam ** (n - 1) * G(n) for n in range(1, N)) + lam ** (N - 1) * G(N)
    return out


def test_td_lambda_matches_bruteforce_lambda_return():
    rng = np.random.default_rng(0)
    T, B = 9, 5
    r = rng.normal(size=(T, B))
    v = rng.normal(size=(T, B))
    d = rng.random((T, B)) < 0.25
    d[-1] = True
    v[d & (rng.random((T, B)) < 0.5)] = 0.0  # some early terminations
    got = td_lambda_targets(torch.tensor(r), torch.tensor(v), torch.tensor(d), gamma=0.97, lam=0.9).numpy()
    np.testing.assert_allclose(got, lambda_return_reference(r, v, d, 0.97, 0.9), rtol=1e-12, atol=1e-12)


def test_td_lambda_zero_is_one_step():
    r, v = torch.randn(6, 3, dtype=torch.float64), torch.randn(6, 3, dtype=torch.float64)
    d = torch.zeros(6, 3, dtype=torch.bool)
    d[-1] = True
    got = td_lambda_targets(r, v, d, gamma=0.9, lam=0.0)
    torch.testing.assert_close(got, r + 0.9 * v)


def test_running_mean_std_matches_numpy_over_batches():
    rng = np.random.default_rng(1)
    x = rng.normal(3.0, 2.0, size=(50, 4))
    rms = RunningMeanStd(4, dtype=torch.float64, epsilon=1e-12)
    for chunk in np.array_split(x, 7):
        rms.update(torch.tensor(chunk))
    np.testing.assert_allclose(rms.mean.numpy(), x.mean(0), rtol=1e-9)
    np.testing.assert_allclose(rms.var.numpy(), x.var(0), rtol=1e-9)
    mean, std = rms.snapshot()
    y = RunningMeanStd.apply(torch.tensor(x), (mean, std), clip=100.0)
    np.testing.assert_allclose(y.mean(0).numpy(), 0.0, atol=1e-6)


def test_image_gate_switches_gradient_at_backward_time():
    x = torch.randn(3, requires_grad=True)
    gate = ImageGate()
    img = x * 2.0
    y = (gate(img) * x).sum()  # two paths into x: through the gated image and directly
    gate.open = True
    (g_open,) = torch.autograd.grad(y, x, retain_graph=True)
    gate.open = False
    (g_closed,) = torch.autograd.grad(y, x)
    torch.testing.assert_close(g_open, 4 * x.detach())  # d/dx (2x * x) = 4x
    torch.testing.assert_close(g_closed, 2 * x.detach())  # image treated as a constant 2x
    # Closed gate equals an explicit detach.
    (g_detach,) = torch.autograd.grad(((x * 2.0).detach() * x).sum(), x)
    torch.testing.assert_close(g_closed, g_detach)


def test_closed_gate_skips_the_renderers_recompute(monkeypatch):
    """A probe's decoupled pass must not pay for a render backward: with the gate closed the tiled
    renderer's backward gets no gradient and recomputes nothing (it used to recompute against zeros)."""
    import diffrender as dr
    from diffrender.raster import tiled

    calls = []
    kernel = tiled.render_pairs
    monkeypatch.setattr(tiled, "render_pairs", lambda *a, **k: (calls.append(1), kernel(*a, **k))[1])
    verts = (torch.tensor([[-0.5, 0.0, 0.3], [0.5, 0.0, 0.3], [0.0, 0.0, 1.0]], dtype=torch.float64)[None]
             .repeat(2, 1, 1).requires_grad_())
    cam = dr.Camera.look_at(torch.tensor([[0.0, -3.0, 0.7]], dtype=torch.float64),
                            torch.tensor([0.0, 0.0, 0.6], dtype=torch.float64), (0.0, 0.0, 1.0), 40.0, 6, 6)
    img = dr.render(verts, torch.tensor([[0, 1, 2]]), torch.full((3, 3), 0.5, dtype=torch.float64), cam,
                    dr.RasterSettings(backend="tiled", sigma=1.0, gamma=0.05, cull_backfaces=False))
    assert len(calls) == 1
    gate = ImageGate(open=False)
    loss = gate(img).square().sum() + verts.square().sum()
    loss.backward(retain_graph=True)
    assert len(calls) == 1 and torch.equal(verts.grad, 2 * verts.detach())
    verts.grad = None
    gate.open = True
    loss.backward()
    assert len(calls) == 2 and not torch.equal(verts.grad, 2 * verts.detach())


def test_cosine_and_flat_grad():
    a = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    assert float(cosine(a, a)) == pytest.approx(1.0)
    assert float(cosine(a, -a)) == pytest.approx(-1.0)
    assert float(cosine(a, torch.zeros(3, dtype=torch.float64))) == 0.0
    net = torch.nn.Linear(2, 2)
    net(torch.ones(1, 2)).sum().backward()
    assert flat_grad(net.parameters()).shape == (6,)


def test_param_groups_partition_the_actors_parameters():
    actors = (VisualActor(9, 16, 16, act_dim=2, trunk_dim=4, hidden=(5,)), StateActor(7, 2, (6, 3)))
    for actor, names in zip(actors, (["encoder", "mlp", "log_std"], ["mlp", "log_std"])):
        groups = actor.param_groups()
        assert list(groups) == names
        grouped = [id(p) for ps in groups.values() for p in ps]
        assert sorted(grouped) == sorted(id(p) for p in actor.parameters())  # each parameter exactly once


def test_group_norms_squares_sum_to_the_total():
    torch.manual_seed(1)
    actor = VisualActor(9, 16, 16, act_dim=2, trunk_dim=4, hidden=(5,)).double()
    params = list(actor.parameters())
    vec = torch.randn(sum(p.numel() for p in params), dtype=torch.float64)
    norms = group_norms(vec, params, actor.param_groups())
    assert sum(float(n) ** 2 for n in norms.values()) == pytest.approx(float(vec.norm()) ** 2, rel=1e-12)
    # log_std is one parameter: its norm is that slice's norm, wherever it sits in the flat vector.
    start = sum(p.numel() for p in params[:params.index(actor.log_std)])
    assert float(norms["log_std"]) == pytest.approx(float(vec[start:start + 2].norm()), rel=1e-12)
    with pytest.raises(ValueError, match="vec has 3 entries"):
        group_norms(vec[:3], params, actor.param_groups())


def test_image_sensitivity_is_the_per_frame_input_gradient_norm():
    torch.manual_seed(2)
    actor = VisualActor(9, 16, 16, act_dim=2, trunk_dim=6, hidden=(5,)).double()
    images = torch.rand(3, 9, 16, 16, dtype=torch.float64)
    got = image_sensitivity(actor.mean, images, frames=3)
    assert got.shape == (3,)
    # By hand: one environment and one frame at a time.
    want = torch.zeros(3, dtype=torch.float64)
    for b in range(3):
        x = images[b:b + 1].clone().requires_grad_(True)
        (g,) = torch.autograd.grad(actor.mean(x).sum(), x)
        for i in range(3):
            want[i] += g[0, 3 * i:3 * i + 3].norm() / 3
            # The norm is the directional derivative along the gradient's direction (central differences).
            v = torch.zeros_like(images[b:b + 1])
            v[0, 3 * i:3 * i + 3] = g[0, 3 * i:3 * i + 3] / g[0, 3 * i:3 * i + 3].norm()
            eps, x0 = 1e-6, images[b:b + 1]
            with torch.no_grad():
                fd = (actor.mean(x0 + eps * v).sum() - actor.mean(x0 - eps * v).sum()) / (2 * eps)
            assert float(fd) == pytest.approx(float(g[0, 3 * i:3 * i + 3].norm()), rel=1e-5)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=0)
    assert all(p.grad is None for p in actor.parameters())  # nothing accumulated in the parameters
    # A policy that cannot see: zero sensitivity to every frame.
    blind = image_sensitivity(lambda x: actor.mean(torch.zeros_like(x)) + 0 * x.sum(), images, frames=3)
    assert torch.equal(blind, torch.zeros(3, dtype=torch.float64))


def test_finite_flags_name_step_and_tensor():
    flags = FiniteFlags(4, ["qpos", "reward"], torch.device("cpu"))
    flags.check(0, "reward", torch.ones(3))
    flags.check(2, "reward", torch.tensor([1.0, float("nan")]))
    flags.check(3, "reward", torch.tensor([float("inf")]))
    with pytest.raises(NonFiniteError, match=r"iteration 7: non-finite forward value at horizon step 2 in reward"):
        flags.raise_if_bad(7)
    flags.reset()
    flags.raise_if_bad(8)  # clean after reset

    # Backward: the NaN is born at the latest step and flows to the earlier ones.
    x = torch.ones(2, requires_grad=True)
    q1 = x * 1.0
    q2 = q1 * 1.0
    flags.watch_grad(1, "qpos", q1)
    flags.watch_grad(3, "qpos", q2)
    (q2 * torch.tensor([float("nan"), 1.0])).sum().backward()
    with pytest.raises(NonFiniteError, match=r"gradient born at horizon step 3 in d\(loss\)/d\(qpos\)"):
        flags.raise_if_bad(9)
    with pytest.raises(KeyError):
        flags.check(0, "unknown", torch.ones(1))


def test_finite_flags_extra_scalars():
    flags = FiniteFlags(2, ["a"], torch.device("cpu"))
    with pytest.raises(NonFiniteError, match="non-finite actor loss"):
        flags.raise_if_bad(0, {"actor loss": torch.tensor(float("nan")), "ok": torch.tensor(1.0)})


def test_networks_shapes_and_action_range():
    torch.manual_seed(0)
    actor = VisualActor(9, 32, 32, act_dim=3, trunk_dim=16, hidden=(8, 8))
    a = actor(torch.rand(5, 9, 32, 32))
    assert a.shape == (5, 3) and bool((a.abs() <= 1).all())
    assert torch.equal(actor(torch.rand(5, 9, 32, 32), deterministic=True).abs() <= 1, torch.ones(5, 3, dtype=bool))
    assert float(actor.log_std.detach().mean()) == pytest.approx(-1.0)
    s = StateActor(7, 2, (16,))
    assert s(torch.randn(4, 7)).shape == (4, 2)
    c = Critic(7, (16, 16))
    assert c(torch.randn(4, 7)).shape == (4,)
    with pytest.raises(ValueError, match="too small"):
        VisualActor(9, 8, 8, act_dim=1, trunk_dim=4, hidden=(4,))


def test_encoder_channels_last_equals_plain_convolutions():
    """The encoder runs NHWC for cuDNN; values and gradients must be those of the plain NCHW network."""
    torch.manual_seed(0)
    enc = VisualActor(9, 21, 21, act_dim=2, trunk_dim=8, hidden=(4,)).encoder.double()
    images = torch.rand(3, 9, 21, 21, dtype=torch.float64, requires_grad=True)

    def plain(x):
        h = x - 0.5
        for m in enc.convs:
            h = torch.relu(h) if isinstance(m, torch.nn.ReLU) else torch.nn.functional.conv2d(
                h, m.weight.contiguous(), m.bias, m.stride)
        return enc.trunk(h.reshape(h.shape[0], -1))

    assert enc.convs[0].weight.is_contiguous(memory_format=torch.channels_last)
    out, ref = enc(images), plain(images.contiguous())
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
    w = torch.randn_like(out)
    g = torch.autograd.grad((out * w).sum(), [images, enc.convs[2].weight])
    g_ref = torch.autograd.grad((ref * w).sum(), [images, enc.convs[2].weight])
    for a, b in zip(g, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_fit_critic_reduces_loss_and_polyak():
    torch.manual_seed(0)
    critic = Critic(3, (32, 32))
    opt = torch.optim.Adam(critic.parameters(), lr=1e-2)
    obs = torch.randn(256, 3)
    y = obs[:, 0] * 2.0 - obs[:, 1]
    before = (critic(obs) - y).square().mean().item()
    last = fit_critic(critic, opt, obs, y, iterations=30, batches=4, grad_clip=1.0)
    assert float(last) < 0.2 * before
    target = Critic(3, (32, 32))
    src = [p.clone() for p in target.parameters()]
    polyak_update(target, critic, 0.25)
    for pt, ps, p0 in zip(target.parameters(), critic.parameters(), src):
        torch.testing.assert_close(pt, 0.25 * p0 + 0.75 * ps)


def test_atomic_checkpoint_roundtrip(tmp_path):
    save_checkpoint(tmp_path / "ckpt_000002.pt", {"a": torch.arange(3)})
    save_checkpoint(tmp_path / "ckpt_000010.pt", {"a": torch.arange(4)})
    (tmp_path / "ckpt_bad.pt").write_text("x")
    assert latest_checkpoint(tmp_path).name == "ckpt_000010.pt"
    assert torch.equal(load_checkpoint(latest_checkpoint(tmp_path))["a"], torch.arange(4))
    atomic_write_json(tmp_path / "x.json", {"b": 1})
    assert json.loads((tmp_path / "x.json").read_text()) == {"b": 1}
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_saved_tensor_bytes_counts_live_saved_storage_once():
    from gradlab.timing import SavedTensorMeter

    x = torch.randn(1000, requires_grad=True)  # 4000 bytes
    with SavedTensorMeter() as s:
        y = x.exp()  # saves its result (4000 B)
        z = (y * y).sum()  # saves y twice: one storage
        w = x.sin().sum()  # saves x (another 4000 B)
        with torch.no_grad():
            x.cos()  # nothing saved
    assert s.bytes == 8000
    with SavedTensorMeter() as s2:
        (x.exp() * 2).sum()  # graph dropped at once: nothing kept for backward
    assert s2.bytes == 0
    del z, w
