"""Semi-supervised LaserMix mean-teacher mode: the step, the EMA teacher, pseudo-labels, the unlabeled stream."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

import segmentation.semi as semi
from segmentation.batches import TrainBatches, train_scans
from segmentation.config import SegTrainConfig
from segmentation.mean_teacher import make_teacher, teacher_mode
from segmentation.models import build_model
from segmentation.optimizer import make_optimizer
from segmentation.semi import UnlabeledStream, semi_step, unlabeled_stream, update_teacher
from segmentation.train import train
from tests.tiny_nets import CPU, REPO
from tests.tiny_worlds import toy_scan, write_toy_root
from u4d_aug.config import load_config
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.data.formats import read_kitti_scan, write_kitti_scan
from u4d_aug.data.labels import SEMANTICKITTI_IGNORE
from u4d_aug.errors import InputError
from u4d_aug.io import read_jsonl
from u4d_aug.validate import NonFiniteLossError

TINY_SEMI = REPO / "configs" / "seg" / "tiny_semi.yaml"


def write_bank(root: Path, frames: int = 2, seed: int = 5) -> Path:
    """A bank of generated scans: SemanticKITTI layout, velodyne only (no labels)."""
    rng = np.random.default_rng(seed)
    for frame in range(frames):
        points, _ = toy_scan(rng, 1000)
        write_kitti_scan(root / "sequences" / "00" / "velodyne" / f"{frame:06d}.bin", points)
    return root


@pytest.fixture(scope="module")
def bank_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_bank(tmp_path_factory.mktemp("bank"))


def semi_config(root: Path, out: Path, *overrides: str) -> SegTrainConfig:
    return load_config(SegTrainConfig, TINY_SEMI, [f"data.root={root}", f"out_dir={out}", *overrides])


# ------------------------------------------------------------------------------------------ unlabeled stream


def test_bank_stream_reads_unlabeled_scans(toy_root, bank_root, tmp_path):
    cfg = semi_config(toy_root, tmp_path, f"semi.banks=[{{path: {bank_root}, ratio: 1.0}}]")
    stream = unlabeled_stream(cfg)
    assert stream.names == [str(bank_root)]  # the split's ratio is 0: it is not a source
    for step in range(4):
        item = stream.load(cfg.seed, step, 0)
        assert item["source"] == str(bank_root)
        path = bank_root / "sequences" / item["seq"] / "velodyne" / f"{item['frame']}.bin"
        assert np.array_equal(item["points"], read_kitti_scan(path))
    # half bank, half split: both sources are drawn, and each draw depends on (seed, step, slot) only
    cfg = semi_config(toy_root, tmp_path, f"semi.banks=[{{path: {bank_root}, ratio: 0.5}}]")
    stream = unlabeled_stream(cfg)
    picks = [stream.pick(cfg.seed, step, slot) for step in range(20) for slot in range(2)]
    assert {source for source, _ in picks} == {0, 1}
    assert picks == [stream.pick(cfg.seed, step, slot) for step in range(20) for slot in range(2)]
    # the split source holds the unlabeled half of the train scans only
    labeled = {entry for entry in train_scans(cfg, CPU).entries}
    assert labeled.isdisjoint(stream.sources[0].entries)
    assert len(labeled) + len(stream.sources[0].entries) == 3


def test_scarce_pool_draws_unlabeled_scans_from_its_places_only(tmp_path):
    root = write_toy_root(tmp_path / "places", ("00", "01", "02", "03", "04", "05"), frames=2)
    base = ("data.train_sequences=00-05", "data.split_mode=sequence", "data.label_fraction=0.2")
    full = unlabeled_stream(semi_config(root, tmp_path / "full", *base))
    labeled = {seq for seq, _ in train_scans(semi_config(root, tmp_path / "full", *base), CPU).entries}
    free = sorted({seq for seq, _ in full.sources[0].entries})
    assert len(free) >= 3 and labeled.isdisjoint(free)
    cfg = semi_config(root, tmp_path / "scarce", *base, f"data.unlabeled_sequences=[{free[0]}]")
    pool = unlabeled_stream(cfg).sources[0].entries
    assert pool == [entry for entry in full.sources[0].entries if entry[0] == free[0]] and len(pool) == 2
    # a labelled place, or one outside the train places, is refused by name
    for bad, message in ((sorted(labeled)[0], "hold labelled scans"), ("09", "09")):
        cfg = semi_config(root, tmp_path / "bad", *base, f"data.unlabeled_sequences=[{bad}]")
        with pytest.raises(InputError, match=f"data.unlabeled_sequences.*{message}|{message}"):
            unlabeled_stream(cfg)


def test_bad_banks_are_reported(toy_root, tmp_path):
    cfg = semi_config(toy_root, tmp_path, f"semi.banks=[{{path: {tmp_path / 'nope'}, ratio: 0.5}}]")
    with pytest.raises(InputError, match=r"semi.banks\[0\].path"):
        unlabeled_stream(cfg)
    with pytest.raises(InputError, match="ratios"):
        semi_config(toy_root, tmp_path, "semi.banks=[{path: a, ratio: 0.7}, {path: b, ratio: 0.7}]")
    with pytest.raises(InputError, match="no source"):
        UnlabeledStream([ScanDataset(toy_root)], [0.0], ["x"])


def test_batches_hold_as_many_unlabeled_scans(toy_root, bank_root, tmp_path):
    cfg = semi_config(toy_root, tmp_path, f"semi.banks=[{{path: {bank_root}, ratio: 0.5}}]", "data.max_points=400")
    batch = TrainBatches(train_scans(cfg, CPU), cfg, 0, 1, unlabeled_stream(cfg))[3]
    assert batch["slots"] == [0, 1] and len(batch["unlabeled"]) == 2
    assert all(p.shape == (400, 4) for p in batch["points"] + batch["unlabeled"])


# ------------------------------------------------------------------------------------------------------ step


def test_semi_step_runs_and_the_teacher_follows_by_ema(toy_root, tmp_path):
    cfg = semi_config(toy_root, tmp_path, "data.max_points=500")
    torch.manual_seed(0)
    student = build_model(cfg.model)
    teacher = teacher_mode(make_teacher(student), cfg.semi.bn_mode)
    optimizer = make_optimizer(student, cfg.optim)
    batch = TrainBatches(train_scans(cfg, CPU), cfg, 0, 1, unlabeled_stream(cfg))[0]
    before = {k: v.clone() for k, v in teacher.named_parameters()}

    losses = semi_step(student, teacher, batch, cfg, torch.device("cpu"))
    assert {"loss", "loss_sup", "loss_mix", "loss_mt", "pseudo_kept"} <= set(losses)
    assert all(torch.isfinite(v) for v in losses.values())
    expected = losses["loss_sup"] + losses["loss_mix"] + cfg.semi.consistency_weight * losses["loss_mt"]
    assert float(losses["loss"].detach()) == pytest.approx(float(expected.detach()), rel=1e-6)
    optimizer.zero_grad()
    losses["loss"].backward()
    assert all(p.grad is None for p in teacher.parameters())  # the teacher gets no gradient
    optimizer.step()
    update_teacher(teacher, student, cfg.semi, step=0)

    student_params = dict(student.named_parameters())
    changed = 0
    for name, t in teacher.named_parameters():
        want = cfg.semi.ema_decay * before[name] + (1 - cfg.semi.ema_decay) * student_params[name].detach()
        torch.testing.assert_close(t, want, rtol=1e-5, atol=1e-7)
        changed += int(not torch.equal(t, before[name]))
    assert changed > 0


def test_voxel_level_semi_step_aligns_student_and_teacher_voxels(toy_root, tmp_path):
    cfg = semi_config(toy_root, tmp_path, "data.max_points=500", "loss.level=voxel")
    torch.manual_seed(0)
    student = build_model(cfg.model)
    batch = TrainBatches(train_scans(cfg, CPU), cfg, 0, 1, unlabeled_stream(cfg))[0]
    # both in eval mode and equal: the student's rows of the unlabeled scans must be the teacher's, row for row
    teacher = make_teacher(student).eval()
    student.eval()
    losses = semi_step(student, teacher, batch, cfg, torch.device("cpu"))
    assert all(torch.isfinite(v) for v in losses.values())
    assert float(losses["loss_mt"].detach()) < 1e-10
    # and in training modes the step backpropagates into the student only
    student.train()
    teacher = teacher_mode(make_teacher(student), cfg.semi.bn_mode)
    losses = semi_step(student, teacher, batch, cfg, torch.device("cpu"))
    assert float(losses["loss_mt"].detach()) > 0
    losses["loss"].backward()
    assert all(p.grad is None for p in teacher.parameters())
    assert sum(float(p.grad.abs().sum()) for p in student.parameters() if p.grad is not None) > 0


class FixedTeacher(nn.Module):
    """Teacher stub: confident (p = 0.99) class 0 on points with x > 0, unsure (p ~ 1/K) elsewhere."""

    def forward(self, points: list[torch.Tensor]) -> torch.Tensor:
        xyz = torch.cat(points)
        logits = torch.zeros(xyz.shape[0], 19)
        logits[xyz[:, 0] > 0, 0] = 10.0  # softmax 0.99 for class 0
        return logits


class UnsureTeacher(nn.Module):
    """Teacher stub: uniform softmax (p = 1/K) everywhere, so no pseudo-label passes the threshold."""

    def forward(self, points: list[torch.Tensor]) -> torch.Tensor:
        return torch.zeros(sum(p.shape[0] for p in points), 19)


def test_pseudo_labels_below_threshold_are_ignored(toy_root, tmp_path, monkeypatch):
    cfg = semi_config(toy_root, tmp_path, "data.max_points=300")
    batch = TrainBatches(train_scans(cfg, CPU), cfg, 0, 1, unlabeled_stream(cfg))[1]
    seen = []
    real_lasermix = semi.lasermix

    def spy(points_a, labels_a, points_b, labels_b, *args, **kwargs):
        seen.append((points_b, labels_b))
        return real_lasermix(points_a, labels_a, points_b, labels_b, *args, **kwargs)

    monkeypatch.setattr(semi, "lasermix", spy)
    torch.manual_seed(0)
    student = build_model(cfg.model)
    losses = semi_step(student, FixedTeacher(), batch, cfg, torch.device("cpu"))
    assert len(seen) == 2
    for points, labels in seen:
        confident = points[:, 0] > 0
        assert confident.any() and (~confident).any()
        assert torch.all(labels[confident] == 0)
        assert torch.all(labels[~confident] == SEMANTICKITTI_IGNORE)
    kept = torch.cat([points[:, 0] > 0 for points, _ in seen]).float().mean()
    assert float(losses["pseudo_kept"]) == pytest.approx(float(kept))


def test_oracle_labels_replace_the_pseudo_labels_with_the_scans_own(toy_root, bank_root, tmp_path, monkeypatch):
    cfg = semi_config(toy_root, tmp_path, "data.max_points=300", "semi.oracle_labels=true")
    stream = unlabeled_stream(cfg)
    batch = TrainBatches(train_scans(cfg, CPU), cfg, 0, 1, stream)[1]
    assert [y.shape for y in batch["unlabeled_labels"]] == [(p.shape[0],) for p in batch["unlabeled"]]
    for slot, labels in zip(batch["slots"], batch["unlabeled_labels"]):
        own = stream.load(cfg.seed, 1, slot, with_labels=True)["labels"]  # (N,) the whole scan's labels
        assert np.isin(labels.numpy(), own).all()  # a subset of the scan's own train ids
        assert len(set(labels.tolist())) > 1  # not the stub teacher's single class
    seen = []
    real_lasermix = semi.lasermix

    def spy(points_a, labels_a, points_b, labels_b, *args, **kwargs):
        seen.append(labels_b)
        return real_lasermix(points_a, labels_a, points_b, labels_b, *args, **kwargs)

    monkeypatch.setattr(semi, "lasermix", spy)
    torch.manual_seed(0)
    losses = semi_step(build_model(cfg.model), FixedTeacher(), batch, cfg, torch.device("cpu"))
    for labels_b, truth in zip(seen, batch["unlabeled_labels"]):
        assert torch.equal(labels_b, truth)  # every point, no threshold
    # the stub's confident class-0 (car) pseudo-labels are right only on the toy scene's car points
    truth = torch.cat(batch["unlabeled_labels"])
    confident = torch.cat([p[:, 0] > 0 for p in batch["unlabeled"]]) & (truth != SEMANTICKITTI_IGNORE)
    assert float(losses["pseudo_accuracy"]) == pytest.approx(float((truth[confident] == 0).float().mean()))
    # a teacher confident nowhere has no accuracy to report: NaN, not a made-up value
    unsure = semi_step(build_model(cfg.model), UnsureTeacher(), batch, cfg, torch.device("cpu"))
    assert torch.isnan(unsure["pseudo_accuracy"]) and torch.isfinite(unsure["loss"])
    with pytest.raises(InputError, match="oracle_labels"):
        semi_config(toy_root, tmp_path, "semi.oracle_labels=true", f"semi.banks=[{{path: {bank_root}, ratio: 0.5}}]")


# -------------------------------------------------------------------------------------------------- training


def test_semi_resume_in_a_fresh_process_is_bit_exact(toy_root, bank_root, tmp_path):
    """6 semi steps with a checkpoint at 3; a new process resumes from step 3; final teacher identical."""
    bank = f"semi.banks=[{{path: {bank_root}, ratio: 0.5}}]"
    full = tmp_path / "full"
    summary = train(semi_config(toy_root, full, bank), progress=False)
    records = read_jsonl(full / "log.jsonl")
    assert summary["miou"] == [r for r in records if "val_miou" in r][-1]["val_miou"]  # the teacher's last evaluation
    assert all(np.isfinite(r["loss_mix"]) and np.isfinite(r["loss_mt"]) for r in records if "loss" in r)
    ckpt = torch.load(full / "checkpoints" / "step_0000006.pt", weights_only=True)
    final = torch.load(full / "model.pt", weights_only=True)["model"]
    assert ckpt["ema"] is not None and ckpt["ema"].keys() == final.keys()
    assert all(torch.equal(ckpt["ema"][k], final[k]) for k in final)  # model.pt holds the teacher
    assert any(not torch.equal(ckpt["model"][k], final[k]) for k in final)

    half = tmp_path / "half"
    (half / "checkpoints").mkdir(parents=True)
    (half / "checkpoints" / "step_0000003.pt").write_bytes((full / "checkpoints" / "step_0000003.pt").read_bytes())
    (half / "log.jsonl").write_text((full / "log.jsonl").read_text())
    code = (
        "import sys; from segmentation.train import train; from segmentation.config import SegTrainConfig; "
        "from u4d_aug.config import load_config; "
        "train(load_config(SegTrainConfig, sys.argv[1], sys.argv[2:]), resume='last', progress=False)"
    )
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    overrides = [f"data.root={toy_root}", f"out_dir={half}", bank]
    subprocess.run([sys.executable, "-c", code, str(TINY_SEMI), *overrides], check=True, cwd=REPO, env=env, timeout=300)
    resumed = torch.load(half / "model.pt", weights_only=True)["model"]
    for key in final:
        assert torch.equal(final[key], resumed[key]), key
    steps = [r["step"] for r in read_jsonl(half / "log.jsonl") if "loss" in r]
    assert steps == list(range(1, 7))


def test_burn_in_trains_supervised_then_switches_to_the_mean_teacher(toy_root, tmp_path):
    """semi.burn_in_steps=3: steps 1-3 are supervised (no unlabeled scans, teacher BN = student BN), then L_mt."""
    cfg = semi_config(toy_root, tmp_path / "run", "semi.burn_in_steps=3", "data.max_points=400")
    batches = TrainBatches(train_scans(cfg, CPU), cfg, 0, 1, unlabeled_stream(cfg))
    assert "unlabeled" not in batches[2] and len(batches[3]["unlabeled"]) == 2

    torch.manual_seed(0)
    student = build_model(cfg.model)
    teacher = teacher_mode(make_teacher(student), cfg.semi.bn_mode)
    student.train()
    student([p for p in batches[0]["points"]])  # moves the student's BatchNorm running statistics
    update_teacher(teacher, student, cfg.semi, step=2)  # a burn-in step: buffers copied
    for (name, t), s in zip(teacher.named_buffers(), student.buffers()):
        assert torch.equal(t, s), name
    student([p for p in batches[1]["points"]])
    update_teacher(teacher, student, cfg.semi, step=3)  # a mean-teacher step: parameters only (bn_mode batch)
    assert any(not torch.equal(t, s) for t, s in zip(teacher.buffers(), student.buffers()))

    train(cfg, progress=False)
    records = [r for r in read_jsonl(tmp_path / "run" / "log.jsonl") if "loss" in r]
    assert [r["step"] for r in records] == list(range(1, 7))
    assert all("loss_ce" in r and "loss_mt" not in r for r in records[:3])
    assert all("loss_mt" in r and np.isfinite(r["loss_mix"]) for r in records[3:])


def test_burn_in_steps_are_the_supervised_runs_steps(toy_root, tmp_path):
    """A semi run's burn-in repeats the supervised run of the same seed bit for bit (the arms share those steps)."""
    common = ["data.max_points=400", "optim.steps=3", "eval_every=3", "checkpoint_every=3"]
    sup = semi_config(toy_root, tmp_path / "sup", "mode=supervised", *common)
    mt = semi_config(toy_root, tmp_path / "mt", "semi.burn_in_steps=3", *common)
    train(sup, progress=False)
    train(mt, progress=False)
    a = torch.load(tmp_path / "sup" / "checkpoints" / "step_0000003.pt", weights_only=False)
    b = torch.load(tmp_path / "mt" / "checkpoints" / "step_0000003.pt", weights_only=False)
    for key, value in a["model"].items():
        assert torch.equal(value, b["model"][key]), key
    for key, value in b["ema"].items():  # during burn-in the teacher is the student
        assert torch.equal(value, b["model"][key]), key
    assert torch.equal(a["rng"]["torch"], b["rng"]["torch"])


