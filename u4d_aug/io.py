"""Atomic file writes (temp file in the same folder + os.replace) so that nothing already written is lost, with the
umask's file mode and one-line errors where nothing can be written; checkpoints read with torch.load(weights_only=True)
and arrays with np.load(allow_pickle=False), so that a file handed to us cannot run code; json without NaN."""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import pickle
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from u4d_aug.errors import InputError

NPY_MAGIC = b"\x93NUMPY"
TEMP_PREFIX, TEMP_SUFFIX = ".", ".tmp"  # atomic_open's temp files: .NAME.RANDOM.tmp beside the target


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb") -> Iterator[BinaryIO]:
    """Open a temp file beside `path`; on success it replaces `path` in one rename, on error it is removed.

    The file gets the mode the umask gives new files (0644 under umask 022; mkstemp alone makes 0600). A folder
    given as the path, or a folder that cannot be created or written (read-only, missing, disk full), is a
    one-line InputError naming the path.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder; expected a file path to write")
    make_folder(path.parent)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f"{TEMP_PREFIX}{path.name}.", suffix=TEMP_SUFFIX, dir=path.parent)
    except OSError as exc:
        raise InputError(f"{path}: cannot write here ({_reason(exc)})") from None
    try:
        os.fchmod(fd, 0o666 & ~current_umask())
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise InputError(f"{path}: cannot write ({_reason(exc, path.parent)})") from None
        raise


def make_folder(path: str | os.PathLike, what: str = "output folder") -> Path:
    """Create `path` (and its parents) if missing; a file in its place or an unwritable place is an InputError."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{path}: is a file; expected an {what}")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise InputError(f"{path}: a file is in the way of the {what}") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot create the {what} ({_reason(exc)})") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise InputError(f"{path}: the {what} is not writable")
    return path


def check_output_file(path: str | os.PathLike | None, what: str = "output file") -> None:
    """Fail early, in one line, when an output file cannot go to `path`: a folder is there, or a file holds its place
    in the folder path (checked before a long computation; `atomic_open` checks again when it writes)."""
    if path is None:
        return
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder; expected a file path for the {what}")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"{parent}: is a file; expected an output folder")
            break


def current_umask() -> int:
    """The process umask, read without changing it where /proc tells it (os.umask both sets and returns it)."""
    with contextlib.suppress(OSError, ValueError), open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def remove_temp_files(folder: str | os.PathLike, name_start: str = "") -> int:
    """Delete the temp files killed atomic writes left under `folder` (any depth) for files whose names begin
    with `name_start`; returns how many.

    Only for files this process holds the run lock of: another writer's temp file would vanish mid-write.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return 0
    removed = 0
    for path in folder.rglob(f"{TEMP_PREFIX}{name_start}*{TEMP_SUFFIX}"):
        if path.is_file() and path.name.count(".") >= 3:  # .NAME.RANDOM.tmp
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
                removed += 1
    return removed


def _a(what: str) -> str:
    """'a checkpoint', 'an extractor checkpoint'."""
    return f"{'an' if what[:1].lower() in 'aeiou' else 'a'} {what}"


def _reason(exc: OSError, folder: Path | None = None) -> str:
    """The OS's words for an I/O error, e.g. 'Permission denied', 'No space left on device' (also when a short
    write says only how much it wrote and the folder's disk is full)."""
    if exc.strerror:
        return exc.strerror
    if folder is not None and _disk_full(folder):
        return "No space left on device"
    return str(exc) or type(exc).__name__


