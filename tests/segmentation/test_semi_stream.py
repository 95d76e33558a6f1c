"""The unlabeled stream of a bank arm (`semi.UnlabeledStream.load`): every scan it loads is the file its item names
(source root, sequence, frame), judged from what was loaded rather than from the stream's own draw."""

from __future__ import annotations

from collections import Counter

import numpy as np

from segmentation.config import SegTrainConfig
from segmentation.semi import unlabeled_stream
from tests.tiny_nets import REPO
from tests.tiny_worlds import write_toy_bank
from u4d_aug.config import load_config
from u4d_aug.data.formats import read_kitti_scan

TINY_SEMI = REPO / "configs" / "seg" / "tiny_semi.yaml"


def test_every_loaded_scan_is_the_file_of_the_source_it_names(toy_root, tmp_path):
    bank = write_toy_bank(tmp_path / "bank", num=4, empty=(), seed=1)  # other scans than the toy root's
    overrides = [f"data.root={toy_root}", f"out_dir={tmp_path / 'run'}", f"semi.banks=[{{path: {bank}, ratio: 0.5}}]"]
    cfg = load_config(SegTrainConfig, TINY_SEMI, overrides)
    stream = unlabeled_stream(cfg)
    roots = {f"{toy_root} (split)": toy_root, str(bank): bank}
    drawn = Counter()
    for step in range(20):
        for slot in range(2):
            item = stream.load(cfg.seed, step, slot)
            path = roots[item["source"]] / "sequences" / item["seq"] / "velodyne" / f"{item['frame']}.bin"
            assert np.array_equal(item["points"], read_kitti_scan(path)), (step, slot, item["source"])
            drawn[item["source"]] += 1
    assert set(drawn) == set(roots) and 10 <= drawn[str(bank)] <= 30  # ratio 0.5 of 40 slots, fixed by the seed