def test_burn_in_teacher_is_the_student_then_its_ema(toy_root, tmp_path):
    """During burn-in the teacher is a copy of the student after every step (Unbiased Teacher); after it, the EMA."""
    cfg = semi_config(toy_root, tmp_path / "run", "semi.burn_in_steps=2")
    torch.manual_seed(0)
    student = build_model(cfg.model)
    teacher = teacher_mode(make_teacher(student), cfg.semi.bn_mode)
    decay = cfg.semi.ema_decay
    for step in range(3):
        before = {k: v.clone() for k, v in teacher.named_parameters()}
        with torch.no_grad():
            for p in student.parameters():
                p.add_(0.1)  # the student moves away from the teacher
        update_teacher(teacher, student, cfg.semi, step)
        copied = step < 2
        for (name, t), s in zip(teacher.named_parameters(), student.parameters()):
            want = s if copied else decay * before[name] + (1 - decay) * s
            torch.testing.assert_close(t, want, rtol=1e-5, atol=1e-7)
        assert copied == all(torch.equal(t, s) for t, s in zip(teacher.parameters(), student.parameters()))


def largest_azimuth_gap_deg(points: torch.Tensor) -> float:
    """Largest circular gap (degrees) between the sorted azimuths of (N, >=2) points."""
    azimuth = torch.rad2deg(torch.atan2(points[:, 1], points[:, 0]).double()).sort().values
    gaps = torch.cat([azimuth.diff(), (azimuth[:1] + 360.0) - azimuth[-1:]])
    return float(gaps.max())