def _disk_full(folder: Path) -> bool:
    """Whether the file system of `folder` has (almost) no free block left for us."""
    try:
        stats = os.statvfs(folder)
    except OSError:
        return False
    return stats.f_bavail * stats.f_frsize < 64 * 1024


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write bytes atomically."""
    with atomic_open(path, "wb") as f:
        f.write(data)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write text (utf-8) atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_copy(source: str | os.PathLike, target: str | os.PathLike) -> None:
    """Copy a file's bytes to `target` atomically (temp file + rename): `target` is the old file or the whole copy."""
    import shutil

    with open(source, "rb") as src, atomic_open(target, "wb") as dst:
        shutil.copyfileobj(src, dst, 1 << 20)


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write an object as indented json atomically (NaN/inf as null: json has no such numbers)."""
    atomic_write_text(path, dumps_json(obj, indent=2) + "\n")


def dumps_json(obj: Any, **kwargs: Any) -> str:
    """json.dumps with numpy values and paths as plain json and non-finite floats as null (valid json)."""
    return json.dumps(json_safe(obj), allow_nan=False, default=_json_default, **kwargs)


def json_safe(obj: Any) -> Any:
    """`obj` with every NaN/inf float (python, numpy) replaced by None, recursively through dicts and lists."""
    if isinstance(obj, dict):
        return {key: json_safe(value) for key, value in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(value) for value in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def atomic_save_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    """Save one array as .npy atomically."""
    with atomic_open(path, "wb") as f:
        np.save(f, array)


def atomic_torch_save(path: str | os.PathLike, obj: Any) -> None:
    """torch.save atomically (checkpoints)."""
    import torch

    buffer = io.BytesIO()  # torch's zip writer turns a full disk into a RuntimeError; a plain write gives OSError
    torch.save(obj, buffer)
    atomic_write_bytes(path, buffer.getbuffer())


def load_npy(path: str | os.PathLike, what: str) -> np.ndarray:
    """np.load(allow_pickle=False) of one array: a missing, truncated, corrupt or object-dtype file is an InputError."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} not found" + (" (a folder)" if path.is_dir() else ""))
    with open(path, "rb") as f:
        magic = f.read(len(NPY_MAGIC))
    if magic != NPY_MAGIC:
        raise InputError(f"{path}: not a readable {what} (not a .npy file)")
    try:
        array = np.load(path, allow_pickle=False)
    except ValueError as exc:
        if "allow_pickle" in str(exc):
            raise InputError(f"{path}: refused as {_a(what)}: it holds python objects (object dtype)") from None
        raise InputError(f"{path}: not a readable {what} (truncated or corrupt .npy file)") from None
    except (OSError, EOFError):
        raise InputError(f"{path}: not a readable {what} (truncated or corrupt .npy file)") from None
    return array


def file_sha256(path: str | os.PathLike, length: int = 16) -> str:
    """Hex sha256 of a file's bytes, first `length` characters (names checkpoints and bank files)."""
    import hashlib

    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:length]


def load_checkpoint(path: str | os.PathLike, what: str) -> dict:
    """torch.load(weights_only=True) of a dict: tensors and plain python only, nothing in the file runs.

    A missing, empty, truncated or corrupt file, one that is no torch checkpoint, or one that holds other objects
    (a class, a function, numpy scalars) is an InputError naming the file and `what` was expected there.
    """
    import torch

    from u4d_aug.weights_store import missing_hint, resolve_weights

    path = resolve_weights(path)  # `weights/NAME.pt` of a shipped net: wherever `u4d weights install` put it
    if not path.is_file():
        raise InputError(f"{path}: {what} not found{missing_hint(path)}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        found = re.search(r"Unsupported global: GLOBAL (\S+)", str(exc))
        if found is None:
            raise InputError(f"{path}: not a readable {what} (corrupt, truncated or not a torch file)") from None
        raise InputError(
            f"{path}: refused as {_a(what)}: it holds {found.group(1).rstrip('.')}, not only tensors and plain python "
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
    make_folder(path.parent)
    try:
        with open(path, "a", encoding="utf-8") as f:
            f.write(json.dumps(record, default=_json_default) + "\n")
    except OSError as exc:
        raise InputError(f"{path}: cannot write ({_reason(exc)})") from None


def read_json_file(path: str | os.PathLike, expected: str) -> Any:
    """The parsed json of `path`, or an InputError naming the file: not found (with `expected`, what should be
    there and what writes it), unreadable, or not valid json (with the parser's message and line)."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: not found (expected {expected})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    except json.JSONDecodeError as err:
        raise InputError(f"{path}: not valid json ({err.msg}, line {err.lineno})") from None


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
