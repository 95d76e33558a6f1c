"""`u4d generate CONFIG --out BANK [--num N] [--mode u4d|baseline|complete] [--steps S] [--seed S]`.

Writes a bank of generated scans (layout in `u4d_aug.bank`). Sample i is drawn with its own generator seeded
seed + i, also inside a batch (`batch_size` samples per sampler call, fixed blocks of consecutive indices), so a
bank does not depend on the number of torchrun ranks that share the work (rank r takes blocks r, r + world, ...);
finished samples are skipped on a re-run, once their files match the digests the manifest records (a sample
changed or truncated since is generated again). A generator trained on L > 1 frames writes each
sample as an L-frame sequence (one bank sequence per sample); in completion mode sample i then completes the
x0_u of window i of L real frames and keeps those frames' relative poses. A sequence generator conditioned on ego
motion (net.pose_dim > 0) gets, for sample i, the motion of an L-frame window of its training sequences' poses.txt
(window drawn with seed + i) or of `motion_file`; the bank sequence's poses.txt holds the poses of that motion
(`u4d_aug.trajectory.poses_from_motion`), so TTCE/CTC (`u4d evaluate`) can score it. Completion mode conditions on
the real frames' own motion. The bank also gets config.yaml (the run's resolved config), log.jsonl (a line per
finished block), identity calib/poses and times.txt where its sequences have no poses of their own, and unless
labels=false the all-ignore labels of `u4d export --layout semantickitti` (a bank is a training set).
With `detail`, a two-level cascade (`u4d_aug.cascade`): the u4d or baseline nets generate each scan's layout at W / s
columns and a detail net completes it to W columns (or detail=nearest repeats each column s times).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from u4d_aug.bank import (
    BankLayout,
    check_compatible,
    file_sha256,
    has_own_poses,
    read_manifest,
    record_digests,
    recorded_digests,
    sample_digests,
    sequence_name,
    verify_samples,
    write_bank_sequence_files,
    write_manifest,
    write_sample,
    write_sequence_poses,
)
from u4d_aug.batches import net_row_mean
from u4d_aug.cascade import NEAREST, spread_columns, upsample_nearest
from u4d_aug.config import config_to_dict, load_config, save_config
from u4d_aug.data.beams import check_beams
from u4d_aug.data.datasets import (
    NuscenesScanDataset,
    NuscenesSequenceDataset,
    ScanDataset,
    SequenceDataset,
    open_scans,
    open_sequences,
)
from u4d_aug.data.formats import read_calib, read_poses
from u4d_aug.data.sensors import get_sensor
from u4d_aug.distributed import DistInfo, barrier, cleanup, init_distributed, shard
from u4d_aug.errors import InputError
from u4d_aug.export_bank import export_bank
from u4d_aug.io import append_jsonl, load_checkpoint, remove_temp_files
from u4d_aug.latent import autoencoder_of, to_latent
from u4d_aug.memory import check_fits
from u4d_aug.nn.autoencoder import RangeAutoencoder
from u4d_aug.outfolder import check_output_folder
from u4d_aug.pipeline import (
    Loaded,
    MeanStart,
    Sampler,
    complete,
    generate_baseline,
    generate_baseline_propagated,
    generate_u4d,
    generate_u4d_propagated,
    load_generator,
    refine,
    stored_mean,
    to_points,
)
from u4d_aug.progress import progress_bar
from u4d_aug.run import CONFIG_NAME, LOG_NAME
from u4d_aug.runlock import run_lock
from u4d_aug.sampling import Grid, check_grid
from u4d_aug.sampling_settings import DEFAULT_SAMPLING, SamplingSettings
from u4d_aug.stage import DiffusionTrainConfig
from u4d_aug.trajectory import POSE_DIM, poses_from_motion, relative_motion
from u4d_aug.uncertainty import load_probs, probs_path, uncertain_range_view
from u4d_aug.weights_store import missing_hint, resolve_weights

logger = logging.getLogger(__name__)

Scans = ScanDataset | NuscenesScanDataset  # single real scans (completion mode)
Windows = SequenceDataset | NuscenesSequenceDataset  # L-frame windows with poses

Mode = Literal["u4d", "baseline", "complete"]


MANIFEST_ENTRY_BYTES = 2048  # one sample's entry in the manifest while it is built (dicts of digests and seeds)


@dataclass
class GenerateConfig:
    """What to generate and with which checkpoints (checkpoint files or run folders: newest step_*.pt)."""

    mode: Mode = "u4d"
    # u4d and complete modes: one net for both stages (train-diffusion stage=u4d), in place of stage1 / stage2
    net: str = ""
    stage1: str = ""  # u4d mode
    stage2: str = ""  # u4d and complete modes
    baseline: str = ""  # baseline mode
    # u4d and baseline modes, a two-level cascade (`u4d_aug.cascade`): the nets above make scans at W / s columns (the
    # layout) and a detail net (train-diffusion stage=detail, at W columns; single scans) completes them at `steps`,
    # or "nearest": each layout column repeated s times up to the sensor's own width (no net; sequences too);
    # "" = no cascade, the scans are the nets' own
    detail: str = ""
    # ddpm: ancestral, as R2DM; ddim: DDIM at few steps keeps x_1 noise with briefly trained nets; dpmpp2m:
    # DPM-Solver++(2M), deterministic 2nd order, the same t grid and one net call per step; dpmpp2m-sde: its
    # stochastic (SDE, η = 1) form, which like ddpm adds fresh noise at every step. The six sampling keys make
    # `sampling()`, with SamplingSettings' defaults (those of configs/u4d/generate_hdl64.yaml)
    sampler: Sampler = DEFAULT_SAMPLING.sampler
    sampler_grid: Grid = DEFAULT_SAMPLING.grid  # "logsnr": steps uniform in log-SNR (dpmpp2m and dpmpp2m-sde only)
    steps: int = DEFAULT_SAMPLING.steps
    stage1_steps: int | None = DEFAULT_SAMPLING.stage1_steps  # None = steps; the uncertain region allows fewer
    # u4d mode: stage 1's mask keeps at most this share of the pixels, those its head is surest of (the share
    # P_u covers in training range images); null = every pixel over the head's calibrated threshold
    stage1_mask_fraction: float | None = DEFAULT_SAMPLING.stage1_mask_fraction
    # below this log-SNR the samplers take each net's training mean image (per row; x0_u's for stage 1) as the x0
    # estimate instead of the net's own, which divides by α ≈ 0 there
    # (benchmarks/results/generation/mean_start_diagnostic.md);
    # null = the net's own at every step. The mean: read from mean_data_root / mean_probs_root when set, else the
    # one `u4d export-weights` stored in the weights file (the shipped nets have it), else read from the training
    # scans the nets' configs name
    mean_start_below: float | None = DEFAULT_SAMPLING.mean_start_below
    mean_data_root: str = ""
    mean_probs_root: str = ""
    num: int = 64
    seed: int = 0  # sample i uses seed + i
    # samples per sampler call (fixed blocks of consecutive indices); each keeps its own seed, so a batch gives
    # the scans of one-by-one calls up to float rounding, and the same batch_size gives the same bytes
    batch_size: int = 8
    frames: int | None = None  # L frames per sample; None = the L the generator was trained with (1: scans)
    device: str = "auto"
    # completion mode: x0_u, m_u from these real scans (sample i completes scan i mod count, or for sequence
    # generators window i mod count of L frames, frame_stride apart as in training, with poses) and their probs;
    # data_root is read in the layout the generator was trained on (its data_format: SemanticKITTI or nuScenes)
    data_root: str = ""
    sequences: list[str] | None = None
    probs_root: str = ""
    # sequence generators with an ego-motion input (net.pose_dim > 0), u4d and baseline modes: a .npy of (L, 4) or
    # (N, L, 4) motions (x, y, z, yaw per frame; sample i takes motion i mod N) or a KITTI poses.txt of L lines
    # (with calib.txt beside it if there is one); "" = windows of the training sequences' poses.txt
    motion_file: str = ""
    # u4d and baseline modes, sequences with an ego motion: frames 1..L-1 are frame 0 moved along the motion
    # (u4d_aug.propagate) and completed where it does not reach (u4d: by stage 2; baseline: by inpainting with the
    # same net), so the frames follow the poses (two sampler passes)
    propagate: bool = False
    # with propagate, u4d mode: stage 2's x̂0 is also pinned to the propagated pixels at every sampler step, as the
    # baseline's inpainting always is (a no-op in baseline mode); it joins the fill to them
    # (benchmarks/results/temporal/propagation_fill_pinned_*.md)
    propagate_pin: bool = False
    # for other codebases (`u4d export` in place, done once every sample is written): all-ignore .label files
    # (value 0 = "unlabeled", which SemanticKITTI readers map to their ignore index; without them Pointcept reads
    # every point as class 0) beside the scans, and mmdetection3d's semantickitti_infos_train.pkl in the bank
    labels: bool = True
    mmdet3d_infos: bool = False  # needs labels

    def __post_init__(self) -> None:
        if self.num < 0 or self.steps < 1 or (self.stage1_steps is not None and self.stage1_steps < 1):
            raise InputError(f"num must be >= 0 and steps >= 1, got num={self.num}, steps={self.steps}")
        if self.stage1_mask_fraction is not None and not 0.0 < self.stage1_mask_fraction <= 1.0:
            raise InputError(f"stage1_mask_fraction must be in (0, 1] or null, got {self.stage1_mask_fraction}")
        if self.batch_size < 1:
            raise InputError(f"batch_size must be >= 1, got {self.batch_size}")
        check_fits(MANIFEST_ENTRY_BYTES * self.num, f"num={self.num} (the bank's sample listing)", "lower num")
        if self.frames is not None and self.frames < 1:
            raise InputError(f"frames must be >= 1 or null (the generator's own), got {self.frames}")
        try:
            check_grid(self.sampler, self.sampler_grid)
        except ValueError as exc:
            raise InputError(f"sampler_grid: {exc}") from None
        self.sampling()  # the rest of the sampling keys' checks

    def sampling(self) -> SamplingSettings:
        """The `SamplingSettings` of the sampling keys, as the pipeline's generate functions read them."""
        return SamplingSettings(
            sampler=self.sampler,
            grid=self.sampler_grid,
            steps=self.steps,
            stage1_steps=self.stage1_steps,
            stage1_mask_fraction=self.stage1_mask_fraction,
            mean_start_below=self.mean_start_below,
        )


