"""Atomic file writes (temp file in the same folder + os.replace) so that nothing already written is lost;
checkpoints read with torch.load(weights_only=True), so that a file handed to us cannot run code (issue 44)."""

from __future__ import annotations

import contextlib
import json
import os
import pickle
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from u4d_aug.errors import InputError


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb") -> Iterator[BinaryIO]:
    """Open a temp file beside `path`; on success it replaces `path` in one rename, on error it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write bytes atomically."""
    with atomic_open(path, "wb") as f:
        f.write(data)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write text (utf-8) atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write an object as indented json atomically."""
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")


def atomic_save_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    """Save one array as .npy atomically."""
    with atomic_open(path, "wb") as f:
        np.save(f, array)


def atomic_torch_save(path: str | os.PathLike, obj: Any) -> None:
    """torch.save atomically (checkpoints)."""
    import torch

    with atomic_open(path, "wb") as f:
        torch.save(obj, f)


def load_checkpoint(path: str | os.PathLike, what: str) -> dict:
    """torch.load(weights_only=True) of a dict: tensors and plain python only, nothing in the file runs (issue 44).

    A missing, empty, truncated or corrupt file, one that is no torch checkpoint, or one that holds other objects
    (a class, a function, numpy scalars) is an InputError naming the file and `what` was expected there.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} not found")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        found = re.search(r"Unsupported global: GLOBAL (\S+)", str(exc))
        if found is None:
            raise InputError(f"{path}: not a readable {what} (corrupt, truncated or not a torch file)") from None
        raise InputError(
            f"{path}: refused as a {what}: it holds {found.group(1).rstrip('.')}, not only tensors and plain python "
            "(weights-only loading, nothing was run)"
        ) from None
    except Exception as exc:  # torch raises many types for non-checkpoints: RuntimeError (zip), EOFError, KeyError
        raise InputError(
            f"{path}: not a readable {what} (corrupt, truncated or not a torch file: {type(exc).__name__})"
        ) from None
    if not isinstance(state, dict):
        raise InputError(f"{path}: not a {what} (expected a dict, found {type(state).__name__})")
    return state


def append_jsonl(path: str | os.PathLike, record: dict) -> None:
    """Append one json line (logs); a torn last line from a killed run is tolerated by `read_jsonl`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(record, default=_json_default) + "\n")


def read_jsonl(path: str | os.PathLike) -> list[dict]:
    """Read a jsonl log, skipping a torn final line."""
    records = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            with contextlib.suppress(json.JSONDecodeError):
                records.append(json.loads(line))
    return records


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
