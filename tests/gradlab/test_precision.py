"""``--precision``: fp32 is the plain float32 computation bit for bit; bf16 runs the encoder's convolutions under
bfloat16 autocast (single encoder and every MemberStack batching) and keeps the trunk in float32; the option
reaches the networks from the config; the CPU and mixed populations are refused in one line."""

import dataclasses
import json

import pytest
import torch

from gradlab import precision
from gradlab.config import SHACConfig
from gradlab.networks import MemberStack, PixelEncoder, VisualActor
from gradlab.probes import cosine, flat_grad
from gradlab.shac import SHAC, check_population

TINY = SHACConfig(task="cartpole", num_envs=2, horizon=2, image_size=16, iters=1, cosine_every=0,
                  critic_iterations=1, critic_batches=1, episode_length=8)


@pytest.fixture(autouse=True)
def _process_precision_restored():
    yield
    precision.use("fp32", "cpu")


def _images(b: int = 4, size: int = 16, seed: int = 3) -> torch.Tensor:
    return torch.rand(b, 9, size, size, generator=torch.Generator().manual_seed(seed))


def _encoder(p: str, seed: int = 0) -> PixelEncoder:
    torch.manual_seed(seed)
    return PixelEncoder(9, 16, 16, 8, precision=p)


def test_fp32_encoder_is_the_plain_float32_computation_bit_for_bit():
    enc = _encoder("fp32")
    x = _images().requires_grad_(True)
    weights = torch.randn(4, 8, generator=torch.Generator().manual_seed(1))
    (enc(x) * weights).sum().backward()
    got = [enc(x).detach(), x.grad.clone(), *(p.grad.clone() for p in enc.parameters())]
    enc.zero_grad(set_to_none=True)
    x.grad = None
    # the encoder's computation as it is without any precision option
    plain = enc.trunk(enc.convs((x - 0.5).contiguous(memory_format=torch.channels_last)).flatten(1))
    (plain * weights).sum().backward()
    want = [plain.detach(), x.grad, *(p.grad for p in enc.parameters())]
    assert all(torch.equal(a, b) for a, b in zip(got, want, strict=True))


def test_the_autocast_context_is_a_static_choice_of_device_and_precision():
    for device in ("cuda", "cpu"):
        ctx = precision.encoder_autocast(device, "bf16")
        assert isinstance(ctx, torch.autocast) and ctx.fast_dtype == torch.bfloat16 and ctx.device == device
        for p in ("fp32", "tf32"):
            assert not isinstance(precision.encoder_autocast(device, p), torch.autocast)
    with pytest.raises(ValueError, match="--precision: unknown precision 'fp16'; valid: fp32, tf32, bf16"):
        precision.encoder_autocast("cuda", "fp16")
    assert precision.backend_flags("fp32") == {"matmul_allow_tf32": False, "cudnn_allow_tf32": True}  # the defaults
    assert precision.backend_flags("tf32") == {"matmul_allow_tf32": True, "cudnn_allow_tf32": True}
    assert precision.backend_flags("bf16") == precision.backend_flags("fp32")  # bf16 is the encoder's alone


def test_bf16_encoder_convolves_in_bfloat16_keeps_the_trunk_float32_and_its_gradient_agrees():
    seen = {}
    x = _images(8)
    weights = torch.randn(8, 8, generator=torch.Generator().manual_seed(1))
    grads, outs = {}, {}
    for p in ("fp32", "bf16"):
        enc = _encoder(p)  # the same seed: the same parameters
        enc.convs[0].register_forward_hook(lambda m, i, o, p=p: seen.__setitem__((p, "conv"), o.dtype))
        enc.trunk[0].register_forward_hook(lambda m, i, o, p=p: seen.__setitem__((p, "trunk"), i[0].dtype))
        outs[p] = enc(x)
        (outs[p] * weights).sum().backward()
        grads[p] = flat_grad(enc.parameters())
    assert seen == {("fp32", "conv"): torch.float32, ("fp32", "trunk"): torch.float32,
                    ("bf16", "conv"): torch.bfloat16, ("bf16", "trunk"): torch.float32}
    assert outs["bf16"].dtype == torch.float32 and not torch.equal(outs["bf16"], outs["fp32"])
    assert float(cosine(grads["bf16"], grads["fp32"])) > 0.99


