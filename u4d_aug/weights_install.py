"""`u4d weights [list | install SOURCE]`: where each shipped net is found, and a checked copy of them from a checkout.

The install copies every file of the shipped table (`weights_store.shipped_table`) that SOURCE (a checkout's
`weights/` or a folder of the .pt files) holds into `weights_store.install_dir()`, after checking its sha256: a file
of another version is refused and nothing is written; each copy is atomic (temp file + rename), under the folder's
run lock.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from u4d_aug.errors import InputError
from u4d_aug.io import atomic_copy, file_sha256
from u4d_aug.runlock import run_lock
from u4d_aug.weights_store import PREFIX, find_weights, install_dir, search_dirs, shipped_table


@dataclass(frozen=True)
class Status:
    """One shipped file on this machine: where it was found (None: nowhere) and whether its sha256 is the table's."""

    name: str
    path: Path | None
    verified: bool


def check_installed() -> list[Status]:
    """Every shipped file: where it is found and whether its bytes are the shipped ones."""
    rows = []
    for name, entry in sorted(shipped_table().items()):
        path = find_weights(name)
        rows.append(Status(name, path, path is not None and file_sha256(path, 64) == entry["sha256"]))
    return rows


def source_folder(source: Path) -> Path:
    """The folder holding the .pt files: SOURCE/weights of a checkout, else SOURCE itself."""
    if not source.is_dir():
        raise InputError(f"{source}: not a folder (expected a u4d-aug checkout or a folder of the shipped .pt files)")
    if (source / PREFIX).is_dir() and any((source / PREFIX).glob("*.pt")):
        return source / PREFIX
    if any(source.glob("*.pt")):
        return source
    raise InputError(f"{source}: no .pt files here or in {source / PREFIX} (expected a u4d-aug checkout)")


def install_weights(source: Path, target: Path) -> list[tuple[str, str]]:
    """Copy every shipped file of `source` into `target` after checking its sha256; [(name, what happened)].

    A file whose bytes differ from the shipped table is refused (nothing of it is written); files already in
    `target` with the right bytes are kept; each copy is atomic (temp file + rename).
    """
    table = shipped_table()
    folder = source_folder(Path(source))
    checked: list[tuple[str, Path]] = []
    for name, entry in sorted(table.items()):
        path = folder / name
        if not path.is_file():
            continue
        digest = file_sha256(path, 64)
        if digest != entry["sha256"]:
            raise InputError(
                f"{path}: sha256 {digest[:16]} is not the shipped {name} ({entry['sha256'][:16]}); a checkout of "
                "another version? nothing was installed"
            )
        checked.append((name, path))
    if not checked:
        raise InputError(f"{folder}: none of the shipped files ({', '.join(sorted(table))})")
    target.mkdir(parents=True, exist_ok=True)
    done = []
    with run_lock(target):
        for name, path in checked:
            destination = target / name
            if destination.is_file() and file_sha256(destination, 64) == table[name]["sha256"]:
                done.append((name, "already installed"))
                continue
            atomic_copy(path, destination)
            done.append((name, "installed"))
    missing = sorted(set(table) - {name for name, _ in checked})
    done += [(name, f"not in {folder}") for name in missing]
    return done


def add_weights_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d weights [list | install SOURCE]`."""
    parser.add_argument(
        "action", nargs="?", choices=["list", "install"], default="list", help="list (default): where each net is"
    )
    parser.add_argument("source", nargs="?", type=Path, help="install: a u4d-aug checkout or a folder of the .pt files")


def run_weights(args: argparse.Namespace) -> int:
    """`u4d weights`: list where the shipped nets are found, or install them from a checkout."""
    if args.action == "install":
        if args.source is None:
            raise InputError("weights install: name the SOURCE (a u4d-aug checkout or a folder of the .pt files)")
        target = install_dir()
        for name, what in install_weights(args.source, target):
            print(f"{name:32s} {what}")
        print(f"installed into {target}")
        return 0
    if args.source is not None:
        raise InputError("weights list takes no SOURCE (did you mean `u4d weights install SOURCE`?)")
    rows = check_installed()
    for row in rows:
        where = str(row.path) if row.path else "not installed"
        flag = "" if row.path is None else ("  ok" if row.verified else "  differs from the shipped file")
        print(f"{row.name:32s} {where}{flag}")
    print(f"looked in: {', '.join(str(folder) for folder in search_dirs())}")
    if any(row.path is None for row in rows):
        print("get the missing ones with `u4d weights install PATH` (PATH: a u4d-aug checkout)")
    return 0
