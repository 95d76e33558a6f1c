"""Inference pipeline: EMA loading, U4D two-stage generation, completion, baseline, unprojection to points."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.tiny_nets import TINY, TINY_MOST, plain_settings, save_checkpoint, save_random_checkpoint
from u4d_aug import sampling
from u4d_aug.data.sensors import hdl64
from u4d_aug.errors import InputError
from u4d_aug.export_weights import export_weights
from u4d_aug.nn.most import MoSTBlock
from u4d_aug.pipeline import (
    LoadedGenerator,
    MeanStart,
    cap_mask,
    complete,
    generate_baseline,
    generate_stage1,
    generate_u4d,
    inpaint,
    load_generator,
    mask_from_logits,
    to_points,
)
from u4d_aug.range_view import project, to_image

PLAIN = plain_settings(3)  # DDIM at 3 steps, no mask cap, no mean start: these nets store no training mean
PLAIN_2 = plain_settings(2)


def test_load_generator_uses_ema_weights(random_ema_checkpoints):
    loaded = load_generator(random_ema_checkpoints["stage2"])
    net, cfg = loaded  # unpacks as the (net, config) pair it once was
    assert isinstance(loaded, LoadedGenerator) and loaded.net is net and loaded.config is cfg
    assert cfg.diffusion.stage == "stage2" and not net.training
    state = torch.load(random_ema_checkpoints["stage2"], weights_only=False)
    for name, param in net.named_parameters():
        torch.testing.assert_close(param, state["ema"]["params"][name])
    assert any(float(p.abs().sum()) > 0 for p in net.parameters())


def test_same_generator_same_output_and_masking(random_ema_checkpoints):
    stage1, stage2 = load_generator(random_ema_checkpoints["stage1"]), load_generator(random_ema_checkpoints["stage2"])
    a = generate_u4d(stage1, stage2, 2, torch.Generator().manual_seed(7), PLAIN)
    b = generate_u4d(stage1, stage2, 2, torch.Generator().manual_seed(7), PLAIN)
    c = generate_u4d(stage1, stage2, 2, torch.Generator().manual_seed(8), PLAIN)
    for key in ("x0", "x0_u", "m_u_pred"):
        assert torch.equal(a[key], b[key])
    assert not torch.equal(a["x0"], c["x0"])
    assert a["x0"].shape == (2, 2, 16, 64) and a["m_u_pred"].shape == (2, 1, 16, 64)
    m = a["m_u_pred"].bool().expand_as(a["x0_u"])
    assert 0 < int(a["m_u_pred"].sum()) < a["m_u_pred"].numel()
    assert bool((a["x0_u"][~m] == -1).all())
    baseline = load_generator(random_ema_checkpoints["baseline"])
    d = generate_baseline(baseline, 1, torch.Generator().manual_seed(1), plain_settings(3, "ddpm"))
    e = generate_baseline(baseline, 1, torch.Generator().manual_seed(1), plain_settings(3, "ddpm"))
    assert torch.equal(d["x0"], e["x0"]) and float(d["x0"].abs().max()) <= 1.0


def test_cap_mask_keeps_the_surest_pixels_of_each_frame():
    logits = torch.randn(2, 3, 1, 4, 8, generator=torch.Generator().manual_seed(0))  # (B, L, 1, H, W)
    full = torch.ones_like(logits)
    capped = cap_mask(full, logits, 0.25)  # 8 of each frame's 32 pixels
    assert capped.shape == logits.shape and capped.sum(dim=(-3, -2, -1)).eq(8).all()
    kept_min = torch.where(capped.bool(), logits, torch.inf).amin(dim=(-3, -2, -1))
    dropped_max = torch.where(capped.bool(), -torch.inf, logits).amax(dim=(-3, -2, -1))
    assert bool((kept_min > dropped_max).all())  # the top logits of every frame, not of the batch
    sparse = (logits > 1.5).float()  # fewer pixels than the cap: left as they are
    assert sparse.sum(dim=(-3, -2, -1)).lt(8).all() and torch.equal(cap_mask(sparse, logits, 0.25), sparse)


def test_mask_fraction_caps_the_stage1_mask(random_ema_checkpoints):
    stage1, stage2 = load_generator(random_ema_checkpoints["stage1"]), load_generator(random_ema_checkpoints["stage2"])
    free = generate_u4d(stage1, stage2, 2, torch.Generator().manual_seed(7), PLAIN)
    capped = generate_u4d(
        stage1, stage2, 2, torch.Generator().manual_seed(7), plain_settings(3, stage1_mask_fraction=0.05)
    )
    limit = round(0.05 * 16 * 64)
    assert bool((free["m_u_pred"].sum(dim=(1, 2, 3)) > limit).all())  # the cap binds
    assert bool((capped["m_u_pred"].sum(dim=(1, 2, 3)) <= limit).all())
    assert bool((capped["m_u_pred"] <= free["m_u_pred"]).all())  # a subset of the thresholded mask
    assert bool((capped["x0_u"][~capped["m_u_pred"].bool().expand_as(capped["x0_u"])] == -1).all())


def test_stage2_output_depends_on_its_condition(random_ema_checkpoints):
    stage2 = load_generator(random_ema_checkpoints["stage2"])
    x0_u = torch.full((1, 2, 16, 64), -1.0)
    m_u = torch.zeros(1, 1, 16, 64)
    empty = complete(stage2, x0_u, m_u, torch.Generator().manual_seed(0), PLAIN)["x0"]
    x0_u[:, :, 4:8, 10:30] = 0.3
    m_u[:, :, 4:8, 10:30] = 1.0
    filled = complete(stage2, x0_u, m_u, torch.Generator().manual_seed(0), PLAIN)["x0"]
    assert float((filled - empty).abs().max()) > 1e-3

    # pinned: x̂0 is the known pixels at every step, so the sample ends on them there and the rest follows
    pinned = complete(stage2, x0_u, m_u, torch.Generator().manual_seed(0), PLAIN, pin_known=True)["x0"]
    known = m_u.bool().expand_as(x0_u)
    assert torch.allclose(pinned[known], x0_u[known], atol=1e-5)
    assert not torch.allclose(filled[known], x0_u[known], atol=1e-3)  # not so without the pin
    assert float((pinned - filled)[~known].abs().max()) > 1e-4


def test_inpaint_keeps_the_known_pixels_and_fills_the_rest_from_them(random_ema_checkpoints):
    baseline = load_generator(random_ema_checkpoints["baseline"])
    x0_u = torch.full((1, 2, 16, 64), -1.0)
    m_u = torch.zeros(1, 1, 16, 64)
    x0_u[:, :, 4:12, 10:40] = 0.3
    m_u[:, :, 4:12, 10:40] = 1.0
    out = inpaint(baseline, x0_u, m_u, torch.Generator().manual_seed(0), PLAIN)
    assert torch.equal(out["x0"][:, :, 4:12, 10:40], x0_u[:, :, 4:12, 10:40])  # exact where known
    free = generate_baseline(baseline, 1, torch.Generator().manual_seed(0), PLAIN)["x0"]
    unknown = ~m_u.bool().expand_as(x0_u)
    assert float((out["x0"] - free)[unknown].abs().max()) > 1e-3  # the known pixels steer the others
    with pytest.raises(InputError, match="16x64"):
        inpaint(baseline, torch.zeros(1, 2, 8, 64), torch.zeros(1, 1, 8, 64), torch.Generator(), PLAIN)
    with pytest.raises(InputError, match="baseline"):
        inpaint(load_generator(random_ema_checkpoints["stage2"]), x0_u, m_u, torch.Generator(), PLAIN)


def test_wrong_stage_or_size_is_an_input_error(random_ema_checkpoints):
    stage1, stage2 = load_generator(random_ema_checkpoints["stage1"]), load_generator(random_ema_checkpoints["stage2"])
    with pytest.raises(InputError, match="stage1"):
        generate_stage1(stage2, 1, torch.Generator(), PLAIN)
    with pytest.raises(InputError, match="16x64"):
        complete(stage2, torch.zeros(1, 2, 8, 64), torch.zeros(1, 1, 8, 64), torch.Generator(), PLAIN)
    with pytest.raises(InputError):
        generate_baseline(stage1, 1, torch.Generator(), PLAIN)


def test_the_mean_start_takes_each_role_s_stored_mean(tmp_path):
    """Exported weights keep their training means as the net's `row_mean_<role>` buffers (not in its state_dict); a
    one-net u4d file without its stage-1 mean still loads, and the mean start names what to do for stage 1."""
    path = tmp_path / "u4d.pt"
    export_weights(save_random_checkpoint(tmp_path / "ckpt.pt", "u4d"), path, data_root=str(tmp_path / "nowhere"))
    state = torch.load(path, weights_only=True)
    mean = torch.stack([torch.linspace(-0.5, 0.5, 16), torch.full((16,), 0.2)])[..., None]  # (2, H, 1)
    state["row_mean"] = {"key": "x0", "mean": mean, "source": {"data_root": "hand-made"}}
    torch.save(state, path)
    loaded = load_generator(path)
    buffers = dict(loaded.net.named_buffers(recurse=False))
    assert torch.equal(buffers["row_mean_stage2"], mean) and "row_mean_stage1" not in buffers
    assert "row_mean_stage2" not in loaded.net.state_dict()
    x0_u, m_u = torch.full((1, 2, 16, 64), -1.0), torch.zeros(1, 1, 16, 64)
    started = complete(loaded, x0_u, m_u, torch.Generator().manual_seed(0), plain_settings(2, mean_start_below=-10.0))
    by_hand = complete(
        (MeanStart(loaded.net, mean, -10.0), loaded.config), x0_u, m_u, torch.Generator().manual_seed(0), PLAIN_2
    )
    own = complete(loaded, x0_u, m_u, torch.Generator().manual_seed(0), PLAIN_2)
    assert torch.equal(started["x0"], by_hand["x0"]) and not torch.equal(started["x0"], own["x0"])
    with pytest.raises(InputError, match="no stored training mean for stage1 .*export-weights --data-root"):
        generate_u4d(loaded, loaded, 1, torch.Generator(), plain_settings(2, mean_start_below=-10.0))


def test_to_points_returns_one_valid_point_per_return_pixel():
    sensor = hdl64()
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(5000, 3)) * np.array([20.0, 20.0, 1.0]) + np.array([0.0, 0.0, -1.0])
    points = torch.from_numpy(np.concatenate([xyz, rng.uniform(0, 1, (5000, 1))], axis=1).astype(np.float32))
    projection = project(points, sensor, 64, 256, "beam")
    image = to_image(projection, sensor)[None]  # (1, 2, 64, 256)
    (cloud,) = to_points(image, sensor, "beam")
    assert cloud.dtype == np.float32 and cloud.shape == (int(projection.mask.sum()), 4)
    depth = np.linalg.norm(cloud[:, :3], axis=1)
    assert depth.min() >= sensor.min_range * 0.999 and depth.max() <= sensor.max_range * 1.001


@pytest.fixture(scope="module")
def sequence_checkpoints(tmp_path_factory) -> dict[str, Path]:
    """Random-EMA 2-frame MoST checkpoints (configs/u4d/tiny_most.yaml)."""
    root = tmp_path_factory.mktemp("ckpt_most")
    most = TINY.with_name("tiny_most.yaml")
    return {s: save_random_checkpoint(root / f"{s}.pt", s, config=most) for s in ("stage1", "stage2", "baseline")}


def nudge_frame_1(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every sampler's x_1 gets +0.5 on frame 1 of each sequence; frame 0's noise is untouched."""
    draw = sampling._randn

    def nudged(shape, generator, device):
        x = draw(shape, generator, device)
        if len(shape) == 5:  # (B, L, C, H, W)
            x[:, 1] += 0.5
        return x

    monkeypatch.setattr(sampling, "_randn", nudged)