def _checkpoint_paths(cfg: GenerateConfig) -> dict[str, Path]:
    needed = {"u4d": ("stage1", "stage2"), "baseline": ("baseline",), "complete": ("stage2",)}[cfg.mode]
    paths = {}
    one_net = cfg.net if cfg.mode != "baseline" else ""  # baseline mode reads `baseline` only, as it ignores stage1/2
    if one_net and (cfg.stage1 or cfg.stage2):
        raise InputError(
            "net: a one-net u4d checkpoint replaces stage1 and stage2; set one or the other "
            "(two stage nets with a preset that names a one net: add net=)"
        )
    if cfg.detail:
        if cfg.mode == "complete":
            raise InputError("detail: a cascade's detail net completes generated layouts (mode u4d or baseline)")
        if cfg.detail != NEAREST:
            needed = (*needed, "detail")
    for name in needed:
        value = getattr(cfg, name) if name == "detail" else one_net or getattr(cfg, name)
        if not value:
            raise InputError(f"{name}: mode {cfg.mode} needs the {name} checkpoint path")
        path = resolve_weights(value)  # `weights/NAME.pt`: the installed shipped net (u4d_aug.weights_store)
        if path.is_dir():
            found = sorted((path / "checkpoints").glob("step_*.pt"))
            if not found:
                raise InputError(f"{path}: no checkpoints/step_*.pt in this run folder")
            path = found[-1]
        if not path.is_file():
            raise InputError(f"{path}: {name} checkpoint not found{missing_hint(path)}")
        paths[name] = path
    return paths