def test_labeled_and_unlabeled_scans_are_cut_to_a_sector(toy_root, tmp_path):
    still = ["augment.rotate=false", "augment.flip=false", "augment.jitter_std=0", "augment.scale_min=1"]
    cfg = semi_config(toy_root, tmp_path, "data.sector_deg=90", "data.max_points=null", *still, "augment.scale_max=1")
    batch = TrainBatches(train_scans(cfg, CPU), cfg, 0, 1, unlabeled_stream(cfg))[3]
    for scan in batch["points"] + batch["unlabeled"]:
        assert scan.shape[0] > 0 and largest_azimuth_gap_deg(scan) >= 270.0 - 1e-6  # all points in one 90-degree arc
    full = semi_config(toy_root, tmp_path, "data.max_points=null", *still, "augment.scale_max=1")
    whole = TrainBatches(train_scans(full, CPU), full, 0, 1, unlabeled_stream(full))[3]
    assert all(largest_azimuth_gap_deg(scan) < 90.0 for scan in whole["points"] + whole["unlabeled"])


def test_a_non_finite_mean_teacher_loss_stops_the_run_before_the_step(toy_root, tmp_path, monkeypatch):
    import segmentation.train as seg_train

    step = seg_train.semi_step

    def nan_semi_step(student, teacher, batch, *args, **kwargs):
        losses = step(student, teacher, batch, *args, **kwargs)
        return {**losses, "loss": losses["loss"] * float("nan")}

    monkeypatch.setattr(seg_train, "semi_step", nan_semi_step)
    out = tmp_path / "nan"
    with pytest.raises(NonFiniteLossError, match="training step 2: the loss is nan"):
        train(semi_config(toy_root, out, "semi.burn_in_steps=1", "checkpoint_every=1"), progress=False)
    assert [c.name for c in (out / "checkpoints").glob("step_*.pt")] == ["step_0000001.pt"]
    state = torch.load(out / "checkpoints" / "step_0000001.pt", weights_only=True)
    assert all(torch.isfinite(value).all() for value in [*state["model"].values(), *state["ema"].values()])