def without_temporal_branch(loaded):
    """A copy whose MoST blocks have a zero temporal conv and constant gates: its frames never meet."""
    net = copy.deepcopy(loaded.net)
    with torch.no_grad():
        for block in net.modules():
            if isinstance(block, MoSTBlock):
                for layer in (block.temporal, block.gate[-1]):
                    layer.weight.zero_()
                block.temporal.bias.zero_()
    return LoadedGenerator(net, loaded.config)


def test_sequence_generation_shapes_and_frame_mixing(sequence_checkpoints, random_ema_checkpoints, monkeypatch):
    stage1, stage2 = load_generator(sequence_checkpoints["stage1"]), load_generator(sequence_checkpoints["stage2"])
    assert stage2.config.frames == 2 and stage2.net.most_names
    a = generate_u4d(stage1, stage2, 2, torch.Generator().manual_seed(7), PLAIN)
    b = generate_u4d(stage1, stage2, 2, torch.Generator().manual_seed(7), PLAIN)
    assert a["x0"].shape == (2, 2, 2, 16, 64) and a["m_u_pred"].shape == (2, 2, 1, 16, 64)
    assert torch.equal(a["x0"], b["x0"]) and not torch.equal(a["x0"][:, 0], a["x0"][:, 1])
    # frames mix: changing only frame 1's starting noise changes frame 0's sample, through the temporal branch
    alone = without_temporal_branch(stage1), without_temporal_branch(stage2)
    c = generate_u4d(*alone, 2, torch.Generator().manual_seed(7), PLAIN)
    with monkeypatch.context() as patch:
        nudge_frame_1(patch)
        nudged = generate_u4d(stage1, stage2, 2, torch.Generator().manual_seed(7), PLAIN)
        nudged_alone = generate_u4d(*alone, 2, torch.Generator().manual_seed(7), PLAIN)
    assert float((nudged["x0"][:, 0] - a["x0"][:, 0]).abs().max()) > 1e-2
    assert float((nudged["x0_u"][:, 0] - a["x0_u"][:, 0]).abs().max()) > 1e-2  # stage 1 mixes its frames too
    # without it frame 0 is bit for bit what it was: nothing else in the net looks across frames
    assert torch.equal(nudged_alone["x0"][:, 0], c["x0"][:, 0]) and torch.equal(
        nudged_alone["x0_u"][:, 0], c["x0_u"][:, 0]
    )
    assert not torch.equal(nudged_alone["x0"][:, 1], c["x0"][:, 1])  # the nudge itself reached frame 1
    m = a["m_u_pred"].bool().expand_as(a["x0_u"])
    assert bool((a["x0_u"][~m] == -1).all())
    clouds = to_points(a["x0"], hdl64(), stage2.config.row_mode)
    assert len(clouds) == 4 and all(c.shape[1] == 4 for c in clouds)  # sample 0 frames 0, 1, sample 1 ...
    sequence_baseline = load_generator(sequence_checkpoints["baseline"])
    assert generate_baseline(sequence_baseline, 1, torch.Generator(), PLAIN)["x0"].shape == (1, 2, 2, 16, 64)
    # a single-frame stage 1 gives stage 2 its L frames, each generated on its own
    mixed = generate_u4d(
        load_generator(random_ema_checkpoints["stage1"]), stage2, 1, torch.Generator().manual_seed(0), PLAIN
    )
    assert mixed["x0_u"].shape == (1, 2, 2, 16, 64)


