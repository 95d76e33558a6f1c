"""Issue 44 item 6: every bad input gets one line. One row per case: `u4d` argv, expected message fragment.

Each case runs in-process through `u4d_aug.cli.main(argv)` and must end with exit code 2, a single line
`error: ...` on stderr holding the fragment, and no traceback. The inputs (a tiny SemanticKITTI root, a one-step
segmentor, an untrained diffusion checkpoint, corrupt and hostile files) are made once per module; `{name}` in an
argv is replaced by the path of that input.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import traceback
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.tiny_nets import REPO, SEG_TINY
from tests.tiny_worlds import write_toy_root
from u4d_aug.cli import main
from u4d_aug.config import load_config
from u4d_aug.data.formats import write_kitti_label, write_kitti_scan, write_nuscenes_scan
from u4d_aug.ema import EMA
from u4d_aug.io import atomic_save_npy, atomic_torch_save
from u4d_aug.stage import DiffusionTrainConfig, build_net, checkpoint_state

U4D_TINY = REPO / "configs" / "u4d" / "tiny.yaml"
EXTRACTOR_TINY = REPO / "configs" / "extractor" / "tiny.yaml"
EXPERIMENT_TINY = REPO / "configs" / "experiment" / "tiny.yaml"
READ_ONLY = "/sys/u4d_bad_input"  # a read-only file system in containers; the cases using it skip elsewhere


class Payload:
    """Unpickled, it would create a file: loaders must refuse it without running it."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (str(self.marker), "w"))


def _read_only_available() -> bool:
    try:
        os.makedirs(READ_ONLY)
    except OSError:
        return True
    os.rmdir(READ_ONLY)
    return False


def _mount_full_disk(folder: Path) -> bool:
    """A 32 KiB tmpfs at `folder` (root with mount rights only): a disk that is full after a few small files."""
    folder.mkdir()
    try:
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=32k", "tmpfs", str(folder)], capture_output=True)
    except OSError:
        return False
    return done.returncode == 0


