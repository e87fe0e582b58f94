"""Windowed local bundle adjustment over the landmark map (issue 17, beyond the sources).

On each new keyframe: the last ``ba_window`` keyframes and every landmark they observe (seen by
at least two keyframes in the graph) are optimised; the older keyframes (among those kept) that
observe the same landmarks enter as fixed poses, which also fixes the gauge (with none, the
oldest keyframe of the window is held fixed). Each observation is a GTSAM
``GenericStereoFactor3D``: the RGB-D depth becomes a virtual disparity ``d = f b / z`` for a
virtual baseline ``b`` (as ORB-SLAM's RGB-D mode does), so the factor measures
``(u_left, u_left − d, v)``. Noise: σ_px on u and v; the right column carries the left one's
pixel noise (a full covariance, correlated) plus the disparity noise ``f b σ_z / z²`` with
σ_z = a + b_z z² (for a Kinect nearly a constant ``f b b_z``). Independent σ on both columns, as
for a real stereo pair, would make the depth ~15x weaker than the sensor's and let the window
slide along the rays. Huber kernel; Levenberg–Marquardt, ``ba_iterations`` iterations.
"""

from __future__ import annotations

import numpy as np

import gtsam
from rgbdslam.config import LandmarksConfig
from rgbdslam.geometry.camera import Camera

X = lambda i: gtsam.symbol("x", int(i))  # noqa: E731
L = lambda i: gtsam.symbol("l", int(i))  # noqa: E731


class StereoFactors:
    """The observation factors of local and global BA: one ``GenericStereoFactor3D`` per (keyframe,
    landmark) observation, depth as a virtual disparity, the correlated covariance of the module
    doc, Huber. The noise models are shared between observations whose disparity noise agrees
    within 1 % (one model per log-spaced bin): building a Gaussian model per factor costs more than the factor."""

    def __init__(self, cfg: LandmarksConfig, camera: Camera):
        self.cfg = cfg
        self.fb = camera.fx * cfg.ba_baseline
        self.K = gtsam.Cal3_S2Stereo(camera.fx, camera.fy, 0.0, camera.cx, camera.cy, cfg.ba_baseline)
        self.huber = gtsam.noiseModel.mEstimator.Huber.Create(cfg.ba_huber)
        self._models: dict[int, object] = {}

    def _model(self, sd: float):
        b = int(np.round(np.log(max(sd, 1e-6)) / np.log(1.01)))
        m = self._models.get(b)
        if m is None:
            s2, sd = self.cfg.sigma_px ** 2, 1.01 ** b
            # u_right = u_left - d: it carries u_left's pixel noise (correlated) plus the disparity's
            C = np.array([[s2, s2, 0.0], [s2, s2 + sd * sd, 0.0], [0.0, 0.0, s2]])
            m = self._models[b] = gtsam.noiseModel.Robust.Create(self.huber, gtsam.noiseModel.Gaussian.Covariance(C))
        return m

    def add(self, graph, kf: int, lm: np.ndarray, uv: np.ndarray, z: np.ndarray, body=None) -> int:
        """Factors of keyframe ``kf`` seeing landmarks ``lm`` at pixels ``uv`` with depth ``z``;
        ``body`` (4x4): the observing camera's pose relative to the keyframe (a frame hanging from it)."""
        c = self.cfg
        sz = c.depth_noise_a + c.depth_noise_b * z * z
        sd = self.fb * sz / (z * z)  # disparity noise (px)
        extra = (False, False) if body is None else (False, False, gtsam.Pose3(body))
        for j in range(len(lm)):
            meas = gtsam.StereoPoint2(uv[j, 0], uv[j, 0] - self.fb / z[j], uv[j, 1])
            graph.add(gtsam.GenericStereoFactor3D(meas, self._model(sd[j]), X(kf), L(lm[j]), self.K, *extra))
        return len(lm)