def test_sequence_completion_mixes_the_frames_conditions(sequence_checkpoints):
    stage2 = load_generator(sequence_checkpoints["stage2"])
    x0_u = torch.full((1, 2, 2, 16, 64), -1.0)
    m_u = torch.zeros(1, 2, 1, 16, 64)
    empty = complete(stage2, x0_u, m_u, torch.Generator().manual_seed(0), PLAIN)["x0"]
    x0_u[:, 0, :, 4:8, 10:30] = 0.3  # only frame 0's condition changes
    m_u[:, 0, :, 4:8, 10:30] = 1.0
    filled = complete(stage2, x0_u, m_u, torch.Generator().manual_seed(0), PLAIN)["x0"]
    assert filled.shape == (1, 2, 2, 16, 64)
    assert float((filled[:, 1] - empty[:, 1]).abs().max()) > 1e-3  # frame 1 sees it through MoST
    with pytest.raises(InputError, match="m_u"):
        complete(stage2, x0_u, m_u[:, :1], torch.Generator(), PLAIN)


@pytest.mark.parametrize("pos_weight", [1.0, 4.0])
def test_mask_threshold_undoes_the_bce_positive_weight(pos_weight):
    """Fit one logit per pixel group to Bernoulli(q) targets with the weighted BCE of training: m_p = 1 iff q > 1/2."""
    frequencies = torch.tensor([0.1, 0.3, 0.45, 0.55, 0.7, 0.9])
    targets = (torch.arange(1000)[None, :] < frequencies[:, None] * 1000).float()  # (6, 1000), exact frequency q
    logits = torch.zeros(6, 1, requires_grad=True)
    optimizer = torch.optim.LBFGS([logits], lr=1.0, max_iter=200)

    def loss():
        optimizer.zero_grad()
        value = torch.nn.functional.binary_cross_entropy_with_logits(
            logits.expand_as(targets), targets, pos_weight=torch.tensor(pos_weight)
        )
        value.backward()
        return value

    optimizer.step(loss)
    fitted = logits.detach()[:, 0]
    expected = torch.log(pos_weight * frequencies / (1 - frequencies))
    torch.testing.assert_close(fitted, expected, atol=1e-3, rtol=1e-3)
    assert mask_from_logits(fitted, pos_weight).tolist() == [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]
    if pos_weight > 1:  # a plain sigmoid > 0.5 would also keep the q = 0.3 and 0.45 pixels
        assert (torch.sigmoid(fitted) > 0.5).sum() == 5