def is_generated_manifest(record: dict) -> bool:
    """Whether a manifest.json is one `u4d generate` wrote (a bank of generated scans it may resume)."""
    return record.get("mode") in ("u4d", "baseline", "complete") and "checkpoints" in record


def generate_bank(cfg: GenerateConfig, out: str | Path, progress: bool = True) -> dict:
    """Generate samples 0..num-1 not yet in the bank (this rank's share); rank 0 writes the manifest.

    Rank 0 holds the bank's run lock (`u4d_aug.runlock`), removes temp files of killed writes and checks the finished
    samples against the digests of the manifest (a changed one is generated again) before any rank writes.
    """
    if cfg.mmdet3d_infos and not cfg.labels:
        raise InputError("mmdet3d_infos: mmdetection3d's info file names a label file per scan; it needs labels=true")
    paths = _checkpoint_paths(cfg)  # a missing net is one error line, before the bank folder exists
    check_output_folder(out, "a generated bank", is_generated_manifest)  # never into a dataset or another output
    info = init_distributed(cfg.device)
    with run_lock(out, enabled=info.is_main):
        manifest = generate_locked(cfg, paths, Path(out), info, progress)
    if info.is_main and cfg.labels:  # the bank in place: labels, calib/poses/times (and the mmdetection3d info file)
        manifest = {**manifest, "export": export_bank(out, "mmdet3d" if cfg.mmdet3d_infos else "semantickitti")}
    return manifest


def generate_locked(cfg: GenerateConfig, paths: dict[str, Path], out: Path, info: DistInfo, progress: bool) -> dict:
    """The work of `generate_bank` once the bank is locked; `paths`: {net role: checkpoint file}."""
    hashes = {name: file_sha256(path) for name, path in paths.items()}
    config = config_to_dict(cfg)
    identity = _bank_identity(cfg, hashes, config)
    nets, mean_sources = _load_nets(cfg, paths, info.device)
    main = nets["stage2"] if "stage2" in nets else nets["baseline"]
    detail_stride = 1
    if "detail" in nets:
        _check_cascade(cfg, main[1], nets["detail"][1])
        main = nets["detail"]  # the final stage: the scans' image, sensor and row mode
        detail_stride = main[1].detail_stride
    elif cfg.detail == NEAREST:
        detail_stride = nearest_stride(main[1])
        main = (main[0], dataclasses.replace(main[1], width=main[1].width * detail_stride))  # the scans' image
    frames = cfg.frames or main[1].frames  # L: 1 = single scans in sequence 00, > 1 = one sequence per sample
    # configs of the nets with an ego-motion input, the final stage's first (its training sequences give the motion)
    posed = [loaded[1] for loaded in (main, *nets.values()) if loaded[1].net.pose_dim > 0] if frames > 1 else []
    motions, motion_sources = _bank_motions(cfg, posed, frames, identity)
    _check_propagate(cfg, motions, frames)
    check_compatible(Path(out), identity)
    layout, old = _open_layout(Path(out), frames)
    scans = _real_scans(cfg, main[1], frames) if cfg.mode == "complete" else None
    run = _Generation(cfg, nets, main[1], frames, bool(posed), motions, layout, scans, detail_stride)
    manifest = _new_manifest(run, identity, config, paths, mean_sources, motion_sources, old)
    if info.is_main:
        _check_finished_samples(layout, old, manifest)
        save_config(cfg, out / CONFIG_NAME)  # the resolved config of this run, as every run folder holds it
        done = sum("sha256" in entry for entry in manifest["samples"][: cfg.num])
        record = {"event": "start", "num": cfg.num, "samples_done": done, "world_size": info.world_size}
        append_jsonl(out / LOG_NAME, record)
    barrier()  # the other ranks look at the samples once rank 0 has checked them
    _generate_blocks(run, info, progress)
    barrier()
    if info.is_main:
        own_poses = has_own_poses(manifest)  # else identity placeholders, after the samples' digests
        write_bank_sequence_files(layout, len(manifest["samples"]), own_poses)
        manifest["placeholder_poses"] = not own_poses
        _finish_manifest(manifest, layout, cfg.num, frames)
        done = sum(map(layout.is_done, range(cfg.num)))
        record = {"event": "finish", "samples_done": done, "complete": manifest["complete"]}
        append_jsonl(out / LOG_NAME, {**record, "seconds": time.perf_counter() - run.started})
    return manifest


