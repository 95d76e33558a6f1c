"""benchmarks/bench_weights_precision.py on a tiny trained segmentor: both exports compared on every picked scan."""

from __future__ import annotations

import json

from segmentation.config import SegTrainConfig
from segmentation.train import train as train_segmentor
from tests.tiny_nets import SEG_TINY, load_script
from tests.tiny_worlds import write_toy_root
from u4d_aug.config import load_config


def test_bench_reports_both_precisions(tmp_path):
    bench = load_script("bench_weights_precision")
    root = write_toy_root(tmp_path / "toy")
    run = tmp_path / "run"
    cfg = load_config(
        SegTrainConfig, SEG_TINY, [f"data.root={root}", f"out_dir={run}", "optim.steps=4", "eval_every=4"]
    )
    train_segmentor(cfg, progress=False)
    out = tmp_path / "precision.json"
    assert bench.main([str(run / "model.pt"), str(root), "--scans", "2", "--out", str(out)]) == 0
    record = json.loads(out.read_text())
    assert len(record["scans"]) == 2
    assert record["bytes"]["int8"] < record["bytes"]["float16"] < record["bytes"]["float32"]
    for precision in ("float16", "int8"):
        summary = record["summary"][precision]
        assert 0.9 < summary["topk_overlap"]["worst"] <= 1.0 and summary["argmax_agree"]["worst"] > 0.95
    assert record["summary"]["float16"]["max_abs"]["worst"] <= record["summary"]["int8"]["max_abs"]["worst"]
    assert "| int8 |" in out.with_suffix(".md").read_text()
    assert bench.main([str(run / "model.pt"), str(tmp_path / "nothing"), "--out", str(out)]) == 2
