"""`u4d bank-real ROOT --sequences A-B --out BANK`: a bank of real scans, the ceiling arm of the downstream study.

The scans of places that no split and no generator uses, written as a generator writes its own (`bank.BankLayout`:
scan i of sequence 00, manifest with per-sample digests), so `u4d experiment` reads them exactly as a generated
bank. By default each scan goes through the generators' range image: projected (`range_view.project`), encoded
(`to_image`) and unprojected at the bin-centre rays (`pipeline.to_points`), as `u4d generate` turns its images into
points; `--raw` copies the scans as they are, to size what the projection costs (`mt+real-raw`).

manifest.json: {"mode": "real", "source": {"root", "sequences"}, "projection": {sensor, height, width, row_mode}
or null (raw), "samples": [{"index", "source", "sha256": {file: digest}}], "complete", "placeholder_poses": true,
"export"}. A re-run resumes; a changed sample is written again; a bank of other sources or another projection is
refused. Like a generated bank it gets all-ignore labels (`--no-labels`: none), identity calib/poses and times.txt
(`bank.write_bank_sequence_files`), config.yaml (this run's settings) and log.jsonl (a record per 64 scans).

The split check (`check_disjoint`): the bank's places must be in no split of the experiment that reads it (its
labelled/unlabelled training and held-out sequences) and in no generator's training; `u4d bank-real --generator`
checks the generators when the bank is written, `u4d experiment` the splits before any run starts.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from u4d_aug.bank import (
    BankLayout,
    read_manifest,
    sample_digests,
    verify_samples,
    write_bank_sequence_files,
    write_manifest,
    write_sample,
)
from u4d_aug.data.datasets import expand_sequences, list_frames, resolve_sequences
from u4d_aug.data.formats import read_kitti_scan
from u4d_aug.data.sensors import get_sensor
from u4d_aug.errors import InputError
from u4d_aug.io import append_jsonl, atomic_write_text, load_checkpoint, make_folder
from u4d_aug.outfolder import check_output_folder
from u4d_aug.progress import progress_bar
from u4d_aug.runlock import run_lock

logger = logging.getLogger(__name__)

MODE = "real"


def projected_points(points: np.ndarray, geometry: dict) -> np.ndarray:
    """(N, 4) points -> (M, 4) points of their range image at `geometry` (one return per occupied pixel, at its
    bin-centre ray, depth and intensity through the [-1, 1] encoding): what a generator at that geometry can output."""
    from u4d_aug.pipeline import to_points
    from u4d_aug.range_view import project, to_image

    sensor = get_sensor(geometry["sensor"])
    projection = project(points, sensor, geometry["height"], geometry["width"], geometry["row_mode"])
    image = to_image(projection, sensor)[None]  # (1, 2, H, W)
    return to_points(image, sensor, geometry["row_mode"])[0]


def source_scans(root: Path, sequences: list[str]) -> list[tuple[str, str]]:
    """(sequence, frame) of every scan of `sequences` under root, in sequence then frame order."""
    return [(seq, frame) for seq in sequences for frame in list_frames(root, seq)]


def split_overlap(places: list[str], splits: dict[str, list[str]]) -> dict[str, list[str]]:
    """{split name: the places of `places` it also holds} for every split that shares one."""
    chosen = set(places)
    shared = {name: sorted(chosen & set(expand_sequences(seqs))) for name, seqs in splits.items()}
    return {name: names for name, names in shared.items() if names}


def check_disjoint(bank: str | Path, places: list[str], splits: dict[str, list[str]]) -> None:
    """InputError naming the split and the shared places when a real bank's places are in one of `splits`."""
    shared = split_overlap(places, splits)
    if shared:
        name, names = next(iter(shared.items()))
        more = f" (and {', '.join(list(shared)[1:])})" if len(shared) > 1 else ""
        shown = ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")
        raise InputError(
            f"{bank}: its real scans come from places also in {name}{more}: {shown} ({len(names)} places); "
            "a ceiling bank must hold places no split and no generator uses"
        )