@pytest.fixture(scope="module")
def paths(tmp_path_factory, request) -> dict[str, str]:
    """Every input of the cases, by name."""
    base = tmp_path_factory.mktemp("bad_inputs")
    full = base / "full_disk"
    if _mount_full_disk(full):
        request.addfinalizer(lambda: subprocess.run(["umount", str(full)], check=False))
        (full / "scan.ply").write_text("a good .ply\n")  # must survive a failed `show --ply` on the full disk
    torch.set_num_threads(1)
    p: dict[str, Path] = {"base": base, "root": write_toy_root(base / "root", frames=2)}
    rng = np.random.default_rng(0)

    # segmentor (1 step) and an untrained diffusion checkpoint of the tiny preset
    seg_out = base / "seg"
    assert main(["seg-train", str(SEG_TINY), f"data.root={p['root']}", "optim.steps=1", "eval_every=1",
                 "--out", str(seg_out), "--no-progress", "--quiet"]) == 0  # fmt: skip
    p["seg_ckpt"] = seg_out / "model.pt"
    cfg = load_config(DiffusionTrainConfig, U4D_TINY, ["diffusion.stage=baseline"])
    net = build_net(cfg)
    p["diffusion_ckpt"] = base / "diffusion.pt"
    atomic_torch_save(p["diffusion_ckpt"], checkpoint_state(cfg, 0, net, EMA(net)))
    stage2 = load_config(DiffusionTrainConfig, U4D_TINY, ["diffusion.stage=stage2"])
    p["stage2_ckpt"] = base / "stage2.pt"
    stage2_net = build_net(stage2)
    atomic_torch_save(p["stage2_ckpt"], checkpoint_state(stage2, 0, stage2_net, EMA(stage2_net)))
    wide = build_net(load_config(DiffusionTrainConfig, U4D_TINY, ["diffusion.stage=baseline", "net.base_channels=16"]))
    p["misfit_ckpt"] = base / "misfit.pt"  # loads safely, but its EMA is of a wider net than its config builds
    atomic_torch_save(p["misfit_ckpt"], checkpoint_state(cfg, 0, net, EMA(wide)))

    seg_state = torch.load(p["seg_ckpt"], weights_only=True)
    first = next(iter(seg_state["model"]))
    seg_state["model"][first] = torch.zeros(2, 3)  # loads safely, fits no net of its config
    p["seg_misfit"] = base / "seg_misfit.pt"
    atomic_torch_save(p["seg_misfit"], seg_state)

    # corrupt and hostile files
    p["junk_pt"] = base / "junk.pt"
    p["junk_pt"].write_bytes(b"not a checkpoint at all")
    p["cut_pt"] = base / "cut.pt"
    p["cut_pt"].write_bytes(p["seg_ckpt"].read_bytes()[:2000])
    p["marker"] = base / "payload_ran"
    p["payload_pt"] = base / "payload.pt"
    torch.save({"format": "u4d-seg-checkpoint", "kind": "u4d-diffusion", "config": {}, "model": Payload(p["marker"])},
               p["payload_pt"])  # fmt: skip
    p["bad_yaml"] = base / "bad.yaml"
    p["bad_yaml"].write_text("optim: {lr: [1, 2\n")
    p["file"] = base / "a_file.txt"
    p["file"].write_text("a file, not a folder\n")
    p["dir"] = base / "a_folder"
    p["dir"].mkdir()
    p["missing"] = base / "missing"

    # scans: a good one, wrong sizes, a mislabelled nuScenes file, NaN points
    good = p["root"] / "sequences" / "00" / "velodyne" / "000000.bin"
    p["scan"] = good
    p["short_bin"] = base / "short.bin"
    p["short_bin"].write_bytes(good.read_bytes()[:-5])
    p["short_pcd"] = base / "short.pcd.bin"
    p["short_pcd"].write_bytes(b"\0" * 24)
    points = np.fromfile(good, dtype=np.float32).reshape(-1, 4)[:400]
    write_nuscenes_scan(base / "nu.pcd.bin", points, rng.integers(0, 32, len(points)))
    p["nuscenes_bin"] = base / "nuscenes.bin"
    p["nuscenes_bin"].write_bytes((base / "nu.pcd.bin").read_bytes())

    def root_with(name: str, bin_bytes: bytes | None = None, label_count: int | None = None) -> Path:
        root = base / name
        for frame in ("000000", "000001"):
            source = p["root"] / "sequences" / "00"
            for folder, suffix in (("velodyne", ".bin"), ("labels", ".label")):
                target = root / "sequences" / "00" / folder / f"{frame}{suffix}"
                target.parent.mkdir(parents=True, exist_ok=True)
                target.write_bytes((source / folder / f"{frame}{suffix}").read_bytes())
        scan = root / "sequences" / "00" / "velodyne" / "000001.bin"
        if bin_bytes is not None:
            scan.write_bytes(bin_bytes)
        if label_count is not None:
            write_kitti_label(root / "sequences" / "00" / "labels" / "000001.label", np.zeros(label_count, np.uint16))
        return root

    p["root_short_bin"] = root_with("root_short_bin", p["short_bin"].read_bytes())
    p["root_nuscenes"] = root_with("root_nuscenes", p["nuscenes_bin"].read_bytes())
    p["root_bad_label"] = root_with("root_bad_label", label_count=7)
    p["root_huge_bin"] = root_with("root_huge_bin")
    with open(p["root_huge_bin"] / "sequences" / "00" / "velodyne" / "000001.bin", "r+b") as f:
        f.truncate(8 * 2**40)  # a sparse 8 TiB file: no disk space used, more than any machine's memory
    p["root_empty"] = base / "root_empty"
    (p["root_empty"] / "sequences").mkdir(parents=True)

    # probabilities: NaN, object dtype, truncated (one file per probs root, for scan 00/000000)
    count = len(np.fromfile(good, dtype=np.float32)) // 4
    probs = rng.dirichlet(np.ones(5), count).astype(np.float16)
    for name in ("probs_nan", "probs_object", "probs_cut", "probs_logits", "probs_unnormalised"):
        p[name] = base / name
        atomic_save_npy(p[name] / "sequences" / "00" / "probs" / "000001.npy", probs)
        target = p[name] / "sequences" / "00" / "probs" / "000000.npy"
        target.parent.mkdir(parents=True, exist_ok=True)
        if name == "probs_nan":
            bad = probs.copy()
            bad[7, 2] = np.nan
            np.save(target, bad)
        elif name == "probs_object":
            np.save(target, probs.astype(object), allow_pickle=True)
        elif name == "probs_logits":  # scores, not a softmax: negative and > 1
            np.save(target, rng.normal(0, 3, probs.shape).astype(np.float16))
        elif name == "probs_unnormalised":  # in [0, 1] but rows summing to ~2.5
            np.save(target, rng.random(probs.shape).astype(np.float16))
        else:
            np.save(target, probs)
            target.write_bytes(target.read_bytes()[:-100])
    # a run folder held by a live process (the test runner's parent)
    p["locked"] = base / "locked"
    p["locked"].mkdir()
    holder = {"pid": os.getppid(), "host": socket.gethostname(), "start": None, "started": 0}
    (p["locked"] / ".lock").write_text(json.dumps(holder))
    # a bank-like root of generated scans for evaluate / gen-report
    p["bank"] = base / "bank"
    write_kitti_scan(p["bank"] / "sequences" / "00" / "velodyne" / "000000.bin", points)
    # output folders with a symbolic link that leaves them: a log file and a checkpoints/ folder
    p["outside"] = base / "outside"
    (p["outside"] / "checkpoints").mkdir(parents=True)
    (p["outside"] / "hosts.jsonl").write_text("kept\n")
    p["linked_log"] = base / "linked_log"
    p["linked_log"].mkdir()
    (p["linked_log"] / "hosts.jsonl").symlink_to(p["outside"] / "hosts.jsonl")
    p["linked_dir"] = base / "linked_dir"
    p["linked_dir"].mkdir()
    (p["linked_dir"] / "checkpoints").symlink_to(p["outside"] / "checkpoints", target_is_directory=True)
    # banks whose manifest is valid json of the wrong shape
    for name, manifest in (("bank_list_manifest", []), ("bank_bad_samples", {"mode": "baseline", "samples": 5}),
                           ("bank_bad_frames", {"mode": "baseline", "frames": "two", "sensor": "hdl64"})):  # fmt: skip
        p[name] = base / name
        write_kitti_scan(p[name] / "sequences" / "00" / "velodyne" / "000000.bin", points)
        (p[name] / "manifest.json").write_text(json.dumps(manifest))
    p["read_only"] = Path(READ_ONLY)
    p["full"] = full
    return {key: str(value) for key, value in p.items()}


