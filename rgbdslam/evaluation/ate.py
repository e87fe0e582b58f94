"""Absolute trajectory error (ATE), as in TUM's ``evaluate_ate.py``.

The estimate's positions are associated with the ground truth by timestamp
(:func:`rgbdslam.evaluation.associate.associate`), aligned onto the ground truth
(Horn/Umeyama closed form; rigid, similarity or none) and the per-pose position error
``|| gt_i - (s R est_i + t) ||`` is summarised.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgbdslam.errors import InputError
from rgbdslam.evaluation.associate import associate
from rgbdslam.io.trajectory import Trajectory

ALIGN_MODES = ("se3", "sim3", "none")


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


def align(model: np.ndarray, data: np.ndarray, mode: str = "se3") -> tuple[np.ndarray, np.ndarray, float]:
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
        raise InputError("cannot align an empty trajectory; check that the timestamps overlap")
    # With fewer than 3 (non-collinear) points the rotation is not unique; the SVD still
    # returns a valid one that attains the minimum.
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
        if var_m <= 0:
            raise InputError("the estimate does not move, so its scale cannot be aligned; use --align se3")
        s = float(np.trace(np.diag(D) @ S) / var_m)
    t = (mu_d - s * R @ mu_m).reshape(3)
    return R, t, s


_align = align  # ``ate`` below has a parameter named ``align``


def apply_alignment(traj: Trajectory, R: np.ndarray, t: np.ndarray, s: float = 1.0) -> Trajectory:
    """Left-multiply every pose by the similarity ``(s, R, t)``: rotations R R_i, positions s R p_i + t."""
    poses = traj.poses.copy()
    poses[:, :3, :3] = R @ traj.poses[:, :3, :3]
    poses[:, :3, 3] = s * traj.positions @ R.T + t
    return Trajectory(traj.timestamps.copy(), poses)


def associate_trajectories(
    gt: Trajectory, est: Trajectory, max_difference: float = 0.02, offset: float = 0.0
) -> tuple[Trajectory, Trajectory]:
    """The associated sub-trajectories (same length, sorted by time); InputError if none overlap."""
    ia, ib = associate(gt.timestamps, est.timestamps, max_difference, offset)
    if len(ia) == 0:
        raise InputError(
            f"no overlapping timestamps between ground truth ({len(gt)} poses, "
            f"{_span(gt)}) and estimate ({len(est)} poses, {_span(est)}) within "
            f"max_difference={max_difference} s, offset={offset} s; check that both files are of the "
            f"same sequence, or raise --max-difference / set --offset"
        )
    return gt.subset(ia), est.subset(ib)


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
    ``sim3`` or ``none``. Raises InputError when no timestamps associate.
    """
    mode = align
    g, e = associate_trajectories(gt, est, max_difference, offset)
    R, t, s = _align(e.positions.T, g.positions.T, mode)
    aligned = apply_alignment(e, R, t, s)
    errors = np.linalg.norm(g.positions - aligned.positions, axis=1)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return AteResult(
        **vars(ErrorStats.of(errors)), n_pairs=len(errors), errors=errors, timestamps=g.timestamps.copy(), gt=g, aligned=aligned,
        transform=T, scale=s, align=mode,
    )