@dataclass
class _Generation:
    """What every block of a bank's samples is generated with (`generate_locked`)."""

    cfg: GenerateConfig
    nets: dict[str, Loaded]  # by role: stage1, stage2, baseline, detail (in MeanStart with mean_start_below)
    train_cfg: DiffusionTrainConfig  # the final stage's: sensor, range image, row mode, frame stride
    frames: int  # L: 1 = single scans in sequence 00, > 1 = one sequence per sample
    posed: bool  # the nets take each frame's ego motion
    motions: np.ndarray | None  # (num, L, 4) ego motion of each sample (u4d and baseline modes), else None
    layout: BankLayout
    scans: Scans | Windows | None  # completion mode: the real scans (or L-frame windows) x0_u is taken from
    detail_stride: int = 1  # a cascade's s: the nets above make W / s columns, the detail level W (1: no cascade)
    started: float = field(default_factory=time.perf_counter)  # wall clock of this run (log.jsonl)
    last_block: float = field(default_factory=time.perf_counter)  # when this rank's previous block was written
    written: int = 0  # samples this rank has written in this run


def _bank_identity(cfg: GenerateConfig, hashes: dict[str, str], config: dict) -> dict:
    """What a re-run must match to add to the bank: mode, checkpoint digests, seed, the sampling options and
    completion mode's real scans; an option left at the value banks had before it existed is left out, so those
    banks stay compatible. `_bank_motions` adds where the ego motions come from."""
    identity = {"mode": cfg.mode, "checkpoints": hashes, "seed": cfg.seed,
                "sampling": {k: config[k] for k in ("sampler", "steps", "stage1_steps")}}  # fmt: skip
    sampling = identity["sampling"]
    if cfg.sampler_grid != "time":
        sampling["sampler_grid"] = cfg.sampler_grid
    if cfg.stage1_mask_fraction is not None:
        sampling["stage1_mask_fraction"] = cfg.stage1_mask_fraction
    if cfg.mode == "complete":
        identity["source"] = {k: config[k] for k in ("data_root", "sequences", "probs_root")}
    if cfg.mean_start_below is not None:
        sampling["mean_start_below"] = cfg.mean_start_below
    if cfg.propagate:
        sampling["propagate"] = True
    if cfg.detail == NEAREST:  # a detail net is among the checkpoints
        identity["detail"] = NEAREST
    if cfg.propagate_pin and cfg.mode == "u4d":  # the baseline's inpainting pins them anyway
        sampling["propagate_pin"] = True
    return identity


def _load_nets(cfg: GenerateConfig, paths: dict[str, Path], device: torch.device) -> tuple[dict[str, Loaded], dict]:
    """The nets by role, each in a `MeanStart` of its training mean image with mean_start_below, and where each
    mean came from ({} without)."""
    nets = {name: load_generator(path, device) for name, path in paths.items()}
    mean_sources = {}
    if cfg.mean_start_below is not None:
        for name, (net, net_cfg) in list(nets.items()):
            mean, mean_sources[name] = training_mean(net_cfg, name, cfg, paths[name], autoencoder_of(net))
            nets[name] = (MeanStart(net, mean.to(device), cfg.mean_start_below), net_cfg)
    return nets, mean_sources


def nearest_stride(layout: DiffusionTrainConfig) -> int:
    """detail=nearest: s, the sensor's own width over the layout nets' (their columns repeated s times); InputError
    unless it is a whole number >= 2."""
    width = get_sensor(layout.sensor).width
    if width % layout.width or width // layout.width < 2:
        raise InputError(
            f"detail=nearest repeats the layout's columns up to the sensor's {width}: the {layout.width}-column nets "
            "must have a whole fraction of it (W / s, s >= 2)"
        )
    return width // layout.width


