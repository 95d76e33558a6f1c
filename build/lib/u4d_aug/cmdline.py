"""Conventions every `u4d` command shares: `key=value` overrides anywhere, one-line usage errors, log levels.

`u4d generate CFG --out BANK mode=baseline baseline=DIR` works as `u4d generate CFG mode=baseline baseline=DIR
--out BANK`: `split_overrides` takes the overrides out before argparse sees the rest, except where a flag takes
them as its value (`--set a=1`, `--bank NAME=DIR`). Library modules log through `logging.getLogger(__name__)`;
the CLI sends those records to stderr at the level of `--quiet` / `--verbose`, and keeps stdout for results.
"""

from __future__ import annotations

import argparse
import logging
import re
import sys
from collections.abc import Sequence

from u4d_aug.progress import set_quiet

# a dotted config key and '=': `optim.steps=3`, `stage=stage1`, `'seeds=[0]'` (never a path: keys hold no '/')
OVERRIDE = re.compile(r"[A-Za-z_][\w-]*(\.[A-Za-z_][\w-]*)*=")
VERBOSITY_FLAGS = {"--quiet": logging.WARNING, "-q": logging.WARNING, "--verbose": logging.DEBUG, "-v": logging.DEBUG}
LOGGERS = ("u4d_aug", "segmentation")


class CommandParser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line, `error: PROG: message (see PROG --help)`, exit code 2."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", argparse.RawDescriptionHelpFormatter)  # the example stays one line
        super().__init__(*args, **kwargs)

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"error: {self.prog}: {message} (see {self.prog} --help)\n")


def _values_taken(nargs: int | str | None) -> int:
    """How many following words a flag takes whatever they look like (optional values never take an override)."""
    if nargs is None:
        return 1
    if isinstance(nargs, int):
        return nargs
    return 0  # "?", "*", "+", argparse.REMAINDER / PARSER: overrides after them stay overrides


def takes_overrides(parser: argparse.ArgumentParser) -> bool:
    """Whether the command has a positional `overrides` (key=value ...) argument."""
    return any(not action.option_strings and action.dest == "overrides" for action in parser._actions)


def split_overrides(parser: argparse.ArgumentParser, argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """(argv without its key=value words, those words in order); a flag's own values and words after `--` stay."""
    flags = {option: action for action in parser._actions for option in action.option_strings}
    rest: list[str] = []
    overrides: list[str] = []
    pending = 0  # words the previous flag still takes
    for index, word in enumerate(argv):
        if pending:
            rest.append(word)
            pending -= 1
        elif word == "--":
            rest += argv[index:]
            break
        elif word.startswith("-") and len(word) > 1:
            flag, inline, _ = word.partition("=")
            action = flags.get(flag)
            pending = 0 if inline or action is None else _values_taken(action.nargs)
            rest.append(word)
        elif OVERRIDE.match(word):
            overrides.append(word)
        else:
            rest.append(word)
    return rest, overrides


def parse_command_line(parser: argparse.ArgumentParser, argv: Sequence[str]) -> argparse.Namespace:
    """`parser.parse_args(argv)`, with key=value overrides accepted before, between and after the flags."""
    if not takes_overrides(parser):
        return parser.parse_args(list(argv))
    rest, overrides = split_overrides(parser, argv)
    args = parser.parse_args(rest)
    args.overrides = [*(args.overrides or []), *overrides]
    return args


def split_verbosity(argv: Sequence[str]) -> tuple[list[str], int]:
    """(argv without --quiet / --verbose, the log level they ask for: INFO by default); words after `--` stay."""
    level = logging.INFO
    rest: list[str] = []
    for index, word in enumerate(argv):
        if word == "--":
            rest += argv[index:]
            break
        if word in VERBOSITY_FLAGS:
            level = VERBOSITY_FLAGS[word]
        else:
            rest.append(word)
    return rest, level


def add_verbosity_arguments(parser: argparse.ArgumentParser) -> None:
    """Document the global --quiet / --verbose in a command's --help (`u4d` takes them out before parsing)."""
    group = parser.add_argument_group("global options (anywhere on the command line)")
    group.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help="warnings and errors only")
    group.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS, help="debug messages too")


class _Formatter(logging.Formatter):
    """Info as the bare message; warnings and errors prefixed with their level, as `warning: ...`."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        return text if record.levelno < logging.WARNING else f"{record.levelname.lower()}: {text}"


class _StderrHandler(logging.StreamHandler):
    """Writes to the sys.stderr of the moment (a test's captured stream, a re-pointed stderr)."""

    @property
    def stream(self):  # type: ignore[override]
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def configure_logging(level: int) -> None:
    """Records of u4d_aug and segmentation at `level` and above go to stderr (one handler, set again each call);
    above INFO (--quiet) no progress bar is drawn either."""
    set_quiet(level > logging.INFO)
    for name in LOGGERS:
        logger = logging.getLogger(name)
        logger.setLevel(level)
        for handler in [h for h in logger.handlers if isinstance(h, _StderrHandler)]:
            logger.removeHandler(handler)
        handler = _StderrHandler()
        handler.setFormatter(_Formatter("%(message)s"))
        logger.addHandler(handler)
