"""The mean start (`u4d generate mean_start_below=...`): each net's per-row training mean image as the samplers' x0
estimate at vanishing SNR (batches.row_mean, pipeline.MeanStart, generate.training_mean), recorded in the bank."""

from __future__ import annotations

import pytest
import torch

from tests.tiny_nets import gen_config, save_random_checkpoint
from tests.tiny_worlds import write_posed_world, write_tiny_world
from u4d_aug.batches import RangeImages, row_mean
from u4d_aug.diffusion import alpha_sigma
from u4d_aug.errors import InputError
from u4d_aug.export_weights import export_weights
from u4d_aug.generate import generate_bank
from u4d_aug.pipeline import MeanStart, load_generator


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A tiny world (4 scans with probabilities) and tiny checkpoints with random weights for the three stages."""
    root = tmp_path_factory.mktemp("mean_start")
    world = (root / "world", root / "probs")
    write_tiny_world(*world, num_scans=4, num_points=3000)
    nets = {stage: save_random_checkpoint(root / f"{stage}.pt", stage) for stage in ("stage1", "stage2", "baseline")}
    return world, nets


def world_overrides(world) -> list[str]:
    return [f"mean_data_root={world[0]}", f"mean_probs_root={world[1]}"]


def test_row_mean_is_the_mean_over_scans_and_columns(setup):
    (data, probs), nets = setup
    _, cfg = load_generator(nets["stage1"])
    cfg.data_root, cfg.probs_root = str(data), str(probs)
    images = RangeImages(cfg)
    for key in ("x0", "x0_u"):
        expected = torch.stack([images[i][key] for i in range(len(images))]).mean(dim=(0, 3)).unsqueeze(-1)
        assert torch.allclose(row_mean(cfg, key), expected, atol=1e-6), key
    assert row_mean(cfg, "x0").shape == (2, cfg.height, 1)
    assert not torch.allclose(row_mean(cfg, "x0"), row_mean(cfg, "x0_u"))  # x0_u holds only the uncertain points


def test_row_mean_of_a_random_selection_net_is_drawn_from_its_seed(setup):
    (data, probs), nets = setup
    _, cfg = load_generator(nets["stage1"])
    cfg.data_root, cfg.probs_root = str(data), str(probs)
    cfg.uncertainty.strategy = "random"  # the selection ablation's nets: P_u drawn at random, not by entropy
    first = row_mean(cfg, "x0_u", seed=0)
    assert torch.equal(first, row_mean(cfg, "x0_u", seed=0)) and not torch.equal(first, row_mean(cfg, "x0_u", seed=1))
    cfg.uncertainty.strategy = "entropy"
    assert not torch.equal(first, row_mean(cfg, "x0_u"))


def test_a_loaded_net_with_mean_start_gives_the_mean_as_x0_and_keeps_its_config(setup):
    (data, probs), nets = setup
    net, cfg = load_generator(nets["stage2"])
    cfg.data_root = str(data)
    mean = row_mean(cfg, "x0")
    assert cfg.net.cond_channels == 3  # the mean's own config (stage "baseline") did not reach the loaded net's
    wrapped = MeanStart(net, mean, below=-10.0)
    x_t = torch.randn(2, 2, cfg.height, cfg.width, generator=torch.Generator().manual_seed(0))
    cond = torch.zeros(2, 3, cfg.height, cfg.width)
    lam = torch.tensor([-15.0, 2.0])
    eps, _ = wrapped(x_t, lam, cond)
    alpha, sigma = alpha_sigma(lam.view(-1, 1, 1, 1))
    x0 = (x_t - sigma * eps) / alpha
    assert torch.allclose(x0[0], mean.expand(2, cfg.height, cfg.width), atol=1e-3)
    assert torch.equal(eps[1], net(x_t, lam, cond)[0][1])  # above the threshold: the net's own ε
    assert next(wrapped.parameters()) is next(net.parameters())  # the pipeline finds the device through it


def test_bank_with_mean_start_records_it_and_differs(setup, tmp_path):
    world, nets = setup
    plain = generate_bank(gen_config(nets, "num=2"), tmp_path / "plain", progress=False)
    started = generate_bank(
        gen_config(nets, "num=2", "mean_start_below=-10", *world_overrides(world)), tmp_path / "started", progress=False
    )
    assert "mean_start_below" not in plain["sampling"] and "mean_start" not in plain  # older banks stay compatible
    assert started["sampling"]["mean_start_below"] == -10.0
    assert started["mean_start"]["stage1"]["key"] == "x0_u" and started["mean_start"]["stage2"]["key"] == "x0"
    assert started["mean_start"]["stage2"]["data_root"] == str(world[0])
    first = [p.read_bytes() for p in sorted((tmp_path / "plain").rglob("*.bin"))]
    second = [p.read_bytes() for p in sorted((tmp_path / "started").rglob("*.bin"))]
    assert len(first) == len(second) == 2 and first != second
    with pytest.raises(InputError):  # a bank is not resumed with another start
        generate_bank(gen_config(nets, "num=2"), tmp_path / "started", progress=False)


def test_missing_training_scans_name_the_keys_to_set(setup, tmp_path):
    _, nets = setup
    cfg = gen_config(nets, "num=1", "mode=baseline", "mean_start_below=-10", f"mean_data_root={tmp_path / 'nowhere'}")
    hint = "set mean_data_root .*export-weights --data-root.* or set mean_start_below=null"
    with pytest.raises(InputError, match=hint):
        generate_bank(cfg, tmp_path / "bank", progress=False)


def test_mean_stored_in_exported_weights_needs_no_training_scans(setup, tmp_path):
    world, nets = setup
    exported = {name: tmp_path / f"{name}.pt" for name in nets}
    for name, path in nets.items():  # the random nets' configs name data/sim, which is not there
        export_weights(path, exported[name], data_root=str(world[0]), probs_root=str(world[1]))
    stored = generate_bank(gen_config(exported, "num=2", "mean_start_below=-10"), tmp_path / "stored", progress=False)
    assert stored["mean_start"]["stage1"]["stored_in"] == str(exported["stage1"])
    assert stored["mean_start"]["stage1"]["key"] == "x0_u" and stored["mean_start"]["stage2"]["key"] == "x0"
    # mean_data_root wins over the stored mean; both are the same mean here, so the scans are the same bytes
    read_cfg = gen_config(exported, "num=2", "mean_start_below=-10", *world_overrides(world))
    read = generate_bank(read_cfg, tmp_path / "read", progress=False)
    assert "stored_in" not in read["mean_start"]["stage2"]
    first = [p.read_bytes() for p in sorted((tmp_path / "stored").rglob("*.bin"))]
    assert len(first) == 2 and first == [p.read_bytes() for p in sorted((tmp_path / "read").rglob("*.bin"))]
    state = torch.load(exported["stage2"], weights_only=True)
    state["row_mean"]["key"] = "x0_u"  # stage 2 starts from full scans, not from their uncertain part
    torch.save(state, exported["stage2"])
    with pytest.raises(InputError, match="row_mean: expected the x0 mean of 16 rows, got x0_u"):
        generate_bank(gen_config(exported, "num=1", "mean_start_below=-10"), tmp_path / "bad", progress=False)


def test_sequence_generators_start_from_the_mean_over_frames(untrained_sequence_checkpoints, tmp_path):
    world = (tmp_path / "world", tmp_path / "probs")
    write_posed_world(*world, num_scans=3)
    _, cfg = load_generator(untrained_sequence_checkpoints["stage2"])
    cfg.data_root, cfg.probs_root = str(world[0]), str(world[1])
    images = RangeImages(cfg)  # 2-frame windows (L, C, H, W)
    frames = torch.cat([images[i]["x0"] for i in range(len(images))])
    assert torch.allclose(row_mean(cfg, "x0"), frames.mean(dim=(0, 3)).unsqueeze(-1), atol=1e-6)
    manifest = generate_bank(
        gen_config(untrained_sequence_checkpoints, "num=1", "mean_start_below=-10", *world_overrides(world)),
        tmp_path / "bank",
        progress=False,
    )
    assert manifest["frames"] == 2 and manifest["mean_start"]["stage1"]["key"] == "x0_u"
    assert len(list((tmp_path / "bank" / "sequences").rglob("*.bin"))) == 2
