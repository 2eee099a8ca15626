"""egovib_ros.cli.options: every numeric option checked by its argparse type before any work,
a bad value one line naming the option, exit status 2."""

from __future__ import annotations

import argparse
import re

import pytest

from egovib_ros.cli import options
from egovib_ros.cli.options import OneLineErrorParser, float_in


@pytest.mark.parametrize(
    "parse, text, value",
    [(float_in(0.0, 1.0), "0", 0.0), (float_in(0.0, 1.0), "1", 1.0),
     (options.positive_float, "1e-9", 1e-9),
     (options.nonneg_float, "0", 0.0), (options.positive_fraction, "1", 1.0),
     (options.positive_int, "7", 7), (options.seed, str(options.MAX_SEED), options.MAX_SEED)],
)  # fmt: skip
def test_values_in_range_are_taken(parse, text, value):
    assert parse(text) == value and type(parse(text)) is type(value)


@pytest.mark.parametrize(
    "parse, text, expected",
    [(float_in(0.0, 1.0), "1.5", "a number in [0, 1]"),
     (float_in(0.0, 1.0, low_open=True), "0", "a number in (0, 1]"),
     (options.positive_float, "0", "a finite number > 0"),
     (options.nonneg_float, "nan", "a finite number"), (options.nonneg_float, "inf", "a finite"),
     (options.nonneg_float, "two", "a number"), (options.positive_int, "0", "an integer >= 1"),
     (options.positive_int, "1.0", "an integer"),
     (options.seed, "-1", f"an integer in [0, {options.MAX_SEED}]")],
)  # fmt: skip
def test_values_out_of_range_name_what_was_expected(parse, text, expected):
    with pytest.raises(argparse.ArgumentTypeError, match=re.escape("expected " + expected)) as info:
        parse(text)
    assert repr(text) in str(info.value)


def test_effects_spec_is_parsed_and_checked():
    assert options.effects_spec("drift=0.5, timing=0.02") == {"drift": 0.5, "timing": 0.02}
    assert options.effects_spec("none") == {}
    with pytest.raises(argparse.ArgumentTypeError, match="SPEC: timing=9 is outside"):
        options.effects_spec("timing=9")


def test_a_bad_option_is_one_line_exit_2(capsys):
    parser = OneLineErrorParser(prog="egovib")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run")
    run.add_argument("--rate", type=options.positive_float, required=True)
    assert parser.parse_args(["run", "--rate", "3000"]).rate == 3000.0
    with pytest.raises(SystemExit) as info:
        parser.parse_args(["run", "--rate", "-1"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err == (
        "egovib run: error: argument --rate: expected a finite number > 0, got '-1' "
        "(see egovib run --help)\n"
    )