SEG = ["seg-train", str(SEG_TINY), "data.root={root}", "optim.steps=1", "--no-progress"]
DIFF = ["train-diffusion", str(U4D_TINY), "data_root={root}", "steps=1", "--no-progress"]
GEN = ["generate", str(REPO / "configs" / "u4d" / "generate_cpu.yaml"), "steps=1", "num=1", "--no-progress"]
EXTRACT = [str(EXTRACTOR_TINY), "data.root={root}", "train.steps=1", "train.val_scans=0"]

# (case id, argv, fragment of the one-line message); every case expects exit code 2
CASES = [
    # info
    ("info-missing-root", ["info", "{missing}"], "missing"),
    ("info-file-as-root", ["info", "{file}"], "a_file.txt"),
    ("info-no-sequences", ["info", "{root_empty}"], "no sequence has a velodyne/ folder"),
    ("info-short-bin", ["info", "{root_short_bin}"], "is not a multiple of 16"),
    ("info-label-count", ["info", "{root_bad_label}"], "7 labels but the scan has"),
    ("info-nuscenes-as-kitti", ["info", "{root_nuscenes}"], "like a nuScenes scan"),
    # show
    ("show-missing-scan", ["show", "{missing}"], "not found"),
    ("show-folder-as-scan", ["show", "{dir}"], "no velodyne/ folder (expected a scan file or a SemanticKITTI sequence"),
    ("show-short-bin", ["show", "{short_bin}"], "is not a multiple of 16"),
    ("show-short-pcd", ["show", "{short_pcd}"], "is not a multiple of 20"),
    ("show-nuscenes-as-kitti", ["show", "{nuscenes_bin}"], "name it *.pcd.bin"),
    ("show-unknown-sensor", ["show", "{scan}", "--sensor", "hdl99"], "hdl99"),
    ("show-negative-width", ["show", "{scan}", "--width", "-5", "--row-mode", "linear"], "at least 3 columns"),
    ("show-zero-width", ["show", "{scan}", "--width", "0", "--row-mode", "linear"], "at least 3 columns"),
    ("show-png-is-folder", ["show", "{scan}", "--png", "{dir}"], "is a folder; expected a file path"),
    ("show-png-under-file", ["show", "{scan}", "--png", "{file}/x.png"], "is a file; expected an output folder"),
    # simulate, sim-report
    ("simulate-out-is-file", ["simulate", "--out", "{file}", "--frames", "1"], "is a file; expected an output folder"),
    ("simulate-zero-sequences", ["simulate", "--out", "{base}/sim0", "--sequences", "0"], "must be >= 1"),
    ("gates-zero-frames", ["gates", "{diffusion_ckpt}", "--png", "{base}/g.png", "--frames", "0"], "--frames 0"),
    ("gates-nan-step", ["gates", "{diffusion_ckpt}", "--png", "{base}/g.png", "--step", "nan"], "--step nan"),
    ("simulate-negative-seed", ["simulate", "--out", "{base}/sim4", "--seed", "-1"], "--seed must be >= 0"),
    ("simulate-nan-setting", ["simulate", "--out", "{base}/sim1", "frame_rate=.nan"], "'frame_rate'"),
    ("simulate-bad-yaml", ["simulate", "--out", "{base}/sim2", "--config", "{bad_yaml}"], "not valid yaml"),
    ("simulate-unknown-key", ["simulate", "--out", "{base}/sim3", "agents.carz=3"], "unknown config key"),
    ("simulate-read-only", ["simulate", "--out", "{read_only}", "--frames", "1"], "cannot create the output folder"),
    ("sim-report-zero-frames", ["sim-report", "{root}", "--real", "{root}", "--max-frames", "0"], "--max-frames"),
    ("sim-report-missing", ["sim-report", "{missing}", "--real", "{root}"], "missing"),
    ("sim-report-png-is-folder", ["sim-report", "{root}", "--real", "{root}", "--png", "{dir}"], "is a folder"),
    # seg-train
    ("seg-train-missing-config", ["seg-train", "{missing}.yaml"], "config file not found"),
    ("seg-train-bad-yaml", ["seg-train", "{bad_yaml}"], "not valid yaml"),
    ("seg-train-lr-inf", [*SEG, "optim.lr=.inf", "--out", "{base}/s1"], "'optim.lr' must be a finite number"),
    ("seg-train-lr-nan", [*SEG, "optim.lr=.nan", "--out", "{base}/s2"], "'optim.lr' must be a finite number"),
    ("seg-train-out-is-file", [*SEG, "--out", "{file}"], "is a file; expected an output folder"),
    ("seg-train-read-only", [*SEG, "--out", "{read_only}"], "cannot create the output folder"),
    ("seg-train-missing-data", [*SEG, "data.root={missing}", "--out", "{base}/s3"], "missing"),
    ("seg-train-resume-junk", [*SEG, "--out", "{base}/s4", "--resume", "{junk_pt}"], "not a readable"),
    ("seg-train-resume-payload", [*SEG, "--out", "{base}/s5", "--resume", "{payload_pt}"], "nothing was run"),
    ("seg-train-locked-folder", [*SEG, "--out", "{locked}"], "in use by another run"),
    # seg-eval
    ("seg-eval-junk", ["seg-eval", "{junk_pt}", "{root}"], "not a readable segmentation checkpoint"),
    ("seg-eval-truncated", ["seg-eval", "{cut_pt}", "{root}"], "not a readable segmentation checkpoint"),
    ("seg-eval-payload", ["seg-eval", "{payload_pt}", "{root}"], "nothing was run"),
    ("seg-eval-diffusion-ckpt", ["seg-eval", "{diffusion_ckpt}", "{root}"], "not a segmentation checkpoint"),
    ("seg-eval-zero-scans", ["seg-eval", "{seg_ckpt}", "{root}", "--max-scans", "0"], "--max-scans"),
    ("seg-eval-views", ["seg-eval", "{seg_ckpt}", "{root}", "--views", "5"], "views"),
    ("seg-eval-bad-label", ["seg-eval", "{seg_ckpt}", "{root_bad_label}", "--no-progress"], "7 labels but the scan"),
    (
        "seg-eval-png-is-folder",
        ["seg-eval", "{seg_ckpt}", "{root}", "--sequences", "01", "--png", "{dir}"],
        "is a folder; expected a file path",
    ),  # fmt: skip
    # seg-predict
    (
        "seg-predict-diffusion-ckpt",
        ["seg-predict", "{diffusion_ckpt}", "{root}", "--out", "{base}/p1"],
        "not a segmentation checkpoint",
    ),  # fmt: skip
    ("seg-predict-payload", ["seg-predict", "{payload_pt}", "{root}", "--out", "{base}/p2"], "nothing was run"),
    ("seg-predict-out-is-file", ["seg-predict", "{seg_ckpt}", "{root}", "--out", "{file}"], "is a file"),
    (
        "seg-predict-nuscenes-as-kitti",
        ["seg-predict", "{seg_ckpt}", "{root_nuscenes}", "--out", "{base}/p3", "--no-progress"],
        "like a nuScenes scan",
    ),  # fmt: skip
    (
        "seg-predict-disk-full",
        ["seg-predict", "{seg_ckpt}", "{root}", "--out", "{full}/p", "--no-progress"],
        "cannot write (No space left on device)",
    ),  # fmt: skip
    ("seg-predict-locked-folder", ["seg-predict", "{seg_ckpt}", "{root}", "--out", "{locked}"], "in use by another"),
    # train-diffusion
    ("diffusion-lr-inf", [*DIFF, "optim.lr=.inf", "--out", "{base}/d1"], "'optim.lr' must be a finite number"),
    ("diffusion-lr-nan", [*DIFF, "optim.lr=.nan", "--out", "{base}/d2"], "'optim.lr' must be a finite number"),
    ("diffusion-lr-negative", [*DIFF, "optim.lr=-1e-3", "--out", "{base}/d3"], "'optim.lr' must be > 0"),
    ("diffusion-ema-decay", [*DIFF, "ema_decay=2", "--out", "{base}/d4"], "'ema_decay' must be in [0, 1]"),
    ("diffusion-height-zero", [*DIFF, "height=0", "--out", "{base}/d5"], "height/width must be >= 1"),
    ("diffusion-bad-stage", [*DIFF, "stage=stage3", "--out", "{base}/d6"], "stage3"),
    (
        "diffusion-probs-nan",
        [*DIFF, "stage=stage1", "probs_root={probs_nan}", "--out", "{base}/d7"],
        "probabilities are NaN/inf",
    ),  # fmt: skip
    (
        "diffusion-probs-object",
        [*DIFF, "stage=stage1", "probs_root={probs_object}", "--out", "{base}/d8"],
        "it holds python objects",
    ),  # fmt: skip
    (
        "diffusion-probs-truncated",
        [*DIFF, "stage=stage1", "probs_root={probs_cut}", "--out", "{base}/d9"],
        "not a readable probability file",
    ),  # fmt: skip
    (
        "diffusion-probs-logits",
        [*DIFF, "stage=stage1", "probs_root={probs_logits}", "--out", "{base}/d12"],
        "values outside [0, 1]",
    ),  # fmt: skip
    (
        "diffusion-probs-unnormalised",
        [*DIFF, "stage=stage1", "probs_root={probs_unnormalised}", "--out", "{base}/d13"],
        "rows do not sum to 1",
    ),  # fmt: skip
    (
        "generate-complete-probs-logits",
        [
            *GEN,
            "mode=complete",
            "stage2={stage2_ckpt}",
            "data_root={root}",
            "probs_root={probs_logits}",
            'sequences=["00"]',
            "--out",
            "{base}/g9",
        ],
        "values outside [0, 1]",
    ),  # fmt: skip
    ("diffusion-resume-payload", [*DIFF, "--out", "{base}/d10", "--resume", "{payload_pt}"], "nothing was run"),
    (
        "diffusion-resume-seg-ckpt",
        [*DIFF, "--out", "{base}/d11", "--resume", "{seg_ckpt}"],
        "not a u4d train-diffusion checkpoint",
    ),  # fmt: skip
    ("diffusion-out-is-file", [*DIFF, "--out", "{file}"], "is a file; expected an output folder"),
    ("diffusion-disk-full", [*DIFF, "--out", "{full}/d"], "cannot write (No space left on device)"),
    ("show-ply-disk-full", ["show", "{scan}", "--ply", "{full}/scan.ply"], "scan.ply"),
    ("diffusion-locked-folder", [*DIFF, "--out", "{locked}"], "in use by another run"),
    ("diffusion-linked-log", [*DIFF, "--out", "{linked_log}"], "hosts.jsonl: a symbolic link to"),
    ("diffusion-linked-checkpoints", [*DIFF, "--out", "{linked_dir}"], "checkpoints: a symbolic link to"),
    ("seg-train-huge-width", [*SEG, "model.width=10000", "--out", "{base}/s9"], "reduce model.width"),
    ("diffusion-huge-width", [*DIFF, "net.base_channels=100000", "--out", "{base}/d14"], "more than the"),
    ("generate-huge-num", [*GEN, "num=100000000000", "--out", "{base}/g10"], "num=100000000000"),
    (
        "generate-huge-steps",
        [*GEN, "mode=baseline", "baseline={diffusion_ckpt}", "steps=1000000000000", "--out", "{base}/g11"],
        "steps=1000000000000",
    ),  # fmt: skip
    ("info-huge-sparse-bin", ["info", "{root_huge_bin}"], "no LiDAR scan is this large"),
    ("seg-train-linked-checkpoints", [*SEG, "--out", "{linked_dir}"], "outside the output folder"),
    # generate
    ("generate-junk-ckpt", [*GEN, "mode=baseline", "baseline={junk_pt}", "--out", "{base}/g1"], "not a readable"),
    ("generate-payload", [*GEN, "mode=baseline", "baseline={payload_pt}", "--out", "{base}/g2"], "nothing was run"),
    (
        "generate-seg-ckpt",
        [*GEN, "mode=baseline", "baseline={seg_ckpt}", "--out", "{base}/g3"],
        "not a u4d train-diffusion checkpoint",
    ),  # fmt: skip
    (
        "generate-misfit-ckpt",
        [*GEN, "mode=baseline", "baseline={misfit_ckpt}", "--out", "{base}/g7"],
        "(ema): its weights do not fit the net",
    ),  # fmt: skip
    ("generate-negative-num", [*GEN, "num=-1", "--out", "{base}/g4"], "num must be >= 0"),
    ("generate-zero-steps", [*GEN, "steps=0", "--out", "{base}/g5"], "steps >= 1"),
    (
        "generate-mask-fraction",
        [*GEN, "stage1_mask_fraction=1.5", "--out", "{base}/g6"],
        "stage1_mask_fraction must be in (0, 1]",
    ),
    ("generate-out-is-file", [*GEN, "mode=baseline", "baseline={diffusion_ckpt}", "--out", "{file}"], "is a file"),
    (
        "generate-locked-bank",
        [*GEN, "mode=baseline", "baseline={diffusion_ckpt}", "--out", "{locked}"],
        "in use by another run",
    ),  # fmt: skip
    # gen-report
    (
        "gen-report-bank-name-path",
        ["gen-report", "{root}", "--bank", "../x={bank}", "--png", "{base}/r.png"],
        "must be a plain name",
    ),  # fmt: skip
    (
        "gen-report-negative-index",
        ["gen-report", "{root}", "--bank", "b={bank}", "--png", "{base}/r.png", "--index", "-1"],
        "--index",
    ),  # fmt: skip
    (
        "gen-report-manifest-a-list",
        ["gen-report", "{root}", "--bank", "b={bank_list_manifest}", "--png", "{base}/r1.png"],
        "manifest.json: expected a json object",
    ),  # fmt: skip
    (
        "gen-report-manifest-frames-text",
        ["gen-report", "{root}", "--bank", "b={bank_bad_frames}", "--png", "{base}/r2.png"],
        "'frames' must be an integer",
    ),  # fmt: skip
    ("export-manifest-a-list", ["export", "{bank_list_manifest}", "--labels"], "expected a json object"),
    ("export-manifest-samples-int", ["export", "{bank_bad_samples}", "--labels"], "'samples' must be a list"),
    # train-extractor
    ("extractor-zero-steps", ["train-extractor", "frd", *EXTRACT, "train.steps=0"], "'train.steps' must be > 0"),
    ("extractor-lr-nan", ["train-extractor", "fpd", *EXTRACT, "train.lr=.nan"], "'train.lr' must be a finite"),
    ("extractor-out-is-file", ["train-extractor", "frd", *EXTRACT, "out_dir={file}"], "is a file"),
    # export-weights
    ("export-junk", ["export-weights", "{junk_pt}", "--out", "{base}/w1.pt"], "not a readable"),
    ("export-payload", ["export-weights", "{payload_pt}", "--out", "{base}/w2.pt"], "nothing was run"),
    ("export-misfit-ema", ["export-weights", "{misfit_ckpt}", "--out", "{base}/w3.pt"], "would not load back"),
    ("export-seg-misfit", ["export-weights", "{seg_misfit}", "--out", "{base}/w4.pt"], "would not load back"),
    ("export-out-is-folder", ["export-weights", "{diffusion_ckpt}", "--out", "{dir}"], "is a folder"),
    # evaluate
    ("evaluate-zero-scans", ["evaluate", "--bank", "{bank}", "--real", "{root}", "--max-scans", "0"], "--max-scans"),
    ("evaluate-unknown-metric", ["evaluate", "--bank", "{bank}", "--real", "{root}", "--metrics", "fid"], "--metrics"),
    ("evaluate-missing-bank", ["evaluate", "--bank", "{missing}", "--real", "{root}", "--metrics", "jsd"], "missing"),
    (
        "evaluate-extractor-payload",
        ["evaluate", "--bank", "{bank}", "--real", "{root}", "--metrics", "frd", "--extractor-frd", "{payload_pt}"],
        "nothing was run",
    ),  # fmt: skip
    (
        "evaluate-json-out-is-file",
        ["evaluate", "--bank", "{bank}", "--real", "{root}", "--metrics", "jsd", "--json", "--out", "{file}"],
        "is a file",
    ),  # fmt: skip
    # experiment
    (
        "experiment-arm-escapes",
        ["experiment", str(EXPERIMENT_TINY), "arms=[{{name: ../../escaped}}]", "--out", "{base}/e1"],
        "must be a plain name",
    ),  # fmt: skip
    (
        "experiment-unknown-arm",
        ["experiment", str(EXPERIMENT_TINY), "--arms", "nope", "--out", "{base}/e2"],
        "'nope' is not an arm",
    ),  # fmt: skip
    (
        "experiment-arm-cannot-run",
        ["experiment", str(EXPERIMENT_TINY), "--arms", "mt-lasermix-u4d", "--out", "{base}/e3"],
        "cannot run: bank",
    ),  # fmt: skip
    ("experiment-missing-config", ["experiment", "{missing}.yaml"], "config file not found"),
]