def _check_cascade(cfg: GenerateConfig, layout: DiffusionTrainConfig, detail: DiffusionTrainConfig) -> None:
    """A detail net completes single scans of its layout nets' sensor, rows and W / s columns; InputError else."""
    if detail.diffusion.stage != "detail":
        raise InputError(f"detail: {cfg.detail} is a {detail.diffusion.stage} net, not a detail net (stage=detail)")
    want = (detail.sensor, detail.height, detail.width // detail.detail_stride, detail.row_mode)
    got = (layout.sensor, layout.height, layout.width, layout.row_mode)
    if got != want:
        raise InputError(
            f"detail: {cfg.detail} completes layouts of sensor {want[0]}, {want[1]}x{want[2]} ({want[3]} rows); the "
            f"{cfg.mode} nets make {got[0]}, {got[1]}x{got[2]} ({got[3]} rows)"
        )
    if (cfg.frames or layout.frames) > 1 or cfg.propagate:
        raise InputError("detail: a cascade generates single scans; frames must be 1 and propagate false")


def _bank_motions(
    cfg: GenerateConfig, posed: list[DiffusionTrainConfig], frames: int, identity: dict
) -> tuple[np.ndarray | None, list[dict]]:
    """(num, L, 4) ego motion of every sample and where each came from, for nets with an ego-motion input in u4d and
    baseline modes (recorded in `identity`); (None, []) otherwise: completion mode conditions on the real frames'."""
    if posed and cfg.mode == "complete":
        if cfg.motion_file:
            raise InputError("motion_file: completion mode conditions on the motion of the real frames it completes")
        return None, []
    if posed:
        motions, sources = sample_motions(cfg, posed[0], frames)
        identity["motion"] = {"file": file_sha256(cfg.motion_file)} if cfg.motion_file else "training sequences"
        return motions, sources
    if cfg.motion_file:
        raise InputError("motion_file: these generators have no ego-motion input (net.pose_dim = 0 or one frame)")
    return None, []


def _check_propagate(cfg: GenerateConfig, motions: np.ndarray | None, frames: int) -> None:
    """Refuse propagate without sequences with an ego motion, and propagate_pin without propagate."""
    if cfg.propagate and (cfg.mode not in ("u4d", "baseline") or motions is None):
        raise InputError(
            "propagate: moves frame 0 along each sequence's ego motion, so it needs mode=u4d or baseline, "
            f"frames >= 2 and nets with an ego-motion input (net.pose_dim > 0); got mode={cfg.mode}, frames={frames}"
        )
    if cfg.propagate_pin and not cfg.propagate:
        raise InputError("propagate_pin: pins stage 2 to the propagated pixels, so it needs propagate=true")


def _open_layout(out: Path, frames: int) -> tuple[BankLayout, dict | None]:
    """The bank's layout and its manifest (None for a new bank); refuses a bank of another frame count."""
    layout = BankLayout(out, frames)
    old = read_manifest(layout.root)
    if old is not None and old.get("frames", 1) != frames:
        raise InputError(
            f"{layout.manifest_path}: bank holds {old.get('frames', 1)}-frame samples, asked for {frames}; "
            "choose another --out or delete the bank"
        )
    return layout, old


def _real_scans(cfg: GenerateConfig, train_cfg: DiffusionTrainConfig, frames: int) -> Scans | Windows:
    """Completion mode: the real scans of data_root (L-frame windows with poses for sequence generators), laid out
    as the generator's training scans were; their beams checked against its sensor."""
    if not cfg.data_root:
        raise InputError("data_root: completion mode needs real scans to take x0_u from")
    real = (train_cfg.data_format, train_cfg.nuscenes_version)  # real scans laid out as the generator's were
    if frames == 1:
        scans = open_scans(cfg.data_root, cfg.sequences, False, *real)
    else:
        try:
            scans = open_sequences(cfg.data_root, frames, cfg.sequences, train_cfg.frame_stride, True, *real)
        except InputError as exc:
            raise InputError(f"completion mode writes the real frames' poses with each sequence: {exc}") from None
    if len(scans) == 0:
        raise InputError(f"{cfg.data_root}: no scans found")
    first = scans[0]
    points = first["points"] if frames == 1 else first["points"][0]
    check_beams(points, get_sensor(train_cfg.sensor), f"{cfg.data_root}: scan of sequence {first['seq']}")
    return scans


def _new_manifest(
    run: _Generation,
    identity: dict,
    config: dict,
    paths: dict[str, Path],
    mean_sources: dict,
    motion_sources: list[dict],
    old: dict | None,
) -> dict:
    """The bank's manifest before any sample is checked or written: identity, config, image and one entry per
    sample; a re-run keeps the larger sample listing and the export record of the old manifest."""
    train_cfg, cfg = run.train_cfg, run.cfg
    manifest = {
        **identity,
        "config": config,
        "checkpoint_paths": {name: str(path) for name, path in paths.items()},
        "sensor": train_cfg.sensor,
        "height": train_cfg.height,
        "width": train_cfg.width,
        "row_mode": train_cfg.row_mode,
        "frames": run.frames,
        **({"mean_start": mean_sources} if mean_sources else {}),
        "samples": [_sample_entry(cfg, i, run.scans, run.frames, motion_sources) for i in range(cfg.num)],
        "complete": False,
    }
    if old is not None and len(old.get("samples", [])) > cfg.num:
        manifest["samples"] = old["samples"]  # a re-run asking for fewer samples keeps the larger listing
    if old is not None and "export" in old:
        manifest["export"] = old["export"]  # what `u4d export` wrote beside the samples stays recorded
    return manifest


def _check_finished_samples(layout: BankLayout, old: dict | None, manifest: dict) -> None:
    """Rank 0, before any rank writes: remove the temp files of killed writes and the samples changed since they
    were written, keep the digests of the others in the manifest, and write it."""
    removed = remove_temp_files(layout.root)
    if removed:
        logger.info("%s: removed %d temp file(s) of a killed run", layout.root, removed)
    verified = verify_samples(layout, old)  # samples changed since they were written are removed
    for entry in manifest["samples"]:
        entry.pop("sha256", None)
        if entry["index"] in verified:
            entry["sha256"] = verified[entry["index"]]
    write_manifest(layout.root, manifest)


def _generate_blocks(run: _Generation, info: DistInfo, progress: bool) -> None:
    """Generate and write this rank's blocks that miss a sample."""
    cfg, layout = run.cfg, run.layout
    # fixed blocks of batch_size consecutive samples, sharded across ranks: a block's scans do not depend on the
    # rank count, and a block with a missing sample is generated again whole (finished samples are not rewritten)
    blocks = [list(range(start, min(start + cfg.batch_size, cfg.num))) for start in range(0, cfg.num, cfg.batch_size)]
    todo = [block for block in shard(blocks, info.rank, info.world_size) if not all(map(layout.is_done, block))]
    bar = progress_bar(total=sum(map(len, todo)), enabled=(progress and info.is_main), desc=f"generate {cfg.mode}")
    sensor = get_sensor(run.train_cfg.sensor)
    for block in todo:
        generators = [torch.Generator().manual_seed(cfg.seed + i) for i in block]  # sample i: seed + i
        if run.motions is not None:
            for i in block:
                if not layout.is_done(i):  # poses first, frames last (a sample is done once all its frames are)
                    write_sequence_poses(layout, i, poses_from_motion(run.motions[i]))
        x0, side = _sample_block(run, block, generators)
        _write_block(run, block, to_points(x0, sensor, run.train_cfg.row_mode), side)
        bar.update(len(block))
    bar.close()


# per sample and frame: stage-1 mask (n, L, H, W), uncertainty (n, L, H, W), x0_u (n, L, 2, H, W), each or None
_Side = tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]


