"""Label splits and scan augmentation for segmentation training."""

from __future__ import annotations

import pytest
import torch

from segmentation.config import SegDataConfig
from segmentation.data import AugmentConfig, augment, load_or_make_split, make_split, paste_instances, training_subset
from u4d_aug.errors import InputError

FRAMES = [(seq, f"{i:06d}") for seq in ("00", "01", "02", "03") for i in range(25)]


def test_uniform_split_is_seeded_disjoint_and_sized():
    labeled, unlabeled = make_split(FRAMES, 0.1, seed=1)
    assert len(labeled) == 10
    assert set(labeled).isdisjoint(unlabeled)
    assert set(labeled) | set(unlabeled) == set(FRAMES)
    assert make_split(FRAMES, 0.1, seed=1) == (labeled, unlabeled)
    assert make_split(FRAMES, 0.1, seed=2)[0] != labeled


def test_sequence_split_keeps_whole_sequences():
    labeled, unlabeled = make_split(FRAMES, 0.2, seed=0, mode="sequence")
    labeled_seqs = {s for s, _ in labeled}
    assert labeled_seqs.isdisjoint({s for s, _ in unlabeled})
    assert len(labeled) == 25 * len(labeled_seqs)


def test_full_split_uses_everything_twice():
    labeled, unlabeled = make_split(FRAMES, 1.0, seed=0)
    assert labeled == FRAMES and unlabeled == FRAMES


def test_split_file_is_written_and_reused(tmp_path):
    first = load_or_make_split(tmp_path, FRAMES, 0.2, 3, "uniform")
    files = list((tmp_path / "splits").glob("*.json"))
    assert len(files) == 1 and files[0].name.startswith("uniform_20pct_seed3_")
    # A re-read gives the same split even if the drawing code changed: the file wins.
    assert load_or_make_split(tmp_path, FRAMES, 0.2, 3, "uniform") == first
    # A smaller train set on the same root gets its own file; the first one is kept and still reused.
    smaller = load_or_make_split(tmp_path, FRAMES[:40], 0.2, 3, "uniform")
    assert set(smaller[0]) | set(smaller[1]) == set(FRAMES[:40])
    assert len(list((tmp_path / "splits").glob("*.json"))) == 2
    assert load_or_make_split(tmp_path, FRAMES, 0.2, 3, "uniform") == first


def test_bad_fraction():
    with pytest.raises(InputError, match="fraction"):
        make_split(FRAMES, 0.0, seed=0)


def test_augment_preserves_ranges_and_intensity():
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(100, 4)
    out = augment(pts, g, AugmentConfig(jitter_std=0.0, scale_min=1.0, scale_max=1.0))
    # rotation + flips about z keep horizontal distance and height; intensity untouched
    assert torch.allclose(out[:, :2].norm(dim=1), pts[:, :2].norm(dim=1), atol=1e-5)
    assert torch.allclose(out[:, 2:], pts[:, 2:])
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    assert torch.equal(augment(pts, g1, AugmentConfig()), augment(pts, g2, AugmentConfig()))


def test_paste_instances_appends_rotated_copies_of_the_chosen_classes():
    g = torch.Generator().manual_seed(0)
    points, labels = torch.randn(50, 4), torch.full((50,), 8)  # road
    source = torch.randn(40, 4)
    source_labels = torch.tensor([0] * 10 + [5] * 6 + [8] * 24)  # car, person, road
    out, out_labels = paste_instances(points, labels, source, source_labels, torch.tensor([5]), 3, g)
    assert out.shape == (50 + 3 * 6, 4)
    assert torch.equal(out[:50], points) and torch.equal(out_labels[:50], labels)  # the scan itself untouched
    assert torch.equal(out_labels[50:], torch.full((18,), 5))
    person = source[10:16]
    for k in range(3):
        copy = out[50 + 6 * k : 56 + 6 * k]
        torch.testing.assert_close(copy[:, 2:], person[:, 2:])  # height and intensity kept
        torch.testing.assert_close(copy[:, :2].norm(dim=1), person[:, :2].norm(dim=1))  # rotated about z
        cross = person[:, 0] * copy[:, 1] - person[:, 1] * copy[:, 0]
        dot = (person[:, :2] * copy[:, :2]).sum(1)
        angle = torch.atan2(cross, dot)
        torch.testing.assert_close(angle, angle[:1].expand(6), atol=1e-5, rtol=0)  # one rigid angle per copy
    again = paste_instances(
        points, labels, source, source_labels, torch.tensor([5]), 3, torch.Generator().manual_seed(0)
    )
    assert torch.equal(again[0], out)  # randomness only from the generator
    none, none_labels = paste_instances(points, labels, source, source_labels, torch.tensor([3]), 2, g)
    assert none is points and none_labels is labels  # no truck in the source: nothing pasted


def test_paste_config_is_validated():
    with pytest.raises(ValueError, match="paste_prob"):
        AugmentConfig(paste_prob=1.5)
    with pytest.raises(ValueError, match="paste_copies"):
        AugmentConfig(paste_copies=0)


def ring_scan(n: int = 3600) -> torch.Tensor:
    """(n, 4) points at azimuths 0.05, 0.15, ... degrees on a 10 m circle (one every 0.1 degree)."""
    azimuth = torch.deg2rad(torch.arange(n, dtype=torch.float64) * 360.0 / n + 0.05)
    return torch.stack([10 * azimuth.cos(), 10 * azimuth.sin(), torch.zeros(n), torch.ones(n)], 1).float()


def test_training_subset_sector_keeps_one_contiguous_arc_at_full_density():
    points = ring_scan()
    keep = training_subset(points, 90.0, None, torch.Generator().manual_seed(3))
    assert keep.numel() == 900  # a quarter of the points, none thinned inside the sector
    azimuth = torch.rad2deg(torch.atan2(points[keep, 1], points[keep, 0])).double() % 360.0
    gaps = (azimuth.sort().values.diff() > 0.2).sum()
    assert int(gaps) <= 1  # one arc (it may wrap past 360 degrees once)
    again = training_subset(points, 90.0, None, torch.Generator().manual_seed(3))
    other = training_subset(points, 90.0, None, torch.Generator().manual_seed(4))
    assert torch.equal(keep, again) and not torch.equal(keep, other)


def test_training_subset_thins_after_the_sector_and_matches_plain_thinning_without_one():
    points = ring_scan()
    keep = training_subset(points, 180.0, 500, torch.Generator().manual_seed(0))
    assert keep.numel() == 500 and keep.unique().numel() == 500
    half = training_subset(points, 180.0, None, torch.Generator().manual_seed(0))
    assert set(keep.tolist()) <= set(half.tolist())
    # without a sector: the random subset training drew before sectors existed (same generator draws)
    expected = torch.randperm(3600, generator=torch.Generator().manual_seed(7))[:500]
    assert torch.equal(training_subset(points, None, 500, torch.Generator().manual_seed(7)), expected)
    assert torch.equal(training_subset(points, 360.0, None, torch.Generator()), torch.arange(3600))


def test_training_subset_keeps_a_scan_whose_sector_is_empty():
    points = ring_scan()[:10]  # all within the first degree
    counts = [training_subset(points, 30.0, None, torch.Generator().manual_seed(s)).numel() for s in range(20)]
    assert min(counts) > 0  # most 30-degree sectors miss that degree: the whole scan is kept, never an empty one


def test_sector_deg_is_validated():
    with pytest.raises(ValueError, match="data.sector_deg"):
        SegDataConfig(sector_deg=0.0)
    with pytest.raises(ValueError, match="data.sector_deg"):
        SegDataConfig(sector_deg=400.0)
