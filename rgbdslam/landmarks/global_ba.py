"""Global bundle adjustment over every keyframe and its landmarks, after the pose graph (issue 17).

ORB-SLAM runs one after a loop closure; here it runs once, in ``SLAM.finish``, after the final
pose-graph optimisation has corrected the keyframes and the landmarks have moved with their
anchor keyframes. Variables: every keyframe pose, every live landmark with >= 2 observations.
Factors: each keyframe observation as in local BA (:class:`rgbdslam.landmarks.local_ba.StereoFactors`:
depth as a virtual disparity, correlated covariance, Huber); the pose graph's loop edges as
``BetweenFactorPose3`` with their information and a Huber kernel, so a loop correction is kept
where the two sides of the loop share no landmark; the odometry edges of keyframes that see fewer
than ``ba_min_observations`` of the optimised landmarks (they would be barely constrained; with
``global_ba_odometry`` every odometry edge, which carries the frames between keyframes); with
``global_ba_frames`` the map inliers of the frames between keyframes too, each a factor on its
keyframe's pose through the frame's pose relative to it (``body_P_sensor``, held); the
first keyframe held fixed (gauge). No landmark prior: the keyframes' observations are the data.
Levenberg–Marquardt, ``global_ba_iterations``. Returns the refined keyframe poses; the landmark
positions are written into the map. Keyframes in no factor keep their pose-graph pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import gtsam
from rgbdslam.config import LandmarksConfig
from rgbdslam.geometry.camera import Camera
from rgbdslam.landmarks.local_ba import StereoFactors, X, L, solve


@dataclass
class GlobalBAResult:
    poses: dict[int, np.ndarray]  # refined keyframe poses (every keyframe that had a factor)
    landmarks: int = 0
    observations: int = 0
    between: int = 0  # loop + odometry relative-pose factors
    error: tuple[float, float] = (0.0, 0.0)  # graph error before, after


def _between(graph, i: int, j: int, T_ij: np.ndarray, info: np.ndarray, huber) -> None:
    info = 0.5 * (np.asarray(info, float) + np.asarray(info, float).T)
    nm = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Gaussian.Information(info))
    graph.add(gtsam.BetweenFactorPose3(X(i), X(j), gtsam.Pose3(np.asarray(T_ij, float)), nm))


def global_bundle_adjustment(cfg: LandmarksConfig, camera: Camera, lmap, keyframes: list,
                             poses: dict[int, np.ndarray], loops=(), odometry=()) -> GlobalBAResult | None:
    """One BA over ``keyframes`` (observations: ``index``, ``lm``, ``uv``, ``z``) at ``poses``
    (keyframe -> camera-to-world, the pose graph's), with ``loops`` / ``odometry`` as
    ``(i, j, T_ij, information)`` relative-pose edges. None when there is nothing to optimise or
    the solve fails (the caller keeps the pose graph's poses)."""
    kfs = [k for k in keyframes if k.index in poses and len(k.lm)]
    if len(kfs) < 2:
        return None
    alive = [k.lm[lmap.alive[k.lm]] for k in kfs] + [f[1][lmap.alive[f[1]]] for k in kfs for f in k.frames]
    counts = np.bincount(np.concatenate(alive), minlength=lmap.n) if any(len(a) for a in alive) else np.zeros(lmap.n)
    use = np.flatnonzero(counts >= 2)
    if len(use) < 10:
        return None
    in_use = np.zeros(lmap.n, bool)
    in_use[use] = True
    graph = gtsam.NonlinearFactorGraph()
    factors = StereoFactors(cfg, camera)
    n_obs, used = 0, set()
    weak = set()
    for k in kfs:
        sel = in_use[k.lm]
        if sel.sum() < cfg.ba_min_observations:
            weak.add(k.index)
        if sel.any():
            n_obs += factors.add(graph, k.index, k.lm[sel], k.uv[sel], k.z[sel])
            used.add(k.index)
        for body, lm, uv, z in k.frames:  # the frames hanging from it (global_ba_frames)
            f = in_use[lm]
            if f.any():
                n_obs += factors.add(graph, k.index, lm[f], uv[f], z[f], body)
                used.add(k.index)
    huber = gtsam.noiseModel.mEstimator.Huber.Create(cfg.ba_huber)
    n_between = 0
    for i, j, T_ij, info in loops:
        if i in poses and j in poses:
            _between(graph, i, j, T_ij, info, huber)
            used |= {i, j}
            n_between += 1
    for i, j, T_ij, info in odometry:  # where the landmarks alone would leave a keyframe loose (or all)
        if (cfg.global_ba_odometry or i in weak or j in weak) and i in poses and j in poses:
            _between(graph, i, j, T_ij, info, huber)
            used |= {i, j}
            n_between += 1
    values = gtsam.Values()
    for k in used:
        values.insert(X(k), gtsam.Pose3(poses[k]))
    first = min(used)
    graph.add(gtsam.NonlinearEqualityPose3(X(first), gtsam.Pose3(poses[first])))
    for i in use:
        values.insert(L(i), lmap.pos[i].astype(np.float64))
    result = solve(graph, values, sorted(used), cfg.global_ba_iterations)
    if result is None:
        return None
    out = {k: result.atPose3(X(k)).matrix() for k in used}
    for i in use:
        lmap.pos[i] = result.atPoint3(L(i))
    return GlobalBAResult(out, len(use), n_obs, n_between, (graph.error(values), graph.error(result)))
