"""`u4d export-weights CKPT --out FILE`: a training checkpoint's inference weights in the shipped format.

The format itself (float16 weights, hashes, loading) is `u4d_aug.weights`; this module writes it for the three
checkpoint kinds and is the only one that knows their loaders (an extractor's hash is checked by loading it).
"""

from __future__ import annotations

import argparse
import functools
import logging
from collections.abc import Callable
from pathlib import Path

from u4d_aug.batches import net_row_mean
from u4d_aug.errors import InputError
from u4d_aug.io import TEMP_PREFIX, TEMP_SUFFIX, atomic_torch_save, file_sha256, load_checkpoint, make_folder
from u4d_aug.latent import load_latent_autoencoder, to_latent
from u4d_aug.metrics.extractors import load_extractor
from u4d_aug.pipeline import load_generator
from u4d_aug.run import newest_checkpoint
from u4d_aug.stage import config_from_checkpoint
from u4d_aug.weights import (
    DIFFUSION_KIND,
    EXTRACTOR_KINDS,
    RECOMPUTED_BUFFERS,
    WEIGHTS_FORMAT,
    checkpoint_kind,
    half_state,
    inference_weights,
    is_exported,
    quantize_int8,
    weights_digest,
)

logger = logging.getLogger(__name__)


def trained_info(state: dict, kind: str, source: Path) -> dict:
    """Step (extractors: steps), wall-clock minutes when the checkpoint has them, sha256[:16] of the source file."""
    info: dict = {"step": state.get("steps") if kind in EXTRACTOR_KINDS else state.get("step")}
    if state.get("elapsed") is not None:
        info["elapsed_minutes"] = round(float(state["elapsed"]) / 60.0, 3)
    info["source_sha256"] = file_sha256(source)
    return info


def checkpoint_file(path: Path) -> Path:
    """The checkpoint itself, or a run folder's newest checkpoints/step_*.pt."""
    return newest_checkpoint(path) if path.is_dir() else path


def training_row_mean(
    state: dict, source: Path, data_root: str = "", probs_root: str = "", role: str | None = None
) -> dict | None:
    """A diffusion stage's `row_mean` entry (`u4d_aug.weights`): `batches.net_row_mean` of its training checkpoint (a
    latent generator's: of its training latents); None (and a warning) when its training scans cannot be read, as
    then `u4d generate mean_start_below=...` reads them itself."""
    try:
        cfg = config_from_checkpoint(state, str(source))
        encode = None
        if cfg.autoencoder:  # a latent generator's mean start is the mean of its training latents
            autoencoder = load_latent_autoencoder(cfg)
            encode = functools.partial(to_latent, autoencoder)
        mean, found = net_row_mean(cfg, data_root, probs_root, role, encode)
    except (InputError, OSError) as exc:
        logger.warning("%s: no row_mean stored, its training scans cannot be read (%s); see --data-root", source, exc)
        return None
    key = found.pop("key")
    return {"key": key, "mean": mean.float().contiguous(), "source": found}


