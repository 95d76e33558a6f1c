"""The downstream comparison's five arms at tiny size on banks that `u4d generate` wrote (configs/experiment/
downstream_10pct.yaml's arms): every arm trains and is scored, and the bank arms draw bank scans at their ratio
into the mean-teacher loss."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
import torch

import segmentation.batches
import segmentation.train
from segmentation.config import SegTrainConfig
from segmentation.experiment import add_experiment_arguments, run_experiment
from segmentation.semi import UnlabeledStream, unlabeled_stream
from tests.tiny_nets import REPO, gen_config, save_random_checkpoint
from tests.tiny_worlds import write_toy_root
from u4d_aug.config import load_config
from u4d_aug.data.formats import read_kitti_scan
from u4d_aug.generate import generate_bank

TINY = REPO / "configs" / "experiment" / "tiny.yaml"
TINY_SEMI = REPO / "configs" / "seg" / "tiny_semi.yaml"
ARMS = ["sup-only", "mt", "mt+r2dm", "mt+u4d", "mt+u4d-random"]
BANK_SCANS = 3
STEPS, BURN_IN = 8, 2  # 6 mean-teacher steps of batch 2: 12 unlabeled slots per arm


@pytest.fixture(scope="module")
def banks(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Three banks written by `generate_bank` from tiny random-weight nets: U4D, R2DM-style, U4D with random P_u."""
    root = tmp_path_factory.mktemp("banks")
    ckpt = {stage: save_random_checkpoint(root / f"{stage}.pt", stage, seed) for seed, stage in
            enumerate(("stage1", "stage2", "baseline"))}  # fmt: skip
    random_stage1 = save_random_checkpoint(root / "stage1_random.pt", "stage1", seed=7)
    jobs = {
        "u4d": gen_config(ckpt, "mode=u4d", f"num={BANK_SCANS}"),
        "r2dm": gen_config(ckpt, "mode=baseline", f"num={BANK_SCANS}"),
        "u4d_random": gen_config({**ckpt, "stage1": random_stage1}, "mode=u4d", f"num={BANK_SCANS}"),
    }
    out = {}
    for name, cfg in jobs.items():
        out[name] = root / name
        manifest = generate_bank(cfg, out[name], progress=False)
        assert manifest["complete"] and len(manifest["samples"]) == BANK_SCANS
    return out


