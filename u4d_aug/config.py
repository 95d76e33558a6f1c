"""Typed configs: dataclass defaults <- yaml file <- `key.sub=value` overrides, checked key by key.

Imitates R2DM `utils/option.py` and dinov2's defaults + yaml + CLI merge: the dataclass holds every default, a
yaml file overrides some, command-line `a.b=value` arguments override those. Unknown keys and wrong types are
rejected with an `InputError` that names the key and lists the valid ones; a key a config class has removed
(`REMOVED_KEYS`) is named as removed, with why. `config_to_dict` gives the resolved config that is saved next to
every output and inside every checkpoint; `saved_config` reads one back, also one saved before a key was removed.
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import math
import re
import types
import typing
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import yaml

from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_text
from u4d_aug.presets import closest_presets, configs_root, did_you_mean, resolve_config_path

_FLOAT_WITHOUT_DOT = re.compile(r"[-+]?\d+[eE][-+]?\d+")

T = TypeVar("T")


def load_config(cls: type[T], yaml_path: str | Path | None = None, overrides: Iterable[str] = ()) -> T:
    """Defaults of `cls`, then the yaml file, then `key.sub=value` overrides (later wins)."""
    merged: dict[str, Any] = {}
    source = "defaults"
    if yaml_path is not None:
        source = str(yaml_path)
        merged = _deep_merge(merged, read_yaml(yaml_path))
    for item in overrides:
        merged = _deep_merge(merged, parse_override(item))
    return config_from_dict(cls, merged, source=source)


def read_yaml(path: str | Path) -> dict[str, Any]:
    """Read a yaml mapping (a file, or a preset named under configs/: `seg/tiny`); one-line error if missing or bad."""
    path = resolve_config_path(path)
    if not path.is_file():
        raise InputError(
            f"{path}: config file not found, nor a preset of that name under {configs_root()}"
            + (did_you_mean(closest_presets(path)) or " (e.g. seg/tiny)")
        )
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        raise InputError(f"{path}: not valid yaml{where}: {getattr(exc, 'problem', exc)}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping of config keys at the top level, got {type(data).__name__}")
    return data


def parse_override(item: str) -> dict[str, Any]:
    """`a.b=value` -> {"a": {"b": value}}; the value is parsed as yaml (so 3, 0.5, true, [1, 2] work)."""
    if "=" not in item:
        raise InputError(f"override '{item}': expected key=value (e.g. train.steps=100)")
    key, _, raw = item.partition("=")
    key = key.strip()
    if not key or any(not part for part in key.split(".")):
        raise InputError(f"override '{item}': empty key")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    out: dict[str, Any] = {}
    node = out
    parts = key.split(".")
    for part in parts[:-1]:
        node = node.setdefault(part, {})
    node[parts[-1]] = value
    return out


def config_from_dict(cls: type[T], data: Mapping[str, Any] | None, source: str = "config", prefix: str = "") -> T:
    """Build dataclass `cls` from a (partial) mapping, checking keys and types recursively."""
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    data = dict(data or {})
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    removed = [name for name in unknown if name in removed_keys(cls)]
    if removed:
        why = removed_keys(cls)[removed[0]][1]
        raise InputError(f"{source}: config key '{prefix}{removed[0]}' was removed ({why}); delete it from the config")
    if unknown:
        key = prefix + str(unknown[0])
        hint = did_you_mean(closest_keys(cls, key, prefix))
        raise InputError(f"{source}: unknown config key '{key}'{hint}; valid keys here: {', '.join(sorted(fields))}")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _coerce(value, hints[name], prefix + name, source)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{source}: invalid value under '{prefix.rstrip('.') or cls.__name__}': {exc}") from None


def config_keys(cls: type, prefix: str = "") -> list[str]:
    """Every dotted key of dataclass `cls`, those of its nested configs included ('optim', 'optim.lr', ...)."""
    hints = typing.get_type_hints(cls)
    keys = []
    for field in dataclasses.fields(cls):
        if not field.init:
            continue
        keys.append(prefix + field.name)
        if isinstance(hints[field.name], type) and dataclasses.is_dataclass(hints[field.name]):
            keys += config_keys(hints[field.name], f"{prefix}{field.name}.")
    return keys


def closest_keys(cls: type, key: str, prefix: str = "", count: int = 3) -> list[str]:
    """The dotted keys of `cls` (under `prefix`) nearest to the unknown `key`: those with its last part (`lr` ->
    'optim.lr'), else the nearest by the whole key or by its last part, best first."""
    keys = config_keys(cls, prefix)
    by_last: dict[str, list[str]] = {}
    for name in keys:
        by_last.setdefault(name.rpartition(".")[2], []).append(name)
    if key.rpartition(".")[2] in by_last:
        return by_last[key.rpartition(".")[2]][:count]
    close = difflib.get_close_matches(key, keys, n=count, cutoff=0.75)
    for last in difflib.get_close_matches(key.rpartition(".")[2], list(by_last), n=count, cutoff=0.75):
        close += by_last[last]
    return list(dict.fromkeys(close))[:count]


def removed_keys(cls: type) -> dict[str, tuple[Any, str]]:
    """{key: (its value that meant "off", why it was removed)} of the keys dataclass `cls` no longer has."""
    return getattr(cls, "REMOVED_KEYS", {})


def without_removed_keys(cls: type, data: Mapping[str, Any], prefix: str = "") -> tuple[dict[str, Any], dict]:
    """A saved config mapping without the keys `cls` (and its nested configs) has removed, and apart from it
    {dotted key: value} of those that held another value than their "off" one (a setting that acted)."""
    data = dict(data)
    acted = {}
    for name, (off, _) in removed_keys(cls).items():
        if name in data:
            value = data.pop(name)
            if value != off:
                acted[prefix + name] = value
    hints = typing.get_type_hints(cls)
    for field in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[field.name]) and isinstance(data.get(field.name), Mapping):
            data[field.name], inner = without_removed_keys(
                hints[field.name], data[field.name], f"{prefix}{field.name}."
            )
            acted |= inner
    return data, acted


def saved_config(cls: type[T], data: Mapping[str, Any] | None, source: str) -> T:
    """A resolved config read back (a checkpoint's, a run's config.yaml), also one saved before a key was removed:
    removed keys are dropped, with a warning for one that was set (the run used a since-removed setting)."""
    clean, acted = without_removed_keys(cls, data or {})
    for key, value in acted.items():
        warnings.warn(f"{source}: trained with {key}={value!r}, a setting since removed; read without it", stacklevel=2)
    return config_from_dict(cls, clean, source=source)


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """Resolved config as plain python (tuples become lists) for yaml/json/checkpoints."""
    return _plain(dataclasses.asdict(cfg))


def save_config(cfg: Any, path: str | Path) -> None:
    """Write the resolved config as yaml, atomically."""
    atomic_write_text(path, yaml.safe_dump(config_to_dict(cfg), sort_keys=False))


def _plain(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _deep_merge(base: dict[str, Any], update: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in update.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    return getattr(tp, "__name__", str(tp).replace("typing.", ""))


def _coerce(value: Any, tp: Any, key: str, source: str) -> Any:
    """Check `value` against annotation `tp` (int/float/bool/str/Path/Literal/Optional/tuple/list/dict/dataclass)."""

    def fail() -> typing.NoReturn:
        raise InputError(f"{source}: key '{key}' expects {_type_name(tp)}, got {value!r} ({type(value).__name__})")

    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, key, source)
            except InputError as exc:
                errors.append(exc)
        fail()
    if origin is typing.Literal:
        if value in args:
            return value
        raise InputError(f"{source}: key '{key}' must be one of {', '.join(repr(a) for a in args)}, got {value!r}")
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, Mapping):
            fail()
        return config_from_dict(tp, value, source=source, prefix=key + ".")
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            fail()
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise InputError(f"{source}: key '{key}' expects {len(args)} values, got {len(value)}")
            items = [_coerce(v, a, f"{key}[{i}]", source) for i, (v, a) in enumerate(zip(value, args))]
        else:
            inner = args[0] if args else Any
            items = [_coerce(v, inner, f"{key}[{i}]", source) for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict or tp is dict:
        if not isinstance(value, Mapping):
            fail()
        return dict(value)
    if tp is bool:
        if isinstance(value, bool):
            return value
        fail()
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        fail()
    if tp is float:
        number = None
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            number = float(value)
        elif isinstance(value, str) and _FLOAT_WITHOUT_DOT.fullmatch(value.strip()):
            number = float(value)  # yaml 1.1 reads '1e-4' (no dot) as a string
        if number is None:
            fail()
        if not math.isfinite(number):
            raise InputError(f"{source}: key '{key}' must be a finite number, got {value}")
        return number
    if tp is str:
        if isinstance(value, str):
            return value
        fail()
    if tp is Path:
        if isinstance(value, (str, Path)):
            return Path(value)
        fail()
    return value


def add_run_arguments(parser: argparse.ArgumentParser, config_example: str, overrides_example: str) -> None:
    """Arguments of a resumable training command: CONFIG [key=value ...] [--resume [CKPT]] [--out DIR]."""
    parser.add_argument("config", type=Path, help=f"yaml preset, e.g. {config_example}")
    parser.add_argument("overrides", nargs="*", help=f"key=value overrides, e.g. {overrides_example}")
    parser.add_argument(
        "--resume",
        nargs="?",
        const="last",
        default=None,
        metavar="CKPT",
        help="continue a run: from CKPT, or without a value from the newest OUT/checkpoints/step_*.pt",
    )
    parser.add_argument("--out", type=Path, default=None, help="output folder (overrides the config's)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
