"""KITTI's odometry metric (Geiger et al. 2012, the devkit's ``evaluate_odometry``): relative
translation error (%) and rotation error (deg/m) over path segments, plus the end-point drift.

For every start frame (every ``step``-th) and every segment length L, the segment ends at the
first frame whose ground-truth path length from the start exceeds L; the error of the
segment's relative motion ``inv(inv(E_a) E_b) (inv(G_a) G_b)`` gives ``|t| / L`` and
``angle / L``; the results are the means over all segments of all lengths. No alignment is
needed (relative motions only). KITTI uses L = 100, 200, ..., 800 m and a step of 10 frames
(1 s); a sequence shorter than 100 m gets shorter segments (:data:`SHORT_LENGTHS`, those below
its path length) and step 1, and the result says so (``note``): numbers from shortened
segments are not comparable with KITTI's leaderboard.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rgbdslam.evaluation.ate import associate_trajectories
from rgbdslam.geometry.se3 import inv, rotation_angle
from rgbdslam.io.trajectory import Trajectory

KITTI_LENGTHS = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
SHORT_LENGTHS = (5.0, 10.0, 20.0, 30.0, 40.0, 50.0)


@dataclass
class KittiResult:
    t_err_pct: float  # mean translational error, % of segment length
    r_err_deg_per_m: float  # mean rotational error, degrees per metre
    n_segments: int
    lengths: list[float]
    step: int
    path_length: float  # ground-truth path length over the associated poses (m)
    end_drift_m: float  # |end position error| with both trajectories started at their first pose
    end_drift_pct: float  # end_drift_m / path_length * 100
    per_length: dict[str, dict[str, float]] = field(default_factory=dict)
    note: str | None = None

    def to_dict(self) -> dict:
        return {"t_err_pct": self.t_err_pct, "r_err_deg_per_m": self.r_err_deg_per_m,
                "r_err_deg_per_100m": self.r_err_deg_per_m * 100.0, "n_segments": self.n_segments,
                "lengths_m": self.lengths, "step_frames": self.step, "path_length_m": self.path_length,
                "end_drift_m": self.end_drift_m, "end_drift_pct": self.end_drift_pct,
                "per_length": self.per_length, "note": self.note}


def path_distances(poses: np.ndarray) -> np.ndarray:
    """Cumulative path length (N,) along camera-to-world poses."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def segment_errors(gt: np.ndarray, est: np.ndarray, lengths, step: int) -> list[tuple[float, float, float]]:
    """(length, t_err / length, r_err_rad / length) of every segment (devkit's calcSequenceErrors)."""
    dist = path_distances(gt)
    out = []
    for a in range(0, len(gt), step):
        for L in lengths:
            b = int(np.searchsorted(dist, dist[a] + L, side="right"))
            if b >= len(gt):
                continue
            dg = inv(gt[a]) @ gt[b]
            de = inv(est[a]) @ est[b]
            err = inv(de) @ dg
            out.append((L, float(np.linalg.norm(err[:3, 3])) / L, float(rotation_angle(err[:3, :3])) / L))
    return out


def kitti_metric(gt: Trajectory, est: Trajectory, max_difference: float = 0.02, offset: float = 0.0,
                 lengths=None, step: int | None = None) -> KittiResult | None:
    """KITTI's relative metric of ``est`` against ``gt`` (poses associated by time stamp); None
    when not even the shortest segment fits into the path."""
    g, e = associate_trajectories(gt, est, max_difference, offset)
    G, E = g.poses, e.poses
    if len(G) < 2:
        return None
    path = float(path_distances(G)[-1])
    note = None
    if lengths is None:
        if path > KITTI_LENGTHS[0]:
            lengths, step = KITTI_LENGTHS, step or 10
        else:
            lengths = tuple(L for L in SHORT_LENGTHS if L < path)
            step = step or 1
            note = (f"the path is {path:.1f} m, shorter than KITTI's shortest segment (100 m): segments of "
                    f"{', '.join(f'{L:g}' for L in lengths)} m from every frame instead (not comparable with KITTI's "
                    f"100-800 m numbers)")
    step = step or 10
    segs = segment_errors(G, E, lengths, step)
    if not segs:
        return None
    arr = np.array(segs)
    per = {}
    for L in sorted(set(arr[:, 0])):
        m = arr[:, 0] == L
        per[f"{L:g}"] = {"t_err_pct": float(arr[m, 1].mean() * 100.0),
                         "r_err_deg_per_m": float(np.degrees(arr[m, 2].mean())), "n": int(m.sum())}
    rel_g = inv(G[0]) @ G[-1]
    rel_e = inv(E[0]) @ E[-1]
    drift = float(np.linalg.norm(rel_g[:3, 3] - rel_e[:3, 3]))
    return KittiResult(float(arr[:, 1].mean() * 100.0), float(np.degrees(arr[:, 2].mean())), len(arr),
                       [float(L) for L in lengths], int(step), path, drift,
                       100.0 * drift / path if path > 0 else float("nan"), per, note)
