"""Exported float16 weights (`u4d export-weights`): about half the size, a stable hash, and the same samples,
features and probabilities as the float32 nets they come from, through the usual loaders.

Tolerances (measured here, and over seeds 0-4 x 4/8 DDIM steps while choosing them -> bound asserted):
one UNet forward max |diff| <= 1.2e-3 with outputs up to 4 -> 5e-3; samples mean |diff| <= 2.5e-3 -> 0.01, pixels
off by > 0.05 (DDIM's clamped x̂0 amplifies a few) <= 0.6% -> 2%, stage-1 mask pixels flipped <= 1 of 2048 -> 1%;
FRD/FPD features max |diff| <= 4.4e-4 of their largest value (1.4e-3 after 20 steps) -> 1%; segmentation
probabilities max |diff| 3.8e-3 (argmax all equal) -> 0.01.
"""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from segmentation.config import SegTrainConfig
from segmentation.predict import load_checkpoint as load_seg_checkpoint
from segmentation.predict import model_from_checkpoint, predict_probs
from segmentation.train import CHECKPOINT_KIND as SEG_CHECKPOINT_KIND
from segmentation.train import train as train_segmentor
from tests.tiny_nets import SEG_TINY, diffusion_config, extractor_config, plain_settings
from tests.tiny_worlds import read_scans, write_tiny_root, write_tiny_world, write_toy_root
from u4d_aug import weights
from u4d_aug.batches import row_mean
from u4d_aug.cli import main as cli_main
from u4d_aug.config import load_config
from u4d_aug.data.formats import read_kitti_scan
from u4d_aug.errors import InputError
from u4d_aug.export_weights import export_weights
from u4d_aug.metrics import extractors
from u4d_aug.metrics.extractors import extract_features, load_extractor, train_extractor
from u4d_aug.pipeline import complete, generate_baseline, generate_u4d, load_generator
from u4d_aug.train import CHECKPOINT_KIND
from u4d_aug.train import train as train_diffusion
from u4d_aug.weights import (
    SHIPPED_DIR,
    SHIPPED_GENERATORS,
    SHIPPED_OPTIONAL,
    SHIPPED_SEQUENCE,
    WEIGHTS_FORMAT,
    shipped_weights,
)

STAGES = ("stage1", "stage2", "baseline")
CPU = torch.device("cpu")


def fp32_size(state_dict: dict[str, torch.Tensor]) -> int:
    """Bytes of torch.save of a float32 state dict (what shipping the EMA weights unconverted would cost)."""
    buffer = io.BytesIO()
    torch.save(state_dict, buffer)
    return len(buffer.getvalue())


@pytest.fixture(scope="module")
def diffusion(tmp_path_factory) -> dict:
    """The three stages trained 30 steps (enough for outputs that depend on the weights), each exported."""
    base = tmp_path_factory.mktemp("diffusion")
    world = (base / "world", base / "probs")
    write_tiny_world(*world)
    found: dict = {"world": world}
    for stage in STAGES:
        cfg = diffusion_config(
            world, base / stage, stage, "steps=30", "checkpoint_every=30", "optim.lr=0.005", "ema_decay=0.5"
        )
        train_diffusion(cfg, progress=False)
        checkpoint = base / stage / "checkpoints" / "step_0000030.pt"
        found[stage] = (checkpoint, export_weights(checkpoint, base / f"{stage}.pt"), base / f"{stage}.pt")
    return found


def test_kind_names_match_their_writers():
    assert weights.DIFFUSION_KIND == CHECKPOINT_KIND
    assert weights.EXTRACTOR_KINDS == extractors.EXTRACTOR_KINDS
    assert weights.SEGMENTATION_KIND == SEG_CHECKPOINT_KIND


def test_diffusion_export_is_half_size_stable_and_keeps_heads(diffusion, tmp_path):
    for stage in STAGES:
        checkpoint, exported, path = diffusion[stage]
        assert exported["format"] == WEIGHTS_FORMAT and exported["kind"] == "u4d-diffusion"
        assert exported["hash"] == exported["weights_hash"] and len(exported["hash"]) == 16
        assert exported["trained"]["step"] == 30 and exported["trained"]["elapsed_minutes"] > 0
        assert len(exported["trained"]["source_sha256"]) == 16
        assert all(t.dtype == torch.float16 for t in exported["model"].values() if t.is_floating_point())
        assert export_weights(checkpoint, tmp_path / f"{stage}_again.pt")["hash"] == exported["hash"]
        net, cfg = load_generator(checkpoint)
        # the ray-angle features are rebuilt from the config, not shipped (4.2 MB of a 64x1024 net in float16)
        assert "ray_features.features" not in exported["model"]
        shipped = {k: v for k, v in net.state_dict().items() if k != "ray_features.features"}
        ratio = path.stat().st_size / fp32_size(shipped)
        assert ratio < 0.6, (stage, ratio)  # 0.54 here: per-tensor overhead of tiny nets; 0.51 on the seg net
        loaded, loaded_cfg = load_generator(path)
        assert torch.equal(loaded.ray_features.features, net.ray_features.features)
        assert loaded_cfg == cfg and all(p.dtype == torch.float32 for p in loaded.state_dict().values())
        assert (loaded.mask_conv is not None) == (stage == "stage1")
        assert loaded_cfg.net.cond_channels == (3 if stage == "stage2" else 0)


