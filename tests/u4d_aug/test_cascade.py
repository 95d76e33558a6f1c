"""The two-level cascade: the layout's columns as a detail net's condition, its training batches, `refine` and a
cascade bank (a W / s layout net, then the detail net at W)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from tests.tiny_nets import PLAIN_SAMPLING, diffusion_config, plain_settings
from tests.tiny_worlds import write_tiny_world
from u4d_aug.bank import BankLayout
from u4d_aug.batches import RangeImages, stage_inputs, training_batch
from u4d_aug.cascade import check_stride, place_columns, spread_columns, upsample_nearest
from u4d_aug.config import load_config
from u4d_aug.data.sensors import get_sensor
from u4d_aug.diffusion import GaussianDiffusion
from u4d_aug.errors import InputError
from u4d_aug.generate import GenerateConfig, generate_bank
from u4d_aug.pipeline import load_generator, refine
from u4d_aug.range_view import project, to_image
from u4d_aug.stage import build_net
from u4d_aug.train import train


@pytest.fixture
def tiny_world(tmp_path: Path) -> tuple[Path, Path]:
    root, probs_root = tmp_path / "world", tmp_path / "probs"
    write_tiny_world(root, probs_root)
    return root, probs_root


def test_place_columns_puts_the_layout_on_every_strided_column():
    x_low = torch.arange(2 * 2 * 3 * 4, dtype=torch.float32).view(2, 2, 3, 4) / 100
    x0_u, m = place_columns(x_low, 4)
    assert x0_u.shape == (2, 2, 3, 16) and m.shape == (2, 1, 3, 16)
    assert torch.equal(x0_u[..., ::4], x_low)
    others = torch.ones(16, dtype=torch.bool)
    others[::4] = False
    assert bool((x0_u[..., others] == -1).all()) and bool((m[..., others] == 0).all())
    assert bool((m[..., ::4] == 1).all())
    assert np.array_equal(spread_columns(np.array([[1, 2]]), 3), np.array([[1, 1, 1, 2, 2, 2]]))
    assert check_stride(1024, 4) == 256
    for width, stride in ((1024, 1), (1000, 3)):
        with pytest.raises(InputError, match="detail_stride must be >= 2 and divide width"):
            check_stride(width, stride)


def test_detail_batches_hold_the_scans_layout_projection_and_train_one_conditioned_net(tiny_world, tmp_path):
    cfg = diffusion_config(tiny_world, tmp_path / "run", "detail", "detail_stride=4", "diffusion.cond_noise=0.05")
    assert (cfg.net.mask_head, cfg.net.cond_channels, cfg.net.num_tasks) == (False, 3, 0)
    images = RangeImages(cfg)
    assert not images.needs_probs  # the condition comes from the scan itself
    item = images[0]
    seq, frame = images.scans.entries[0]
    points = torch.from_numpy(images.scans.load_points(seq, frame))
    sensor = get_sensor(cfg.sensor)
    x_low = to_image(project(points, sensor, cfg.height, cfg.width // 4, cfg.row_mode), sensor)
    # the condition is the scan's W/s-column projection (what the layout net learns), not a subsample of x0
    assert torch.equal(item["x0_u"][..., ::4], x_low) and float(item["m_u"].mean()) == 0.25
    assert torch.equal(item["x0"], to_image(project(points, sensor, cfg.height, cfg.width, cfg.row_mode), sensor))
    batch, offsets, generator = training_batch(images, cfg, 0, 0, torch.device("cpu"))
    x0, cond, m_u = stage_inputs("detail", batch)
    assert cond is batch["x0_u"] and m_u is batch["m_u"] and x0 is batch["x0"]
    losses = GaussianDiffusion(build_net(cfg), cfg.diffusion)(x0, cond, m_u, generator, offsets)
    assert np.isfinite(float(losses["loss"].detach())) and "mask_bce" not in losses


def test_detail_stage_refuses_a_stride_that_does_not_divide_the_width(tiny_world, tmp_path):
    with pytest.raises(InputError, match="detail_stride must be >= 2 and divide width 64, got 3"):
        diffusion_config(tiny_world, tmp_path / "run", "detail", "detail_stride=3")
    with pytest.raises(InputError, match="stage detail completes single range-image scans"):
        diffusion_config(tiny_world, tmp_path / "run", "detail", "frames=2")


def test_cascade_bank_makes_full_width_scans_from_layout_scans(tiny_world, tmp_path):
    layout, detail = tmp_path / "layout", tmp_path / "detail"
    train(diffusion_config(tiny_world, layout, "baseline", "width=16"), progress=False)
    train(diffusion_config(tiny_world, detail, "detail", "detail_stride=4"), progress=False)
    loaded = load_generator(detail)
    x_low = torch.rand(2, 2, 16, 16) * 2 - 1
    result = refine(loaded, x_low, torch.Generator().manual_seed(0), plain_settings(2, "ddpm"))
    assert result["x0"].shape == (2, 2, 16, 64) and torch.equal(result["x0_u"][..., ::4], x_low)
    with pytest.raises(InputError, match=r"expected x_low \(B, 2, 16, 16\), got \(2, 2, 16, 64\)"):
        refine(loaded, result["x0"], torch.Generator().manual_seed(0), plain_settings(2, "ddpm"))

    base = [f"baseline={layout}", "mode=baseline", "num=2", "sampler=ddpm", "steps=2", *PLAIN_SAMPLING]
    base += ["device=cpu", "batch_size=2", "labels=false"]
    manifest = generate_bank(load_config(GenerateConfig, None, [*base, f"detail={detail}"]), tmp_path / "bank")
    assert manifest["complete"] and set(manifest["checkpoints"]) == {"baseline", "detail"}
    assert (manifest["height"], manifest["width"]) == (16, 64)
    scan = np.fromfile(BankLayout(tmp_path / "bank", 1).scan_path(0), dtype=np.float32).reshape(-1, 4)
    assert len(scan) > 16 * 16  # more returns than a 16x16 layout can hold
    # U4D's one net as the layout: its stage-1 mask and x0_u lie over the full-width scan, each column spread s times
    u4d = tmp_path / "u4d"
    train(diffusion_config(tiny_world, u4d, "u4d", "width=16"), progress=False)
    as_u4d = [*base, "mode=u4d", f"net={u4d}", f"detail={detail}"]
    generate_bank(load_config(GenerateConfig, None, as_u4d), tmp_path / "bank_u4d")
    bank = BankLayout(tmp_path / "bank_u4d", 1)
    mask, x0_u = np.load(bank.mask_path(1)), np.load(bank.stage1_path(1))
    assert mask.shape == (16, 64) and x0_u.shape == (2, 16, 64)
    assert np.array_equal(mask, np.repeat(mask[:, ::4], 4, axis=-1))
    # a detail net that does not fit the layout net's image is refused before any scan is made
    wrong = tmp_path / "detail8"
    train(diffusion_config(tiny_world, wrong, "detail", "detail_stride=8"), progress=False)
    with pytest.raises(InputError, match="completes layouts of sensor hdl64, 16x8"):
        generate_bank(load_config(GenerateConfig, None, [*base, f"detail={wrong}"]), tmp_path / "bank2")
    with pytest.raises(InputError, match="detail: a cascade's detail net completes generated layouts"):
        generate_bank(load_config(GenerateConfig, None, [*base, "mode=complete", f"detail={detail}"]), tmp_path / "b3")


def test_nearest_detail_repeats_each_layout_column_up_to_the_sensor_width(tiny_world, tmp_path):
    x_low = torch.rand(2, 3, 2, 4, 5)
    up = upsample_nearest(x_low, 3)
    assert up.shape == (2, 3, 2, 4, 15) and torch.equal(up[..., 1::3], x_low) and torch.equal(up[..., 2::3], x_low)
    layout = tmp_path / "layout"
    train(diffusion_config(tiny_world, layout, "baseline", "width=256"), progress=False)
    base = [f"baseline={layout}", "mode=baseline", "num=2", "sampler=ddpm", "steps=2", *PLAIN_SAMPLING]
    base += ["device=cpu", "batch_size=2", "labels=false"]
    plain = generate_bank(load_config(GenerateConfig, None, base), tmp_path / "plain")
    manifest = generate_bank(load_config(GenerateConfig, None, [*base, "detail=nearest"]), tmp_path / "bank")
    assert (
        manifest["width"] == 1024 and manifest["detail"] == "nearest" and set(manifest["checkpoints"]) == {"baseline"}
    )
    # the same samples (seed + i) as without the cascade, each point now at the 4 azimuths of its column's bin
    for index in range(2):
        low = np.fromfile(BankLayout(tmp_path / "plain", 1).scan_path(index), dtype=np.float32).reshape(-1, 4)
        up = np.fromfile(BankLayout(tmp_path / "bank", 1).scan_path(index), dtype=np.float32).reshape(-1, 4)
        assert len(up) == 4 * len(low)
        np.testing.assert_allclose(np.sort(np.linalg.norm(up[:, :3], axis=1))[::4],
                                   np.sort(np.linalg.norm(low[:, :3], axis=1)), rtol=1e-5)  # fmt: skip
    assert plain["width"] == 256
    # a bank made without the cascade is not continued with it
    with pytest.raises(InputError, match="bank was generated with a different detail"):
        generate_bank(load_config(GenerateConfig, None, [*base, "detail=nearest"]), tmp_path / "plain")
    odd = tmp_path / "odd"
    train(diffusion_config(tiny_world, odd, "baseline", "width=24"), progress=False)
    with pytest.raises(InputError, match="detail=nearest repeats the layout's columns up to the sensor's 1024"):
        generate_bank(load_config(GenerateConfig, None, [*base, f"baseline={odd}", "detail=nearest"]), tmp_path / "o")
