"""Entropy, top-K selection of P_u and its projection to (x0_u, m_u)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from u4d_aug.data.formats import read_kitti_scan
from u4d_aug.data.sensors import hdl64
from u4d_aug.errors import InputError
from u4d_aug.range_view import project, to_image
from u4d_aug.uncertainty import entropy, load_probs, select_uncertain, uncertain_range_view


def _random_probs(num_points: int, num_classes: int, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    logits = torch.randn(num_points, num_classes, generator=generator) * 3
    return logits.softmax(dim=1)


def _ring_points(num_points: int, seed: int = 0) -> torch.Tensor:
    """Points on HDL-64 rays at 5-40 m, random azimuth (every one projects into the image)."""
    rng = np.random.default_rng(seed)
    sensor = hdl64()
    elevation = np.deg2rad(np.asarray(sensor.elevations_deg))[rng.integers(0, 64, num_points)]
    azimuth = rng.uniform(-np.pi, np.pi, num_points)
    depth = rng.uniform(5.0, 40.0, num_points)
    xyz = np.stack(
        [
            depth * np.cos(elevation) * np.cos(azimuth),
            depth * np.cos(elevation) * np.sin(azimuth),
            depth * np.sin(elevation),
        ],
        axis=1,
    )
    return torch.from_numpy(np.concatenate([xyz, rng.uniform(0, 1, (num_points, 1))], axis=1).astype(np.float32))


def test_entropy_one_hot_is_zero_and_uniform_is_log_k():
    one_hot = torch.eye(19)[torch.tensor([0, 5, 18])]
    assert torch.equal(entropy(one_hot), torch.zeros(3))
    uniform = torch.full((4, 19), 1 / 19)
    torch.testing.assert_close(entropy(uniform), torch.full((4,), math.log(19)))
    # float16 files as written by seg-predict
    torch.testing.assert_close(
        entropy(np.full((2, 7), 1 / 7, dtype=np.float16)), torch.full((2,), math.log(7)), atol=1e-3, rtol=0
    )
    # golden: p = (0.5, 0.25, 0.25) -> 1.5 log 2
    assert float(entropy(torch.tensor([[0.5, 0.25, 0.25]]))[0]) == pytest.approx(1.5 * math.log(2), abs=1e-6)


def test_top_k_selects_exactly_the_highest_entropy_points():
    probs = _random_probs(500, 19)
    h = entropy(probs)
    chosen = select_uncertain(probs, 40, "entropy")
    assert chosen.shape == (40,) and len(set(chosen.tolist())) == 40
    rest = torch.ones(500, dtype=torch.bool)
    rest[chosen] = False
    assert float(h[chosen].min()) >= float(h[rest].max())
    # fraction form: 10% of 500
    assert select_uncertain(probs, 0.1, "entropy").shape == (50,)
    assert torch.equal(select_uncertain(probs, 0.08, "entropy"), chosen)


def test_confidence_random_none_strategies():
    probs = _random_probs(300, 5, seed=1)
    chosen = select_uncertain(probs, 30, "confidence")
    max_prob = probs.max(dim=1).values
    rest = torch.ones(300, dtype=torch.bool)
    rest[chosen] = False
    assert float(max_prob[chosen].max()) <= float(max_prob[rest].min())
    a = select_uncertain(probs, 30, "random", torch.Generator().manual_seed(3))
    b = select_uncertain(probs, 30, "random", torch.Generator().manual_seed(3))
    assert torch.equal(a, b) and len(set(a.tolist())) == 30
    assert select_uncertain(probs, 30, "none").numel() == 0
    with pytest.raises(InputError):
        select_uncertain(probs, 1.5, "entropy")
    with pytest.raises(InputError):
        select_uncertain(probs, 3, "most")  # type: ignore[arg-type]


def test_m_u_marks_the_pixels_p_u_wins_and_x0_u_is_x0_there():
    sensor = hdl64()
    points = _ring_points(3000)
    probs = _random_probs(3000, 19, seed=2)
    x0_u, m_u, entropy_image = uncertain_range_view(points, probs, sensor, 64, 256, "beam", k=200)
    assert x0_u.shape == (2, 64, 256) and m_u.shape == (1, 64, 256) and entropy_image.shape == (64, 256)
    chosen = select_uncertain(probs, 200, "entropy")
    full = project(points, sensor, 64, 256, "beam")
    # m_u: the pixels whose shown point (of the full scan) is in P_u; x0_u = x0 · m_u exactly, -1 elsewhere
    in_p_u = torch.zeros(points.shape[0], dtype=torch.bool)
    in_p_u[chosen] = True
    expected = (full.winner >= 0) & in_p_u[full.winner.clamp(min=0)]
    assert torch.equal(m_u[0].bool(), expected)
    x0 = to_image(full, sensor)
    assert torch.equal(x0_u[:, m_u[0] == 1], x0[:, m_u[0] == 1])
    assert torch.equal(x0_u, torch.where(m_u.bool(), x0, torch.full_like(x0, -1.0)))
    assert bool((x0_u[:, m_u[0] == 0] == -1).all())
    # a P_u point hidden behind a nearer point outside P_u does not enter m_u
    hidden = chosen[~expected.flatten()[full.pixel[chosen].clamp(min=0)]]
    assert len(hidden) > 0
    # the entropy image holds the entropy of the winning point and NaN where there is no return
    full = project(points, sensor, 64, 256, "beam")
    h = entropy(probs)
    torch.testing.assert_close(entropy_image[full.mask], h[full.winner[full.mask]])
    assert bool(entropy_image[~full.mask].isnan().all())
    _, m_none, _ = uncertain_range_view(points, probs, sensor, 64, 256, "beam", k=200, strategy="none")
    assert float(m_none.sum()) == 0.0


def test_real_scan_uncertain_region(kitti_root):
    points = read_kitti_scan(kitti_root / "sequences" / "00" / "velodyne" / "000000.bin")
    probs = _random_probs(points.shape[0], 19, seed=4).numpy().astype(np.float16)
    x0_u, m_u, _ = uncertain_range_view(points, probs, hdl64(), k=0.05)
    assert 0 < float(m_u.sum()) <= 0.05 * points.shape[0] + 1
    with pytest.raises(InputError):
        uncertain_range_view(points, probs[:-1], hdl64(), k=0.05)


def test_nan_or_inf_probabilities_are_refused_in_one_line(tmp_path):
    probs = _random_probs(50, 4).numpy()
    probs[3, 1] = np.nan
    with pytest.raises(InputError, match="1 NaN/inf values"):
        entropy(probs)
    with pytest.raises(InputError, match="NaN/inf"):
        uncertain_range_view(_ring_points(50), probs, hdl64(), k=5)
    np.save(tmp_path / "nan.npy", probs.astype(np.float16))
    with pytest.raises(InputError, match="nan.npy: 1 probabilities are NaN/inf"):
        load_probs(tmp_path / "nan.npy", 50)


def test_probability_files_of_objects_truncated_or_wrong_dtype_are_one_line(tmp_path):
    np.save(tmp_path / "objects.npy", np.array([[0.5, 0.5]], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match="objects.npy: refused as a probability file: it holds python objects"):
        load_probs(tmp_path / "objects.npy")
    np.save(tmp_path / "ok.npy", _random_probs(20, 3).numpy().astype(np.float16))
    (tmp_path / "cut.npy").write_bytes((tmp_path / "ok.npy").read_bytes()[:-10])
    with pytest.raises(InputError, match="cut.npy: not a readable probability file"):
        load_probs(tmp_path / "cut.npy")
    np.save(tmp_path / "ints.npy", np.zeros((20, 3), dtype=np.int64))
    with pytest.raises(InputError, match="ints.npy: expected an \\(N, K\\) float array"):
        load_probs(tmp_path / "ints.npy")
    assert load_probs(tmp_path / "ok.npy", 20).shape == (20, 3)


def test_logits_or_unnormalised_scores_are_refused_a_float16_softmax_is_not(tmp_path):
    rng = np.random.default_rng(3)
    logits = rng.normal(0, 3, (40, 6))
    softmax = np.exp(logits) / np.exp(logits).sum(axis=1, keepdims=True)
    np.save(tmp_path / "softmax.npy", softmax.astype(np.float16))  # float16 rounding stays within the tolerances
    assert load_probs(tmp_path / "softmax.npy", 40).shape == (40, 6)
    np.save(tmp_path / "logits.npy", logits.astype(np.float16))
    with pytest.raises(InputError, match=r"logits.npy: \d+ values outside \[0, 1\] \(min -"):
        load_probs(tmp_path / "logits.npy", 40)
    scores = softmax * 0.5
    np.save(tmp_path / "scores.npy", np.clip(scores, 0, 1).astype(np.float32))
    with pytest.raises(InputError, match=r"scores.npy: 40 of 40 rows do not sum to 1"):
        load_probs(tmp_path / "scores.npy", 40)
    with pytest.raises(InputError, match="values outside \\[0, 1\\]; expected softmax outputs, not logits"):
        entropy(logits)  # the library function refuses them too: their entropy would come out negative
    assert float(entropy(softmax).min()) >= 0.0