def assert_close_samples(x: torch.Tensor, y: torch.Tensor) -> None:
    """Mean |x - y| < 0.01 and under 2% of the values off by more than 0.05."""
    diff = (x - y).abs()
    assert float(diff.mean()) < 0.01 and float((diff > 0.05).float().mean()) < 0.02


def test_exported_generators_sample_like_the_fp32_ema_nets(diffusion):
    fp32 = {stage: load_generator(diffusion[stage][0]) for stage in STAGES}
    fp16 = {stage: load_generator(diffusion[stage][2]) for stage in STAGES}
    generator = torch.Generator().manual_seed(0)
    x_t, cond = torch.randn(2, 2, 16, 64, generator=generator), torch.randn(2, 3, 16, 64, generator=generator)
    for stage in STAGES:
        inputs = (x_t, torch.zeros(2), cond if stage == "stage2" else None)
        with torch.no_grad():
            a, b = fp32[stage][0](*inputs), fp16[stage][0](*inputs)
        a, b = (a, b) if isinstance(a, torch.Tensor) else (a[0], b[0])  # stage 1: (eps, mask logits)
        assert float(a.std()) > 0.5 and float((a - b).abs().max()) < 5e-3, stage

    ddim = plain_settings(4)
    u4d_a = generate_u4d(fp32["stage1"], fp32["stage2"], 2, torch.Generator().manual_seed(3), ddim)
    u4d_b = generate_u4d(fp16["stage1"], fp16["stage2"], 2, torch.Generator().manual_seed(3), ddim)
    assert float((u4d_a["m_u_pred"] != u4d_b["m_u_pred"]).float().mean()) < 0.01
    assert_close_samples(u4d_a["x0_u"], u4d_b["x0_u"])
    assert_close_samples(u4d_a["x0"], u4d_b["x0"])
    same_condition = [
        complete(nets["stage2"], u4d_a["x0_u"], u4d_a["m_u_pred"], torch.Generator().manual_seed(3), ddim)["x0"]
        for nets in (fp32, fp16)
    ]
    assert_close_samples(*same_condition)
    baseline = [
        generate_baseline(nets["baseline"], 2, torch.Generator().manual_seed(3), ddim)["x0"] for nets in (fp32, fp16)
    ]
    assert_close_samples(*baseline)
    other_seed = generate_baseline(fp32["baseline"], 2, torch.Generator().manual_seed(4), ddim)["x0"]
    assert float((baseline[0] - other_seed).abs().mean()) > 0.1  # the tolerances are far below a sample's spread


def test_extractor_export_keeps_hash_and_features(tmp_path):
    root = write_tiny_root(tmp_path / "root")
    scans = read_scans(root)
    for kind in ("frd", "fpd"):
        checkpoint, digest = train_extractor(kind, extractor_config(root, tmp_path / "out"))
        exported = export_weights(checkpoint, tmp_path / f"{kind}.pt")
        assert exported["hash"] == digest and exported["weights_hash"] != digest
        assert export_weights(checkpoint, tmp_path / f"{kind}_again.pt")["weights_hash"] == exported["weights_hash"]
        assert exported["trained"]["step"] == 3
        a, b = load_extractor(checkpoint), load_extractor(tmp_path / f"{kind}.pt")
        assert b.hash == a.hash == digest
        assert (tmp_path / f"{kind}.pt").stat().st_size / fp32_size(a.model.state_dict()) < 0.6
        features_a, features_b = extract_features(a, scans), extract_features(b, scans)
        for name, value in features_a.items():
            scale = np.abs(value).max()
            assert scale > 0 and np.abs(features_b[name] - value).max() < 0.01 * scale, name
    tampered = torch.load(checkpoint, weights_only=True)
    tampered["hash"] = "0" * 16
    torch.save(tampered, tmp_path / "tampered.pt")
    _one_line_error(export_weights, tmp_path / "tampered.pt", tmp_path / "tampered_w.pt", match="does not match")


