"""TUM trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line, '#' comments."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rgbdslam.io.text import read_lines, require_file
from rgbdslam.errors import InputError
from rgbdslam.geometry.se3 import pose_from_tum, pose_to_tum
from rgbdslam.io.atomic import atomic_write_text
from rgbdslam.io.numbers import MAX_COORD, check_magnitude, check_stamps, unit_quaternions


@dataclass
class Trajectory:
    """Timestamped camera-to-world poses: ``timestamps`` (N,), ``poses`` (N, 4, 4)."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.poses):
            raise ValueError("timestamps and poses differ in length")

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    def subset(self, idx: np.ndarray) -> "Trajectory":
        return Trajectory(self.timestamps[idx], self.poses[idx])


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory; malformed lines are reported with file and line number."""
    path = Path(path)
    require_file(path, "trajectory file")
    stamps, rows, linenos = [], [], []
    for lineno, line in enumerate(read_lines(path, "trajectory file"), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            raise InputError(
                f"{path}:{lineno}: expected 8 numbers 'timestamp tx ty tz qx qy qz qw'; got {s[:60]!r}"
            ) from None
        if len(vals) != 8:
            raise InputError(
                f"{path}:{lineno}: expected 8 numbers 'timestamp tx ty tz qx qy qz qw'; got {len(vals)}"
            )
        if not np.isfinite(vals).all():
            raise InputError(f"{path}:{lineno}: non-finite value; fix or delete the line")
        stamps.append(vals[0])
        rows.append(vals[1:8])
        linenos.append(lineno)
    if not rows:
        raise InputError(f"trajectory file {path} holds no poses; it must have lines 'timestamp tx ty tz qx qy qz qw'")
    a = np.array(rows)
    check_stamps(stamps, path, linenos)
    check_magnitude(a[:, :3], MAX_COORD, path, linenos, "position", "positions must be metres")
    a[:, 3:7] = unit_quaternions(a[:, 3:7], path, linenos)
    order = np.argsort(np.array(stamps), kind="stable")
    return Trajectory(np.array(stamps)[order], pose_from_tum(a[order, :3], a[order, 3:7]))


def format_tum(traj: Trajectory) -> str:
    if len(traj) == 0:
        return "# timestamp tx ty tz qx qy qz qw\n"
    t, q = pose_to_tum(traj.poses)
    # a value that prints as zero prints as "0.000000000", never "-0.000000000": the sign of a ~1e-17 rounding
    # residue is not kept by a read-back pose (its quaternion), so a file written again from one would differ
    t, q = (np.where(np.abs(a) < 5e-10, 0.0, a) for a in (t, q))
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for ts, p, r in zip(traj.timestamps, t, q):
        lines.append(
            f"{ts:.6f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {r[0]:.9f} {r[1]:.9f} {r[2]:.9f} {r[3]:.9f}"
        )
    return "\n".join(lines) + "\n"


def as_written(traj: Trajectory) -> Trajectory:
    """The trajectory as :func:`write_tum` writes it and :func:`read_tum` reads it back (9 decimals, unit
    quaternions): a run's trajectory files, its live map and its evaluation use these poses, so a later
    ``fuse`` or ``evaluate`` of the written files gives the same bytes (the map file keeps the pose graph's
    keyframe poses as optimised). Unlike :func:`read_tum` it neither checks nor sorts: the poses stay in the
    run's frame order, which the run's records index."""
    if len(traj) == 0:
        return traj
    rows = np.array([[float(x) for x in line.split()] for line in format_tum(traj).splitlines()[1:]])
    return Trajectory(rows[:, 0].copy(), pose_from_tum(rows[:, 1:4], unit_quaternions(rows[:, 4:8], "", [])))


def write_tum(traj: Trajectory, path: str | Path) -> None:
    """Write atomically: the file is either the old one or the complete new one."""
    atomic_write_text(path, format_tum(traj))
