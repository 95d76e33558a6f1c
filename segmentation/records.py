"""Run records: one finished experiment run as a small json file that outlives its run folder.

A run folder (checkpoints, model.pt) stays on the machine that trained it; its record (the run's config, the
figures the tables report: mIoU, ECEs, per-class and per-band IoU, reliability bins, wall-clock; its learning curves,
the banks it read and the host) is kept where the experiment's `records_dir` says (a folder in the repository), so
that a table over seeds can be built from runs trained on different machines. A record stands for a finished run only
while its config equals the run's config of today (bookkeeping keys aside); otherwise it is ignored, with a warning.
"""

from __future__ import annotations

import hashlib
import json
import logging
from datetime import datetime, timezone
from pathlib import Path

from segmentation.config import SegTrainConfig
from u4d_aug.bank import read_manifest
from u4d_aug.config import config_to_dict
from u4d_aug.errors import InputError
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json, dumps_json, load_checkpoint, read_json_file, read_jsonl
from u4d_aug.weights import weights_digest

logger = logging.getLogger(__name__)

FORMAT = 1
# keys that change where and how often a run writes, never what it learns
BOOKKEEPING = ("out_dir", "checkpoint_every", "keep_checkpoints", "num_workers", "threads")
# keys added to the config after records were written, with the value that means what the runs did before: a recipe
# leaves them out at that value, so the records written before the key existed still stand for their runs
ADDED_KEYS = {("data", "unlabeled_sequences"): None}
CURVE_KEYS = ("loss", "val_miou")
PROVENANCE = ("host", "burn_in_weights", "banks")  # record keys a table shows beside the figures


def record_path(records_dir: Path, arm: str, backbone: str, seed: int) -> Path:
    """records_dir/ARM/BACKBONE/seedS.json (arm names are plain names: `ArmConfig` checks them)."""
    return Path(records_dir) / arm / backbone / f"seed{seed}.json"


def recipe(run: SegTrainConfig) -> dict:
    """What fixes a run's result: its config as plain json without the bookkeeping keys."""
    data = json_roundtrip(config_to_dict(run))
    for key in BOOKKEEPING:
        data.pop(key, None)
    for (section, key), before in ADDED_KEYS.items():
        if data.get(section, {}).get(key, before) == before:
            data.get(section, {}).pop(key, None)
    return data


def json_roundtrip(obj: object) -> object:
    """`obj` as json would give it back (paths as strings, tuples as lists), for comparing with a stored record."""
    return json.loads(dumps_json(obj))


def log_curves(log: Path) -> dict[str, list[list[float]]]:
    """(step, value) pairs of the training loss and the periodic held-out mIoU from a run's log.jsonl."""
    records = read_jsonl(log) if log.is_file() else []
    return {key: [[float(r["step"]), float(r[key])] for r in records if r.get(key) is not None] for key in CURVE_KEYS}


def bank_provenance(root: Path) -> dict:
    """What a bank held when a run read it: its generator (mode, checkpoint hashes, sampling), scan count and a digest
    of its scans' sha256 (banks are written again on each machine; equal digests = the same scans)."""
    manifest = read_manifest(root) or {}
    samples = manifest.get("samples", [])
    digests = "".join(str(entry.get("sha256", "")) for entry in samples)
    return {
        "path": str(root),
        "complete": bool(manifest.get("complete")),
        "scans": len(samples),
        "mode": manifest.get("mode"),
        "checkpoints": manifest.get("checkpoints"),
        "sampling": manifest.get("sampling"),
        "content_sha256": hashlib.sha256(digests.encode()).hexdigest()[:16] if digests else None,
    }


def burn_in_digest(checkpoint: Path) -> str:
    """`u4d_aug.weights.weights_digest` of a checkpoint's model tensors: equal digests = the same weights bit for bit
    (the burn-in a mean-teacher arm shares with sup-only, on one machine or two)."""
    return weights_digest(load_checkpoint(checkpoint, "checkpoint")["model"], {})


def write_record(path: Path, run: SegTrainConfig, metrics: dict, curves: dict, burn_in: str | None = None) -> None:
    """Save one finished run's record atomically (the figures `run_metrics` gives, bins included; burn_in: the
    weights digest of its step-semi.burn_in_steps state, when known)."""
    record = {
        "format": FORMAT,
        "seed": run.seed,
        "recipe": recipe(run),
        "metrics": metrics,
        "curves": curves,
        "burn_in_weights": burn_in,
        "banks": [bank_provenance(Path(bank.path)) for bank in run.semi.banks] if run.mode == "semi" else [],
        "host": host_info(),
        "trained_in": str(run.out_dir),
        "written": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    atomic_write_json(path, record)


def read_record(path: Path, run: SegTrainConfig) -> dict | None:
    """The record at `path` when it stands for `run` (same recipe), None when there is none or it is stale.

    A file that is not a record raises an InputError naming it; a record of another recipe is ignored with a
    warning naming the first key that differs (the run then trains again).
    """
    if not path.is_file():
        return None
    record = read_json_file(path, "a run record")
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise InputError(f"{path}: expected a run record (an object with format {FORMAT}), got something else")
    for key in ("recipe", "metrics", "curves"):
        if not isinstance(record.get(key), dict):
            raise InputError(f"{path}: field {key!r} must be an object")
    if not isinstance(record["metrics"].get("miou"), (int, float)):
        raise InputError(f"{path}: field 'metrics.miou' must be a number")
    differs = first_difference(record["recipe"], recipe(run))
    if differs is not None:
        logger.warning("%s: ignored, recorded for another recipe (%s)", path, differs)
        return None
    return record


def first_difference(old: object, new: object, where: str = "") -> str | None:
    """The first key path at which two json values differ, with both values; None when equal."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in sorted(set(old) | set(new)):
            if key not in old or key not in new:
                return f"{where}{key}: only in the {'record' if key in old else 'run'}"
            found = first_difference(old[key], new[key], f"{where}{key}.")
            if found is not None:
                return found
        return None
    return None if old == new else f"{where.rstrip('.')}: record {old!r}, run {new!r}"