def test_segmentation_export_predicts_the_same_probabilities(tmp_path):
    root = write_toy_root(tmp_path / "toy")
    run = tmp_path / "run"
    cfg = load_config(
        SegTrainConfig, SEG_TINY, [f"data.root={root}", f"out_dir={run}", "optim.steps=4", "eval_every=4"]
    )
    train_segmentor(cfg, progress=False)
    exported = export_weights(run / "model.pt", tmp_path / "seg.pt")
    assert exported["kind"] == SEG_CHECKPOINT_KIND and exported["trained"]["step"] == 4
    assert export_weights(run / "model.pt", tmp_path / "seg_again.pt")["hash"] == exported["hash"]
    a, b = load_seg_checkpoint(run / "model.pt"), load_seg_checkpoint(tmp_path / "seg.pt")
    assert b["step"] == 4 and b["config"] == a["config"]
    assert (tmp_path / "seg.pt").stat().st_size / fp32_size(a["model"]) < 0.55
    points = read_kitti_scan(root / "sequences" / "01" / "velodyne" / "000000.bin")
    probs_a = predict_probs(model_from_checkpoint(a, CPU), points, CPU)
    probs_b = predict_probs(model_from_checkpoint(b, CPU), points, CPU)
    assert float((probs_a - probs_b).abs().max()) < 0.01
    assert float((probs_a.argmax(1) == probs_b.argmax(1)).float().mean()) > 0.99


def test_cli_command(diffusion, tmp_path, capsys):
    checkpoint, exported, _ = diffusion["baseline"]
    assert cli_main(["export-weights", str(checkpoint), "--out", str(tmp_path / "w.pt")]) == 0
    assert exported["hash"] in capsys.readouterr().out
    # a run folder stands for its newest checkpoint (the one the fixture exported)
    assert cli_main(["export-weights", str(checkpoint.parents[1]), "--out", str(tmp_path / "r.pt")]) == 0
    assert exported["hash"] in capsys.readouterr().out
    assert cli_main(["export-weights", str(tmp_path), "--out", str(tmp_path / "y.pt")]) == 2
    assert "checkpoints: no step_*.pt checkpoint in this run folder" in capsys.readouterr().err
    assert cli_main(["export-weights", str(tmp_path / "missing.pt"), "--out", str(tmp_path / "x.pt")]) == 2
    assert "missing.pt: training checkpoint not found" in capsys.readouterr().err


def _one_line_error(call, *args, match: str) -> str:
    with pytest.raises(InputError, match=match) as caught:
        call(*args)
    assert "\n" not in str(caught.value)
    return str(caught.value)


def test_bad_input_is_a_one_line_error(diffusion, tmp_path):
    checkpoint, _, path = diffusion["stage2"]
    text = tmp_path / "notes.pt"
    text.write_text("not a checkpoint\n")
    assert str(text) in _one_line_error(export_weights, text, tmp_path / "out.pt", match="not a readable")
    _one_line_error(export_weights, path, tmp_path / "out.pt", match="already exported")
    _one_line_error(export_weights, checkpoint, checkpoint, match="overwrite")
    _one_line_error(load_extractor, path, match="not an extractor checkpoint")
    _one_line_error(load_seg_checkpoint, path, match="not a segmentation checkpoint")
    resume = diffusion_config(diffusion["world"], tmp_path / "resume", "stage2")
    _one_line_error(
        train_diffusion,
        resume,
        path,
        False,
        match="holds weights only \\(exported weights or a final model.pt\\), no optimizer",
    )
    state = torch.load(path, weights_only=True)
    name = next(iter(state["model"]))
    state["model"][name] = state["model"][name] + 1
    torch.save(state, tmp_path / "tampered.pt")
    _one_line_error(load_generator, tmp_path / "tampered.pt", match="does not match")


