"""MoST block: temporal conv == conv3d, gates, CV² loss, gate noise, frame mixing inside the RangeUNet."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from u4d_aug.diffusion import DiffusionConfig, GaussianDiffusion
from u4d_aug.errors import InputError
from u4d_aug.nn.most import MoSTBlock, cv_squared, temporal_conv
from u4d_aug.nn.unet import RangeUNet, UNetConfig

H, W, E = 16, 64, 12


def randomized(module: torch.nn.Module, seed: int = 0, scale: float = 0.2) -> torch.nn.Module:
    """Random values for every weight, the zero-initialised ones included, so every path carries signal."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=generator) * scale)
    return module


def tiny(**overrides) -> UNetConfig:
    base = dict(
        base_channels=8,
        channel_multipliers=(1, 2, 2),
        num_res_blocks=1,
        attention=True,
        attention_heads=2,
        fourier_features=False,
        gn_groups=4,
    )
    base.update(overrides)
    return UNetConfig(**base)


# ---------------------------------------------------------------------------------------------- block level


@pytest.mark.parametrize("kernel_t", [1, 3, 5])
def test_temporal_conv_equals_conv3d_along_frames(kernel_t, generator):
    batch, frames, channels = 2, 4, 3
    x = torch.randn(batch * frames, channels, 5, 7, generator=generator)
    weight3d = torch.randn(6, channels, kernel_t, 1, 1, generator=generator)
    bias = torch.randn(6, generator=generator)
    reference = F.conv3d(x.unflatten(0, (batch, frames)).transpose(1, 2), weight3d, bias, padding=(kernel_t // 2, 0, 0))
    weight2d = weight3d.permute(0, 2, 1, 3, 4).reshape(6, kernel_t * channels, 1, 1)  # block j = tap j
    out = temporal_conv(x, weight2d, bias, frames)
    torch.testing.assert_close(out, reference.transpose(1, 2).flatten(0, 1), atol=1e-5, rtol=1e-5)


def test_single_frame_temporal_conv_sees_only_itself(generator):
    """L = 1: zero padding leaves only the centre tap, a 1x1 conv of the frame itself."""
    x = torch.randn(3, 4, 5, 6, generator=generator)
    weight = torch.randn(4, 3 * 4, 1, 1, generator=generator)
    out = temporal_conv(x, weight, None, frames=1)
    torch.testing.assert_close(out, F.conv2d(x, weight[:, 4:8]))


@pytest.mark.parametrize("frames", [1, 3])
def test_block_shapes_identity_at_init_and_gates(frames, generator):
    block = MoSTBlock(8, E, kernel_t=3, noise_std=0.5, groups=4).eval()
    x = torch.randn(2 * frames, 8, H, W, generator=generator)
    emb = torch.randn(2, E, generator=generator).repeat_interleave(frames, dim=0)
    assert torch.equal(block(x, emb, frames), x)  # zero-initialised branches: a new block is the identity
    assert torch.equal(block.last_gates, torch.full((2, 2), 0.5))  # zero-initialised gate: (½, ½)
    with (
        torch.random.fork_rng()
    ):  # the weights and train-mode gate noise from a fixed global seed, not the order of tests
        torch.manual_seed(0)
        randomized(block)
        _check_gates(block, x, emb, frames)


def _check_gates(block: MoSTBlock, x: torch.Tensor, emb: torch.Tensor, frames: int) -> None:
    """In eval and train mode: the randomized block changes x, its gates are probabilities, CV² is a live loss."""
    for mode in (block.eval(), block.train()):
        out = mode(x, emb, frames)
        assert out.shape == x.shape and not torch.allclose(out, x)
        gates = block.last_gates
        assert gates.shape == (2, 2) and not gates.requires_grad
        assert torch.all((gates > 0) & (gates < 1))
        torch.testing.assert_close(gates.sum(dim=1), torch.ones(2))
        # the CV² of the batch's gate importances (Shazeer et al. 2017): positive for these unequal gates, and a
        # loss that moves the gate net
        torch.testing.assert_close(block.last_cv.detach(), cv_squared(gates.sum(dim=0)))
        assert float(block.last_cv.detach()) > 1e-6
        block.zero_grad()
        block.last_cv.backward()
        assert float(block.gate[-1].weight.grad.abs().sum()) > 0


def test_branch_updates_are_recorded_only_when_asked(generator):
    block = randomized(MoSTBlock(8, E, kernel_t=3, noise_std=0.0, groups=4).eval())
    x = torch.randn(6, 8, H, W, generator=generator)
    emb = torch.randn(2, E, generator=generator).repeat_interleave(3, dim=0)
    out = block(x, emb, 3)
    assert block.last_updates is None  # training never pays for the norms
    block.record_updates = True
    torch.testing.assert_close(block(x, emb, 3), out)  # recording does not change the output
    alpha = block.last_gates.repeat_interleave(3, dim=0)[:, :, None, None, None]
    h = F.silu(block.norm(x))
    update_s = alpha[:, 0] * block.spatial(h)
    update_t = alpha[:, 1] * temporal_conv(h, block.temporal.weight, block.temporal.bias, 3)
    torch.testing.assert_close(out, x + update_s + update_t)
    rms = [v.square().mean().sqrt() for v in (x, update_s, update_t)]
    torch.testing.assert_close(block.last_updates, torch.stack(rms))


def test_block_rejects_a_batch_that_is_not_whole_sequences():
    block = MoSTBlock(8, E, groups=4)
    with pytest.raises(ValueError, match="3-frame"):
        block(torch.zeros(4, 8, 4, 6), torch.zeros(4, E), frames=3)
    with pytest.raises(ValueError, match="kernel_t"):
        MoSTBlock(8, E, kernel_t=2, groups=4)


def test_cv_squared_is_zero_for_equal_importance_and_positive_otherwise():
    assert float(cv_squared(torch.tensor([2.0, 2.0]))) == 0.0
    assert float(cv_squared(torch.tensor([1.0, 3.0]))) == pytest.approx(0.25)  # var 1 / mean² 4
    assert float(cv_squared(torch.tensor([4.0, 0.0]))) == pytest.approx(1.0)  # collapsed onto one branch


def test_gate_noise_only_in_training_and_drawn_from_the_generator(generator):
    block = randomized(MoSTBlock(8, E, noise_std=0.5, groups=4))
    x = torch.randn(4, 8, H, W, generator=generator)
    emb = torch.randn(4, E, generator=generator)

    def gates(seed: int | None) -> torch.Tensor:
        return block.gates(x, emb, 2, None if seed is None else torch.Generator().manual_seed(seed))

    block.eval()
    clean = gates(0)
    assert torch.equal(clean, gates(1)) and torch.equal(clean, gates(None))
    block.train()
    assert torch.equal(gates(3), gates(3))  # same generator, same noise
    assert not torch.allclose(gates(3), gates(4))
    assert not torch.allclose(gates(3), clean)
    block.noise_std = 0.0
    assert torch.equal(gates(3), clean)


def test_gates_read_the_timestep_embedding(generator):
    block = randomized(MoSTBlock(8, E, groups=4)).eval()
    x = torch.randn(2, 8, H, W, generator=generator)
    a = block.gates(x, torch.zeros(2, E), 1)
    b = block.gates(x, torch.ones(2, E), 1)
    assert not torch.allclose(a, b)


# ------------------------------------------------------------------------------------------------- in the UNet


def test_unet_places_blocks_in_depth_order_and_reports_gates(generator):
    net = RangeUNet(tiny(most=True))
    assert net.most_names == ["enc0", "enc1", "enc2", "mid", "dec2", "dec1", "dec0"]
    assert [b.spatial.in_channels for b in net.most_blocks()] == [8, 16, 16, 16, 16, 16, 8]
    assert net.gate_weights().shape == (0, 2) and float(net.most_aux_loss()) == 0.0  # before any forward
    randomized(net).train()
    net(torch.randn(2, 3, 2, H, W, generator=generator), torch.zeros(2))
    gates = net.gate_weights()
    assert gates.shape == (7, 2)
    torch.testing.assert_close(gates.sum(dim=1), torch.ones(7))
    assert net.most_aux_loss().requires_grad and float(net.most_aux_loss().detach()) > 0
    subset = RangeUNet(tiny(most=True, most_levels=(1,)))
    assert subset.most_names == ["enc1", "dec1"]
    assert RangeUNet(tiny(most=True, most_levels=(2, 0))).most_names == ["enc0", "enc2", "mid", "dec2", "dec0"]


@pytest.mark.parametrize("frames", [1, 3])
def test_unet_shapes_with_most(frames, generator):
    net = randomized(RangeUNet(tiny(most=True, mask_head=True, cond_channels=3))).eval()
    eps, logits = net(torch.randn(2, frames, 2, H, W), torch.tensor([0.0, 1.0]), torch.randn(2, frames, 3, H, W))
    assert eps.shape == (2, frames, 2, H, W) and logits.shape == (2, frames, 1, H, W)
    eps, logits = net(torch.randn(2, 2, H, W), torch.tensor([0.0, 1.0]), torch.randn(2, 3, H, W))  # (B, C, H, W)
    assert eps.shape == (2, 2, H, W) and logits.shape == (2, 1, H, W)


def test_new_most_blocks_leave_the_net_unchanged(generator):
    """MoST modules are built last and start as the identity: same seed, same function as without MoST."""
    torch.manual_seed(3)
    plain = RangeUNet(tiny(mask_head=True))
    torch.manual_seed(3)
    with_most = RangeUNet(tiny(mask_head=True, most=True))
    for name, value in plain.state_dict().items():
        assert torch.equal(with_most.state_dict()[name], value)
    assert not any("most" in name for name in plain.state_dict())
    with torch.no_grad():  # non-zero outputs, so the comparison is not 0 == 0
        for net in (plain, with_most):
            net.out_conv.weight.fill_(0.01)
    x_t = torch.randn(2, 3, 2, H, W, generator=generator)
    a, b = plain(x_t, torch.zeros(2))[0], with_most.eval()(x_t, torch.zeros(2))[0]
    assert a.abs().max() > 0 and torch.equal(a, b)


@pytest.mark.parametrize("most", [False, True])
def test_temporal_branch_mixes_frames_only_with_most(most, generator):
    net = randomized(RangeUNet(tiny(most=most))).eval()
    x_t = torch.randn(1, 3, 2, H, W, generator=generator)
    changed = x_t.clone()
    changed[:, 0] += torch.randn(1, 2, H, W, generator=generator)
    log_snr = torch.tensor([0.5])
    with torch.no_grad():
        eps, eps_changed = net(x_t, log_snr)[0], net(changed, log_snr)[0]
    assert not torch.allclose(eps[:, 0], eps_changed[:, 0])
    difference = float((eps[:, 1] - eps_changed[:, 1]).abs().max())
    if most:
        assert difference > 1e-3  # frame 0 reaches frame 1 through the temporal convs
    else:
        assert difference == 0.0  # frames folded into the batch never meet


def test_single_frame_sequence_equals_the_frame(generator):
    net = randomized(RangeUNet(tiny(most=True))).eval()
    x_t = torch.randn(2, 2, H, W, generator=generator)
    torch.testing.assert_close(net(x_t[:, None], torch.zeros(2))[0][:, 0], net(x_t, torch.zeros(2))[0])


@pytest.mark.parametrize("shift", [4, 36])
def test_azimuth_roll_equivariance_with_most(shift, generator):
    net = randomized(RangeUNet(tiny(most=True))).eval().requires_grad_(False)
    x_t = torch.randn(1, 2, 2, H, W, generator=generator)
    eps = net(x_t, torch.tensor([1.0]))[0]
    eps_r = net(torch.roll(x_t, shift, -1), torch.tensor([1.0]))[0]
    torch.testing.assert_close(eps_r, torch.roll(eps, shift, -1), atol=1e-4 * float(eps.abs().max()), rtol=0)


def test_every_parameter_gets_a_gradient_with_most(generator):
    net = randomized(RangeUNet(tiny(most=True, mask_head=True))).train()
    eps, logits = net(torch.randn(2, 3, 2, H, W, generator=generator), torch.zeros(2), generator=generator)
    (eps.square().mean() + logits.mean() + net.most_aux_loss()).backward()
    missing = [n for n, p in net.named_parameters() if p.grad is None or p.grad.abs().sum() == 0]
    assert not missing


def test_diffusion_adds_the_weighted_cv_term(generator):
    net = randomized(RangeUNet(tiny(most=True, attention=False, channel_multipliers=(1, 2))), scale=0.1).train()
    x0 = torch.rand(2, 3, 2, H, W, generator=generator) * 2 - 1
    losses = GaussianDiffusion(net, DiffusionConfig(stage="baseline", most_cv_weight=0.5))(
        x0, generator=torch.Generator().manual_seed(1)
    )
    assert set(losses) == {"loss", "eps_mse", "most_cv"} and float(losses["most_cv"]) > 0
    torch.testing.assert_close(losses["loss"].detach(), losses["eps_mse"] + 0.5 * losses["most_cv"])
    again = GaussianDiffusion(net, DiffusionConfig(stage="baseline", most_cv_weight=0.5))(
        x0, generator=torch.Generator().manual_seed(1)
    )
    assert torch.equal(again["loss"], losses["loss"])  # t, ε and the gate noise all come from the generator
    plain = GaussianDiffusion(RangeUNet(tiny(attention=False, channel_multipliers=(1, 2))), DiffusionConfig())
    assert "most_cv" not in plain(x0, generator=torch.Generator().manual_seed(1))


def test_config_checks():
    with pytest.raises(InputError, match="most_levels"):
        tiny(most=True, most_levels=(3,))
    with pytest.raises(InputError, match="most_kernel_t"):
        tiny(most=True, most_kernel_t=4)
    with pytest.raises(InputError, match="most_gate_noise"):
        tiny(most=True, most_gate_noise=-1.0)
    with pytest.raises(InputError, match="most_cv_weight"):
        DiffusionConfig(most_cv_weight=-0.1)
    assert tiny(most_levels=[2, 0, 2]).most_levels == (0, 2)


@pytest.mark.parametrize("fusion", ["cascade", "add", "concat"])
def test_fusion_variants_start_as_identity_and_train_every_parameter(fusion, generator):
    block = MoSTBlock(8, E, groups=4, fusion=fusion)
    x = torch.randn(6, 8, H, W, generator=generator)  # 2 sequences of 3 frames
    emb = torch.randn(6, E, generator=generator)
    assert torch.equal(block(x, emb, 3), x)  # a new block of any fusion is the identity
    assert block.last_gates is None and block.last_cv is None  # only gating has gates
    assert not hasattr(block, "gate")
    for _ in range(2):  # step 1 moves the zero-initialised layers; step 2 reaches everything behind them
        out = block(x, emb, 3)
        assert out.shape == x.shape
        out.square().mean().backward()
        with torch.no_grad():
            for p in block.parameters():
                p -= 0.1 * p.grad
    block.zero_grad()
    block(x, emb, 3).square().mean().backward()
    dead = [name for name, p in block.named_parameters() if p.grad is None or p.grad.abs().max() == 0]
    assert not dead, dead


def test_fusion_variants_compute_what_they_name(generator):
    """add = x + F^s + F^t; concat = x + W[F^s; F^t]; cascade = the temporal branch on x + F^s(x)."""
    x = torch.randn(4, 8, H, W, generator=generator)  # 2 sequences of 2 frames
    emb = torch.randn(4, E, generator=generator)
    blocks = {f: randomized(MoSTBlock(8, E, groups=4, fusion=f), seed=1) for f in ("add", "concat", "cascade")}
    add = blocks["add"]
    h = F.silu(add.norm(x))
    f_s, f_t = add.spatial(h), temporal_conv(h, add.temporal.weight, add.temporal.bias, 2)
    torch.testing.assert_close(add(x, emb, 2), x + f_s + f_t)
    concat = blocks["concat"]  # same seed: same norm / branch weights as add, plus the fuse conv
    torch.testing.assert_close(concat(x, emb, 2), x + concat.fuse(torch.cat([f_s, f_t], dim=1)))
    cascade = blocks["cascade"]
    x_s = x + cascade.spatial(F.silu(cascade.norm(x)))
    h_t = F.silu(cascade.norm_t(x_s))
    expected = x_s + temporal_conv(h_t, cascade.temporal.weight, cascade.temporal.bias, 2)
    torch.testing.assert_close(cascade(x, emb, 2), expected)


@pytest.mark.parametrize("fusion", ["gating", "cascade", "add", "concat"])
def test_every_fusion_mixes_frames_in_the_unet(fusion, generator):
    net = randomized(RangeUNet(tiny(most=True, most_fusion=fusion))).eval()
    x_t = torch.randn(1, 3, 2, H, W, generator=generator)
    changed = x_t.clone()
    changed[:, 0] += torch.randn(1, 2, H, W, generator=generator)
    with torch.no_grad():
        eps, eps_changed = net(x_t, torch.tensor([0.5]))[0], net(changed, torch.tensor([0.5]))[0]
    assert eps.shape == (1, 3, 2, H, W)
    assert float((eps[:, 1] - eps_changed[:, 1]).abs().max()) > 1e-3
    assert net.gate_weights().shape == ((len(net.most_names), 2) if fusion == "gating" else (0, 2))


def test_fusion_is_checked():
    with pytest.raises(ValueError, match="fusion"):
        MoSTBlock(8, E, groups=4, fusion="mul")
    with pytest.raises(InputError, match="most_fusion"):
        tiny(most=True, most_fusion="mul")


@pytest.mark.parametrize("most", [False, True])
def test_ego_motion_conditions_each_frame_and_crosses_frames_only_with_most(most, generator):
    """A frame's pose changes that frame's output; other frames see it only through the temporal branch."""
    net = randomized(RangeUNet(tiny(most=most, pose_dim=4))).eval()
    x_t = torch.randn(1, 3, 2, H, W, generator=generator)
    poses = torch.tensor([[[0, 0, 0, 0], [1.2, 0.1, 0, 0.05], [2.4, 0.3, 0, 0.1]]])  # (B, L, 4)
    moved = poses.clone()
    moved[0, 2] = torch.tensor([3.5, -0.5, 0.1, -0.2])
    with torch.no_grad():
        eps, eps_moved = net(x_t, torch.tensor([0.5]), poses=poses)[0], net(x_t, torch.tensor([0.5]), poses=moved)[0]
    assert float((eps[:, 2] - eps_moved[:, 2]).abs().max()) > 1e-3
    other = float((eps[:, :2] - eps_moved[:, :2]).abs().max())
    assert (other > 1e-4) if most else (other == 0.0)


def test_pose_condition_starts_as_no_condition_and_is_required(generator):
    torch.manual_seed(0)
    plain = RangeUNet(tiny(most=True))
    torch.manual_seed(0)
    posed = RangeUNet(tiny(most=True, pose_dim=4))  # built last, zero-initialised output
    randomized(plain)
    with torch.no_grad():  # same weights everywhere but the pose MLP, whose output layer stays zero
        for name, p in posed.named_parameters():
            if not name.startswith("pose_embed."):
                p.copy_(dict(plain.named_parameters())[name])
            elif name.startswith("pose_embed.mlp.0"):
                p.copy_(torch.randn(p.shape, generator=generator))
    x_t = torch.randn(2, 3, 2, H, W, generator=generator)
    poses = torch.randn(2, 3, 4, generator=generator)
    torch.testing.assert_close(posed.eval()(x_t, torch.zeros(2), poses=poses)[0], plain.eval()(x_t, torch.zeros(2))[0])
    with pytest.raises(ValueError, match="needs poses"):
        posed(x_t, torch.zeros(2))
    with pytest.raises(ValueError, match="needs poses"):
        plain(x_t, torch.zeros(2), poses=poses)
    with pytest.raises(ValueError, match=r"poses must be \(B, \[L,\] 4\)"):
        posed(x_t, torch.zeros(2), poses=poses[:, :2])
