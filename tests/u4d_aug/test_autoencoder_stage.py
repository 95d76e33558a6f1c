"""The autoencoder's contract: its run config's checks, and the weights file latent generators read."""

from __future__ import annotations

import pytest
import torch

from u4d_aug.autoencoder_stage import (
    WEIGHTS_KIND,
    AutoencoderTrainConfig,
    build_autoencoder,
    load_autoencoder,
    save_autoencoder,
)
from u4d_aug.config import config_to_dict
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_torch_save
from u4d_aug.nn.autoencoder import AutoencoderConfig

TINY_AE = AutoencoderConfig(base_channels=8, channel_multipliers=(1, 2), z_channels=4, gn_groups=4)


def tiny_config(**fields) -> AutoencoderTrainConfig:
    base = dict(height=16, width=64, row_mode="linear", crop_width=0, crop_margin=0, ae=TINY_AE)
    return AutoencoderTrainConfig(**(base | fields))


@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({"width": 63}, "multiples of the latent factor"),
        ({"crop_width": 31}, "crop_width"),
        ({"crop_width": 32, "crop_margin": 8}, "crop_margin"),
        ({"uncertain_share": 1.0}, "uncertain_share"),
        ({"value_weights": (1.0,)}, "value_weights"),
        ({"value_weights": (0.0, 0.0)}, "value_weights"),
        ({"kl_weight": -1.0}, "kl_weight"),
        ({"steps": 0}, "steps"),
    ],
)
def test_bad_settings_name_the_key(fields, match):
    with pytest.raises(InputError, match=match):
        tiny_config(**fields)


def test_weights_round_trip_with_the_latent_statistics(tmp_path):
    cfg = tiny_config()
    net = build_autoencoder(cfg.ae, seed=5)
    net.set_latent_statistics(torch.randn(3, 4, 8, 32, generator=torch.Generator().manual_seed(0)) * 2.0 + 0.5)
    save_autoencoder(tmp_path / "ae.pt", net, cfg)
    loaded, loaded_cfg = load_autoencoder(tmp_path / "ae.pt")
    assert loaded_cfg == cfg and not loaded.training
    x = torch.rand(1, 2, 16, 64) * 2 - 1
    with torch.no_grad():
        torch.testing.assert_close(loaded.to_latent(x), net.eval().to_latent(x))
    torch.testing.assert_close(loaded.latent_scale, net.latent_scale)
    (tmp_path / "run").mkdir()
    save_autoencoder(tmp_path / "run" / "autoencoder.pt", net, cfg)
    folder, _ = load_autoencoder(tmp_path / "run")  # a run folder stands for its autoencoder.pt
    torch.testing.assert_close(folder.latent_shift, net.latent_shift)


def test_the_seed_decides_the_initial_weights():
    a, b, c = (build_autoencoder(TINY_AE, seed) for seed in (1, 1, 2))
    assert torch.equal(a.encoder[0].weight, b.encoder[0].weight)
    assert not torch.equal(a.encoder[0].weight, c.encoder[0].weight)


def test_other_files_are_refused(tmp_path):
    atomic_torch_save(tmp_path / "other.pt", {"kind": "u4d-diffusion", "model": {}})
    with pytest.raises(InputError, match="not the autoencoder weights"):
        load_autoencoder(tmp_path / "other.pt")
    state = {"kind": WEIGHTS_KIND, "config": config_to_dict(tiny_config()), "model": {"x": torch.zeros(1)}}
    atomic_torch_save(tmp_path / "broken.pt", state)
    with pytest.raises(InputError, match="do not fit"):
        load_autoencoder(tmp_path / "broken.pt")