def _sample_block(run: _Generation, block: list[int], generators: list[torch.Generator]) -> tuple[Tensor, _Side]:
    """The scans x0 of a block's samples, (n[·L], 2, H, W), and the side images written beside them."""
    motion = None if run.motions is None else torch.from_numpy(run.motions[block])  # (n, L, 4)
    if run.cfg.mode == "u4d":
        x0, side = _generate_u4d(run, block, generators, motion)
    elif run.cfg.mode == "baseline":
        x0, side = _generate_baseline(run, block, generators, motion)
    else:
        return _complete_block(run, block, generators)
    stride = run.detail_stride
    if stride == 1:
        return x0, side
    # the cascade's second level: the full-width scans, with the layout's side images spread over them
    if "detail" in run.nets:
        x0 = refine(run.nets["detail"], x0, generators, run.cfg.sampling())["x0"]
    else:
        x0 = upsample_nearest(x0, stride)
    return x0, tuple(None if part is None else spread_columns(part, stride) for part in side)


def _block_poses(run: _Generation, block: list[int]) -> np.ndarray:
    """(n, L, 4, 4) poses of the ego motions of a block's samples (propagate)."""
    assert run.motions is not None  # checked with the config
    return np.stack([poses_from_motion(run.motions[i]) for i in block])


def _generate_u4d(
    run: _Generation, block: list[int], generators: list[torch.Generator], motion: Tensor | None
) -> tuple[Tensor, _Side]:
    """U4D mode: stage 1's uncertain region, then stage 2 completes it (with propagate: frame 0 moved along the
    motion first); the scans with stage 1's mask and x0_u."""
    cfg, n = run.cfg, len(block)
    if cfg.propagate:
        result = generate_u4d_propagated(
            run.nets["stage1"],
            run.nets["stage2"],
            n,
            generators,
            _block_poses(run, block),
            cfg.sampling(),
            motion=motion,
            pin_known=cfg.propagate_pin,
        )
    else:
        result = generate_u4d(run.nets["stage1"], run.nets["stage2"], n, generators, cfg.sampling(), run.frames, motion)
    return result["x0"], (_per_sample(result["m_u_pred"], n)[:, :, 0], None, _per_sample(result["x0_u"], n))


def _generate_baseline(
    run: _Generation, block: list[int], generators: list[torch.Generator], motion: Tensor | None
) -> tuple[Tensor, _Side]:
    """Baseline mode: one unconditional stage (with propagate: frames 1..L-1 inpainted around frame 0 moved along
    the motion); the scans, no side images."""
    cfg, n = run.cfg, len(block)
    net = run.nets["baseline"]
    if cfg.propagate:
        poses = _block_poses(run, block)
        result = generate_baseline_propagated(net, n, generators, poses, cfg.sampling(), motion=motion)
    else:
        result = generate_baseline(net, n, generators, cfg.sampling(), run.frames, motion=motion)
    return result["x0"], (None, None, None)


def _complete_block(run: _Generation, block: list[int], generators: list[torch.Generator]) -> tuple[Tensor, _Side]:
    """Completion mode: stage 2 completes the x0_u of real scans (sequences: their frames' poses written first and
    their own motion as the condition); the scans with m_u, the entropy image and x0_u."""
    cfg, n, frames = run.cfg, len(block), run.frames
    parts = [
        _real_sample_condition(run.scans, i, generator, frames, run.train_cfg, cfg)
        for i, generator in zip(block, generators)
    ]
    for i, (_, _, _, poses) in zip(block, parts):
        if poses is not None and not run.layout.is_done(i):  # finished samples of the block stay untouched
            write_sequence_poses(run.layout, i, poses)
    x0_u, m_u, entropy_image = (torch.stack([part[k] for part in parts]) for k in range(3))  # (n, L, ...)
    if frames == 1:
        x0_u, m_u = x0_u[:, 0], m_u[:, 0]  # single scans: (n, C, H, W)
    motion = None
    if run.posed:  # the real frames' own motion, (n, L, 4)
        motion = torch.from_numpy(np.stack([relative_motion(part[3]) for part in parts]))
    result = complete(run.nets["stage2"], x0_u, m_u, generators, cfg.sampling(), motion=motion)
    return result["x0"], (_per_sample(m_u, n)[:, :, 0], entropy_image.numpy(), _per_sample(x0_u, n))


def _write_block(run: _Generation, block: list[int], clouds: list[np.ndarray], side: _Side) -> None:
    """Write the n·L point clouds (samples then frames) of a block's unfinished samples with their side images."""
    for j, i in enumerate(block):
        if run.layout.is_done(i):
            continue
        for frame in range(run.frames):
            images = [None if part is None else part[j, frame] for part in side]
            write_sample(run.layout, i, clouds[j * run.frames + frame], *images, frame=frame)
        record_digests(run.layout, i)  # a sample without this record is generated again on resume
        run.written += 1
    now = time.perf_counter()
    seconds = now - run.last_block  # sampling and writing of the block
    record = {"event": "block", "block": [block[0], block[-1]], "samples_done": run.written, "seconds": seconds}
    append_jsonl(run.layout.root / LOG_NAME, record)  # one line per block (each rank appends its own)
    run.last_block = now


