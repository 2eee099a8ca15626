"""Option checks and options shared by the `egovib` commands: every numeric option is
checked by its argparse `type=` before any work starts (finite, in range, integral where
it must be); a bad value is a one-line error naming the option, exit status 2."""

from __future__ import annotations

import argparse
import math
from typing import Callable, NoReturn

from egovib_ros.core.adapt import AdaptSettings
from egovib_ros.errors import ConfigError
from egovib_ros.sim.params import check_effects, parse_effects

MAX_SEED = 2**32 - 1


class OneLineErrorParser(argparse.ArgumentParser):
    """argparse parser whose errors (and its subparsers') are one line, exit status 2."""

    #: the sub-commands of this command, None if it has none (egovib_ros.cli.add_commands)
    commands: argparse._SubParsersAction | None = None

    def add_subparsers(self, **kwargs) -> argparse._SubParsersAction:
        self.commands = super().add_subparsers(**kwargs)
        return self.commands

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _number(text: str) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def float_in(
    low: float, high: float = math.inf, *, low_open: bool = False
) -> Callable[[str], float]:
    """argparse type: a finite float in [low, high] ((low, high] with `low_open`)."""
    if math.isinf(high):
        expected = f"a finite number {'>' if low_open else '>='} {low:g}"
    else:
        expected = f"a number in {'(' if low_open else '['}{low:g}, {high:g}]"

    def parse(text: str) -> float:
        value = _number(text)
        if (value <= low if low_open else value < low) or value > high:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return value

    parse.__name__ = "number"
    return parse


def int_in(low: int, high: int | None = None) -> Callable[[str], int]:
    """argparse type: an integer in [low, high] (>= low without `high`)."""
    expected = f"an integer >= {low}" if high is None else f"an integer in [{low}, {high}]"

    def parse(text: str) -> int:
        try:
            value = int(text, 10)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return value

    parse.__name__ = "integer"
    return parse


positive_float = float_in(0.0, low_open=True)
nonneg_float = float_in(0.0)
fraction = float_in(0.0, 1.0)  # [0, 1]
positive_fraction = float_in(0.0, 1.0, low_open=True)  # (0, 1]
positive_int = int_in(1)
seed = int_in(0, MAX_SEED)


def joint_lag_option(parser: argparse.ArgumentParser) -> None:
    """--joint-lag of the commands that read joint states against the sensor."""
    parser.add_argument(
        "--joint-lag",
        type=float_in(-1.0, 1.0),
        default=0.0,
        metavar="SECONDS",
        help="joint lag: seconds the vibration trails the joint states, by which their stamps "
        "are moved later (egovib gap's advice; negative: the vibration leads them, i.e. the "
        "joint states are stamped late)",
    )


#: What --quiet means in every command.
QUIET_HELP = (
    "no progress bar and no summary of the results; warnings, errors and the counts of bad "
    "input, if any, are still said"
)


def force_and_quiet(parser: argparse.ArgumentParser, force_help: str) -> None:
    """--force (what it may replace: `force_help`) and --quiet (QUIET_HELP)."""
    parser.add_argument("--force", action="store_true", help=force_help)
    parser.add_argument("--quiet", action="store_true", help=QUIET_HELP)


def effects_spec(text: str) -> dict[str, float]:
    """argparse type: the effects SPEC `name=strength,...` (INTERFACES.md section 3), checked."""

    try:
        return check_effects(parse_effects(text), source="SPEC")
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def adapt_options(parser: argparse.ArgumentParser) -> None:
    """--adapt and --forget-s: online adaptation of the model (core.adapt)."""
    defaults = AdaptSettings()
    parser.add_argument(
        "--adapt",
        action="store_true",
        help="the model goes on learning while the contact detector sees no contact (with "
        f"{defaults.guard_s:g} s of guard time around every detection): the residual table's "
        "cells at the joint speeds met, calibrated or not, and the harmonic map's corrections "
        "and amplitudes (methods cancel and hybrid)",
    )
    parser.add_argument(
        "--forget-s",
        type=float_in(0.01, 1e6),
        default=None,
        metavar="SECONDS",
        help=f"with --adapt: the forgetting time (default {defaults.forget_s:g} s of "
        "contact-free time at a speed)",
    )


def adapt_settings(args: argparse.Namespace) -> AdaptSettings | None:
    """The AdaptSettings of --adapt / --forget-s (None without --adapt)."""
    if not args.adapt:
        if args.forget_s is not None:
            raise ConfigError("--forget-s applies with --adapt only")
        return None
    if args.forget_s is None:
        return AdaptSettings()
    return AdaptSettings(forget_s=args.forget_s)
