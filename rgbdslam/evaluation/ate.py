"""Absolute trajectory error (ATE), as in TUM's ``evaluate_ate.py``.

The estimate's positions are associated with the ground truth by timestamp
(:func:`rgbdslam.evaluation.associate.associate`), aligned onto the ground truth
(Horn/Umeyama closed form; rigid, similarity or none) and the per-pose position error
``|| gt_i - (s R est_i + t) ||`` is summarised.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rgbdslam.errors import InputError
from rgbdslam.evaluation.associate import associate
from rgbdslam.io.trajectory import Trajectory

ALIGN_MODES = ("se3", "sim3", "none")
_NAMES = {"se3": "SE(3)", "sim3": "Sim(3)"}
MIN_ALIGN_PAIRS = 3  # an SE(3)/Sim(3) fit to fewer pose pairs is exact by construction: ATE 0
STATIC_SPREAD = 1e-6  # metres: positions within this of their mean do not move (no scale to fit)


class PairingError(InputError):
    """The two trajectories cannot be paired or aligned; :func:`rgbdslam.evaluation.report.evaluate_files`
    prefixes the message with both file names."""


@dataclass
class ErrorStats:
    """Summary statistics of a vector of non-negative errors."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float

    @classmethod
    def of(cls, errors: np.ndarray) -> "ErrorStats":
        e = np.asarray(errors, dtype=np.float64)
        if e.size == 0:
            nan = float("nan")
            return cls(nan, nan, nan, nan, nan, nan)
        return cls(
            rmse=float(np.sqrt(np.mean(e * e))),
            mean=float(np.mean(e)),
            median=float(np.median(e)),
            std=float(np.std(e)),
            min=float(np.min(e)),
            max=float(np.max(e)),
        )


@dataclass
class AteResult(ErrorStats):
    """ATE of one estimate against ground truth (distances in metres).

    The statistics fields (rmse, mean, median, std, min, max) are inherited from ErrorStats.
    """

    n_pairs: int
    errors: np.ndarray  # (N,) position error per associated pose
    timestamps: np.ndarray  # (N,) ground-truth stamps of the associated poses
    gt: Trajectory  # associated ground-truth poses
    aligned: Trajectory  # associated estimate poses after alignment (estimate's own stamps)
    transform: np.ndarray  # 4x4 [R t; 0 1] applied to the estimate (scale not included)
    scale: float
    align: str = "se3"


def umeyama_alignment(model: np.ndarray, data: np.ndarray, mode: str = "se3") -> tuple[np.ndarray, np.ndarray, float]:
    """Closed-form alignment of ``model`` onto ``data`` (both (3, N)): ``data ~ s R model + t``.

    ``mode``: ``'se3'`` rigid (Horn 1987 / Umeyama 1991 without scale, like TUM's
    ``evaluate_ate.py``), ``'sim3'`` with Umeyama's scale, ``'none'`` identity.
    Returns ``(R (3,3), t (3,), s)``.
    """
    if mode not in ALIGN_MODES:
        raise InputError(f"unknown alignment {mode!r}; use one of {', '.join(ALIGN_MODES)}")
    model = np.asarray(model, dtype=np.float64).reshape(3, -1)
    data = np.asarray(data, dtype=np.float64).reshape(3, -1)
    if model.shape != data.shape:
        raise ValueError(f"model {model.shape} and data {data.shape} differ in shape")
    if mode == "none":
        return np.eye(3), np.zeros(3), 1.0
    n = model.shape[1]
    if n == 0:
        raise PairingError("cannot align an empty trajectory; check that the timestamps overlap")
    if n < MIN_ALIGN_PAIRS:
        raise PairingError(
            f"only {n} pose pair{'s' if n != 1 else ''} matched in time, but {_NAMES[mode]} alignment needs at least "
            f"{MIN_ALIGN_PAIRS} (it would fit fewer almost exactly, so the ATE would mean nothing); check that both "
            f"files are of the same sequence, raise --max-difference, or use --align none"
        )
    # With collinear (or identical) ground-truth positions the rotation about the line is not
    # unique; the SVD returns one that attains the minimum, and the per-pose errors (the ATE)
    # are the same for all of them, so rigid alignment stays valid. A scale is not: see below.
    mu_m = model.mean(axis=1, keepdims=True)
    mu_d = data.mean(axis=1, keepdims=True)
    mc = model - mu_m
    dc = data - mu_d
    cov = dc @ mc.T / n  # Sigma_dm (Umeyama eq. 38)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = 1.0
    if mode == "sim3":
        var_m = float(np.mean(np.sum(mc * mc, axis=0)))
        var_d = float(np.mean(np.sum(dc * dc, axis=0)))
        if var_d <= STATIC_SPREAD**2:
            raise PairingError(
                f"the ground truth does not move (the spread of its {n} matched positions is below "
                f"{STATIC_SPREAD:g} m), so the Sim(3) scale is undefined (it would come out as 0); use --align se3"
            )
        if var_m <= STATIC_SPREAD**2:
            raise PairingError("the estimate does not move, so its scale cannot be aligned; use --align se3")
        s = float(np.trace(np.diag(D) @ S) / var_m)
        if not np.isfinite(s) or s <= 1e-9:
            raise PairingError(
                f"the Sim(3) scale came out as {s:.3g}: the estimate's motion does not correspond to the ground "
                f"truth's at all; check the files, or use --align se3"
            )
    t = (mu_d - s * R @ mu_m).reshape(3)
    return R, t, s


