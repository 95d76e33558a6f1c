"""segmentation.lasermix: points keep their labels, areas alternate, the two mixes partition the inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from segmentation.lasermix import draw_num_areas, lasermix, pitch_areas

PITCH = (-25.0, 3.0)


def _scan(n: int, first_id: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """(n, 5) points x, y, z, intensity, unique id; pitch spread over [-35, 12] deg so some get clamped."""
    pitch = torch.deg2rad(torch.empty(n).uniform_(-35.0, 12.0, generator=generator))
    yaw = torch.empty(n).uniform_(-math.pi, math.pi, generator=generator)
    rng = torch.empty(n).uniform_(2.0, 60.0, generator=generator)
    xyz = torch.stack(
        [
            rng * torch.cos(pitch) * torch.cos(yaw),
            rng * torch.cos(pitch) * torch.sin(yaw),
            rng * torch.sin(pitch),
        ],
        1,
    )
    intensity = torch.rand(n, 1, generator=generator)
    ids = torch.arange(first_id, first_id + n, dtype=torch.float32)[:, None]
    labels = torch.randint(0, 20, (n,), generator=generator)
    return torch.cat([xyz, intensity, ids], 1), labels


@pytest.fixture
def pair(generator):
    points_a, labels_a = _scan(3000, 0, generator)
    points_b, labels_b = _scan(2500, 10_000, generator)
    return points_a, labels_a, points_b, labels_b


def test_pitch_areas_hand_computed():
    # n = 4 on [-25, 3] deg: edges 3, -4, -11, -18, -25 ; area i covers (edge[i+1], edge[i]]
    pitches = [2.0, -3.0, -5.0, -12.0, -17.0, -20.0, 10.0, -40.0]
    expected = [0, 0, 1, 2, 2, 3, 0, 3]  # the last two are clamped into the top / bottom area
    rad = torch.deg2rad(torch.tensor(pitches, dtype=torch.float64))
    points = torch.stack([10 * torch.cos(rad), torch.zeros_like(rad), 10 * torch.sin(rad)], 1)
    assert pitch_areas(points, 4, PITCH).tolist() == expected
    assert pitch_areas(points.float(), 1, PITCH).tolist() == [0] * len(pitches)


def test_every_point_keeps_its_label_and_mixes_partition_the_inputs(pair):
    points_a, labels_a, points_b, labels_b = pair
    mix1_p, mix1_l, mix2_p, mix2_l = lasermix(*pair, generator=torch.Generator().manual_seed(3))
    label_of = torch.cat([labels_a, labels_b])
    id_to_row = {int(i): r for r, i in enumerate(torch.cat([points_a, points_b])[:, 4])}
    for p, lab in ((mix1_p, mix1_l), (mix2_p, mix2_l)):
        rows = torch.tensor([id_to_row[int(i)] for i in p[:, 4]])
        torch.testing.assert_close(lab, label_of[rows])  # every point carries its own label
        torch.testing.assert_close(p, torch.cat([points_a, points_b])[rows])  # and its own coordinates
    # multiset equality: together the two mixes hold exactly the input points, none dropped or duplicated
    ids_out = torch.cat([mix1_p[:, 4], mix2_p[:, 4]]).sort().values
    ids_in = torch.cat([points_a[:, 4], points_b[:, 4]]).sort().values
    torch.testing.assert_close(ids_out, ids_in, rtol=0, atol=0)
    assert len(mix1_p) > 0 and len(mix2_p) > 0


def test_areas_alternate_and_mixes_are_complementary(pair):
    points_a, labels_a, points_b, labels_b = pair
    seen = set()
    for seed in range(12):
        mix1_p, _, mix2_p, _ = lasermix(*pair, generator=torch.Generator().manual_seed(seed))
        n = draw_num_areas((3, 4, 5, 6), torch.Generator().manual_seed(seed))  # the draw lasermix made
        seen.add(n)
        area_of = {}
        for points in (points_a, points_b):
            for i, a in zip(points[:, 4].tolist(), pitch_areas(points, n, PITCH).tolist()):
                area_of[i] = a
        for mix, a_parity in ((mix1_p, 0), (mix2_p, 1)):
            ids = mix[:, 4]
            from_a, from_b = ids[ids < 10_000], ids[ids >= 10_000]
            # mix1: a's even areas + b's odd areas ; mix2: a's odd areas + b's even areas
            assert {area_of[int(i)] % 2 for i in from_a} == {a_parity}
            assert {area_of[int(i)] % 2 for i in from_b} == {1 - a_parity}
            # every area of the pitch range is present in the mix, from one source, alternating
            areas = sorted({area_of[int(i)] for i in ids})
            assert areas == list(range(n))
        # complementary: for each source, the two mixes split its points with no overlap
        for lo, hi in ((0, 10_000), (10_000, 20_000)):
            in1 = set(mix1_p[(mix1_p[:, 4] >= lo) & (mix1_p[:, 4] < hi), 4].tolist())
            in2 = set(mix2_p[(mix2_p[:, 4] >= lo) & (mix2_p[:, 4] < hi), 4].tolist())
            src = points_a if lo == 0 else points_b
            assert in1.isdisjoint(in2) and in1 | in2 == set(src[:, 4].tolist())
    assert seen == {3, 4, 5, 6}  # n drawn per pair from the choices


def test_areas_are_ordered_bands_top_first(generator):
    points, _ = _scan(2000, 0, generator)
    phi = torch.atan2(points[:, 2], points[:, :2].norm(dim=1))
    area = pitch_areas(points, 5, PITCH)
    order = torch.argsort(phi, descending=True)
    assert (area[order].diff() >= 0).all()  # area index never decreases as pitch goes down


def test_same_generator_same_mix_and_validation(pair):
    out1 = lasermix(*pair, generator=torch.Generator().manual_seed(7))
    out2 = lasermix(*pair, generator=torch.Generator().manual_seed(7))
    for x, y in zip(out1, out2):
        torch.testing.assert_close(x, y)
    with pytest.raises(ValueError, match="points_a"):
        lasermix(pair[0][:, :2], pair[1], pair[2], pair[3], generator=torch.Generator())
    with pytest.raises(ValueError, match="down < up"):
        pitch_areas(pair[0], 3, (3.0, -25.0))
    with pytest.raises(ValueError, match="empty"):
        lasermix(*pair, num_areas_choices=(), generator=torch.Generator())


def test_real_hdl64_scan_fills_every_area(kitti_root):
    scan = kitti_root / "sequences" / "00" / "velodyne" / "000000.bin"
    points = torch.from_numpy(np.fromfile(scan, dtype=np.float32).reshape(-1, 4))
    for n in (3, 4, 5, 6):
        counts = torch.bincount(pitch_areas(points, n, PITCH), minlength=n)
        assert len(counts) == n and (counts > 0).all()
    labels = torch.zeros(len(points), dtype=torch.long)
    mix1_p, _, mix2_p, _ = lasermix(points, labels, points.flip(0), labels + 1, generator=torch.Generator())
    assert len(mix1_p) + len(mix2_p) == 2 * len(points)