def solve(graph, values, pose_ids, iterations: int):
    """Levenberg–Marquardt with the landmarks eliminated first and the poses last (the Schur
    complement of BA: ~10x faster than plain COLAMD); None when the system is indeterminate."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    params.setRelativeErrorTol(1e-4)
    poses = gtsam.KeyVector([X(kf) for kf in pose_ids])
    params.setOrdering(gtsam.Ordering.ColamdConstrainedLastNonlinearFactorGraph(graph, poses))
    try:
        return gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except RuntimeError:
        return None


class LocalBA:
    def __init__(self, cfg: LandmarksConfig, camera: Camera):
        self.cfg = cfg
        self.camera = camera
        self.last_moved: list[int] = []
        self.last_fixed: list[int] = []  # the held keyframes of the last solve (diagnostics)
        self.last_landmarks = np.zeros(0, np.int64)  # the landmarks of the last solve (diagnostics)
        self.last_error: tuple[float, float] = (0.0, 0.0)
        self.rejected = 0  # solutions dropped (a keyframe moved more than ba_max_move)
        self.factors = StereoFactors(cfg, camera)

    def run(self, lmap, keyframes: list, kf_pose: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Optimise; writes landmark positions into ``lmap`` and returns ``{keyframe: refined pose}``
        for the window's keyframes (empty when there was nothing to optimise)."""
        c = self.cfg
        if len(keyframes) < 2:
            return {}
        window = keyframes[-c.ba_window:]
        older = keyframes[:-c.ba_window]
        win_ids = np.unique(np.concatenate([k.lm for k in window]))
        win_ids = win_ids[lmap.alive[win_ids]]
        if not len(win_ids):
            return {}
        # observations: (keyframe, landmark id, u, v, z) of window + older keyframes on those landmarks
        obs = []
        for k in window + older:
            sel = np.isin(k.lm, win_ids)
            if sel.any():
                obs.append((k.index, k.lm[sel], k.uv[sel], k.z[sel]))
        counts = np.bincount(np.concatenate([o[1] for o in obs]), minlength=lmap.n)
        use = win_ids[counts[win_ids] >= 2]
        if len(use) > c.ba_max_landmarks:  # the best-observed ones (the cost is Python-side factor building)
            use = use[np.argsort(-counts[use], kind="stable")[: c.ba_max_landmarks]]
        if len(use) < 10:
            return {}
        # a keyframe with few observations of the optimised landmarks is left out: it would be
        # barely constrained (on fr1/rpy such a keyframe swung by metres)
        n_obs = {o[0]: int(np.isin(o[1], use).sum()) for o in obs}
        obs = [o for o in obs if n_obs[o[0]] >= c.ba_min_observations]
        win_idx = {k.index for k in window if n_obs.get(k.index, 0) >= c.ba_min_observations}
        fixed = {o[0] for o in obs if o[0] not in win_idx}
        if not fixed:
            fixed = {min(win_idx)} if win_idx else set()
        if len(win_idx - fixed) == 0:
            return {}
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        poses_used = set()
        for kf, lm, uv, z in obs:
            sel = np.isin(lm, use)
            if not sel.any():
                continue
            poses_used.add(kf)
            self.factors.add(graph, kf, lm[sel], uv[sel], z[sel])
        for kf in poses_used:
            values.insert(X(kf), gtsam.Pose3(kf_pose[kf]))
            if kf in fixed:
                graph.add(gtsam.NonlinearEqualityPose3(X(kf), gtsam.Pose3(kf_pose[kf])))
        for i in use:
            values.insert(L(i), lmap.pos[i].astype(np.float64))
            if c.ba_landmark_prior:  # the Kalman estimate (every frame's observations, not only keyframes')
                graph.add(gtsam.PriorFactorPoint3(L(i), lmap.pos[i].astype(np.float64), gtsam.noiseModel.Gaussian.Covariance(
                    lmap.cov[i] + (c.ba_prior_floor ** 2 + 1e-12) * np.eye(3))))
        result = solve(graph, values, sorted(poses_used), c.ba_iterations)
        if result is None:  # an indeterminate system: keep the map as it is
            return {}
        self.last_error = (graph.error(values), graph.error(result))
        out = {kf: result.atPose3(X(kf)).matrix() for kf in poses_used if kf in win_idx and kf not in fixed}
        for kf, P in out.items():  # a keyframe moved further than a tracking error: a bad solution, dropped
            d = np.linalg.inv(kf_pose[kf]) @ P
            if np.linalg.norm(d[:3, 3]) > c.ba_max_move or \
                    np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1))) > c.ba_max_move_deg:
                self.rejected += 1
                return {}
        for i in use:
            lmap.pos[i] = result.atPoint3(L(i))
        self.last_moved = sorted(out)
        self.last_fixed = sorted(fixed & poses_used)
        self.last_landmarks = use
        return out
