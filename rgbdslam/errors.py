"""User-facing errors: one clear sentence naming the file and the fix, never a traceback."""

from __future__ import annotations

import signal


def one_line(text: str) -> str:
    """``text`` with every character that would break or hide a terminal line (newline, carriage
    return, tab, NUL, Unicode line separators, other control characters) written as its Python
    escape, so an error naming a path such as 'a\\nb' stays one line."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


ECHO_CHARS = 60  # the most characters of a user's value an error message repeats


def shorten(value, limit: int = ECHO_CHARS) -> str:
    """``repr(value)`` cut to about ``limit`` characters (``...`` where cut), so a message echoing a
    user's value (a long string, a huge or deeply nested list, an expanded YAML alias, a
    120,000-digit number) stays one short line. Containers are never formatted in full first
    (:mod:`reprlib`: a few items per level, a few levels)."""
    import reprlib

    r = reprlib.Repr()
    r.maxlevel, r.maxdict = 3, 4
    r.maxtuple = r.maxlist = r.maxarray = r.maxset = r.maxfrozenset = r.maxdeque = 6
    r.maxstring = r.maxlong = r.maxother = limit
    try:
        text = r.repr(value)
    except (ValueError, RecursionError):  # an int beyond Python's digit limit for str()
        return f"a {type(value).__name__} too large to show"
    return text if len(text) <= limit + 20 else text[:limit] + "..."


def cut(text, limit: int = ECHO_CHARS) -> str:
    """``str(text)`` cut to ``limit`` characters (``...`` where cut): a user's key or path echoed
    as it is written, not quoted."""
    text = str(text)
    return text if len(text) <= limit else text[: limit - 3] + "..."


MAX_MESSAGE = 1000  # characters of one error line


def bounded(text: str, limit: int = MAX_MESSAGE) -> str:
    """``text`` when it is at most ``limit`` characters, else its beginning and end with how much
    was left out: whatever a message echoes (a value, a list of names), the line stays readable."""
    if len(text) <= limit:
        return text
    tail = limit // 5
    return f"{text[: limit - tail - 40]} ... [{len(text) - limit + 40:,} characters left out] ... {text[-tail:]}"


class RgbdslamError(Exception):
    """An error caused by the user's input or environment.

    The CLI prints ``str(error)`` on one line and exits with a non-zero code; control characters
    in the message (from a file name or a file's text) are escaped (:func:`one_line`).
    """

    exit_code = 2

    def __str__(self) -> str:
        return bounded(one_line(super().__str__()))


class InputError(RgbdslamError):
    """Missing, malformed or inconsistent input files."""


class ConfigError(RgbdslamError):
    """Unknown or ill-typed configuration keys."""


class TrackingLost(RgbdslamError):
    """The front end could not register enough frames to produce a trajectory."""

    exit_code = 3


# ---------------------------------------------------------------------------- Ctrl-C and SIGTERM

_interrupted = False
_signal_name = "SIGINT"  # the signal that stopped the command (SIGTERM: kill, timeout, docker stop)


IMPORT_MACHINERY = "<frozen importlib"  # the code name of importlib's own frames
REDELIVER_S = 0.02  # a Ctrl-C that arrived inside the import machinery is raised again this much later


def on_sigint(signum, frame) -> None:
    """SIGINT and SIGTERM handler of the command line: remember the interruption, then raise as
    Python's own Ctrl-C (KeyboardInterrupt), so SIGTERM (``kill``, ``timeout``, a batch scheduler,
    ``docker stop``) ends a command exactly as Ctrl-C does: run.json says "interrupted", the
    map's temporary folder is removed, the helper processes are ended, finished work is kept.

    Not inside the import machinery: a KeyboardInterrupt raised between importlib's taking of the
    global import lock and its ``try`` (or in its weak-reference callback, whose exceptions Python
    only prints) leaves that lock held, and the next import in any other thread waits forever (a
    run hung after Ctrl-C that way). There the signal is sent again a moment later, when the import
    is done."""
    global _interrupted, _signal_name
    f = frame
    while f is not None:
        if f.f_code.co_filename.startswith(IMPORT_MACHINERY):
            _redeliver(signum)
            return
        f = f.f_back
    _interrupted = True
    if signum == signal.SIGTERM:
        _signal_name = "SIGTERM"
    raise KeyboardInterrupt


def _redeliver(signum) -> None:
    import os
    import threading

    t = threading.Timer(REDELIVER_S, os.kill, (os.getpid(), signum))
    t.daemon = True
    t.start()


def was_interrupted() -> bool:
    """True once the user pressed Ctrl-C (an exception after that is a consequence of it)."""
    return _interrupted


def exit_interrupted() -> None:
    """One line on stderr and exit code 130 after Ctrl-C, 143 after SIGTERM (what a shell reports
    for a process those signals ended: 128 + the signal's number)."""
    import sys

    term = _signal_name == "SIGTERM"
    try:
        sys.stderr.write("terminated (SIGTERM): finished work was saved\n" if term
                         else "interrupted: finished work was saved\n")
        sys.stderr.flush()
    except (OSError, ValueError, KeyboardInterrupt):
        pass
    sys.exit(128 + (signal.SIGTERM if term else signal.SIGINT))
