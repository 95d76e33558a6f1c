"""Progress bars (tqdm) that the command line's --quiet turns off everywhere, whatever each call asks for."""

from __future__ import annotations

from typing import Any

from tqdm.auto import tqdm

_quiet = False


def set_quiet(quiet: bool) -> None:
    """`u4d --quiet` (warnings and errors only): no progress bar is drawn until this is called with False."""
    global _quiet
    _quiet = quiet


def progress_bar(*args: Any, enabled: bool = True, **kwargs: Any) -> tqdm:
    """tqdm(*args, **kwargs), drawn when `enabled` (the caller's --no-progress / rank) and not under --quiet."""
    return tqdm(*args, disable=not enabled or _quiet, **kwargs)
