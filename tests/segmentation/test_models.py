"""MinkUNet-like and SPVCNN-like nets: shapes, per-point logits in order, permutations, backward."""

from __future__ import annotations

import pytest
import torch

from segmentation.models import SPVCNN, MinkUNet, SegModelConfig, build_model, point_features

NAMES = ["minkunet", "spvcnn"]


def tiny_config(name: str, **kwargs) -> SegModelConfig:
    """Width 1/8 (channels 4..32), 1 block per stage, 0.25 m voxels: forward+backward well under 1 s."""
    fields = dict(name=name, num_classes=5, voxel_size=0.25, width=0.125, blocks=(1, 1, 1, 1))
    fields.update(decoder_blocks=(1, 1, 1, 1))
    fields.update(kwargs)
    return SegModelConfig(**fields)


def random_scans(generator: torch.Generator, sizes=(700, 400)) -> list[torch.Tensor]:
    """Scans of (N_b, 4) points in a 16 x 16 x 3 m box with intensity in [0, 1]."""
    scale = torch.tensor([16.0, 16.0, 3.0, 1.0])
    shift = torch.tensor([8.0, 8.0, 2.0, 0.0])
    return [torch.rand(n, 4, generator=generator) * scale - shift for n in sizes]


@pytest.mark.parametrize("name", NAMES)
def test_logits_for_every_point_and_backward(name, generator):
    torch.manual_seed(0)  # parameter init only
    model = build_model(tiny_config(name))
    scans = random_scans(generator)
    logits = model(scans)
    assert logits.shape == (1100, 5) and bool(torch.isfinite(logits).all())
    labels = torch.randint(0, 5, (1100,), generator=generator)
    torch.nn.functional.cross_entropy(logits, labels).backward()
    grads = [p.grad for p in model.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0


@pytest.mark.parametrize("name", NAMES)
def test_permuting_points_permutes_logits(name, generator):
    torch.manual_seed(0)
    model = build_model(tiny_config(name)).eval()
    scans = random_scans(generator)
    perm = torch.randperm(700, generator=generator)
    with torch.no_grad():
        logits = model(scans)
        permuted = model([scans[0][perm], scans[1]])
    torch.testing.assert_close(permuted[:700], logits[:700][perm], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(permuted[700:], logits[700:], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("name", NAMES)
def test_scans_in_a_batch_are_independent_in_eval(name, generator):
    torch.manual_seed(0)
    model = build_model(tiny_config(name)).eval()
    scans = random_scans(generator)
    with torch.no_grad():
        together = model(scans)
        alone = model([scans[1]])
    torch.testing.assert_close(together[700:], alone, rtol=1e-4, atol=1e-4)


def test_points_in_one_voxel_share_minkunet_logits(generator):
    torch.manual_seed(0)
    model = build_model(tiny_config("minkunet")).eval()
    scan = random_scans(generator, sizes=(300,))[0]
    twin = scan[:1].clone()
    twin[0, :3] = torch.floor(scan[0, :3] / 0.25) * 0.25 + 0.01  # same voxel, other position
    with torch.no_grad():
        logits = model([torch.cat([scan, twin])])
    torch.testing.assert_close(logits[0], logits[300])


def test_minkunet_voxel_output_is_what_its_points_read(generator):
    torch.manual_seed(0)
    model = build_model(tiny_config("minkunet")).eval()
    scans = random_scans(generator)
    with torch.no_grad():
        points = model(scans)
        out = model(scans, voxel_output=True)
    assert out.logits.shape[0] < 1100 and out.inverse.shape == (1100,)
    torch.testing.assert_close(out.logits[out.inverse], points)
    # voxel rows sorted by scan, and each point's voxel belongs to its own scan
    assert bool((out.batch[1:] >= out.batch[:-1]).all())
    assert out.batch[out.inverse].tolist() == [0] * 700 + [1] * 400


def test_trilinear_readout_interpolates_the_voxel_softmax(generator):
    """readout=trilinear: a point at a voxel centre reads that voxel's softmax, one halfway between two occupied
    centres (with the other 6 corners empty) the mean of their two; log-probabilities, voxel output unchanged."""
    torch.manual_seed(0)
    cfg = tiny_config("minkunet", readout="trilinear")
    model = build_model(cfg).eval()
    centres = torch.tensor([[0.125, 0.125, 0.125, 0.5], [0.375, 0.125, 0.125, 0.2], [2.125, 2.125, 0.125, 0.9]])
    halfway = torch.tensor([[0.25, 0.125, 0.125, 0.0]])  # between the first two centres (in the second voxel)
    scan = torch.cat([centres, halfway])
    with torch.no_grad():
        voxel = model([scan], voxel_output=True)
        logits = model([scan])
    softmax = torch.softmax(voxel.logits, dim=1)[voxel.inverse]  # (4, K): each point's voxel
    torch.testing.assert_close(logits.exp().sum(dim=1), torch.ones(4))
    torch.testing.assert_close(logits[:3].exp(), softmax[:3])
    torch.testing.assert_close(logits[3].exp(), (softmax[0] + softmax[1]) / 2)
    assert not torch.allclose(softmax[0], softmax[1])  # so the mean differs from the point's own voxel
    with torch.no_grad():
        plain = build_model(tiny_config("minkunet"))
        plain.load_state_dict(model.state_dict())
        assert torch.equal(plain.eval()([scan], voxel_output=True).logits, model([scan], voxel_output=True).logits)
    with pytest.raises(ValueError, match="readout"):
        tiny_config("spvcnn", readout="trilinear")


def test_default_channels_follow_minkunet18_w32():
    model = build_model(SegModelConfig())
    assert isinstance(model, MinkUNet)
    unet = model.unet
    assert unet.base_channels == 32
    assert unet.encoder_channels == [32, 64, 128, 256]
    assert unet.decoder_channels == [256, 128, 96, 96]
    assert model.head.in_features == 96 and model.head.out_features == 19
    w16 = build_model(SegModelConfig(name="spvcnn", width=0.5))
    assert isinstance(w16, SPVCNN)
    assert w16.unet.encoder_channels == [16, 32, 64, 128] and w16.unet.decoder_channels == [128, 64, 48, 48]
    assert [m[0].out_features for m in w16.point_mlps] == [128, 64, 48]


def test_blocks_config_sets_residual_blocks():
    model = build_model(tiny_config("minkunet", blocks=(2, 3, 4, 6)))
    assert [len(stage) - 1 for stage in model.unet.encoder] == [2, 3, 4, 6]


@pytest.mark.parametrize("name", ["minkunet", "spvcnn"])
@pytest.mark.parametrize("in_features", ["xyz", "i", "xyzir", "local"])
def test_input_feature_choices(name, in_features, generator):
    torch.manual_seed(0)
    model = build_model(tiny_config(name, in_features=in_features))
    scans = random_scans(generator)
    assert model(scans).shape == (1100, 5)
    width = {"xyz": 3, "i": 1, "xyzir": 5, "local": 6}[in_features]
    assert point_features(scans[0], in_features, 0.25).shape == (scans[0].shape[0], width)


def test_local_features_do_not_turn_with_the_scan():
    points = torch.tensor([[1.125, -2.125, -1.625, 0.3], [3.0, 4.0, 0.5, 0.9], [-0.1, 0.2, 1.0, 0.0]])
    f = point_features(points, "local", 0.25)
    # the first point sits at its voxel's centre, the second on a voxel corner, the third inside one
    torch.testing.assert_close(f[0, :3], torch.zeros(3))
    torch.testing.assert_close(f[1, :3], torch.full((3,), -0.5))
    torch.testing.assert_close(f[2, :3], torch.tensor([0.1, 0.3, -0.5]))
    torch.testing.assert_close(f[:, 3:5], points[:, 2:4])  # z, intensity as they are
    torch.testing.assert_close(f[1, 5], torch.tensor(0.5))  # horizontal range 5 m / 10 m
    turned = points.clone()
    turned[:, :2] = points[:, :2] @ torch.tensor([[0.6, -0.8], [0.8, 0.6]]).T  # a rotation about z
    torch.testing.assert_close(point_features(turned, "local", 0.25)[:, 3:], f[:, 3:])


def test_bad_configs_and_inputs():
    with pytest.raises(ValueError, match="minkunet"):
        build_model(SegModelConfig(name="pointnet"))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="same length"):
        SegModelConfig(blocks=(2, 2))
    with pytest.raises(ValueError, match="dropout"):
        SegModelConfig(dropout=1.0)
    model = build_model(tiny_config("minkunet"))
    with pytest.raises(ValueError, match="scan 0"):
        model([torch.zeros(5, 3)])
    with pytest.raises(ValueError, match="at least one scan"):
        model([])


def test_real_scan_forward(real_root):
    """One real SemanticKITTI scan through the tiny SPVCNN: logits for all ~124k points."""
    import numpy as np

    path = real_root / "semantickitti" / "sequences" / "00" / "velodyne" / "000000.bin"
    points = torch.from_numpy(np.fromfile(path, dtype=np.float32).reshape(-1, 4))
    torch.manual_seed(0)
    model = build_model(tiny_config("spvcnn", voxel_size=0.4)).eval()
    with torch.no_grad():
        logits = model([points])
    assert logits.shape == (points.shape[0], 5) and bool(torch.isfinite(logits).all())
