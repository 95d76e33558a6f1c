"""Ring convolutions, down/upsampling, log-SNR embedding, ResBlock, attention and ray Fourier features."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from u4d_aug.errors import InputError
from u4d_aug.nn.layers import (
    AttentionBlock,
    Downsample,
    RayFourierFeatures,
    ResBlock,
    RingConv2d,
    Upsample,
    num_fourier_frequencies,
    ray_fourier_features,
    sinusoidal_embedding,
)


@pytest.mark.parametrize(("stride", "width"), [(1, 10), (1, 3), (2, 10), (2, 9)])
def test_ring_conv_equals_conv_on_circular_w_zero_h_padding(stride, width, generator):
    conv = RingConv2d(3, 5, 3, stride=stride)
    x = torch.randn(2, 3, 6, width, generator=generator)
    padded = F.pad(F.pad(x, (1, 1, 0, 0), mode="circular"), (0, 0, 1, 1))  # ring along W, zeros along H
    expected = F.conv2d(padded, conv.weight, conv.bias, stride=stride)
    assert torch.allclose(conv(x), expected, atol=1e-5)


def test_ring_conv_gradients_match_the_padded_reference(generator):
    conv = RingConv2d(2, 3, 3, stride=2)
    x = torch.randn(1, 2, 4, 8, generator=generator, requires_grad=True)
    upstream = torch.randn(1, 3, 2, 4, generator=generator)
    (conv(x) * upstream).sum().backward()
    grads = (x.grad.clone(), conv.weight.grad.clone(), conv.bias.grad.clone())
    x.grad = None
    conv.zero_grad()
    padded = F.pad(F.pad(x, (1, 1, 0, 0), mode="circular"), (0, 0, 1, 1))
    (F.conv2d(padded, conv.weight, conv.bias, stride=2) * upstream).sum().backward()
    for got, want in zip(grads, (x.grad, conv.weight.grad, conv.bias.grad)):
        assert torch.allclose(got, want, atol=1e-5)


def test_ring_conv_wraps_azimuth_but_not_elevation():
    conv = RingConv2d(1, 1, 3, bias=False)
    torch.nn.init.ones_(conv.weight)
    x = torch.zeros(1, 1, 4, 8)
    x[0, 0, 0, 0] = 1.0  # top-left pixel
    y = conv(x)[0, 0]
    assert y[0, -1] == 1.0 and y[1, -1] == 1.0  # its neighbour across the azimuth seam sees it
    assert y[-1].abs().sum() == 0.0  # the bottom row is not its neighbour: no wrap along elevation


@pytest.mark.parametrize("shift", [2, 4, 6])
def test_downsample_shape_and_even_roll_equivariance(shift, generator):
    down = Downsample(4)
    x = torch.randn(1, 4, 8, 16, generator=generator)
    y = down(x)
    assert y.shape == (1, 4, 4, 8)
    assert torch.allclose(down(torch.roll(x, shift, -1)), torch.roll(y, shift // 2, -1), atol=1e-6)


@pytest.mark.parametrize("shift", [1, 3])
def test_upsample_shape_and_roll_equivariance(shift, generator):
    up = Upsample(4)
    x = torch.randn(1, 4, 4, 8, generator=generator)
    y = up(x)
    assert y.shape == (1, 4, 8, 16)
    assert torch.allclose(up(torch.roll(x, shift, -1)), torch.roll(y, 2 * shift, -1), atol=1e-6)


def test_sinusoidal_embedding_golden_and_distinct():
    emb = sinusoidal_embedding(torch.tensor([0.0, 1.0, -15.0]), 8)
    assert emb.shape == (3, 8)
    assert torch.equal(emb[0], torch.tensor([1.0, 1, 1, 1, 0, 0, 0, 0]))  # cos(0) = 1, sin(0) = 0
    assert math.isclose(emb[1, 4].item(), math.sin(1.0), rel_tol=1e-6)  # first frequency is 1
    assert not torch.allclose(emb[1], emb[2])


def test_resblock_starts_as_scaled_skip_and_reads_the_embedding(generator):
    block = ResBlock(4, 8, embed_channels=16, groups=4)
    x = torch.randn(2, 4, 4, 8, generator=generator)
    emb = torch.randn(2, 16, generator=generator)
    assert torch.allclose(block(x, emb), block.skip(x) / math.sqrt(2.0), atol=1e-6)  # zero-init conv2
    torch.nn.init.normal_(block.conv2.weight, std=0.1)
    assert not torch.allclose(block(x, emb), block(x, emb + 1.0))  # AdaGN scale-shift changes the output


def test_attention_block_starts_as_scaled_identity_and_mixes_pixels(generator):
    attn = AttentionBlock(8, groups=4, num_heads=2)
    x = torch.randn(1, 8, 2, 4, generator=generator)
    assert torch.allclose(attn(x), x / math.sqrt(2.0), atol=1e-6)
    torch.nn.init.normal_(attn.proj.weight, std=0.1)
    x2 = x.clone()
    x2[..., 1, 3] += 1.0  # one far pixel changes -> every output pixel changes (global receptive field)
    assert (attn(x2) - attn(x))[0, :, 0, 0].abs().max() > 0
    with pytest.raises(InputError):
        AttentionBlock(6, groups=2, num_heads=4)


def test_ray_fourier_features_shape_periodic_azimuth_and_distinct_rows():
    assert num_fourier_frequencies(64) == 6 and num_fourier_frequencies(1024) == 10  # R2DM: 32 channels
    elevation = torch.deg2rad(torch.linspace(2.0, -24.0, 64))
    azimuth = torch.linspace(math.pi, -math.pi, 1024 + 1, dtype=torch.float64)[:-1]
    feats = ray_fourier_features(elevation, azimuth)
    assert feats.shape == (2 * (6 + 10), 64, 1024)
    wrapped = ray_fourier_features(elevation, azimuth + 2 * math.pi)  # same rays, azimuth one turn later
    assert torch.allclose(feats, wrapped, atol=1e-5)
    rows = feats[:, :, 0].T  # (H, C)
    assert torch.cdist(rows, rows).add(torch.eye(64) * 10).min() > 1e-2  # every row has its own code
    assert feats.abs().max() <= 1.0


def test_ray_fourier_module_rejects_2d_angles_and_broadcasts():
    with pytest.raises(InputError, match="1-D"):
        RayFourierFeatures(torch.zeros(4, 2), torch.zeros(8), 4)
    module = RayFourierFeatures(torch.linspace(0.1, -0.4, 4), torch.linspace(3.0, -3.0, 8), 4)
    assert module.size == (4, 8) and module().shape == (1, 4, 4, 8)
    assert "features" in module.state_dict()  # the angle grid travels with checkpoints
