"""Yaml presets named by their path under `configs/` (`seg/tiny`, `u4d/cpu_hdl64.yaml`), found from any folder.

The top-level `configs/` folder of the repository is the one source: a wheel ships it as the package data
`u4d_aug/configs/` (pyproject `package-dir` maps it there), a source checkout or an editable install reads it in
place. A path that exists is used as it is, so `configs/seg/tiny.yaml` from the repository root, an absolute path or
a yaml of one's own keep working.
"""

from __future__ import annotations

import difflib
import os
from pathlib import Path

PRESET_SUFFIXES = (".yaml", ".yml")


def configs_root() -> Path:
    """The shipped presets: `u4d_aug/configs` of an installed wheel, else the checkout's top-level `configs/`."""
    packaged = Path(__file__).resolve().parent / "configs"
    if packaged.is_dir():
        return packaged
    return Path(__file__).resolve().parents[1] / "configs"


def _relative_name(name: str | os.PathLike) -> str:
    """`name` as a path under `configs_root()`: a leading `./` and `configs/` dropped."""
    text = Path(name).as_posix()
    if text.startswith("./"):
        text = text[2:]
    if text.startswith("configs/"):
        text = text[len("configs/") :]
    return text


def preset_candidates(name: str | os.PathLike) -> list[Path]:
    """Where preset `name` may live under `configs_root()`: a leading `configs/` dropped, `.yaml` added if absent."""
    text = _relative_name(name)
    names = [text] if text.endswith(PRESET_SUFFIXES) else [text + ".yaml", text + ".yml", text]
    return [configs_root() / n for n in names]


def resolve_config_path(path: str | os.PathLike) -> Path:
    """An existing file as given; else the preset of that name (`seg/tiny`, `configs/seg/tiny.yaml`); else `path`."""
    path = Path(path)
    if path.is_file() or path.is_absolute():
        return path
    for candidate in preset_candidates(path):
        if candidate.is_file():
            return candidate
    return path


def list_presets() -> list[str]:
    """Names of the shipped presets (`seg/tiny`, ...), sorted."""
    root = configs_root()
    found = [p for suffix in PRESET_SUFFIXES for p in root.glob(f"**/*{suffix}")]
    return sorted(p.relative_to(root).with_suffix("").as_posix() for p in found)


def closest_presets(name: str | os.PathLike, count: int = 3) -> list[str]:
    """The shipped presets nearest to `name` (`seg/tny` -> ['seg/tiny']), best first; [] for an absolute path."""
    if Path(name).is_absolute():
        return []
    text = _relative_name(name)
    for suffix in PRESET_SUFFIXES:
        text = text.removesuffix(suffix)
    return difflib.get_close_matches(text, list_presets(), n=count, cutoff=0.75)


def did_you_mean(choices: list[str]) -> str:
    """A hint naming `choices`, " (did you mean 'a' or 'b'?)", or "" when there are none."""
    if not choices:
        return ""
    return f" (did you mean {' or '.join(repr(c) for c in choices)}?)"
