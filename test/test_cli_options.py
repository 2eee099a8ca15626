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


def _subcommands(parser: argparse.ArgumentParser, prefix: str = "") -> dict:
    """Every (sub)command's parser by its name ("gap", "simulate robot", ...)."""
    found = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found[f"{prefix}{name}"] = sub
                found.update(_subcommands(sub, f"{prefix}{name} "))
    return found


# bench: `egovib bench` says the same in its own words ("no progress bar or summary")
OWN_QUIET = {"bench"}


def test_quiet_means_the_same_in_every_command():
    """--quiet was "no progress bar" in denoise, calibrate and gap, "no summary line" in
    detect, both elsewhere: now one meaning, one help text."""
    from egovib_ros.cli import build_parser

    commands = _subcommands(build_parser())
    quiet = {
        name: next(a.help for a in sub._actions if "--quiet" in a.option_strings)
        for name, sub in commands.items()
        if any("--quiet" in a.option_strings for a in sub._actions) and name not in OWN_QUIET
    }
    assert {"denoise", "calibrate", "evaluate", "detect", "gap", "model show"} <= set(quiet)
    assert set(quiet.values()) == {options.QUIET_HELP}, quiet


def test_quiet_runs_say_only_the_bad_input(sim_bags, tmp_path):
    """`denoise --quiet` of a clean bag says nothing; of a bag with bad samples only their
    counts; `calibrate --quiet` likewise (no coverage lines; its warnings). The session's
    sweep (sim_bags): its harmonic fit is made once for the suite."""
    import contextlib
    import io

    import numpy as np

    from egovib_ros import cli
    from egovib_ros.bag import write_recording
    from egovib_ros.sim import simulate_motion

    def run(*args) -> str:
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(err):
            assert cli.main([str(a) for a in args]) == 0, err.getvalue()
        return err.getvalue()

    motion, _ = simulate_motion(duration_s=2.0, max_speed=0.5, seed=4)
    write_recording(tmp_path / "clean", motion)
    bad = motion.sensor.copy()
    bad[1000:1012] = np.nan
    motion.sensor = bad
    write_recording(tmp_path / "bad", motion)
    said = run("calibrate", sim_bags / "sweep", "--out", tmp_path / "m.npz", "--quiet")
    # a warning only: this 53 s sweep is short for the detector's thresholds
    assert said.count("\n") == 1 and said.startswith("warning: the contact detector's"), said
    model = tmp_path / "m.npz"
    assert (
        run("denoise", tmp_path / "clean", "--model", model, "--out", tmp_path / "a", "--quiet")
        == ""
    )
    said = run("denoise", tmp_path / "bad", "--model", model, "--out", tmp_path / "b", "--quiet")
    assert said.count("\n") == 1 and "12 sensor samples non-finite" in said, said
    loud = run("denoise", tmp_path / "clean", "--model", model, "--out", tmp_path / "c")
    assert "samples denoised" in loud and "wrote" in loud
    # detect and model show printed their summary line with --quiet too
    detect = ["detect", tmp_path / "clean", "--model", model, "--threshold", "1.0"]
    assert run(*detect, "--out", tmp_path / "e.json", "--quiet") == ""
    assert "events in" in run(*detect, "--out", tmp_path / "f.json")
    assert run("model", "show", model, "--out", tmp_path / "show", "--quiet") == ""


def test_no_help_text_shows_a_doubled_percent_sign():
    """`figures --help` printed "speeds 25-100 %%": argparse %-formats argument help, not a
    description. Every command's help, as printed."""
    from egovib_ros.cli import build_parser

    parser = build_parser()
    helps = {"egovib": parser.format_help()}
    helps.update({name: sub.format_help() for name, sub in _subcommands(parser).items()})
    assert "figures" in helps
    assert not [name for name, text in helps.items() if "%%" in text]