def run_case(argv: list[str], capsys) -> tuple[int, str, str | None]:
    """(exit code, stderr, traceback text if an exception escaped main)."""
    try:
        code = main(argv)
    except SystemExit as exit_:  # argparse usage errors
        code = exit_.code
    except BaseException:  # noqa: BLE001 - the point is that nothing escapes
        return -1, capsys.readouterr().err, traceback.format_exc()
    return code, capsys.readouterr().err, None


@pytest.mark.parametrize(("case", "argv", "fragment"), CASES, ids=[case[0] for case in CASES])
def test_bad_input_gives_one_clean_line_and_exit_code_2(paths, capsys, case, argv, fragment):
    if "{read_only}" in " ".join(argv) and not _read_only_available():
        pytest.skip(f"{READ_ONLY} is writable on this machine")
    if "{full}" in " ".join(argv) and not os.path.ismount(paths["full"]):
        pytest.skip("no small file system could be mounted to fill (needs root with mount rights)")
    filled = [word.format(**paths) for word in argv]
    code, stderr, escaped = run_case(filled, capsys)
    assert escaped is None, escaped
    lines = stderr.strip().splitlines()
    assert code == 2, stderr
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    assert fragment in lines[0] and "Traceback" not in stderr
    assert not Path(paths["marker"]).exists()  # no checkpoint ran its payload
    assert not (Path(paths["base"]).parent / "escaped").exists()
    if argv[0] == "export-weights":  # a refused export writes no file
        assert not Path(filled[filled.index("--out") + 1]).is_file()
    if os.path.ismount(paths["full"]):  # a failed write on the full disk keeps the file that was there
        assert (Path(paths["full"]) / "scan.ply").read_text() == "a good .ply\n"
    outside = Path(paths["outside"])  # nothing written through a link that leaves --out
    assert (outside / "hosts.jsonl").read_text() == "kept\n" and not any((outside / "checkpoints").iterdir())


def test_the_suite_covers_every_command_with_40_cases_or_more():
    commands = {argv[0] for _, argv, _ in CASES}
    assert len(CASES) >= 40 and len({case for case, _, _ in CASES}) == len(CASES)
    assert commands >= {"info", "show", "simulate", "sim-report", "seg-train", "seg-eval", "seg-predict",
                        "train-diffusion", "generate", "gen-report", "train-extractor", "export-weights", "evaluate",
                        "experiment"}  # fmt: skip
