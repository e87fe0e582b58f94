"""Sanity limits for numbers read from text inputs (trajectories, lists, graphs, camera files).

A finite but absurd value (a time stamp of 1e300 s, a position of 1e300 m, a quaternion
``1e200 1e200 1e200 1e200``) is refused where it is read, naming ``file:line``, instead of
turning into overflow warnings and silent garbage (ATE ``inf``, RPE of 180 degrees) later.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from rgbdslam.errors import InputError

MAX_STAMP = 1e12  # seconds (Unix time is ~1.8e9 s; nanosecond stamps, ~1.8e18, are not seconds)
MAX_COORD = 1e9  # metres: positions in trajectories and poses
QUAT_TOL = 1e-2  # |‖q‖ - 1| allowed for a quaternion read from a file (the g2o reader's tolerance too)


def check_magnitude(values, limit: float, path: str | Path, lines: Sequence[int], what: str, fix: str) -> None:
    """InputError at the first row of ``values`` (N,) or (N, k) holding a number beyond ±``limit``
    (``lines[i]``: the line number of row i)."""
    a = np.abs(np.asarray(values, dtype=np.float64))
    bad = np.flatnonzero((a > limit).reshape(len(a), -1).any(axis=1)) if a.size else []
    if len(bad):
        v = np.asarray(values, dtype=np.float64).reshape(len(a), -1)[bad[0]]
        worst = v[np.argmax(np.abs(v))]
        raise InputError(f"{path}:{lines[bad[0]]}: {what} {worst:g} is beyond ±{limit:g}; {fix}")


def check_stamps(stamps, path: str | Path, lines: Sequence[int]) -> None:
    check_magnitude(stamps, MAX_STAMP, path, lines, "time stamp",
                    "time stamps must be seconds (e.g. 1305031102.175304)")


def unit_quaternions(q, path: str | Path, lines: Sequence[int], order: str = "qx qy qz qw") -> np.ndarray:
    """``q`` (N, 4) normalised; InputError at the first one whose length is not 1 within
    :data:`QUAT_TOL` (computed without overflow, so 1e200-sized entries are reported, not inf)."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    m = np.max(np.abs(q), axis=1)
    safe = np.where(m > 0, m, 1.0)
    n = np.linalg.norm(q / safe[:, None], axis=1) * m
    bad = np.flatnonzero(~(np.abs(n - 1.0) <= QUAT_TOL))
    if len(bad):
        raise InputError(f"{path}:{lines[bad[0]]}: the quaternion ({order}) has length {n[bad[0]]:.6g}, not 1; "
                         f"write unit quaternions")
    return q / n[:, None]
