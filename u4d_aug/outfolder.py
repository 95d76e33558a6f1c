"""Which `--out` a command may write into: a missing or empty folder, or one holding its own record of the same kind.

A folder with anything else in it (a dataset root, another command's output, a bank of another kind) is refused
with one line naming what is there, before a file is written: `u4d simulate` into a SemanticKITTI root would
rewrite its poses and add frames to its sequences, `u4d generate` into one would record the real scans as its
samples. The run lock (`LOCK_NAME`) and the temp files of killed atomic writes (`io.TEMP_PREFIX`) do not
count as content. The record is the folder's `manifest.json`; `owns(manifest)` says whether it is this command's.
A run that fails before writing anything but its scaffolding (lock, config) leaves no folder it created behind
(`removed_if_failed`, which `runlock.run_lock` applies).
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Callable, Collection, Iterator
from pathlib import Path
from typing import Any

from u4d_aug.errors import InputError
from u4d_aug.io import TEMP_PREFIX, TEMP_SUFFIX

LOCK_NAME = ".lock"  # the run lock's file in an output folder (`runlock` takes it from here)

MANIFEST = "manifest.json"


def folder_content(out: Path) -> list[str]:
    """Names in `out` other than the run lock and temp files, sorted (empty for a missing folder)."""
    if not out.is_dir():
        return []
    names = (p.name for p in out.iterdir())
    return sorted(n for n in names if n != LOCK_NAME and not (n.startswith(TEMP_PREFIX) and n.endswith(TEMP_SUFFIX)))


def check_output_folder(out: str | Path, what: str, owns: Callable[[dict[str, Any]], bool]) -> None:
    """InputError unless `out` is missing, empty, or has a manifest.json that `owns` accepts (this command's own
    output, which it may resume); `what` names the command's output in the message ('a simulated world')."""
    out = Path(out)
    content = folder_content(out)
    if not content:
        return
    manifest = out / MANIFEST
    if manifest.is_file():
        try:
            record = json.loads(manifest.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            record = None
        if isinstance(record, dict) and owns(record):
            return
        raise InputError(
            f"{manifest}: not the manifest of {what}; this folder holds another kind of output. Choose an empty "
            "--out (nothing in a folder that this command did not write is overwritten)"
        )
    shown = ", ".join(content[:4]) + (", ..." if len(content) > 4 else "")
    kind = " (a dataset root?)" if "sequences" in content else ""
    raise InputError(
        f"{out}: holds {shown}{kind} and no manifest.json of {what}; choose an empty --out (nothing in a folder "
        "that this command did not write is overwritten)"
    )


def missing_folders(out: str | Path) -> list[Path]:
    """`out` and those of its parents that do not exist yet, innermost first: the folders a run in `out` creates."""
    out = Path(out)
    missing = []
    for folder in (out, *out.parents):
        if folder.exists() or folder.is_symlink():
            break
        missing.append(folder)
    return missing


def remove_created(created: list[Path], scaffolding: Collection[str] = ()) -> None:
    """Remove the folders `created` by a failed run (`missing_folders` before it), innermost first, while the first
    holds only `scaffolding` files (its config) and the others nothing: anything else, a run lock too, is kept."""
    if not created or not created[0].is_dir():
        return
    names = [p.name for p in created[0].iterdir()]
    if not all(name in scaffolding and (created[0] / name).is_file() for name in names):
        return
    for name in names:
        (created[0] / name).unlink(missing_ok=True)
    for folder in created:
        try:
            folder.rmdir()
        except OSError:  # another run's files appeared in it, or it is gone: keep the rest
            return


@contextlib.contextmanager
def removed_if_failed(out: str | Path, scaffolding: Collection[str] = ()) -> Iterator[None]:
    """Run the body; if it raises, remove the folders of `out` it created while they hold nothing but `scaffolding`
    files (`remove_created`): a run that fails at once leaves no empty output folder; one existing before is kept."""
    created = missing_folders(out)
    try:
        yield
    except BaseException:
        with contextlib.suppress(OSError):  # the run's own error is the one to report
            remove_created(created, scaffolding)
        raise
