"""User-facing errors: one clear sentence naming the file and the fix, never a traceback."""

from __future__ import annotations


class RgbdslamError(Exception):
    """An error caused by the user's input or environment.

    The CLI prints ``str(error)`` on one line and exits with a non-zero code.
    """

    exit_code = 2


class InputError(RgbdslamError):
    """Missing, malformed or inconsistent input files."""


class ConfigError(RgbdslamError):
    """Unknown or ill-typed configuration keys."""


class TrackingLost(RgbdslamError):
    """The front end could not register enough frames to produce a trajectory."""

    exit_code = 3
