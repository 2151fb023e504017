"""MemberStack: N members evaluated together equal each member evaluated alone, forward and backward."""

import pytest
import torch

from gradlab.networks import Critic, MemberStack, StateActor, VisualActor


def _members(kind: str, n: int) -> list[torch.nn.Module]:
    out = []
    for seed in range(n):
        torch.manual_seed(seed)
        if kind == "visual":
            m = VisualActor(9, 16, 16, 3, trunk_dim=16, hidden=(8, 6), init="default")
        elif kind == "state":
            m = StateActor(11, 3, (8, 6), init="orthogonal")
        else:
            m = Critic(11, (8, 6))
        out.append(m.double())
    return out


def _inputs(kind: str, n: int, b: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(5)
    shape = (n * b, 9, 16, 16) if kind == "visual" else (n * b, 11)
    return torch.rand(shape, generator=g, dtype=torch.float64, requires_grad=True)


def _apply(stack: MemberStack, kind: str, params, x):
    return stack.value(params, x) if kind == "critic" else stack.mean(params, x)


def _grads(module) -> list[torch.Tensor]:
    return [torch.zeros_like(p) if p.grad is None else p.grad.clone() for p in module.parameters()]


def _alone(member, kind: str, x):
    return member(x) if kind == "critic" else member.mean(x)


@pytest.mark.parametrize("kind,batching", [("visual", "grouped"), ("visual", "loop"), ("visual", "modules"),
                                           ("state", "grouped"), ("critic", "grouped"), ("critic", "modules")])
def test_stacked_members_equal_each_member_alone_forward_and_backward(kind, batching):
    n, b = 3, 4
    members = _members(kind, n)
    stack = MemberStack(members, batching=batching)
    x = _inputs(kind, n, b)
    weights = torch.randn(_apply(stack, kind, stack.stack(), x.detach()).shape, dtype=torch.float64)
    out = _apply(stack, kind, stack.stack(), x)
    (out * weights).sum().backward()
    batched_grads = [_grads(m) for m in members]
    batched_x_grad = x.grad.clone()

    for m in members:
        m.zero_grad(set_to_none=True)
    x.grad = None
    for i, m in enumerate(members):
        rows = slice(i * b, (i + 1) * b)
        alone = _alone(m, kind, x[rows])
        torch.testing.assert_close(out[rows], alone, rtol=1e-12, atol=1e-12)
        (alone * weights[rows]).sum().backward()
        for g_batched, g_alone in zip(batched_grads[i], _grads(m)):
            torch.testing.assert_close(g_batched, g_alone, rtol=1e-11, atol=1e-12)
    torch.testing.assert_close(batched_x_grad, x.grad, rtol=1e-11, atol=1e-12)


def test_one_members_loss_gives_exactly_zero_gradient_to_the_others():
    n, b = 3, 2
    members = _members("visual", n)
    stack = MemberStack(members)
    out = stack.mean(stack.stack(), _inputs("visual", n, b).detach())
    out[b:2 * b].sum().backward()  # member 1's rows only
    for i, m in enumerate(members):
        grads = [p.grad for p in m.parameters()]
        if i == 1:
            assert any(g is not None and g.abs().sum() > 0 for g in grads)
        else:
            assert all(g is None or torch.count_nonzero(g) == 0 for g in grads)


def test_a_single_member_runs_the_module_itself():
    (member,) = _members("visual", 1)
    stack = MemberStack([member])
    x = _inputs("visual", 1, 3).detach()
    assert stack.stack() == {}
    assert torch.equal(stack.mean({}, x), member.mean(x))


def test_members_of_different_shapes_or_kinds_are_refused():
    with pytest.raises(ValueError, match="shapes differ"):
        MemberStack([StateActor(11, 3, (8, 6)), StateActor(11, 3, (8, 7))])
    with pytest.raises(ValueError, match="one kind"):
        MemberStack([StateActor(11, 1, (8,)), Critic(11, (8,))])
    with pytest.raises(ValueError, match="member batching"):
        MemberStack([Critic(11, (8,))], batching="vmap")