def generator_splits(runs: list[Path]) -> dict[str, tuple[Path, list[str]]]:
    """{f"generator {run}": (its data root, its training sequences)} from each diffusion checkpoint's config."""
    from u4d_aug.run import newest_checkpoint

    found = {}
    for run in runs:
        path = newest_checkpoint(run) if run.is_dir() else run
        cfg = load_checkpoint(path, "diffusion checkpoint").get("config", {})
        if not isinstance(cfg, dict) or "data_root" not in cfg or "sequences" not in cfg:
            raise InputError(f"{path}: no data_root/sequences in its config (expected a `u4d train-diffusion` run)")
        found[f"generator {run}"] = (Path(cfg["data_root"]), list(cfg["sequences"]))
    return found


def check_real_bank(bank: str | Path, root: Path, splits: dict[str, Any]) -> None:
    """If `bank` is a real bank drawn from `root`, its places must be in none of `splits` (of that root: lists,
    'A-B' ranges or split names, as `resolve_sequences` reads them)."""
    manifest = read_manifest(bank)
    if manifest is None or manifest.get("mode") != MODE:
        return
    source = manifest.get("source", {})
    if Path(str(source.get("root", ""))).resolve() != Path(root).resolve():
        return  # another dataset: its places are other places
    resolved = {name: resolve_sequences(root, seqs) for name, seqs in splits.items()}
    check_disjoint(bank, list(source.get("sequences", [])), resolved)


def write_real_bank(
    root: Path,
    sequences: list[str],
    out: Path,
    geometry: dict | None,
    generators: list[Path] | None = None,
    max_scans: int | None = None,
    progress: bool = True,
    labels: bool = True,
) -> dict[str, Any]:
    """Write the bank (resuming) and return its manifest; geometry None copies the scans unprojected; labels: the
    all-ignore labels of `u4d export --layout semantickitti` (a bank is a training set, read as unlabeled)."""
    from u4d_aug.export_bank import export_bank
    from u4d_aug.run import CONFIG_NAME, LOG_NAME

    places = resolve_sequences(root, sequences)
    for name, (gen_root, gen_sequences) in generator_splits(generators or []).items():
        if gen_root.resolve() == root.resolve():
            check_disjoint(out, places, {name: gen_sequences})
    scans = source_scans(root, places)[:max_scans]
    if not scans:
        raise InputError(f"{root}: sequences {', '.join(places)} hold no scans")
    if geometry is not None:
        get_sensor(geometry["sensor"])  # a bad sensor name fails before anything is written
    identity = {"mode": MODE, "source": {"root": str(root.resolve()), "sequences": places}, "projection": geometry}
    check_output_folder(out, "a bank of real scans", lambda record: record.get("mode") == MODE)
    out = make_folder(out)
    with run_lock(out):
        old = read_manifest(out)
        if old is not None and any(old.get(key) != value for key, value in identity.items()):
            raise InputError(f"{out}/manifest.json: a bank of other scans or another projection; choose another --out")
        layout = BankLayout(out)
        verified = verify_samples(layout, old)
        manifest: dict[str, Any] = {**identity, "samples": [], "complete": False}
        if old is not None and "export" in old:
            manifest["export"] = old["export"]  # what `u4d export` wrote beside the samples stays recorded
        write_manifest(out, manifest)
        settings = {
            "root": str(root),
            "sequences": list(sequences),
            "out": str(out),
            "geometry": geometry,
            "generators": [str(g) for g in generators or []],
            "max_scans": max_scans,
            "labels": labels,
        }
        atomic_write_text(out / CONFIG_NAME, yaml.safe_dump(settings, sort_keys=False))  # this run's settings
        started = time.perf_counter()
        append_jsonl(out / LOG_NAME, {"event": "start", "scans": len(scans), "samples_done": len(verified)})
        for index, (seq, frame) in enumerate(progress_bar(scans, desc="bank-real", unit="scan", enabled=progress)):
            source = f"sequences/{seq}/velodyne/{frame}.bin"
            if index not in verified:
                points = read_kitti_scan(root / source)
                points = points[np.isfinite(points).all(axis=1)]
                write_sample(layout, index, points if geometry is None else projected_points(points, geometry))
            digests = verified.get(index) or sample_digests(layout, index)
            manifest["samples"].append({"index": index, "source": source, "sha256": digests})
            if index % 64 == 63:
                write_manifest(out, manifest)  # a cut run keeps the record of what it wrote
                record = {"event": "block", "samples_done": index + 1, "seconds": time.perf_counter() - started}
                append_jsonl(out / LOG_NAME, record)
        write_bank_sequence_files(layout, len(scans), own_poses=False)  # identity placeholders: scans of many places
        manifest["complete"], manifest["placeholder_poses"] = True, True
        write_manifest(out, manifest)
        if labels:
            manifest = {**manifest, "export": export_bank(out, "semantickitti")}
        record = {"event": "finish", "samples_done": len(scans), "seconds": time.perf_counter() - started}
        append_jsonl(out / LOG_NAME, record)
    return manifest