def test_ego_motion_reaches_the_net_through_every_generator(tmp_path):
    """A net trained with poses samples only with motion of the right shape, and the motion changes the sample."""
    from u4d_aug.errors import InputError
    from u4d_aug.pipeline import generate_baseline, generate_u4d, load_generator
    from u4d_aug.trajectory import straight_motion

    def randomize(net) -> None:  # random weights everywhere (zero-initialised outputs too), so the motion matters
        weights = torch.Generator().manual_seed(1)
        with torch.no_grad():
            for p in net.parameters():
                p.copy_(torch.randn(p.shape, generator=weights) * 0.1)

    loaded = {}
    for stage in ("stage1", "stage2", "baseline"):
        overrides = (f"diffusion.stage={stage}", "net.pose_dim=4")
        loaded[stage] = load_generator(save_checkpoint(tmp_path / f"{stage}.pt", TINY_MOST, overrides, 1, randomize))
    straight = torch.from_numpy(straight_motion(2, 1.2))[None]  # (1, L=2, 4)
    turning = torch.from_numpy(straight_motion(2, 1.2, yaw_rate=0.3))[None]
    a = generate_baseline(loaded["baseline"], 1, torch.Generator().manual_seed(0), PLAIN, motion=straight)["x0"]
    b = generate_baseline(loaded["baseline"], 1, torch.Generator().manual_seed(0), PLAIN, motion=turning)["x0"]
    assert a.shape == (1, 2, 2, 16, 64) and not torch.allclose(a, b)
    u4d = generate_u4d(loaded["stage1"], loaded["stage2"], 1, torch.Generator().manual_seed(0), PLAIN, motion=straight)
    assert u4d["x0"].shape == (1, 2, 2, 16, 64)
    with pytest.raises(InputError, match="conditioned on ego motion"):
        generate_baseline(loaded["baseline"], 1, torch.Generator(), PLAIN)
    with pytest.raises(InputError, match="conditioned on ego motion"):
        generate_baseline(loaded["baseline"], 2, torch.Generator(), PLAIN, motion=straight)  # 1 motion, 2 samples
