"""Shipped weights: the float16 format that `u4d export-weights` (u4d_aug/export_weights.py) writes and loaders read.

The file is {kind, format, config, model, hash, weights_hash, trained}: `model` is the state dict inference uses
with every floating tensor in float16 (non-float buffers unchanged), about half the size of the float32 weights,
so that the nets committed under `weights/` fit their 25 MB budget. Inference weights per kind: a diffusion stage
(`u4d train-diffusion`) its EMA weights, as `pipeline.load_generator` samples with; an FRD/FPD extractor
(`u4d train-extractor`) its `state_dict`; a segmentor (`u4d seg-train`) its `model`, which `seg-predict` reads.
`weights_hash` = sha256[:16] of the float16 weights + config, checked on load; `hash` names the net in results:
the same, except for extractors, which keep the hash of their training checkpoint so FRD/FPD stay comparable.
The loaders of the three kinds read either file and cast the weights back to float32 (`exported_model`).
With `--int8` (`quantize_int8`) the large weight tensors are stored as int8 in groups of `INT8_GROUP` values with
one float16 scale per group (absmax, as GGML's Q8_0 blocks), about a quarter of float32; the file then carries
`int8: {name: shape}` and the loaders expand those tensors back before use.
A diffusion stage's file may also carry `row_mean` = {key, mean (C, H, 1) float32, source}: the per-row mean of its
training images (`batches.row_mean`) that `u4d generate mean_start_below=...` starts from, so that the mean start
needs no training scans where the weights are used (`stored_row_mean`); a one-net u4d file carries the x0 mean as
`row_mean` and its stage-1 task's x0_u mean as `row_mean_stage1`.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import torch
from torch import Tensor

from u4d_aug.errors import InputError
from u4d_aug.run import checkpoint_kind as checkpoint_kind_of
from u4d_aug.validate import check_state_fits

WEIGHTS_FORMAT = "u4d-weights-v1"
# The checkpoint kinds, as their writers name them (tests/u4d_aug/test_weights.py checks they agree; u4d_aug does not
# import segmentation): u4d_aug.stage.CHECKPOINT_KIND, u4d_aug.metrics.extractors.EXTRACTOR_KINDS,
# segmentation.train.CHECKPOINT_KIND (seg-train checkpoints older than the run layer carry it as "format").
DIFFUSION_KIND = "u4d-diffusion"
# buffers a loader rebuilds from the config (the ray-angle Fourier features of the sensor: 4.2 MB at 64x1024 in
# float16), so they are not shipped; `load_exported` checks that only these are absent
RECOMPUTED_BUFFERS = ("ray_features.features",)
EXTRACTOR_KINDS = ("frd", "fpd")
SEGMENTATION_KIND = "u4d-seg-checkpoint"
INT8_GROUP = 64  # values per float16 scale: 3 % overhead on top of one byte per weight
INT8_MIN_NUMEL = 4096  # smaller tensors (biases, norms, small convolutions) stay float16
SCALE_SUFFIX = ":scale"


def is_exported(state: dict) -> bool:
    """Whether a loaded file was written by `export_weights` (else it is a training checkpoint)."""
    return state.get("format") == WEIGHTS_FORMAT


def checkpoint_kind(state: dict, source: str) -> str:
    """'u4d-diffusion', 'frd', 'fpd' or 'u4d-seg-checkpoint': the kind of a training checkpoint, also of one written
    before the run layer (`u4d_aug.run.checkpoint_kind`)."""
    kind = checkpoint_kind_of(state)
    if kind == DIFFUSION_KIND:
        return DIFFUSION_KIND
    elif kind in EXTRACTOR_KINDS:
        return kind
    elif kind == SEGMENTATION_KIND:
        return SEGMENTATION_KIND
    raise InputError(
        f"{source}: not a training checkpoint of u4d train-diffusion, train-extractor or seg-train "
        f"(kind {state.get('kind')!r}, format {state.get('format')!r})"
    )


def inference_weights(state: dict, kind: str, source: str) -> dict[str, Tensor]:
    """The state dict inference loads: diffusion EMA shadow under the net's state-dict names, extractor
    `state_dict`, segmentor `model` (as `segmentation.predict.model_from_checkpoint`)."""
    if kind == DIFFUSION_KIND:
        ema, names = state.get("ema"), state.get("model")
        if not isinstance(ema, dict) or not isinstance(names, dict):
            raise InputError(f"{source}: diffusion checkpoint without its 'model' and 'ema' weights")
        shadow = {**ema.get("buffers", {}), **ema.get("params", {})}  # EMA.copy_to, then net.state_dict()
        missing = sorted(set(names) - set(shadow))
        if missing:
            raise InputError(f"{source}: the EMA weights lack {', '.join(missing[:3])}")
        return {name: shadow[name] for name in names}
    elif kind in EXTRACTOR_KINDS:
        weights = state.get("state_dict")
    elif kind == SEGMENTATION_KIND:
        weights = state.get("model")
    else:
        raise ValueError(f"checkpoint kind {kind!r} is not one of {DIFFUSION_KIND}, frd, fpd, {SEGMENTATION_KIND}")
    if not isinstance(weights, dict):
        raise InputError(f"{source}: {kind} checkpoint without its weights")
    return weights


def check_finite_weight(tensor: Tensor, name: str, source: str) -> None:
    """InputError when a floating weight holds NaN or inf (a diverged run): a net of them generates nothing."""
    bad = int((~torch.isfinite(tensor)).sum())
    if bad:
        raise InputError(f"{source}: weight {name} has {bad} non-finite values (NaN/inf) of {tensor.numel()}")


def half_state(model: dict[str, Tensor], source: str) -> dict[str, Tensor]:
    """Floating tensors cast to float16, others copied; a weight beyond float16's range is an error, not an inf."""
    limit = torch.finfo(torch.float16).max
    out = {}
    for name, tensor in model.items():
        if not isinstance(tensor, Tensor):
            raise InputError(f"{source}: weight {name} is a {type(tensor).__name__}, not a tensor")
        tensor = tensor.detach().cpu()
        if tensor.is_floating_point():
            check_finite_weight(tensor, name, source)
            finite = tensor[torch.isfinite(tensor)]
            if finite.numel() and float(finite.abs().max()) > limit:
                raise InputError(f"{source}: weight {name} exceeds the float16 range (|w| > {limit:g})")
            out[name] = tensor.to(torch.float16)
        else:
            out[name] = tensor.clone()
    return out


