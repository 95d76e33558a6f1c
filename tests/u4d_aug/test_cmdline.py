"""Command-line conventions: key=value overrides anywhere, one-line usage errors, --quiet / --verbose logging."""

from __future__ import annotations

import argparse
import logging

import pytest

from u4d_aug.cmdline import (
    CommandParser,
    configure_logging,
    parse_command_line,
    split_overrides,
    split_verbosity,
)
from u4d_aug.config import add_run_arguments


def run_parser() -> argparse.ArgumentParser:
    """The arguments of `u4d seg-train` / `u4d train-diffusion`, plus a flag with one value and one with several."""
    parser = CommandParser(prog="u4d test")
    add_run_arguments(parser, "seg/tiny", "optim.steps=3")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--arms", nargs="+", default=None)
    return parser


@pytest.mark.parametrize(
    "argv",
    [
        ["seg/tiny", "a=1", "b.c=[1, 2]", "--out", "X"],
        ["seg/tiny", "--out", "X", "a=1", "b.c=[1, 2]"],
        ["--out", "X", "a=1", "seg/tiny", "b.c=[1, 2]"],
        ["seg/tiny", "a=1", "--out=X", "b.c=[1, 2]"],
    ],
)
def test_overrides_before_between_and_after_flags(argv):
    args = parse_command_line(run_parser(), argv)
    assert str(args.config) == "seg/tiny" and str(args.out) == "X"
    assert args.overrides == ["a=1", "b.c=[1, 2]"]


def test_flag_values_stay_with_their_flag():
    args = parse_command_line(run_parser(), ["seg/tiny", "--set", "x=1", "--arms", "sup", "mt", "seeds=[0]"])
    assert args.set == ["x=1"] and args.arms == ["sup", "mt"] and args.overrides == ["seeds=[0]"]
    args = parse_command_line(run_parser(), ["seg/tiny", "--resume", "optim.steps=5"])
    assert args.resume == "last" and args.overrides == ["optim.steps=5"]  # an override is no checkpoint path
    args = parse_command_line(run_parser(), ["seg/tiny", "--resume", "runs/lr=0.1/step_9.pt", "a=1"])
    assert args.resume == "runs/lr=0.1/step_9.pt" and args.overrides == ["a=1"]


def test_split_keeps_order_and_words_after_double_dash():
    rest, overrides = split_overrides(run_parser(), ["b=2", "seg/tiny", "a=1", "--", "c=3"])
    assert rest == ["seg/tiny", "--", "c=3"] and overrides == ["b=2", "a=1"]


def test_parsers_without_overrides_are_left_alone():
    parser = CommandParser(prog="u4d x")
    parser.add_argument("real")
    assert parse_command_line(parser, ["name=dir"]).real == "name=dir"


def test_unknown_flag_is_a_one_line_usage_error(capsys):
    with pytest.raises(SystemExit) as exit_info:
        parse_command_line(run_parser(), ["seg/tiny", "a=1", "--bogus"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err == "error: u4d test: unrecognized arguments: --bogus (see u4d test --help)\n"


def test_verbosity_flags_anywhere():
    assert split_verbosity(["info", "ROOT", "--quiet"]) == (["info", "ROOT"], logging.WARNING)
    assert split_verbosity(["-v", "info", "ROOT"]) == (["info", "ROOT"], logging.DEBUG)
    assert split_verbosity(["info", "--", "--quiet"]) == (["info", "--", "--quiet"], logging.INFO)


def test_library_records_reach_stderr_at_the_chosen_level(capsys):
    log = logging.getLogger("segmentation.some_module")
    configure_logging(logging.INFO)
    log.info("step 1 done")
    log.debug("details")
    log.warning("careful")
    assert capsys.readouterr().err == "step 1 done\nwarning: careful\n"
    configure_logging(logging.WARNING)  # --quiet
    log.info("step 2 done")
    assert capsys.readouterr().err == ""
    configure_logging(logging.INFO)
    assert len([h for h in logging.getLogger("segmentation").handlers if type(h).__name__ == "_StderrHandler"]) == 1