def _finish_manifest(manifest: dict, layout: BankLayout, num: int, frames: int) -> None:
    """Rank 0, once every rank is done: the digests of the new samples, whether all are there, the empty ones."""
    for entry in manifest["samples"]:
        if "sha256" not in entry and layout.is_done(entry["index"]):
            entry["sha256"] = recorded_digests(layout, entry) or sample_digests(layout, entry["index"])
    manifest["complete"] = all(layout.is_done(i) for i in range(num))
    if frames == 1:
        manifest["empty"] = [i for i in range(num) if layout.is_empty(i)]
    else:  # [sample, frame] pairs
        manifest["empty"] = [[i, f] for i in range(num) for f in range(frames) if layout.is_empty(i, f)]
    write_manifest(layout.root, manifest)


def _per_sample(images: torch.Tensor, n: int) -> np.ndarray:
    """Images of n samples, (n, [L,] C, H, W) -> (n, L, C, H, W) numpy."""
    return images.detach().cpu().reshape(n, -1, *images.shape[-3:]).numpy()


def _real_sample_condition(
    scans: Scans | Windows,
    index: int,
    generator: torch.Generator,
    frames: int,
    train_cfg: DiffusionTrainConfig,
    cfg: GenerateConfig,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, np.ndarray | None]:
    """Completion mode: x0_u (L, 2, H, W), m_u (L, 1, H, W), entropy (L, H, W) and poses (or None) of sample index."""
    item = scans[index % len(scans)]
    if frames == 1:
        item = {"points": [item["points"]], "seq": item["seq"], "frames": [item["frame"]], "poses": None}
    conditions = [
        _real_condition(points, item["seq"], frame, train_cfg, cfg.probs_root, generator)
        for points, frame in zip(item["points"], item["frames"])
    ]
    x0_u, m_u, entropy_image = (torch.stack(parts) for parts in zip(*conditions))
    return x0_u, m_u, entropy_image, (item["poses"] if frames > 1 else None)


def training_mean(
    net_cfg: DiffusionTrainConfig,
    name: str,
    cfg: GenerateConfig,
    path: Path,
    autoencoder: RangeAutoencoder | None = None,
) -> tuple[Tensor, dict]:
    """(C, H, 1) per-row mean of a net's training images (`batches.net_row_mean`; `name` is the role) and where it
    came from: read from mean_data_root when set, else the one stored in its weights file `path` (`u4d
    export-weights`), else read from the training scans its config names; an InputError naming the keys to set when
    none of these is there. A latent generator's (its `autoencoder` given) is the mean of its latents, (C_z, h, 1)."""
    if not cfg.mean_data_root and not Path(path).is_dir():
        stored = stored_mean(load_checkpoint(Path(path), "diffusion checkpoint"), net_cfg, name, str(path))
        if stored is not None:
            return stored[0], {**stored[1], "stored_in": str(path)}
    encode = None
    if autoencoder is not None:
        device = next(autoencoder.parameters()).device

        def encode(images: Tensor) -> Tensor:
            return to_latent(autoencoder, images.to(device)).cpu()

    try:
        return net_row_mean(net_cfg, cfg.mean_data_root, cfg.mean_probs_root, name, encode)
    except (InputError, OSError) as exc:
        raise InputError(
            f"mean_start_below: the {name} net's mean image is read from its training scans ({exc}); set "
            "mean_data_root (and mean_probs_root for stage 1) to where they are, export the net with "
            "`u4d export-weights --data-root` to store it, or set mean_start_below=null"
        ) from None


def load_motion_file(path: str | Path, frames: int) -> np.ndarray:
    """(N, L, 4) float32 ego motions from a .npy of (L, 4) or (N, L, 4), or from a KITTI poses.txt of L lines."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: motion_file not found")
    if path.suffix == ".npy":
        try:
            motion = np.load(path, allow_pickle=False)
        except ValueError as exc:
            raise InputError(f"{path}: not a numeric .npy ({exc})") from None
        if not np.issubdtype(motion.dtype, np.number):
            raise InputError(f"{path}: expected numbers, got a {motion.dtype} array")
        if motion.ndim == 2:
            motion = motion[None]
    elif path.suffix == ".txt":
        calib_path = path.parent / "calib.txt"
        poses = read_poses(path, read_calib(calib_path) if calib_path.is_file() else None)  # (T, 4, 4) LiDAR poses
        if len(poses) != frames:
            raise InputError(f"{path}: {len(poses)} poses, expected the {frames} of one sequence")
        motion = relative_motion(poses)[None]
    else:
        raise InputError(f"{path}: motion_file must be a .npy of (L, 4) or (N, L, 4) motions or a poses .txt")
    if motion.ndim != 3 or motion.shape[1:] != (frames, POSE_DIM) or len(motion) == 0:
        raise InputError(
            f"{path}: expected ({frames}, {POSE_DIM}) or (N, {frames}, {POSE_DIM}) motion, got {motion.shape}"
        )
    if not np.isfinite(motion).all():
        raise InputError(f"{path}: motion holds non-finite values")
    return motion.astype(np.float32)


def training_windows(train_cfg: DiffusionTrainConfig, frames: int) -> Windows:
    """L-frame windows (and poses, no scans) of the sequences a pose-conditioned generator was trained on."""
    if not train_cfg.data_root:
        raise InputError("the generator's config names no data_root to draw trajectories from")
    return open_sequences(
        train_cfg.data_root, frames, train_cfg.sequences, train_cfg.frame_stride, True,
        train_cfg.data_format, train_cfg.nuscenes_version,
    )  # fmt: skip


def window_motion(windows: Windows, index: int) -> tuple[np.ndarray, list[str]]:
    """(L, 4) ego motion of window `index` of `windows` and its frames as 'seq/frame' names."""
    seq, start = windows.windows[index]
    positions = list(range(start, start + windows.num_frames * windows.stride, windows.stride))
    assert windows.poses is not None  # built with_poses=True
    return relative_motion(windows.poses[seq][positions]), [f"{seq}/{windows.frames[seq][p]}" for p in positions]


def sample_motions(cfg: GenerateConfig, train_cfg: DiffusionTrainConfig, frames: int) -> tuple[np.ndarray, list[dict]]:
    """(num, L, 4) ego motion of every sample and where it came from; sample i's depends only on seed + i."""
    if cfg.motion_file:
        motions = load_motion_file(cfg.motion_file, frames)
        rows = [i % len(motions) for i in range(cfg.num)]
        return motions[rows].reshape(cfg.num, frames, POSE_DIM), [{"file": cfg.motion_file, "row": r} for r in rows]
    try:
        windows = training_windows(train_cfg, frames)
    except InputError as exc:
        raise InputError(
            f"motion_file: the generator is conditioned on ego motion and no trajectory source was found ({exc}); "
            "set motion_file=PATH (.npy of (L, 4) or (N, L, 4) x, y, z, yaw, or a poses.txt of L lines)"
        ) from None
    motions, sources = [np.zeros((0, frames, POSE_DIM), dtype=np.float32)], []
    for i in range(cfg.num):
        index = int(np.random.default_rng(cfg.seed + i).integers(len(windows)))  # sample i: seed + i
        motion, names = window_motion(windows, index)
        motions.append(motion[None])
        sources.append({"window": names})
    return np.concatenate(motions), sources


