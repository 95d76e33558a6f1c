"""collate_scans: scans batched the sparse-conv way; a default DataLoader over a bank and over a labelled root."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from tests.tiny_worlds import write_toy_bank, write_toy_root
from u4d_aug.data.collate import collate_scans, split_points
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.errors import InputError


def item(n: int, labels: bool, seq: str = "00", frame: str = "000000") -> dict:
    points = np.arange(4 * n, dtype=np.float32).reshape(n, 4)
    return {"points": points, "labels": np.arange(n) % 3 if labels else None, "seq": seq, "frame": frame}


def test_points_concatenated_with_batch_index_and_offsets():
    batch = collate_scans([item(3, True, frame="a"), item(2, True, frame="b")])
    assert batch["points"].shape == (5, 4) and batch["points"].dtype == torch.float32
    assert batch["batch_index"].tolist() == [0, 0, 0, 1, 1]
    assert batch["offsets"].tolist() == [0, 3, 5]
    assert batch["labels"].tolist() == [0, 1, 2, 0, 1] and batch["labels"].dtype == torch.int64
    assert batch["seq"] == ["00", "00"] and batch["frame"] == ["a", "b"]
    first, second = split_points(batch)
    np.testing.assert_array_equal(first.numpy(), item(3, True)["points"])
    np.testing.assert_array_equal(second.numpy(), item(2, True)["points"])


def test_labels_none_when_no_scan_has_any_and_ignore_for_the_unlabelled_ones():
    assert collate_scans([item(3, False), item(2, False)])["labels"] is None
    mixed = collate_scans([item(2, False), item(3, True)], ignore_index=7)
    assert mixed["labels"].tolist() == [7, 7, 0, 1, 2]


def test_bad_items_are_refused():
    with pytest.raises(ValueError, match="at least one"):
        collate_scans([])
    with pytest.raises(ValueError, match=r"\(N, 4\)"):
        collate_scans([{"points": np.zeros((3, 3), np.float32), "labels": None, "seq": "00", "frame": "0"}])


def _scan(n: int, labels=None, **drop) -> dict:
    item = {"points": np.zeros((n, 4), np.float32), "labels": labels, "seq": "00", "frame": "000000"}
    return {key: value for key, value in item.items() if key not in drop}


def test_malformed_items_are_one_line_naming_the_item_and_field():
    with pytest.raises(InputError, match=r"items\[1\] has no seq; expected keys points, seq, frame"):
        collate_scans([_scan(2), _scan(2, seq=True)])
    with pytest.raises(InputError, match=r"items\[0\] is a str; expected a dict"):
        collate_scans(["scan.bin"])
    # label counts that cancel across scans (3 + 1 for 2 + 2 points) are caught per scan
    cancel = [_scan(2, np.zeros(3, np.int64)), _scan(2, np.zeros(1, np.int64))]
    with pytest.raises(InputError, match=r"items\[0\]\['labels'\] has shape \(3,\); expected \(2,\), one per point"):
        collate_scans(cancel)
    with pytest.raises(InputError, match=r"items\[0\]\['labels'\] are float32; expected integer class ids"):
        collate_scans([_scan(2, np.array([1.7, 2.2], np.float32))])  # never truncated to 1, 2
    batch = collate_scans([_scan(2, np.array([1, 2], np.uint16)), _scan(1)])
    assert batch["labels"].tolist() == [1, 2, 19] and batch["labels"].dtype == torch.int64


def test_default_dataloader_over_a_bank(tmp_path):
    bank = write_toy_bank(tmp_path / "bank")
    dataset = ScanDataset(bank)
    assert [frame for _, frame in dataset.entries] == ["000000", "000001", "000003"]  # the empty sample has no .bin
    batches = list(DataLoader(dataset, batch_size=2, collate_fn=collate_scans))
    assert [len(b["offsets"]) - 1 for b in batches] == [2, 1]
    first = batches[0]
    assert first["labels"] is None and first["points"].shape == (500 + 600, 4)
    assert first["offsets"].tolist() == [0, 500, 1100] and int(first["batch_index"].sum()) == 600


def test_default_dataloader_over_a_labelled_root(tmp_path):
    root = write_toy_root(tmp_path / "toy", sequences=("00",), frames=3)
    batch = next(iter(DataLoader(ScanDataset(root), batch_size=2, shuffle=True, collate_fn=collate_scans)))
    assert batch["points"].shape == (6000, 4) and batch["labels"].shape == (6000,)
    assert set(batch["labels"].unique().tolist()) <= {0, 8, 12, 19}  # car, road, building, ignore


def test_real_root_with_unlabelled_frames(kitti_root):
    """Frames 0-2 of the sample sequence have labels, 3-5 not: frame 3's points get the ignore id."""
    dataset = ScanDataset(kitti_root)
    batch = collate_scans([dataset[2], dataset[3]])
    start, stop = batch["offsets"][1:].tolist()
    assert (batch["labels"][start:stop] == 19).all() and (batch["labels"][:start] != 19).any()