def float32_state(model: dict[str, Tensor]) -> dict[str, Tensor]:
    """Floating tensors back to float32 (what the nets compute in), others unchanged."""
    return {name: t.float() if t.is_floating_point() else t for name, t in model.items()}


def quantize_int8(model: dict[str, Tensor]) -> tuple[dict[str, Tensor], dict[str, list[int]]]:
    """Float16 tensors of >= INT8_MIN_NUMEL values as int8 groups (n/64, 64) + float16 absmax scales (n/64, 1);
    returns the new state dict and {name: original shape} of the quantized tensors."""
    out: dict[str, Tensor] = {}
    shapes: dict[str, list[int]] = {}
    for name, tensor in model.items():
        if not tensor.is_floating_point() or tensor.numel() < INT8_MIN_NUMEL:
            out[name] = tensor
            continue
        flat = tensor.float().flatten()
        flat = torch.cat([flat, flat.new_zeros(-flat.numel() % INT8_GROUP)]).view(-1, INT8_GROUP)
        scale = (flat.abs().amax(dim=1, keepdim=True) / 127.0).to(torch.float16)
        safe = torch.where(scale > 0, scale.float(), torch.ones_like(scale, dtype=torch.float32))
        out[name] = torch.round(flat / safe).clamp(-127, 127).to(torch.int8)
        out[name + SCALE_SUFFIX] = scale
        shapes[name] = list(tensor.shape)
    return out, shapes


def dequantize_int8(model: dict[str, Tensor], shapes: object, source: str) -> dict[str, Tensor]:
    """Expand the int8 groups of `quantize_int8` back to float16 tensors of their recorded shapes."""
    if not isinstance(shapes, dict):
        raise InputError(f"{source}: field 'int8' must map weight names to shapes, got {type(shapes).__name__}")
    out = {name: t for name, t in model.items() if not name.endswith(SCALE_SUFFIX)}
    for name, shape in shapes.items():
        groups, scale = model.get(name), model.get(name + SCALE_SUFFIX)
        if groups is None or scale is None or groups.dtype != torch.int8:
            raise InputError(f"{source}: int8 weight {name} lacks its int8 groups or its scales")
        count = int(torch.tensor(shape).prod()) if len(shape) else 1
        if groups.dim() != 2 or scale.shape != (groups.shape[0], 1) or groups.numel() < count:
            raise InputError(
                f"{source}: int8 weight {name}: groups {tuple(groups.shape)} and scales {tuple(scale.shape)} "
                f"cannot hold shape {shape}"
            )
        values = groups.float() * scale.float()
        out[name] = values.flatten()[:count].view(shape).to(torch.float16)
    return out


