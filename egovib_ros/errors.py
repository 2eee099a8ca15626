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


class GapDataError(EgovibError):
    """A recording does not hold enough usable (no-contact, matched) data for a gap diagnosis."""
