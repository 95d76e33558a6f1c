"""RangeUNet: shapes, (B, L) folding, azimuth-roll equivariance, condition channels, mask head, config."""

from __future__ import annotations

import pytest
import torch

from u4d_aug.config import config_from_dict, config_to_dict, load_config
from u4d_aug.errors import InputError
from u4d_aug.nn.unet import RangeUNet, UNetConfig, crop_columns

H, W = 16, 64


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


def angles() -> tuple[torch.Tensor, torch.Tensor]:
    return torch.linspace(0.05, -0.4, H), torch.linspace(3.1, -3.1, W)


def randomized(net: RangeUNet, seed: int = 0) -> RangeUNet:
    """Give every weight (including the zero-initialised outputs) a random value so all paths carry signal."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=generator) * 0.2)
    return net.eval()


def test_shapes_and_zero_init_outputs(generator):
    net = RangeUNet(tiny(mask_head=True, fourier_features=True), *angles())
    x_t = torch.randn(2, 2, H, W, generator=generator)
    eps, logits = net(x_t, torch.tensor([0.0, 3.0]))
    assert eps.shape == (2, 2, H, W) and logits.shape == (2, 1, H, W)
    assert eps.abs().max() == 0 and logits.abs().max() == 0  # zero-init output convs
    eps, logits = RangeUNet(tiny())(x_t, torch.tensor(1.0))  # scalar log-SNR broadcasts
    assert eps.shape == (2, 2, H, W) and logits is None


def test_sequences_fold_frames_into_the_batch(generator):
    net = randomized(RangeUNet(tiny(cond_channels=3, mask_head=True)))
    x_t = torch.randn(2, 3, 2, H, W, generator=generator)  # (B, L, C, H, W)
    cond = torch.randn(2, 3, 3, H, W, generator=generator)
    log_snr = torch.tensor([-2.0, 4.0])
    eps, logits = net(x_t, log_snr, cond)
    assert eps.shape == (2, 3, 2, H, W) and logits.shape == (2, 3, 1, H, W)
    frame_eps, frame_logits = net(x_t[:, 1], log_snr, cond[:, 1])
    assert torch.allclose(eps[:, 1], frame_eps, atol=1e-5)
    assert torch.allclose(logits[:, 1], frame_logits, atol=1e-5)


@pytest.mark.parametrize("shift", [4, 12, 36])
def test_azimuth_roll_equivariance(shift, generator):
    """Rolling the scan along W by a multiple of the total downsampling rolls ε̂ and the mask the same way."""
    net = randomized(RangeUNet(tiny(mask_head=True, cond_channels=3)))
    assert shift % net.cfg.downsampling_factor == 0
    x_t = torch.randn(1, 2, H, W, generator=generator)
    cond = torch.randn(1, 3, H, W, generator=generator)
    log_snr = torch.tensor([1.5])
    eps, logits = net(x_t, log_snr, cond)
    eps_r, logits_r = net(torch.roll(x_t, shift, -1), log_snr, torch.roll(cond, shift, -1))
    scale = eps.abs().max().item()
    assert scale > 0
    assert torch.allclose(eps_r, torch.roll(eps, shift, -1), atol=1e-4 * scale)
    assert torch.allclose(logits_r, torch.roll(logits, shift, -1), atol=1e-4 * logits.abs().max().item())
    # elevation is not a ring: flipping rows is not a symmetry (zero padding, top and bottom differ)
    eps_f, _ = net(torch.flip(x_t, (-2,)), log_snr, torch.flip(cond, (-2,)))
    assert not torch.allclose(eps_f, torch.flip(eps, (-2,)), atol=1e-3 * scale)


def test_fourier_features_break_roll_symmetry(generator):
    net = randomized(RangeUNet(tiny(fourier_features=True), *angles()))
    x_t = torch.zeros(1, 2, H, W)  # a constant image: without position codes every column would be equal
    eps, _ = net(x_t, torch.tensor([0.0]))
    assert eps.std(dim=-1).max() > 1e-3


def test_condition_channels_are_read(generator):
    net = randomized(RangeUNet(tiny(cond_channels=3)))
    x_t = torch.randn(1, 2, H, W, generator=generator)
    x0_u = torch.full((1, 2, H, W), -1.0)
    m_u = torch.zeros(1, 1, H, W)
    eps_a, _ = net(x_t, torch.tensor([0.0]), torch.cat([x0_u, m_u], 1))
    x0_u[..., 5, 10:20] = 0.3
    m_u[..., 5, 10:20] = 1.0
    eps_b, _ = net(x_t, torch.tensor([0.0]), torch.cat([x0_u, m_u], 1))
    assert (eps_a - eps_b).abs().max() > 1e-3


def test_log_snr_is_read(generator):
    net = randomized(RangeUNet(tiny()))
    x_t = torch.randn(1, 2, H, W, generator=generator)
    assert not torch.allclose(net(x_t, torch.tensor([-5.0]))[0], net(x_t, torch.tensor([5.0]))[0])


def test_every_parameter_gets_a_gradient(generator):
    net = randomized(RangeUNet(tiny(mask_head=True, cond_channels=3, fourier_features=True), *angles())).train()
    eps, logits = net(torch.randn(2, 2, H, W, generator=generator), torch.zeros(2), torch.randn(2, 3, H, W))
    (eps.square().mean() + logits.mean()).backward()
    missing = [n for n, p in net.named_parameters() if p.grad is None or p.grad.abs().sum() == 0]
    assert not missing


def test_bad_inputs_raise_clear_errors():
    net = RangeUNet(tiny(cond_channels=3))
    with pytest.raises(InputError, match="multiples of 4"):
        net(torch.zeros(1, 2, 15, W), torch.zeros(1), torch.zeros(1, 3, 15, W))
    with pytest.raises(ValueError, match="cond"):
        net(torch.zeros(1, 2, H, W), torch.zeros(1))
    with pytest.raises(ValueError, match="channels"):
        net(torch.zeros(1, 3, H, W), torch.zeros(1), torch.zeros(1, 3, H, W))
    with pytest.raises(InputError, match="ray angles"):
        RangeUNet(tiny(fourier_features=True))
    with_angles = RangeUNet(tiny(fourier_features=True), *angles())
    with pytest.raises(InputError, match="ray-angle grid"):
        with_angles(torch.zeros(1, 2, H, 2 * W), torch.zeros(1))
    with pytest.raises(InputError, match="gn_groups"):
        RangeUNet(tiny(base_channels=6))


def test_task_is_checked_as_an_int_or_by_a_tensors_values_and_an_int_sizes_the_net_on_meta():
    net = RangeUNet(tiny(num_tasks=2))
    x_t = torch.zeros(2, 2, H, W)
    with pytest.raises(ValueError, match="needs task"):
        net(x_t, torch.zeros(2))
    with pytest.raises(ValueError, match=r"task must be in 0..1, got 2"):
        net(x_t, torch.zeros(2), task=2)
    with pytest.raises(ValueError, match=r"task must be in 0..1, got \[0, -1\]"):
        net(x_t, torch.zeros(2), task=torch.tensor([0, -1]))
    assert net(x_t, torch.zeros(2), task=torch.tensor([0, 1]))[0].shape == x_t.shape
    on_meta = RangeUNet(tiny(num_tasks=2)).to("meta")
    eps, _ = on_meta(x_t.to("meta"), torch.zeros(2, device="meta"), task=1)  # as FLOP counting on meta does
    assert eps.shape == x_t.shape and eps.device.type == "meta"


def test_config_defaults_and_checks():
    cfg = UNetConfig()
    assert cfg.num_res_blocks == (2, 2, 2, 2) and cfg.downsampling_factor == 8
    assert UNetConfig(num_res_blocks=(1, 2, 2, 3)).num_res_blocks == (1, 2, 2, 3)
    with pytest.raises(InputError, match="num_res_blocks"):
        UNetConfig(num_res_blocks=(1, 2))
    with pytest.raises(InputError, match="dropout"):
        UNetConfig(dropout=1.5)


def test_config_loads_from_overrides_and_round_trips():
    cfg = load_config(UNetConfig, overrides=["num_res_blocks=3", "channel_multipliers=[1, 2]", "mask_head=true"])
    assert cfg.num_res_blocks == (3, 3) and cfg.mask_head
    assert config_from_dict(UNetConfig, config_to_dict(cfg)) == cfg


def test_golden_output_without_most_and_no_most_modules():
    """Numbers recorded before the MoST blocks were added: a net with most=False computes what it did then."""
    torch.manual_seed(0)
    cfg = tiny(mask_head=True, cond_channels=3, fourier_features=True, num_res_blocks=2)
    net = RangeUNet(cfg, *angles())
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(torch.randn(p.shape, generator=generator) * 0.2)
        x_t = torch.randn(2, 3, 2, H, W, generator=generator)
        cond = torch.randn(2, 3, 3, H, W, generator=generator)
        eps, logits = net.train()(x_t, torch.tensor([-1.0, 2.0]), cond)
    assert float(eps.double().abs().mean()) == pytest.approx(0.7960736616779513, rel=1e-5)
    assert float(eps[0, 1, 0, 3, 5]) == pytest.approx(-0.3852289319038391, rel=1e-4)
    assert float(logits.double().mean()) == pytest.approx(-1.1508832460950014, rel=1e-5)
    assert net.most_names == [] and net.gate_weights().shape == (0, 2) and float(net.most_aux_loss()) == 0.0
    assert not any("most" in name for name in net.state_dict())


def test_crop_of_a_periodic_panorama_equals_the_panorama_at_its_columns(generator):
    """A crop is padded as a ring of its own: on a panorama that repeats every crop width, the crop sees exactly the
    neighbourhoods (and, for attention, the keys) the panorama has, so the net's output is the panorama's columns."""
    net = randomized(RangeUNet(tiny(mask_head=True, cond_channels=3)))
    crop = W // 4
    x_t = torch.randn(2, 2, H, crop, generator=generator).repeat(1, 1, 1, 4)  # period = crop width
    cond = torch.randn(2, 3, H, crop, generator=generator).repeat(1, 1, 1, 4)
    log_snr = torch.tensor([0.5, -1.0])
    eps, logits = net(x_t, log_snr, cond)
    offsets = torch.tensor([0, 3 * net.cfg.downsampling_factor])
    columns = crop_columns(offsets, crop, W)  # (2, crop)
    pick = lambda t: torch.stack([t[i][..., columns[i]] for i in range(2)])  # noqa: E731
    eps_c, logits_c = net(pick(x_t), log_snr, pick(cond), crop_offsets=offsets)
    assert eps_c.shape == (2, 2, H, crop)
    assert torch.allclose(eps_c, pick(eps), atol=1e-4 * eps.abs().max().item())
    assert torch.allclose(logits_c, pick(logits), atol=1e-4 * logits.abs().max().item())


def test_crop_reads_the_ray_features_at_its_columns(generator):
    """A full-width crop starting at column k is the panorama rolled by k: with the ray features read at the crop's
    columns the output is the rolled output (without them the first column would get column 0's angles)."""
    net = randomized(RangeUNet(tiny(fourier_features=True), *angles()))
    x_t = torch.randn(1, 2, H, W, generator=generator)
    log_snr = torch.tensor([1.0])
    eps, _ = net(x_t, log_snr)
    shift = 3 * net.cfg.downsampling_factor
    eps_c, _ = net(torch.roll(x_t, -shift, -1), log_snr, crop_offsets=torch.tensor([shift]))
    assert torch.allclose(eps_c, torch.roll(eps, -shift, -1), atol=1e-4 * eps.abs().max().item())
    eps_wrong, _ = net(torch.roll(x_t, -shift, -1), log_snr, crop_offsets=torch.tensor([0]))
    assert not torch.allclose(eps_wrong, torch.roll(eps, -shift, -1), atol=1e-2 * eps.abs().max().item())
    with pytest.raises(InputError, match="azimuth crop and needs crop_offsets"):
        net(x_t[..., : W // 2], log_snr)  # a narrower image without offsets
