"""KITTI odometry files: poses (one row-major 3x4 camera-to-world matrix per line), times and
the ``calib.txt`` projection matrices.

``poses.txt`` has no time stamps: line k is frame k. :func:`write_kitti_poses` writes one line
per pose of a trajectory (the caller decides which frames are in it); ``times.txt`` beside it
keeps the time stamps when wanted.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rgbdslam.errors import InputError, shorten
from rgbdslam.io import validate
from rgbdslam.io.atomic import atomic_write_text
from rgbdslam.io.text import read_lines, require_file
from rgbdslam.io.trajectory import Trajectory


def _numbers(path: Path, lineno: int, text: str, n: int, what: str) -> list[float]:
    try:
        vals = [float(x) for x in text.split()]
    except ValueError:
        raise InputError(f"{path}:{lineno}: expected {n} numbers ({what}); got {shorten(text)}") from None
    if len(vals) != n or not np.isfinite(vals).all():
        raise InputError(f"{path}:{lineno}: expected {n} finite numbers ({what}); got {len(vals)}")
    return vals


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """Poses (N, 4, 4) from a KITTI pose file; errors name file and line."""
    path = require_file(path, "KITTI pose file")
    rows, lines = [], []
    for lineno, line in enumerate(read_lines(path, "KITTI pose file"), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        rows.append(_numbers(path, lineno, s, 12, "a row-major 3x4 camera-to-world matrix"))
        lines.append(lineno)
    if not rows:
        raise InputError(f"KITTI pose file {path} holds no poses; it needs one line of 12 numbers per frame")
    return validate.poses(np.array(rows).reshape(-1, 3, 4), str(path), lines)


def format_kitti_poses(poses: np.ndarray) -> str:
    P = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    return "".join(" ".join(f"{v:.9e}" for v in p[:3, :].ravel()) + "\n" for p in P)


def write_kitti_poses(traj: Trajectory | np.ndarray, path: str | Path) -> None:
    """Write poses (a Trajectory or an (N, 4, 4) array) in KITTI's format, atomically."""
    poses = traj.poses if isinstance(traj, Trajectory) else traj
    atomic_write_text(path, format_kitti_poses(poses))


def read_kitti_times(path: str | Path) -> np.ndarray:
    path = Path(path)
    out, lines = [], []
    for lineno, line in enumerate(read_lines(path, "KITTI times file"), 1):
        s = line.strip()
        if s and not s.startswith("#"):
            out.append(_numbers(path, lineno, s, 1, "seconds")[0])
            lines.append(lineno)
    return validate.stamps(out, str(path), lines)


def read_kitti_calib(path: str | Path) -> dict[str, np.ndarray]:
    """The ``NAME: v1 ... v12`` matrices of a KITTI ``calib.txt`` as 3x4 arrays."""
    path = require_file(path, "KITTI calibration", "the sequence folder needs calib.txt (P0: and P1: lines)")
    out = {}
    for lineno, line in enumerate(read_lines(path, "KITTI calibration"), 1):
        s = line.strip()
        if not s or ":" not in s:
            continue
        key, rest = s.split(":", 1)
        vals = rest.split()
        if len(vals) == 12:
            out[key.strip()] = np.array(_numbers(path, lineno, rest, 12, f"the 3x4 matrix {key}")).reshape(3, 4)
    return out


def format_kitti_calib(P0: np.ndarray, P1: np.ndarray) -> str:
    return "".join(f"{k}: " + " ".join(f"{v:.12e}" for v in np.asarray(P).ravel()) + "\n"
                   for k, P in (("P0", P0), ("P1", P1)))
