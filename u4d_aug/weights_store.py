"""Where the shipped nets are on this machine: a name like `weights/u4d.pt` resolved to a file.

A config or a call names a shipped net as `weights/NAME.pt` (or `NAME.pt`). A path that exists as written is used as
it is; otherwise the name is looked up, first hit wins, in
  1. `--weights-dir DIR` / the `U4D_WEIGHTS` environment variable, when set (an explicit choice);
  2. the checkout's `weights/` (a source checkout or an editable install);
  3. the user cache `$XDG_CACHE_HOME/u4d/weights` (default `~/.cache/u4d/weights`),
as torch.hub keeps downloaded checkpoints in `$TORCH_HOME/hub/checkpoints` and torchvision's `weights=` resolves to it.
A wheel carries no `.pt`: `u4d weights install SOURCE` (u4d_aug/weights_install.py) copies them from a checkout into
the explicit folder, else the user cache, checked against the table the package ships (`shipped_weights.json`, written
by `python scripts/weights_table.py` from the checkout's `weights/`). Standard library only: `io.load_checkpoint`
resolves every checkpoint path through here.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from u4d_aug.errors import InputError

WEIGHTS_ENV = "U4D_WEIGHTS"
CHECKOUT_DIR = Path(__file__).resolve().parents[1] / "weights"
TABLE_PATH = Path(__file__).resolve().with_name("shipped_weights.json")
TABLE_FORMAT = "u4d-shipped-weights-v1"
PREFIX = "weights"  # the folder name configs write in front of a shipped net's file name


def cache_dir() -> Path:
    """The user cache `u4d weights install` fills by default: $XDG_CACHE_HOME/u4d/weights, else ~/.cache/u4d/weights."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "u4d" / "weights"


def explicit_dir() -> Path | None:
    """The folder `--weights-dir` / U4D_WEIGHTS names, or None."""
    value = os.environ.get(WEIGHTS_ENV, "").strip()
    return Path(value).expanduser() if value else None


def search_dirs() -> list[Path]:
    """The folders a shipped net's name is looked up in, in order (explicit, checkout, user cache)."""
    found = [folder for folder in (explicit_dir(), CHECKOUT_DIR, cache_dir()) if folder is not None]
    return list(dict.fromkeys(found))


def install_dir() -> Path:
    """Where `u4d weights install` writes: the explicit folder, else the user cache."""
    return explicit_dir() or cache_dir()


def shipped_table(path: Path | None = None) -> dict[str, dict]:
    """{file name: {sha256, bytes, hash}} of the nets this version ships (`path`: TABLE_PATH)."""
    path = path or TABLE_PATH
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: the shipped-weights table is unreadable ({exc}); reinstall u4d-aug") from None
    if (
        not isinstance(record, dict)
        or record.get("format") != TABLE_FORMAT
        or not isinstance(record.get("files"), dict)
    ):
        raise InputError(f"{path}: not a shipped-weights table (format {TABLE_FORMAT})")
    return record["files"]


def shipped_name(value: str | os.PathLike) -> str | None:
    """The shipped file name `value` refers to (`weights/NAME.pt`, `NAME.pt`, `NAME`), or None for any other path."""
    path = Path(value)
    if path.is_absolute():
        return None
    parts = path.parts
    if len(parts) == 2 and parts[0] == PREFIX:
        name = parts[1]
    elif len(parts) == 1:
        name = parts[0]
    else:
        return None
    name = name if name.endswith(".pt") else f"{name}.pt"
    return name if name in shipped_table() else None


def find_weights(name: str) -> Path | None:
    """The first `search_dirs()` file called `name`, or None."""
    for folder in search_dirs():
        if (folder / name).is_file():
            return folder / name
    return None


def resolve_weights(value: str | os.PathLike) -> Path:
    """`value` if it exists as written, else the installed shipped net it names, else `value` unchanged."""
    path = Path(value)
    if path.exists():
        return path
    name = shipped_name(path)
    found = find_weights(name) if name else None
    return found or path


def missing_hint(value: str | os.PathLike) -> str:
    """What to do when `value` names a shipped net that is not installed ("" for other paths)."""
    name = shipped_name(value)
    if name is None or find_weights(name) is not None:
        return ""
    looked = ", ".join(str(folder) for folder in search_dirs())
    return (
        f" (a shipped net, not installed: looked in {looked}; install the shipped nets with "
        f"`u4d weights install PATH`, PATH a u4d-aug checkout or a folder holding {name}, or point {WEIGHTS_ENV} / "
        "--weights-dir at them)"
    )


def split_weights_dir(argv: list[str]) -> list[str]:
    """argv without `--weights-dir DIR` (anywhere, as the verbosity flags), which sets U4D_WEIGHTS for this process."""
    rest: list[str] = []
    index = 0
    while index < len(argv):
        word = argv[index]
        if word == "--":
            rest += argv[index:]
            break
        if word == "--weights-dir" or word.startswith("--weights-dir="):
            if "=" in word:
                value = word.split("=", 1)[1]
            elif index + 1 < len(argv):
                index += 1
                value = argv[index]
            else:
                raise InputError("--weights-dir: expected a folder")
            if not value:
                raise InputError("--weights-dir: expected a folder")
            os.environ[WEIGHTS_ENV] = value
        else:
            rest.append(word)
        index += 1
    return rest