@pytest.mark.parametrize("batching", MemberStack.BATCHINGS)
def test_every_member_batching_runs_the_encoder_in_its_precision(batching):
    n, b = 3, 4
    x = _images(n * b)
    out = {}
    for p in ("fp32", "bf16"):
        members = []
        for seed in range(n):
            torch.manual_seed(seed)
            members.append(VisualActor(9, 16, 16, 3, trunk_dim=8, hidden=(6,), init="default", precision=p))
        stack = MemberStack(members, batching=batching)
        out[p] = stack.mean(stack.stack(), x)
        alone = torch.cat([m.mean(x[i * b:(i + 1) * b]) for i, m in enumerate(members)])
        torch.testing.assert_close(out[p], alone, rtol=0, atol=1e-5 if p == "fp32" else 2e-2)
    assert out["bf16"].dtype == torch.float32 and not torch.equal(out["bf16"], out["fp32"])
    torch.testing.assert_close(out["bf16"], out["fp32"], rtol=0, atol=5e-2)


def test_member_stack_refuses_encoders_of_different_precisions():
    members = [VisualActor(9, 16, 16, 3, trunk_dim=8, hidden=(6,), precision=p) for p in ("fp32", "bf16")]
    with pytest.raises(ValueError, match=r"encoders differ in precision: \['bf16', 'fp32'\]"):
        MemberStack(members)


@pytest.mark.parametrize("p", precision.PRECISIONS)
def test_the_config_reaches_the_encoders_of_a_run_and_of_a_population(p):
    precision.use(p, "cpu", allow_cpu=True)  # as ablate's start-up does (which refuses tf32/bf16 on the CPU)
    single = SHAC([dataclasses.replace(TINY, precision=p)], device="cpu")
    population = SHAC([dataclasses.replace(TINY, precision=p, mode=m) for m in ("decoupled", "full")], device="cpu")
    assert single.members[0].actor.encoder.precision == p
    assert {m.actor.encoder.precision for m in population.members} == {p}
    for trainer in (single, population):
        rows = trainer.train_iteration()
        assert all(torch.isfinite(torch.tensor(r["grad_norm"])) for r in rows)


def test_the_cpu_trains_in_fp32_only_and_says_so_in_one_line():
    precision.use("fp32", "cpu")
    assert precision.current() == "fp32"
    for p in ("tf32", "bf16"):
        with pytest.raises(ValueError) as e:
            precision.use(p, "cpu")
        assert str(e.value) == (f"--precision {p} is for CUDA devices (TF32 and bfloat16 tensor cores); on cpu runs "
                                "train in fp32: drop --precision or give --precision fp32")
    assert precision.current() == "fp32"  # a refusal changes nothing
    with pytest.raises(ValueError, match="--precision: unknown precision 'half'"):
        SHAC([dataclasses.replace(TINY, precision="half")], device="cpu")


def test_a_population_shares_one_precision():
    cfgs = [dataclasses.replace(TINY, precision="fp32"), dataclasses.replace(TINY, precision="bf16", seed=1)]
    with pytest.raises(ValueError, match="the members of one population share --precision, got 'fp32' and 'bf16'"):
        check_population(cfgs)


@pytest.mark.slow
def test_ablate_records_the_precision_and_refuses_what_cannot_apply(tmp_path, capsys):
    from ablations.cli import ablate_main

    tiny = ["--task", "cartpole", "--num-envs", "2", "--horizon", "2", "--image-size", "16", "--critic-iterations",
            "1", "--critic-batches", "1", "--device", "cpu", "--no-progress", "--threads", "1", "--iters", "1",
            "--eval-every", "0", "--cosine-every", "0", "--out", str(tmp_path)]
    for args, message in ((["--precision", "bf16", "--seed", "0", "1"], "--precision bf16 is for CUDA devices"),
                          (["--member", "mode=full,seed=0,precision=bf16"], "not a member's own setting")):
        with pytest.raises(SystemExit) as e:
            ablate_main([*tiny, *args])
        err = capsys.readouterr().err
        assert e.value.code == 2 and message in err and len(err.strip().splitlines()) == 1
        assert not any(tmp_path.iterdir())  # nothing left behind
    ablate_main([*tiny, "--precision", "fp32", "--name", "run"])
    record = json.loads((tmp_path / "run" / "config.json").read_text())
    assert record["config"]["precision"] == "fp32"


def test_one_precision_flag_gives_every_member_of_a_seeded_population_its_value():
    from ablations.cli import ABLATE_GROUPS, parse
    from ablations.population import AblateConfig
    from ablations.run_config import shac_part
    from gradlab.config import resolve_config

    cfg = parse(AblateConfig, ["--task", "hopper", "--mode", "decoupled", "full", "--seed", "0", "1", "2", "3", "4",
                               "--precision", "bf16"], groups=ABLATE_GROUPS)
    members = cfg.members()
    assert len(members) == 10 and {m.precision for m in members} == {"bf16"}
    check_population([resolve_config(shac_part(m)) for m in members])  # one population
