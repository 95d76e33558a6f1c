"""Label splits and scan augmentation for segmentation training."""

from __future__ import annotations

import pytest
import torch

from segmentation.data import AugmentConfig, augment, load_or_make_split, make_split
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
    assert [f.name for f in files] == ["uniform_20pct_seed3.json"]
    # A re-read gives the same split even if the drawing code changed: the file wins.
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
