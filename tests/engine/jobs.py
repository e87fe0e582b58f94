"""Module-level jobs for the engine tests (they travel to worker processes by reference)."""

from __future__ import annotations

import os
from pathlib import Path

from rgbdslam.errors import InputError


def square(x):
    return x * x


def scaled(shared, x):
    return shared["factor"] * x, os.getpid()


def die_once(marker: str, x):
    """Kills its worker process the first time (a real crash: no exception, the process is gone)."""
    p = Path(marker)
    if not p.exists():
        p.write_text("died")
        os._exit(17)
    return x + 100


def refuse(x):
    raise InputError(f"bad input {x}")


def die_always(x):
    os._exit(17)