@pytest.mark.slow
def test_five_arms_run_on_generated_banks_and_draw_them_into_the_loss(tmp_path, banks, monkeypatch):
    root = write_toy_root(tmp_path / "toy")
    for bank in banks.values():  # real generated scans, not empty files
        scans = sorted((bank / "sequences").rglob("*.bin"))
        assert len(scans) == BANK_SCANS and all(len(read_kitti_scan(p)) > 50 for p in scans)
    # every unlabeled scan each semi step receives, and the item it was made from: its source, sequence, frame, points
    items: list[dict] = []
    loaded: list[torch.Tensor] = []
    given: list[torch.Tensor] = []
    original_item, original_load = UnlabeledStream.load, segmentation.batches.load_unlabeled
    original_step = segmentation.train.semi_step

    def spy_item(stream: UnlabeledStream, seed, step, slot, with_labels=False):
        item = original_item(stream, seed, step, slot, with_labels)
        items.append(item)
        return item

    def spy_load(stream: UnlabeledStream, cfg, step, slots):
        scans, labels = original_load(stream, cfg, step, slots)
        loaded.extend(scans)
        return scans, labels

    def spy_step(student, teacher, batch, cfg, device, class_weight=None):
        given.extend(batch["unlabeled"])
        out = original_step(student, teacher, batch, cfg, device, class_weight)
        assert torch.isfinite(out["loss"]) and out["loss_mt"] > 0
        return out

    monkeypatch.setattr(UnlabeledStream, "load", spy_item)
    monkeypatch.setattr(segmentation.batches, "load_unlabeled", spy_load)
    monkeypatch.setattr(segmentation.train, "semi_step", spy_step)

    arms = (
        "arms=[{name: sup-only, mode: supervised}, {name: mt, mode: semi}, "
        f"{{name: mt+r2dm, mode: semi, bank: {banks['r2dm']}, bank_ratio: 0.5}}, "
        f"{{name: mt+u4d, mode: semi, bank: {banks['u4d']}, bank_ratio: 0.5}}, "
        f"{{name: mt+u4d-random, mode: semi, bank: {banks['u4d_random']}, bank_ratio: 0.5}}]"
    )
    parser = argparse.ArgumentParser()
    add_experiment_arguments(parser)
    overrides = f"overrides=[data.root={root}, optim.steps={STEPS}, eval_every={STEPS}, semi.burn_in_steps={BURN_IN}]"
    records = f"records_dir={tmp_path / 'records'}"
    argv = [str(TINY), f"base={TINY_SEMI}", overrides, arms, records, "--no-progress", "--out", str(tmp_path / "out")]
    assert run_experiment(parser.parse_args(argv)) == 0

    results = json.loads((tmp_path / "out" / "results.json").read_text())
    by_arm = {entry["arm"]: entry for entry in results["arms"]}
    assert list(by_arm) == ARMS
    assert all(entry["status"] == "done" and 0 < entry["miou"]["mean"] < 1 for entry in by_arm.values())
    # the arms run one after the other, each semi step's unlabeled scans are the ones loaded for it, unchanged
    assert len(given) == len(loaded) == len(items) == 4 * (STEPS - BURN_IN) * 2
    assert all(torch.equal(a, b) for a, b in zip(given, loaded))
    # each loaded item is the file of the source it names: its source is what was loaded, not the stream's draw
    roots = {f"{root} (split)": root, **{str(bank): bank for bank in banks.values()}}
    for item in items:
        path = roots[item["source"]] / "sequences" / item["seq"] / "velodyne" / f"{item['frame']}.bin"
        assert np.array_equal(item["points"], read_kitti_scan(path)), path
    per_arm = [items[i : i + 12] for i in range(0, len(items), 12)]  # mt, mt+r2dm, mt+u4d, mt+u4d-random
    assert all(item["source"] == f"{root} (split)" for item in per_arm[0])  # MT+LaserMix alone: the split only
    for arm_items, bank in zip(per_arm[1:], (banks["r2dm"], banks["u4d"], banks["u4d_random"])):
        names = {item["source"] for item in arm_items}
        assert names <= {str(bank), f"{root} (split)"}
        from_bank = sum(item["source"] == str(bank) for item in arm_items)
        assert 2 <= from_bank <= 10, from_bank  # ratio 0.5 of 12 slots: P(outside 2..10) < 0.7 %; fixed by the seed
    # the configured ratio, over many draws of the stream a bank arm trained with (read back from its run folder)
    runs = tmp_path / "out" / "runs"
    run_cfg = load_config(SegTrainConfig, runs / "mt+u4d" / "minkunet" / "seed0" / "config.yaml")
    stream = unlabeled_stream(run_cfg)
    assert stream.names == [f"{root} (split)", str(banks["u4d"])]
    picks = [stream.pick(run_cfg.seed, step, slot)[0] for step in range(1000) for slot in range(2)]
    assert abs(sum(picks) / len(picks) - 0.5) < 0.04
    # each bank arm's record names the bank it read: its generator and a digest of its scans
    record = json.loads((tmp_path / "records" / "mt+u4d" / "minkunet" / "seed0.json").read_text())
    (bank,) = record["banks"]
    manifest = json.loads((banks["u4d"] / "manifest.json").read_text())
    assert bank["path"] == str(banks["u4d"]) and bank["scans"] == BANK_SCANS and bank["complete"]
    assert bank["checkpoints"] == manifest["checkpoints"] and len(bank["content_sha256"]) == 16
    sup = json.loads((tmp_path / "records" / "sup-only" / "minkunet" / "seed0.json").read_text())
    assert sup["banks"] == []
    # the banks changed the training: each bank arm ends with other weights than MT+LaserMix alone
    mt = torch.load(runs / "mt" / "minkunet" / "seed0" / "model.pt", weights_only=True)["model"]
    for arm in ("mt+r2dm", "mt+u4d", "mt+u4d-random"):
        other = torch.load(runs / arm / "minkunet" / "seed0" / "model.pt", weights_only=True)["model"]
        assert any(not torch.equal(mt[k], other[k]) for k in mt), arm
