"""RangeAutoencoder: shapes, input checks, ring equivariance, the losses of its forward on hand-made decoder
outputs, decoded_image, the latent statistics and an overfit of one tiny image."""

from __future__ import annotations

import math

import pytest
import torch

from u4d_aug.errors import InputError
from u4d_aug.nn.autoencoder import NO_RETURN, AutoencoderConfig, RangeAutoencoder, decoded_image

TINY = AutoencoderConfig(base_channels=8, channel_multipliers=(1, 2, 2), z_channels=4, gn_groups=4)  # factor 4


def tiny_net(cfg: AutoencoderConfig = TINY, seed: int = 0) -> RangeAutoencoder:
    """A RangeAutoencoder initialised from `seed`, the caller's global RNG untouched."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return RangeAutoencoder(cfg)


def range_image(generator: torch.Generator, batch: int = 1, height: int = 8, width: int = 32) -> torch.Tensor:
    """(B, 2, H, W) values in (-1, 1) with about a quarter of the pixels no-return (-1 in both channels)."""
    x = torch.rand(batch, 2, height, width, generator=generator) * 1.8 - 0.9
    missing = torch.rand(batch, 1, height, width, generator=generator) < 0.25
    return torch.where(missing.expand_as(x), torch.full_like(x, NO_RETURN), x)


@pytest.mark.parametrize(("multipliers", "factor"), [((1,), 1), ((1, 2), 2), ((1, 2, 2), 4)])
def test_latent_is_image_over_factor_and_decode_gives_values_and_mask_logits(multipliers, factor, generator):
    cfg = AutoencoderConfig(base_channels=8, channel_multipliers=multipliers, z_channels=3, gn_groups=4)
    assert cfg.factor == factor == 2 ** (len(multipliers) - 1)
    net = tiny_net(cfg)
    x = range_image(generator, batch=2, height=8, width=32)
    mean, logvar = net.encode(x)
    assert mean.shape == logvar.shape == (2, 3, 8 // factor, 32 // factor)
    values, logits = net.decode(mean)
    assert values.shape == (2, 2, 8, 32) and logits.shape == (2, 1, 8, 32)
    assert net.to_latent(x).shape == mean.shape and net.from_latent(mean).shape == x.shape


def test_posterior_log_variance_is_clamped(generator):
    net = tiny_net()
    with torch.no_grad():
        net.encoder[-1].bias[TINY.z_channels :] = 1e3  # the log-variance half of the last conv
    _, logvar = net.encode(range_image(generator))
    assert torch.equal(logvar, torch.full_like(logvar, 20.0))
    with torch.no_grad():
        net.encoder[-1].bias[TINY.z_channels :] = -1e3
    assert torch.equal(net.encode(range_image(generator))[1], torch.full_like(logvar, -30.0))


@pytest.mark.parametrize(("height", "width"), [(8, 30), (6, 32), (10, 34)])
def test_sizes_that_are_not_multiples_of_the_factor_name_it(height, width):
    with pytest.raises(InputError, match=rf"image {height}x{width}: H and W must be multiples of 4"):
        tiny_net().encode(torch.zeros(1, 2, height, width))


@pytest.mark.parametrize("shape", [(1, 3, 8, 32), (1, 1, 8, 32), (2, 8, 32)])
def test_wrong_image_channels_or_rank_are_refused(shape):
    with pytest.raises(InputError, match=r"expected images \(B, 2, H, W\)"):
        tiny_net()(torch.zeros(shape))


def test_wrong_latent_channels_are_refused():
    with pytest.raises(InputError, match=r"expected latents \(B, 4, h, w\)"):
        tiny_net().decode(torch.zeros(1, 5, 2, 8))


@pytest.mark.parametrize("shift", [4, 8, -12])
def test_encode_and_decode_are_equivariant_to_azimuth_rolls_by_multiples_of_the_factor(shift, generator):
    """Ring padding everywhere: rolling the scan by k·f columns rolls its latent by k columns, and back."""
    net = tiny_net()
    x = range_image(generator, batch=2)
    with torch.no_grad():
        mean, logvar = net.encode(x)
        rolled_mean, rolled_logvar = net.encode(torch.roll(x, shift, dims=-1))
        values, logits = net.decode(mean)
        rolled_values, rolled_logits = net.decode(torch.roll(mean, shift // 4, dims=-1))
    assert not torch.allclose(torch.roll(mean, 1, dims=-1), mean, atol=1e-3)  # the latent does vary with azimuth
    torch.testing.assert_close(rolled_mean, torch.roll(mean, shift // 4, dims=-1), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(rolled_logvar, torch.roll(logvar, shift // 4, dims=-1), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(rolled_values, torch.roll(values, shift, dims=-1), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(rolled_logits, torch.roll(logits, shift, dims=-1), rtol=1e-4, atol=1e-5)


def test_forward_loss_is_l1_plus_weighted_mask_bce_and_kl(generator):
    net = tiny_net()
    x = range_image(generator, batch=2)
    losses = net(x, torch.Generator().manual_seed(1), kl_weight=0.3, mask_weight=2.0)
    assert set(losses) == {"loss", "l1", "l1_depth", "mask_bce", "kl"}
    expected = losses["l1"] + 2.0 * losses["mask_bce"] + 0.3 * losses["kl"]
    torch.testing.assert_close(losses["loss"].detach(), expected)
    assert losses["loss"].requires_grad and not losses["l1"].requires_grad
    again = net(x, torch.Generator().manual_seed(1), kl_weight=0.3, mask_weight=2.0)
    other = net(x, torch.Generator().manual_seed(2), kl_weight=0.3, mask_weight=2.0)
    assert torch.equal(again["loss"], losses["loss"])  # the posterior draw comes from the generator alone
    assert not torch.equal(other["l1"], losses["l1"])


def fixed_outputs(
    monkeypatch: pytest.MonkeyPatch, net: RangeAutoencoder, values: torch.Tensor, logits: torch.Tensor, mean: float
) -> None:
    """The net's encoder answers a posterior N(mean, 1) per latent element, its decoder (values, logits)."""

    def encode(x):
        shape = (x.shape[0], net.cfg.z_channels, x.shape[-2] // net.cfg.factor, x.shape[-1] // net.cfg.factor)
        return torch.full(shape, mean), torch.zeros(shape)

    monkeypatch.setattr(net, "encode", encode)
    monkeypatch.setattr(net, "decode", lambda z: (values, logits))


def test_l1_counts_only_returns_and_the_losses_match_hand_computed_values(monkeypatch):
    """3 returns decoded 0.5 off, every no-return pixel 3.0 off: l1 = 0.5; logits 0 -> bce = log 2; posterior
    N(1, 1) -> kl = 0.5 per element."""
    x = torch.full((1, 2, 8, 8), NO_RETURN)
    rows, columns = torch.tensor([1, 4, 6]), torch.tensor([2, 7, 0])
    x[0, 0, rows, columns] = torch.tensor([0.2, -0.5, 0.9])
    x[0, 1, rows, columns] = torch.tensor([0.1, 0.3, -0.7])
    returns = x[:, :1] > NO_RETURN
    values = torch.where(returns, x + 0.5, x + 3.0)
    net = tiny_net()
    fixed_outputs(monkeypatch, net, values, torch.zeros(1, 1, 8, 8), mean=1.0)
    losses = net(x, torch.Generator().manual_seed(0), kl_weight=0.1, mask_weight=2.0)
    assert losses["l1"].item() == pytest.approx(0.5) and losses["l1_depth"].item() == pytest.approx(0.5)
    assert losses["mask_bce"].item() == pytest.approx(math.log(2.0))
    assert losses["kl"].item() == pytest.approx(0.5)
    assert losses["loss"].item() == pytest.approx(0.5 + 2.0 * math.log(2.0) + 0.1 * 0.5)


def test_value_weights_weigh_the_channels_of_the_l1(monkeypatch):
    x = torch.full((1, 2, 4, 8), 0.0)
    values = x.clone()
    values[:, 0] += 0.4  # depth 0.4 off, reflectance 0.1 off
    values[:, 1] += 0.1
    net = tiny_net()
    fixed_outputs(monkeypatch, net, values, torch.full((1, 1, 4, 8), 5.0), mean=0.0)
    assert net(x)["l1"].item() == pytest.approx(0.25)
    assert net(x, value_weights=(1.0, 0.0))["l1"].item() == pytest.approx(0.4)
    assert net(x, value_weights=(3.0, 1.0))["l1"].item() == pytest.approx((3 * 0.4 + 0.1) / 4)
    assert net(x, value_weights=(3.0, 1.0))["l1_depth"].item() == pytest.approx(0.4)
    for bad in [(1.0,), (1.0, -1.0), (0.0, 0.0)]:
        with pytest.raises(InputError, match="value_weights"):
            net(x, value_weights=bad)


def test_column_weight_zero_columns_leave_the_losses(monkeypatch):
    """Columns 0-1 and 6-7 (a crop's margins) are decoded badly; weighted 0 they change neither l1 nor bce."""
    x = torch.full((1, 2, 4, 8), 0.3)
    x[0, :, 0, :] = NO_RETURN
    margins = torch.tensor([0, 1, 6, 7])
    values = x + 0.25
    values[..., margins] += 2.0
    logits = torch.zeros(1, 1, 4, 8)  # bce log 2 on every pixel of the inner columns
    wrong = torch.where(x[:, :1] > NO_RETURN, -20.0, 20.0)  # confidently wrong about every pixel
    logits[..., margins] = wrong[..., margins]
    weight = torch.tensor([0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0])
    net = tiny_net()
    fixed_outputs(monkeypatch, net, values, logits, mean=0.0)
    weighted, plain = net(x, column_weight=weight), net(x)
    assert weighted["l1"].item() == pytest.approx(0.25)
    assert weighted["mask_bce"].item() == pytest.approx(math.log(2.0))
    assert plain["l1"].item() > 1.0 and plain["mask_bce"].item() > 5.0  # the margins do count without the weight
    only_margins = torch.full_like(x, NO_RETURN)
    only_margins[..., [0, 7]] = 0.5  # every return sits in a zero-weight column: nothing to average, no nan
    assert net(only_margins, column_weight=weight)["l1"].item() == 0.0


def test_decoded_image_is_clamped_values_where_the_logit_is_positive_else_no_return():
    values = torch.tensor([[0.5, 2.0, -0.3, 0.9, -4.0], [-2.0, 0.1, 0.4, 0.2, 0.6]]).view(1, 2, 1, 5)
    logits = torch.tensor([1.0, 3.0, 0.0, -2.0, 0.5]).view(1, 1, 1, 5)
    image = decoded_image(values, logits)
    assert image.shape == (1, 2, 1, 5)
    assert image[0, 0, 0].tolist() == pytest.approx([0.5, 1.0, NO_RETURN, NO_RETURN, -1.0])
    assert image[0, 1, 0].tolist() == pytest.approx([-1.0, 0.1, NO_RETURN, NO_RETURN, 0.6])


def test_latent_statistics_normalise_the_latents_they_were_set_from(generator):
    net = tiny_net().eval()
    images = range_image(generator, batch=6)
    with torch.no_grad():
        means = net.encode(images)[0]
        assert torch.equal(net.to_latent(images), means)  # shift 0, scale 1 until set
        net.set_latent_statistics(means)
        z = net.to_latent(images)
        assert not torch.allclose(net.latent_shift, torch.zeros(4))
        torch.testing.assert_close(z.mean(dim=(0, 2, 3)), torch.zeros(4), atol=1e-5, rtol=0)
        torch.testing.assert_close(z.std(dim=(0, 2, 3)), torch.ones(4), atol=1e-5, rtol=0)
        torch.testing.assert_close(net.from_latent(z), decoded_image(*net.decode(means)), atol=1e-5, rtol=0)
    state = net.state_dict()  # saved with the weights
    assert torch.equal(state["latent_shift"], net.latent_shift) and torch.equal(state["latent_scale"], net.latent_scale)


def test_overfits_one_tiny_image():
    """200 Adam steps on one smooth 8x32 scan: the L1 on the returns drops >10x, the return mask is learned."""
    cfg = AutoencoderConfig(base_channels=8, channel_multipliers=(1, 2), z_channels=4, gn_groups=4)
    net = tiny_net(cfg)
    rows = torch.linspace(-0.8, 0.6, 8)[:, None]
    columns = torch.arange(32)[None] * 2 * math.pi / 32
    x = torch.stack([rows + 0.2 * torch.sin(columns), 0.3 * torch.cos(2 * columns).expand(8, 32)])[None].clone()
    x[:, :, 0, ::3] = NO_RETURN
    optimizer = torch.optim.Adam(net.parameters(), lr=3e-3)
    generator = torch.Generator().manual_seed(0)
    first = net(x, generator)
    for _ in range(200):
        losses = net(x, generator)
        optimizer.zero_grad()
        losses["loss"].backward()
        optimizer.step()
    assert losses["l1"] < 0.1 * first["l1"], (first, losses)
    assert losses["mask_bce"] < 0.3 < first["mask_bce"]
    with torch.no_grad():
        image = decoded_image(*net.decode(net.encode(x)[0]))
    assert ((image[:, 0] > NO_RETURN) == (x[:, 0] > NO_RETURN)).float().mean() > 0.9


@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({"base_channels": 8, "gn_groups": 3}, "gn_groups=3 must divide every width; 8 does not"),
        ({"base_channels": 12, "channel_multipliers": (1, 2), "gn_groups": 8}, "12 does not"),
        ({"base_channels": 0}, "must be >= 1"),
        ({"z_channels": 0}, "must be >= 1"),
        ({"num_res_blocks": 0}, "must be >= 1"),
        ({"in_channels": 0}, "must be >= 1"),
        ({"channel_multipliers": ()}, "channel_multipliers must be positive integers"),
        ({"channel_multipliers": (1, 0)}, "channel_multipliers must be positive integers"),
    ],
)
def test_config_errors(fields, match):
    with pytest.raises(InputError, match=match):
        AutoencoderConfig(**fields)


def test_config_takes_a_yaml_list_of_multipliers():
    assert AutoencoderConfig(channel_multipliers=[1, 2], gn_groups=4, base_channels=8).channel_multipliers == (1, 2)