def apply_alignment(traj: Trajectory, R: np.ndarray, t: np.ndarray, s: float = 1.0) -> Trajectory:
    """Left-multiply every pose by the similarity ``(s, R, t)``: rotations R R_i, positions s R p_i + t."""
    poses = traj.poses.copy()
    poses[:, :3, :3] = R @ traj.poses[:, :3, :3]
    poses[:, :3, 3] = s * traj.positions @ R.T + t
    return Trajectory(traj.timestamps.copy(), poses)


def associate_trajectories(
    gt: Trajectory, est: Trajectory, max_difference: float = 0.02, offset: float = 0.0
) -> tuple[Trajectory, Trajectory]:
    """The associated sub-trajectories (same length, sorted by time); InputError if none overlap,
    if the estimate has two poses at one time stamp (which one to use is ambiguous) or if
    ``max_difference`` / ``offset`` are not sane numbers."""
    if not (math.isfinite(max_difference) and max_difference > 0):
        raise InputError(f"--max-difference must be a positive number of seconds (e.g. 0.02); got {max_difference}")
    if not math.isfinite(offset):
        raise InputError(f"--offset must be a finite number of seconds; got {offset}")
    check_unique_stamps(est, "the estimate")
    ia, ib = associate(gt.timestamps, est.timestamps, max_difference, offset)
    if len(ia) == 0:
        raise PairingError(
            f"no overlapping timestamps between ground truth ({len(gt)} poses, "
            f"{_span(gt)}) and estimate ({len(est)} poses, {_span(est)}) within "
            f"max_difference={max_difference} s, offset={offset} s; check that both files are of the "
            f"same sequence, or raise --max-difference / set --offset"
        )
    return gt.subset(ia), est.subset(ib)


def check_unique_stamps(traj: Trajectory, name: str) -> None:
    """InputError when ``traj`` (sorted by time, as read_tum returns it) has repeated time stamps:
    an estimate must have one pose per time; which of two would be evaluated is arbitrary."""
    ts = np.sort(traj.timestamps)
    dup = np.flatnonzero(np.diff(ts) == 0)
    if len(dup):
        more = f" (and {len(dup) - 1} more repeat{'s' if len(dup) > 2 else ''})" if len(dup) > 1 else ""
        raise PairingError(
            f"{name} has more than one pose at time stamp {ts[dup[0]]:.6f}{more}; an estimate needs one pose per "
            f"time stamp: remove the duplicate lines"
        )


def _span(traj: Trajectory) -> str:
    if len(traj) == 0:
        return "empty"
    return f"{traj.timestamps[0]:.3f}..{traj.timestamps[-1]:.3f}"


def ate(
    gt: Trajectory,
    est: Trajectory,
    max_difference: float = 0.02,
    offset: float = 0.0,
    align: str = "se3",
) -> AteResult:
    """Absolute trajectory error of ``est`` against ``gt`` (TUM ``evaluate_ate.py`` semantics).

    ``offset`` is added to the estimate's stamps for association; ``align`` is ``se3``,
    ``sim3`` or ``none``. Raises InputError when no timestamps associate, when SE(3)/Sim(3)
    alignment has fewer than 3 pairs, or when the Sim(3) scale is undefined (a static ground
    truth).
    """
    mode = align
    g, e = associate_trajectories(gt, est, max_difference, offset)
    R, t, s = umeyama_alignment(e.positions.T, g.positions.T, mode)
    aligned = apply_alignment(e, R, t, s)
    errors = np.linalg.norm(g.positions - aligned.positions, axis=1)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return AteResult(
        **vars(ErrorStats.of(errors)), n_pairs=len(errors), errors=errors, timestamps=g.timestamps.copy(), gt=g, aligned=aligned,
        transform=T, scale=s, align=mode,
    )