def parse_geometry(args: argparse.Namespace) -> dict | None:
    """--raw -> None; else {sensor, height, width, row_mode} from --like (a generator run) or the flags."""
    if args.raw:
        return None
    if args.like is not None:
        from u4d_aug.run import newest_checkpoint

        path = newest_checkpoint(args.like) if args.like.is_dir() else args.like
        cfg = load_checkpoint(path, "diffusion checkpoint").get("config", {})
        try:
            return {key: cfg[key] for key in ("sensor", "height", "width", "row_mode")}
        except (KeyError, TypeError):
            raise InputError(f"{path}: its config has no sensor/height/width/row_mode") from None
    if args.height < 1 or args.width < 1:
        raise InputError(f"--height {args.height} --width {args.width}: expected positive sizes")
    return {"sensor": args.sensor, "height": args.height, "width": args.width, "row_mode": args.row_mode}


def add_bank_real_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d bank-real ROOT --sequences ... --out BANK`."""
    parser.add_argument("root", type=Path, help="a SemanticKITTI-layout root (sequences/XX/velodyne)")
    parser.add_argument("--sequences", nargs="+", required=True, help="the places of the bank, e.g. 100-163")
    parser.add_argument("--out", type=Path, required=True, help="the bank folder")
    parser.add_argument("--raw", action="store_true", help="copy the scans unprojected (the projection's cost)")
    parser.add_argument("--like", type=Path, default=None, help="a generator run or checkpoint: its range image")
    parser.add_argument("--sensor", default="hdl64", help="without --like: hdl64 | hdl32 | sensor yaml")
    parser.add_argument("--height", type=int, default=64, help="without --like: range-image rows")
    parser.add_argument("--width", type=int, default=1024, help="without --like: range-image columns")
    parser.add_argument("--row-mode", choices=["beam", "linear"], default="beam", help="without --like: row order")
    parser.add_argument(
        "--generator",
        type=Path,
        action="append",
        default=[],
        help="a generator run whose training places the bank must not share (repeatable)",
    )
    parser.add_argument("--max-scans", type=int, default=None, help="only the first scans (in place order)")
    parser.add_argument(
        "--no-labels", action="store_true", help="no all-ignore labels/NNNNNN.label (0 = unlabeled) beside the scans"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run_bank_real(args: argparse.Namespace) -> int:
    """`u4d bank-real`: write the bank, print where and how many scans."""
    if args.max_scans is not None and args.max_scans < 1:
        raise InputError(f"--max-scans {args.max_scans}: expected a positive count")
    geometry = parse_geometry(args)
    manifest = write_real_bank(
        args.root, args.sequences, args.out, geometry, args.generator, args.max_scans, not args.no_progress,
        not args.no_labels,
    )  # fmt: skip
    places = manifest["source"]["sequences"]
    how = "unprojected" if geometry is None else f"through the {geometry['height']}x{geometry['width']} range image"
    print(
        f"{len(manifest['samples'])} real scans of {len(places)} places ({places[0]}-{places[-1]}) {how} -> {args.out}"
    )
    return 0