def weights_digest(model: dict[str, Tensor], config: dict) -> str:
    """sha256[:16] of the config (sorted json) and every tensor's name, dtype, shape and bytes, in name order."""
    digest = hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode())
    for name in sorted(model):
        tensor = model[name].detach().cpu().contiguous()
        digest.update(f"{name}|{tensor.dtype}|{tuple(tensor.shape)}".encode())
        digest.update(tensor.numpy().tobytes())
    return digest.hexdigest()[:16]


def exported_model(state: dict, source: str) -> dict[str, Tensor]:
    """The float32 weights of an exported file, after checking them against its `weights_hash`."""
    model, config = state.get("model"), state.get("config")
    if not isinstance(model, dict) or not isinstance(config, dict):
        raise InputError(f"{source}: exported weights without 'model' and 'config'")
    odd = [name for name, value in model.items() if not isinstance(value, Tensor)]
    if odd:
        raise InputError(f"{source}: 'model' entry {odd[0]!r} is a {type(model[odd[0]]).__name__}, not a tensor")
    digest = weights_digest(model, config)
    if digest != state.get("weights_hash"):
        raise InputError(
            f"{source}: stored weights_hash {state.get('weights_hash')} does not match the weights ({digest})"
        )
    if "int8" in state:
        model = dequantize_int8(model, state["int8"], source)
    for name, tensor in model.items():
        if isinstance(tensor, Tensor) and tensor.is_floating_point():
            check_finite_weight(tensor, name, source)
    return float32_state(model)


def load_exported(net: torch.nn.Module, state: dict, source: str) -> None:
    """Load exported weights into `net` (built from the file's config); only `RECOMPUTED_BUFFERS` may be absent."""
    model = exported_model(state, source)
    expected = {name: t for name, t in net.state_dict().items() if name in model or name not in RECOMPUTED_BUFFERS}
    check_state_fits(model, expected, source, "exported weights must fit the net of their own config")
    net.load_state_dict(model, strict=False)


def stored_row_mean(state: dict, source: str, role: str | None = None) -> tuple[Tensor, dict] | None:
    """(mean (C, H, 1) float32, {key, source...}) of an exported diffusion stage's `row_mean` (a one-net u4d file:
    `row_mean_stage1` for its stage-1 `role`), or None without one."""
    name = "row_mean_stage1" if role == "stage1" and "row_mean_stage1" in state else "row_mean"
    if not is_exported(state) or name not in state:
        return None
    entry = state[name]
    mean = entry.get("mean") if isinstance(entry, dict) else None
    if not isinstance(mean, Tensor) or mean.ndim != 3 or mean.shape[-1] != 1 or not mean.is_floating_point():
        raise InputError(f"{source}: row_mean: expected {{key, mean: a (C, H, 1) float tensor, source}}")
    info = {"key": entry.get("key"), **(entry.get("source") or {})}
    return mean.float(), info


# The nets committed under the checkout's weights/ (weights/README.md), by role. A wheel does not carry them: `u4d
# weights install` copies them where `u4d_aug.weights_store` looks.
SHIPPED_DIR = Path(__file__).resolve().parents[1] / "weights"
SHIPPED_GENERATORS = ("u4d", "baseline")  # u4d: one net for both stages (train-diffusion stage=u4d)
SHIPPED_OPTIONAL = ("extractor_frd", "extractor_fpd", "uncertainty_segmentor")
# the 4D sequence nets (configs/u4d/cpu_hdl64_most.yaml: MoST + ego-motion input), optional as well
SHIPPED_SEQUENCE = ("u4d_most_stage1", "u4d_most_stage2", "baseline_most")


def shipped_weights(root: Path | None = None) -> dict[str, Path] | None:
    """{role: file} of the shipped nets under `root` (None: wherever `weights_store.find_weights` finds each), or None
    when either generator is absent."""
    from u4d_aug.weights_store import find_weights

    found: dict[str, Path] = {}
    for name in (*SHIPPED_GENERATORS, *SHIPPED_OPTIONAL, *SHIPPED_SEQUENCE):
        path = root / f"{name}.pt" if root is not None else find_weights(f"{name}.pt")
        if path is not None and path.is_file():
            found[name] = path
    if not all(name in found for name in SHIPPED_GENERATORS):
        return None
    return found