def _sample_entry(
    cfg: GenerateConfig,
    index: int,
    scans: Scans | Windows | None,
    frames: int,
    motion_sources: list[dict],
) -> dict:
    entry: dict = {"index": index, "seed": cfg.seed + index}
    if motion_sources:  # the trajectory this sample was generated for (its poses.txt)
        entry["motion"] = motion_sources[index]
    if frames == 1:
        entry["file"] = f"sequences/00/velodyne/{index:06d}.bin"
    else:
        entry["sequence"] = sequence_name(index)
        entry["files"] = [f"sequences/{sequence_name(index)}/velodyne/{f:06d}.bin" for f in range(frames)]
    if isinstance(scans, Scans):
        seq, frame = scans.entries[index % len(scans)]
        entry["source"] = f"{seq}/{frame}"
    elif isinstance(scans, Windows):
        seq, start = scans.windows[index % len(scans)]
        names = scans.frames[seq][start : start + frames * scans.stride : scans.stride]
        entry["source"] = [f"{seq}/{name}" for name in names]
    return entry


def _real_condition(
    points: np.ndarray, seq: str, frame: str, train_cfg: DiffusionTrainConfig, probs_root: str, generator
):
    """x0_u (2, H, W), m_u (1, H, W), entropy image (H, W) of one real scan, as stage 2 was trained."""
    points = torch.from_numpy(points)
    strategy = train_cfg.uncertainty.strategy
    if strategy == "none":
        probs = np.zeros((points.shape[0], 1), dtype=np.float32)
    else:
        root = probs_root or train_cfg.probs_root
        if not root:
            raise InputError("probs_root: completion mode needs the probability files of the real scans")
        probs = load_probs(probs_path(root, seq, frame), points.shape[0])
    sensor = get_sensor(train_cfg.sensor)
    return uncertain_range_view(
        points, probs, sensor, train_cfg.height, train_cfg.width, train_cfg.row_mode,
        train_cfg.uncertainty.k, strategy, generator,
    )  # fmt: skip


def add_generate_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d generate CONFIG --out BANK [--num N] [--mode ...] [--steps S] [--seed S] [key=value ..]`."""
    parser.add_argument("config", type=Path, help="yaml naming the checkpoints, sampler and steps")
    parser.add_argument(
        "overrides",
        nargs="*",
        help="key=value overrides, e.g. stage1=runs/s1 sampler=dpmpp2m (ddpm|ddim|dpmpp2m|dpmpp2m-sde) "
        "sampler_grid=logsnr (time|logsnr) motion_file=trajectory.npy (ego-motion-conditioned sequence nets)",
    )
    parser.add_argument("--out", type=Path, required=True, help="bank folder (SemanticKITTI layout)")
    parser.add_argument("--num", type=int, default=None, help="number of scans (default: the config's num)")
    parser.add_argument("--mode", choices=["u4d", "baseline", "complete"], default=None)
    parser.add_argument("--steps", type=int, default=None, help="sampling steps")
    parser.add_argument("--seed", type=int, default=None, help="base seed: sample i uses seed + i")
    parser.add_argument(
        "--labels",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="all-ignore labels/NNNNNN.label (0 = unlabeled) beside every scan, as `u4d export --layout "
        "semantickitti` (default: on; --no-labels: none)",
    )
    parser.add_argument(
        "--mmdet3d-infos", action="store_true", help="also write mmdetection3d's semantickitti_infos_train.pkl"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run_generate(args: argparse.Namespace) -> int:
    """`u4d generate`: write a bank of generated scans (torchrun shards the samples across ranks)."""
    overrides = list(args.overrides)
    for key in ("num", "mode", "steps", "seed"):
        if getattr(args, key) is not None:
            overrides.append(f"{key}={getattr(args, key)}")
    if args.labels is not None:  # --labels / --no-labels
        overrides.append(f"labels={str(args.labels).lower()}")
    if args.mmdet3d_infos:
        overrides.append("mmdet3d_infos=true")
    cfg = load_config(GenerateConfig, args.config, overrides)
    try:
        generate_bank(cfg, args.out, progress=not args.no_progress)
    finally:
        cleanup()
    return 0
