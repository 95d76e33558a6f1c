"""Latent generators: a diffusion net on a trained autoencoder's latents, trained on encoded scans, sampled and
decoded by the same pipeline functions as a range-image net (u4d one net, baseline, completion)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from tests.tiny_nets import diffusion_config, plain_settings
from tests.tiny_worlds import write_tiny_world
from u4d_aug.autoencoder_stage import AutoencoderTrainConfig, build_autoencoder, save_autoencoder
from u4d_aug.batches import RangeImages, training_batch
from u4d_aug.diffusion import noisy_condition
from u4d_aug.errors import InputError
from u4d_aug.latent import (
    LatentNet,
    autoencoder_of,
    encode_item,
    latent_mask,
    load_latent_autoencoder,
    pixel_mask,
)
from u4d_aug.nn.autoencoder import AutoencoderConfig
from u4d_aug.pipeline import MeanStart, complete, generate_baseline, generate_u4d, inpaint, load_generator
from u4d_aug.stage import build_net
from u4d_aug.train import train

LATENT = ("latent_factor=2", "net.in_channels=4", "net.out_channels=4")  # the tiny autoencoder's latent


@pytest.fixture
def tiny_world(tmp_path: Path) -> tuple[Path, Path]:
    root, probs_root = tmp_path / "world", tmp_path / "probs"
    write_tiny_world(root, probs_root)
    return root, probs_root


@pytest.fixture
def autoencoder_file(tmp_path: Path) -> Path:
    """An untrained tiny autoencoder (factor 2, 4 latent channels) for configs/u4d/tiny.yaml's 16x64 linear rows,
    its latent statistics set so that they are not the identity."""
    cfg = AutoencoderTrainConfig(
        height=16, width=64, row_mode="linear", crop_width=0, crop_margin=0,
        ae=AutoencoderConfig(base_channels=8, channel_multipliers=(1, 2), z_channels=4, gn_groups=4),
    )  # fmt: skip
    net = build_autoencoder(cfg.ae, seed=3)
    net.set_latent_statistics(torch.randn(6, 4, 8, 32, generator=torch.Generator().manual_seed(0)) * 3.0 + 1.0)
    path = tmp_path / "ae" / "autoencoder.pt"
    save_autoencoder(path, net, cfg)
    return path


def latent_config(world, out: Path, stage: str, autoencoder: Path, *extra: str):
    return diffusion_config(world, out, stage, f"autoencoder={autoencoder}", *LATENT, *extra)


def test_masks_between_pixels_and_latent():
    m_u = torch.zeros(2, 1, 4, 8)
    m_u[0, 0, 1, 5] = 1.0
    pooled = latent_mask(m_u, 2)
    assert pooled.shape == (2, 1, 2, 4)
    assert pooled[0, 0, 0, 2] == 1 and pooled.sum() == 1  # the latent pixel that covers (1, 5)
    back = pixel_mask(pooled, 2)
    assert back.shape == m_u.shape and back.sum() == 4 and bool((back >= m_u).all())
    sequence = torch.zeros(1, 3, 1, 4, 8)  # (B, L, 1, H, W) keeps its leading dims
    assert latent_mask(sequence, 2).shape == (1, 3, 1, 2, 4)


def test_the_config_sets_autoencoder_and_factor_together(tiny_world, tmp_path, autoencoder_file):
    with pytest.raises(InputError, match="latent_factor"):
        diffusion_config(tiny_world, tmp_path / "a", "baseline", f"autoencoder={autoencoder_file}")
    with pytest.raises(InputError, match="crop_width"):
        latent_config(tiny_world, tmp_path / "b", "baseline", autoencoder_file, "crop_width=32")
    cfg = latent_config(tiny_world, tmp_path / "c", "u4d", autoencoder_file)
    assert (cfg.net.cond_channels, cfg.net.mask_head) == (5, True)  # z_u (4) + m_u on the latent
    net = build_net(cfg)
    assert net.ray_features is not None and net.ray_features.size == (8, 32)


def test_a_mismatched_autoencoder_names_the_keys(tiny_world, tmp_path, autoencoder_file):
    cfg = latent_config(tiny_world, tmp_path / "run", "baseline", autoencoder_file, "net.in_channels=8",
                        "net.out_channels=8")  # fmt: skip
    with pytest.raises(InputError, match="net.in_channels=8"):
        load_latent_autoencoder(cfg)
    missing = latent_config(tiny_world, tmp_path / "run", "baseline", tmp_path / "nothing.pt")
    with pytest.raises(InputError, match="does not exist"):
        load_latent_autoencoder(missing)


def test_training_items_are_the_latents_of_the_scans(tiny_world, tmp_path, autoencoder_file):
    cfg = latent_config(tiny_world, tmp_path / "run", "u4d", autoencoder_file)
    autoencoder = load_latent_autoencoder(cfg)
    pixels = RangeImages(diffusion_config(tiny_world, tmp_path / "px", "u4d"))[0]
    latents = RangeImages(cfg, lambda item: encode_item(autoencoder, 2, item))[0]
    assert latents["x0"].shape == (4, 8, 32) and latents["m_u"].shape == (1, 8, 32)
    with torch.no_grad():
        expected = autoencoder.to_latent(pixels["x0"][None])[0]
    torch.testing.assert_close(latents["x0"], expected)
    torch.testing.assert_close(latents["m_u"], latent_mask(pixels["m_u"], 2))
    batch, _, _ = training_batch(RangeImages(cfg, lambda item: encode_item(autoencoder, 2, item)), cfg, 0, 0, "cpu")
    assert batch["x0"].shape == (2, 4, 8, 32)


def test_the_condition_noise_of_a_latent_is_not_clamped():
    z_u = torch.full((2, 4, 2, 2), 3.0)
    mask = torch.ones(2, 1, 2, 2)
    noisy = noisy_condition(z_u, mask, 0.5, torch.Generator().manual_seed(0), clamp=False)
    assert float(noisy.max()) > 1.0 and not torch.equal(noisy, z_u)
    assert float(noisy_condition(z_u, mask, 0.5, torch.Generator().manual_seed(0)).max()) <= 1.0


def test_latent_u4d_trains_and_samples_decoded_scans(tiny_world, tmp_path, autoencoder_file):
    out = tmp_path / "u4d"
    record = train(latent_config(tiny_world, out, "u4d", autoencoder_file), progress=False)
    assert record["step"] == 4 and "mask_bce" in record
    loaded = load_generator(out)
    assert isinstance(loaded.net, LatentNet) and autoencoder_of(loaded.net) is not None
    assert not any(name.startswith("autoencoder") for name in loaded.net.state_dict())
    x = generate_u4d(loaded, loaded, 2, torch.Generator().manual_seed(0), plain_settings(2))
    assert x["x0"].shape == (2, 2, 16, 64) and x["x0_u"].shape == (2, 2, 16, 64)
    assert float(x["x0"].min()) >= -1.0 and float(x["x0"].max()) <= 1.0
    # P_u is a set of points: the stage-1 mask keeps decoded returns only
    assert bool((x["x0_u"][:, :1][x["m_u_pred"].bool()] > -1.0).all())
    # the zero-latent mean start of a latent net without a stored mean
    settings = plain_settings(2, mean_start_below=-10.0)
    again = generate_u4d(loaded, loaded, 1, torch.Generator().manual_seed(0), settings)
    assert again["x0"].shape == (1, 2, 16, 64)


def test_latent_completion_keeps_the_known_pixels_when_pinned(tiny_world, tmp_path, autoencoder_file):
    out = tmp_path / "u4d"
    train(latent_config(tiny_world, out, "u4d", autoencoder_file), progress=False)
    loaded = load_generator(out)
    item = RangeImages(diffusion_config(tiny_world, tmp_path / "px", "u4d"))[0]
    x0_u, m_u = item["x0_u"][None], item["m_u"][None]
    pinned = complete(loaded, x0_u, m_u, torch.Generator().manual_seed(0), plain_settings(2), pin_known=True)
    known = m_u.bool().expand_as(x0_u)
    assert torch.equal(pinned["x0"][known], x0_u[known])
    free = complete(loaded, x0_u, m_u, torch.Generator().manual_seed(0), plain_settings(2))
    assert free["x0"].shape == x0_u.shape


def test_latent_baseline_samples_and_refuses_inpainting(tiny_world, tmp_path, autoencoder_file):
    out = tmp_path / "baseline"
    train(latent_config(tiny_world, out, "baseline", autoencoder_file), progress=False)
    loaded = load_generator(out)
    x0 = generate_baseline(loaded, 2, torch.Generator().manual_seed(0), plain_settings(2))["x0"]
    assert x0.shape == (2, 2, 16, 64)
    with pytest.raises(InputError, match="latent baseline"):
        inpaint(loaded, x0, torch.ones(2, 1, 16, 64), torch.Generator().manual_seed(0), plain_settings(2))


def test_autoencoder_of_looks_through_a_mean_start(tiny_world, tmp_path, autoencoder_file):
    cfg = latent_config(tiny_world, tmp_path / "run", "baseline", autoencoder_file)
    autoencoder = load_latent_autoencoder(cfg)
    wrapped = MeanStart(LatentNet(build_net(cfg), autoencoder), torch.zeros(4, 8, 1), -10.0)
    assert autoencoder_of(wrapped) is autoencoder
    assert autoencoder_of(build_net(diffusion_config(tiny_world, tmp_path / "px", "baseline"))) is None


def test_exported_latent_weights_store_the_latent_mean(tiny_world, tmp_path, autoencoder_file):
    from u4d_aug.export_weights import export_weights
    from u4d_aug.pipeline import stored_mean, with_mean_start

    out = tmp_path / "u4d"
    train(latent_config(tiny_world, out, "u4d", autoencoder_file), progress=False)
    exported = export_weights(out, tmp_path / "u4d.pt")
    assert exported["row_mean"]["mean"].shape == (4, 8, 1) and exported["row_mean"]["source"]["latent"]
    assert exported["row_mean_stage1"]["key"] == "x0_u"
    loaded = load_generator(tmp_path / "u4d.pt")
    mean, info = stored_mean(exported, loaded.config, "stage2", "u4d.pt")
    torch.testing.assert_close(mean, exported["row_mean"]["mean"].float())
    started, _ = with_mean_start(loaded, "stage2", plain_settings(2, mean_start_below=-10.0))
    assert isinstance(started, MeanStart) and torch.equal(started.mean, mean)
    x = generate_u4d(loaded, loaded, 1, torch.Generator().manual_seed(0), plain_settings(2, mean_start_below=-10.0))
    assert x["x0"].shape == (1, 2, 16, 64)