def test_diffusion_export_stores_the_row_mean_of_its_training_images(diffusion, tmp_path, caplog):
    world = diffusion["world"]
    for stage in STAGES:
        checkpoint, exported, path = diffusion[stage]
        key = "x0_u" if stage == "stage1" else "x0"
        cfg = diffusion_config(world, tmp_path / stage, stage)
        assert exported["row_mean"]["key"] == key
        assert torch.equal(exported["row_mean"]["mean"], row_mean(cfg, key))  # the mean generate would read
        assert exported["row_mean"]["source"]["data_root"] == str(world[0])
        assert ("probs_root" in exported["row_mean"]["source"]) == (stage == "stage1")
        mean, info = weights.stored_row_mean(torch.load(path, weights_only=True), str(path))
        assert torch.equal(mean, exported["row_mean"]["mean"]) and info["key"] == key
    # training scans that cannot be read: the weights are still written, without the mean, and a warning says why
    checkpoint = diffusion["baseline"][0]
    gone = export_weights(checkpoint, tmp_path / "gone.pt", data_root=str(tmp_path / "nowhere"))
    assert "row_mean" not in gone and "no row_mean stored" in caplog.text
    assert weights.stored_row_mean(torch.load(tmp_path / "gone.pt", weights_only=True), "gone.pt") is None
    state = torch.load(diffusion["baseline"][2], weights_only=True)
    state["row_mean"]["mean"] = state["row_mean"]["mean"][..., 0]  # (C, H): not a per-row image
    _one_line_error(weights.stored_row_mean, state, "bad.pt", match="bad.pt: row_mean: expected")


def test_shipped_generators_carry_their_row_mean():
    shipped = shipped_weights(SHIPPED_DIR)
    assert shipped is not None
    # (file, role, images): the one U4D net stores its stage-1 task's x0_u mean beside its x0 mean
    nets = [("u4d", "stage1", "x0_u"), ("u4d", "stage2", "x0"), ("baseline", None, "x0")]
    sequence = [("u4d_most_stage1", None, "x0_u"), ("u4d_most_stage2", None, "x0"), ("baseline_most", None, "x0")]
    nets += [(name, role, key) for name, role, key in sequence if name in shipped]  # the 4D nets
    for name, role, key in nets:
        state = torch.load(shipped[name], weights_only=True)
        mean, info = weights.stored_row_mean(state, name, role)
        assert info["key"] == key and mean.shape == (2, state["config"]["height"], 1), name
        assert torch.isfinite(mean).all() and float(mean.abs().max()) <= 1.0, name  # range-encoded images


def test_shipped_weights_are_found_by_role(tmp_path):
    assert shipped_weights(tmp_path) is None  # a wheel install: no weights/ folder
    for name in ("u4d", "extractor_frd", "u4d_stage1", "u4d_stage2"):  # a two-net U4D's files fill no role
        (tmp_path / f"{name}.pt").write_bytes(b"x")
    assert shipped_weights(tmp_path) is None  # a generator missing: the demo falls back to its own nets
    (tmp_path / "baseline.pt").write_bytes(b"x")
    found = shipped_weights(tmp_path)
    assert found == {name: tmp_path / f"{name}.pt" for name in ("u4d", "baseline", "extractor_frd")}
    # the checkout's own weights/ folder holds the two generators (U4D one net for both stages) and both extractors
    shipped = shipped_weights(SHIPPED_DIR)
    roles = {"u4d", "baseline", "extractor_frd", "extractor_fpd"}
    assert shipped is not None and roles <= set(shipped)


def test_shipped_files_match_the_hashes_and_sizes_their_readme_records():
    shipped = shipped_weights(SHIPPED_DIR)
    assert shipped is not None
    rows = {}
    for line in (SHIPPED_DIR / "README.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if line.startswith("| `") and cells[0].endswith(".pt`"):
            rows[cells[0].strip("`")[: -len(".pt")]] = (cells[-2].strip("`"), float(cells[-1]))
    # every file in weights/ (the demo's roles and the experiments' nets) has its row, and no row names an absent file
    files = {path.stem: path for path in SHIPPED_DIR.glob("*.pt")}
    assert set(rows) == set(files)
    for name, path in files.items():
        state = torch.load(path, weights_only=True)
        assert state["hash"] == rows[name][0], name
        assert abs(path.stat().st_size / 1e6 - rows[name][1]) < 0.1, name
    single = [shipped[name] for name in (*SHIPPED_GENERATORS, *SHIPPED_OPTIONAL) if name in shipped]
    assert sum(p.stat().st_size for p in single) <= 25e6  # what the demo and generate read by default
    sequence = [shipped[name] for name in SHIPPED_SEQUENCE if name in shipped]
    assert sum(p.stat().st_size for p in sequence) <= 21e6  # the 4D nets of generate_hdl64_most.yaml
    assert sum(p.stat().st_size for p in files.values()) <= 70e6  # the experiments' nets included
    for kind in ("frd", "fpd"):
        extractor = load_extractor(shipped[f"extractor_{kind}"])
        assert extractor.kind == kind and (extractor.height, extractor.width) == (64, 1024)
