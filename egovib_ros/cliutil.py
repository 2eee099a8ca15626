"""Option checks for the `egovib` commands, in one place (issue 11).

Every numeric option is checked by its argparse `type=` before any work starts:
finite, in range, integral where it must be. A bad value is a one-line error naming
the option (`OneLineErrorParser`), exit status 2, like every other bad input.
"""

from __future__ import annotations

import argparse
import math
from typing import Callable, NoReturn

from egovib_ros.errors import ConfigError

# Effect strengths the simulator models sensibly (CONTRACT section 5, sim/hand.py):
# position scales a source by 1 + s cos(...), so |s| <= 1 keeps it non-negative;
# coupling/acceleration/drift are gains (>= 0); timing is a clock offset in seconds.
EFFECT_RANGES: dict[str, tuple[float, float]] = {
    "position": (-1.0, 1.0),
    "coupling": (0.0, 100.0),
    "acceleration": (0.0, 100.0),
    "timing": (-1.0, 1.0),
    "drift": (0.0, 100.0),
}
MAX_SEED = 2**32 - 1


class OneLineErrorParser(argparse.ArgumentParser):
    """argparse parser whose errors are one line (`PROG: error: ...`), exit status 2.

    Subparsers inherit the class, so every subcommand reports bad options this way.
    """

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
    low: float = -math.inf,
    high: float = math.inf,
    *,
    low_open: bool = False,
    high_open: bool = False,
    what: str = "",
) -> Callable[[str], float]:
    """argparse type: a finite float in [low, high] (open ends where asked)."""

    def parse(text: str) -> float:
        value = _number(text)
        too_low = value <= low if low_open else value < low
        too_high = value >= high if high_open else value > high
        if too_low or too_high:
            raise argparse.ArgumentTypeError(f"expected {describe()}, got {text!r}")
        return value

    def describe() -> str:
        if what:
            return what
        if math.isinf(low) and math.isinf(high):
            return "a finite number"
        if math.isinf(high):
            return f"a finite number {'>' if low_open else '>='} {low:g}"
        if math.isinf(low):
            return f"a finite number {'<' if high_open else '<='} {high:g}"
        left, right = "(" if low_open else "[", ")" if high_open else "]"
        return f"a number in {left}{low:g}, {high:g}{right}"

    parse.__name__ = "number"
    return parse


def int_in(low: int | None = None, high: int | None = None) -> Callable[[str], int]:
    """argparse type: an integer in [low, high]."""

    def parse(text: str) -> int:
        try:
            value = int(text, 10)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if (low is not None and value < low) or (high is not None and value > high):
            if high is None:
                expected = f"an integer >= {low}"
            elif low is None:
                expected = f"an integer <= {high}"
            else:
                expected = f"an integer in [{low}, {high}]"
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return value

    parse.__name__ = "integer"
    return parse


finite_float = float_in()
positive_float = float_in(0.0, low_open=True)
nonneg_float = float_in(0.0)
fraction = float_in(0.0, 1.0)  # [0, 1]
positive_fraction = float_in(0.0, 1.0, low_open=True)  # (0, 1]
nonneg_int = int_in(0)
positive_int = int_in(1)
seed = int_in(0, MAX_SEED)


def check_effects(effects: dict[str, float], *, source: str = "--effects") -> dict[str, float]:
    """Raise ConfigError unless every strength is finite and within EFFECT_RANGES."""
    for name, strength in effects.items():
        if not math.isfinite(strength):
            raise ConfigError(f"{source}: {name}={strength!r}: strength must be finite")
        low, high = EFFECT_RANGES.get(name, (-math.inf, math.inf))
        if not low <= strength <= high:
            unit = " s" if name == "timing" else ""
            raise ConfigError(f"{source}: {name}={strength:g} is outside [{low:g}, {high:g}]{unit}")
    return effects


def effects_spec(text: str) -> dict[str, float]:
    """argparse type: the effects SPEC `name=strength,...` (CONTRACT section 3), checked."""
    from egovib_ros.sim.params import parse_effects

    try:
        return check_effects(parse_effects(text), source="SPEC")
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def effects_spec_text(text: str) -> str:
    """Like effects_spec but keeps the text (for commands that pass the SPEC on)."""
    effects_spec(text)
    return text


def check_stream(stats: dict, where: str, *, joint_states: int, limit: float | None = None) -> str:
    """Refuse a recording the core found mostly unusable; else the line of counts to print.

    stats: of calibrate_arrays / denoise_batch. Refused (one-line StreamError naming
    `where`): more than `limit` (core.MAX_BAD_SHARE) of the sensor samples bad
    (non-finite, beyond the sensor range, out of order), or of the `joint_states`
    messages dropped (non-finite, or stamped not after the previous one: a stuck clock).
    """
    from egovib_ros.core import MAX_BAD_SHARE, check_bad_share
    from egovib_ros.errors import StreamError

    limit = MAX_BAD_SHARE if limit is None else limit
    check_bad_share(stats, where, limit)
    dropped = int(stats.get("joint_states_dropped", 0))
    if joint_states and dropped > limit * joint_states:
        raise StreamError(
            f"{where}: {dropped} of {joint_states} joint states "
            f"({100 * dropped / joint_states:.1f} %) are unusable (non-finite, or "
            f"not "
            f"stamped after the previous one: a stuck clock?); more than "
            f"{100 * limit:g} % is refused"
        )
    return (
        f"bad input treated as missing: {int(stats.get('samples_bad', 0))} sensor samples "
        f"non-finite or beyond the sensor range, {int(stats.get('dropped_out_of_order', 0))} "
        f"out of order, {int(stats.get('gap_filled_samples', 0))} bridged, "
        f"{int(stats.get('resets', 0))} restarts; {dropped} of {joint_states} joint states "
        f"dropped"
    )
