"""Relative pose error (RPE) with a fixed delta, after TUM's ``evaluate_rpe.py --fixed_delta``.

For every pair ``(i, j)`` of associated poses a delta apart the error is
``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` (Q ground truth, P estimate; Sturm et al. 2012, the
same product evo uses); the translational error is ``||t(E)||`` in metres and the rotational
error the angle of ``R(E)`` in degrees. All pairs are used (TUM samples at most
``param_max_pairs`` at random; evo's default uses consecutive, non-overlapping pairs).

Delta units (``delta_unit``):
  ``f``   frames of the associated sequence: ``j = i + delta``;
  ``s``   seconds: ``j`` is the first associated pose with ``t_j >= t_i + delta`` (estimate's
          stamps; with ``delta=1`` the result is drift per second);
  ``m``   metres travelled along the ground truth: first ``j`` with ``d_j >= d_i + delta``;
  ``rad`` / ``deg`` rotation accumulated along the ground truth, likewise.
A pose with no such ``j`` starts no pair.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rgbdslam.errors import InputError
from rgbdslam.evaluation.ate import ErrorStats, associate_trajectories
from rgbdslam.geometry.se3 import inv
from rgbdslam.io.trajectory import Trajectory

DELTA_UNITS = ("f", "s", "m", "rad", "deg")


@dataclass
class RpeResult:
    """RPE statistics: ``trans`` in metres, ``rot`` in degrees, per pair arrays."""

    trans: ErrorStats
    rot: ErrorStats
    n_pairs: int
    delta: float
    delta_unit: str
    trans_errors: np.ndarray  # (M,) metres
    rot_errors: np.ndarray  # (M,) degrees
    timestamps: np.ndarray  # (M,) estimate stamp of each pair's first pose
    pairs: np.ndarray  # (M, 2) indices into the associated sequence


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle (rad) of rotation matrices (..., 3, 3); atan2 form, accurate near 0 and pi."""
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    return np.arctan2(np.linalg.norm(w, axis=-1) / 2.0, c)


def check_delta(delta: float, delta_unit: str) -> None:
    """InputError unless ``delta`` is a finite positive number (whole for frames) and the unit known."""
    if delta_unit not in DELTA_UNITS:
        raise InputError(f"unknown RPE delta unit {delta_unit!r}; use one of {', '.join(DELTA_UNITS)}")
    if isinstance(delta, bool) or not isinstance(delta, (int, float, np.integer, np.floating)) \
            or not math.isfinite(delta) or not delta > 0:
        raise InputError(f"RPE delta must be a finite positive number, got {delta}; pass e.g. --delta 1")
    if delta_unit == "f" and not float(delta).is_integer():
        raise InputError(f"a delta in frames must be a whole number, got {delta}")


def delta_pairs(stamps: np.ndarray, gt_poses: np.ndarray, delta: float, delta_unit: str) -> np.ndarray:
    """Index pairs ``(i, j)`` a fixed ``delta`` apart along an associated sequence; (M, 2) ints."""
    check_delta(delta, delta_unit)
    n = len(stamps)
    i = np.arange(n)
    if delta_unit == "f":
        j = i + min(int(delta), n)  # a delta longer than the sequence gives no pair (and no overflow)
    else:
        if delta_unit == "s":
            axis = np.asarray(stamps, dtype=np.float64)
        elif delta_unit == "m":
            steps = np.linalg.norm(np.diff(gt_poses[:, :3, 3], axis=0), axis=1)
            axis = np.concatenate([[0.0], np.cumsum(steps)])
        else:
            rel = np.swapaxes(gt_poses[:-1, :3, :3], -1, -2) @ gt_poses[1:, :3, :3]
            steps = rotation_angle(rel)
            if delta_unit == "deg":
                steps = np.degrees(steps)
            axis = np.concatenate([[0.0], np.cumsum(steps)])
        # For 's' the axis is increasing (sorted stamps); path/angle axes are non-decreasing.
        # ``j > i`` is enforced so a zero-length step never pairs a pose with itself.
        j = np.maximum(np.searchsorted(axis, axis + delta, side="left"), i + 1)
    keep = j < n
    return np.stack([i[keep], j[keep]], axis=1).astype(np.int64)


def relative_errors(gt_poses: np.ndarray, est_poses: np.ndarray, pairs: np.ndarray, scale: float = 1.0):
    """Per pair ``(trans m, rot deg)`` of ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``."""
    i, j = pairs[:, 0], pairs[:, 1]
    q_rel = inv(gt_poses[i]) @ gt_poses[j]
    p_rel = inv(est_poses[i]) @ est_poses[j]
    if scale != 1.0:
        p_rel = p_rel.copy()
        p_rel[:, :3, 3] *= scale
    E = inv(q_rel) @ p_rel
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rot = np.degrees(rotation_angle(E[:, :3, :3]))
    return trans, rot


def rpe(
    gt: Trajectory,
    est: Trajectory,
    delta: float = 1.0,
    delta_unit: str = "f",
    max_difference: float = 0.02,
    offset: float = 0.0,
    scale: float = 1.0,
) -> RpeResult:
    """Relative pose error of ``est`` against ``gt`` over all pairs a fixed ``delta`` apart.

    Poses are first associated one-to-one by timestamp (as for ATE); ``scale`` multiplies the
    estimate's relative translations (TUM's ``--scale``). Raises InputError when no timestamps
    associate or no pair fits inside the associated span.
    """
    g, e = associate_trajectories(gt, est, max_difference, offset)
    pairs = delta_pairs(e.timestamps, g.poses, delta, delta_unit)
    if len(pairs) == 0:
        raise InputError(
            f"no RPE pairs {delta} {delta_unit} apart among the {len(g)} associated poses; "
            f"use a smaller --delta"
        )
    trans, rot = relative_errors(g.poses, e.poses, pairs, scale)
    return RpeResult(
        trans=ErrorStats.of(trans), rot=ErrorStats.of(rot), n_pairs=len(pairs), delta=float(delta),
        delta_unit=delta_unit, trans_errors=trans, rot_errors=rot,
        timestamps=e.timestamps[pairs[:, 0]].copy(), pairs=pairs,
    )
