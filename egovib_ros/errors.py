"""Typed errors. Every message is one line naming the file/topic and the problem."""

from __future__ import annotations


class EgovibError(Exception):
    """Base class of all errors raised on bad input."""


class ModelFileError(EgovibError):
    """A noise-model file is missing, corrupt, or of an unsupported version."""


class BagError(EgovibError):
    """A bag is missing, unreadable, or lacks a required topic."""


class ConfigError(EgovibError, ValueError):
    """A setting (parameter, effects SPEC, config file) is invalid."""


class StreamError(EgovibError, ValueError):
    """Data given to a streaming processor do not fit its settings."""


class RateError(StreamError):
    """A stream's sample rate does not fit the model (at its start, or since it changed): the
    stream is refused while it lasts; a live node waits for the rate to come back."""


class GapDataError(EgovibError):
    """A recording does not hold enough usable (no-contact, matched) data for a gap diagnosis."""


def bag_error(where: str, exc: Exception) -> BagError:
    """`exc` (a processor's ValueError) as the bag's error, naming `where` once: the
    processor's message may name it already (its source)."""
    text = str(exc)
    return BagError(text if text.startswith(f"{where}: ") else f"{where}: {text}")


def check_ranges(obj, checks, what: str = "") -> None:
    """ConfigError unless each attribute `name` of `obj` in `checks` ((name, low, high), ...)
    is a number (not a bool) in [low, high]; the message starts with `what`."""
    for name, low, high in checks:
        value = getattr(obj, name)
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float))
            or not low <= value <= high
        ):
            raise ConfigError(
                f"{what}{name} must be a number in [{low:g}, {high:g}], got {value!r}"
            )