def export_weights(
    checkpoint_path: str | Path,
    out_path: str | Path,
    int8: bool = False,
    data_root: str = "",
    probs_root: str = "",
    load_segmentor: Callable[[Path], object] | None = None,
) -> dict:
    """Write the float16 (`int8`: large tensors as int8 groups) inference weights of a training checkpoint to
    `out_path` atomically, once they load back (`write_loadable`); returns what it wrote. A run folder stands for its
    newest checkpoint. A diffusion stage also gets the row mean of its training images (`training_row_mean`;
    `data_root` / `probs_root` say where)."""
    source, out = checkpoint_file(Path(checkpoint_path)), Path(out_path)
    state = load_checkpoint(source, "training checkpoint")
    if is_exported(state):
        raise InputError(f"{source}: already exported weights; export from the training checkpoint")
    if out.is_dir():  # before the row mean is read (seconds at 64x1024) and its warning printed
        raise InputError(f"{out}: is a folder; expected a file path to write")
    if out.exists() and out.resolve() == source.resolve():
        raise InputError(f"{out}: --out would overwrite the training checkpoint itself")
    kind = checkpoint_kind(state, str(source))
    config = state.get("config")
    if not isinstance(config, dict):
        raise InputError(f"{source}: {kind} checkpoint without its resolved config")
    model = half_state(inference_weights(state, kind, str(source)), str(source))
    if kind == DIFFUSION_KIND:
        model = {name: tensor for name, tensor in model.items() if name not in RECOMPUTED_BUFFERS}
    shapes = None
    if int8:
        model, shapes = quantize_int8(model)
    digest = weights_digest(model, config)
    identity = digest
    if kind in EXTRACTOR_KINDS:
        identity = load_extractor(source).hash  # the stored hash, checked against the float32 weights
    exported = {
        "kind": kind,
        "format": WEIGHTS_FORMAT,
        "config": config,
        "model": model,
        "hash": identity,
        "weights_hash": digest,
        "trained": trained_info(state, kind, source),
    }
    if shapes is not None:
        exported["int8"] = shapes
    check_loads_back(out, exported, kind, source, load_segmentor)  # before the row mean, which reads the scans
    if kind == DIFFUSION_KIND:
        mean = training_row_mean(state, source, data_root, probs_root)
        if mean is not None:
            exported["row_mean"] = mean
        if config.get("diffusion", {}).get("stage") == "u4d":  # one net for both stages: stage 1's x0_u mean too
            mean = training_row_mean(state, source, data_root, probs_root, role="stage1")
            if mean is not None:
                exported["row_mean_stage1"] = mean
    atomic_torch_save(out, exported)
    return exported


def _mean_name(entry: dict) -> str:
    """'x0', or 'x0 latents' for a latent generator's stored mean."""
    return entry["key"] + (" latents" if entry.get("source", {}).get("latent") else "")


def check_loads_back(
    out: Path, exported: dict, kind: str, source: Path, load_segmentor: Callable[[Path], object] | None
) -> None:
    """InputError unless the kind's loader reads `exported` back from a temp file beside `out` (`generate`,
    `evaluate` and `seg-predict` load it the same way), so that no file is written that they could not load.
    Segmentation weights are read by `load_segmentor` (u4d_aug does not import segmentation)."""
    temp = out.parent / f"{TEMP_PREFIX}{out.name}.check{TEMP_SUFFIX}"
    make_folder(out.parent)
    atomic_torch_save(temp, exported)
    try:
        if kind == DIFFUSION_KIND:
            load_generator(temp)
        elif kind in EXTRACTOR_KINDS:
            load_extractor(temp)
        elif load_segmentor is not None:
            load_segmentor(temp)
    except InputError as exc:
        reason = str(exc).replace(str(temp), "the exported file")
        raise InputError(f"{source}: its exported weights would not load back ({reason}); nothing written") from None
    finally:
        temp.unlink(missing_ok=True)


def add_export_weights_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d export-weights CKPT --out FILE`."""
    parser.add_argument(
        "checkpoint",
        type=Path,
        help="training checkpoint of train-diffusion, train-extractor or seg-train, or a run folder "
        "(its newest checkpoints/step_*.pt)",
    )
    parser.add_argument("--out", type=Path, required=True, help="the float16 weights file to write (e.g. weights/*.pt)")
    parser.add_argument(
        "--int8",
        action="store_true",
        help="store tensors of >= 4096 values as int8 with a float16 scale per 64 (half the float16 size)",
    )
    parser.add_argument(
        "--data-root", default="",
        help="diffusion stages: their training scans, if not where the checkpoint's config says (for the row mean)",
    )  # fmt: skip
    parser.add_argument("--probs-root", default="", help="stage 1: their seg-predict probabilities, likewise")


def run_export_weights(args: argparse.Namespace, load_segmentor: Callable[[Path], object] | None = None) -> int:
    """`u4d export-weights`: float16 inference weights + config + hash of a training checkpoint (segmentation weights
    are checked with `load_segmentor`, which the CLI passes)."""
    exported = export_weights(
        args.checkpoint, args.out, args.int8, args.data_root, args.probs_root, load_segmentor=load_segmentor
    )
    size, before = args.out.stat().st_size, checkpoint_file(args.checkpoint).stat().st_size
    print(
        f"{exported['kind']} weights: {args.out} ({size / 1e6:.2f} MB; checkpoint {before / 1e6:.2f} MB), "
        f"hash {exported['hash']}, step {exported['trained']['step']}"
        + (f", row mean of {_mean_name(exported['row_mean'])}" if "row_mean" in exported else "")
    )
    return 0
