"""Windowed local bundle adjustment over the landmark map (beyond the sources).

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

from dataclasses import dataclass

import numpy as np

import gtsam
from rgbdslam.geometry.camera import Camera
from rgbdslam.landmarks.config import LandmarksConfig
from rgbdslam.landmarks.kalman import observation_covariance
from rgbdslam.landmarks.tracking import match_to_map

X = lambda i: gtsam.symbol("x", int(i))  # noqa: E731
L = lambda i: gtsam.symbol("l", int(i))  # noqa: E731


class StereoFactors:
    """The observation factors of local and global BA: one ``GenericStereoFactor3D`` per (keyframe,
    landmark) observation, depth as a virtual disparity, the correlated covariance of the module
    doc, Huber. The noise models are shared between observations whose disparity noise agrees
    within 1 % (one model per log-spaced bin): building a Gaussian model per factor costs more than the factor."""

    def __init__(self, cfg: LandmarksConfig, camera: Camera):
        self.cfg = cfg
        self.camera = camera
        self.fb = camera.fx * cfg.ba_baseline
        self.K = gtsam.Cal3_S2Stereo(camera.fx, camera.fy, 0.0, camera.cx, camera.cy, cfg.ba_baseline)
        self.huber = gtsam.noiseModel.mEstimator.Huber.Create(cfg.ba_huber)
        self._models: dict[int, object] = {}

    @staticmethod
    def binned(sd: np.ndarray) -> np.ndarray:
        """The disparity noise each observation's shared model has: ``sd`` rounded to a power of 1.01."""
        return 1.01 ** np.round(np.log(np.maximum(sd, 1e-6)) / np.log(1.01))

    def disparity_sigma(self, z: np.ndarray) -> np.ndarray:
        """Disparity noise (px) of depth ``z`` (m): f b σ_z / z², σ_z = a + b_z z² (unbinned)."""
        c = self.cfg
        return self.fb * (c.depth_noise_a + c.depth_noise_b * z * z) / (z * z)

    def _model(self, sd: float, spx: float):
        b = int(np.round(np.log(max(sd, 1e-6)) / np.log(1.01)))
        m = self._models.get((b, spx))
        if m is None:
            s2, sd = spx ** 2, 1.01 ** b
            # u_right = u_left - d: it carries u_left's pixel noise (correlated) plus the disparity's
            C = np.array([[s2, s2, 0.0], [s2, s2 + sd * sd, 0.0], [0.0, 0.0, s2]])
            m = self._models[(b, spx)] = gtsam.noiseModel.Robust.Create(self.huber,
                                                                        gtsam.noiseModel.Gaussian.Covariance(C))
        return m

    def add(self, graph, kf: int, lm: np.ndarray, uv: np.ndarray, z: np.ndarray, body=None,
            scale: tuple[float, float] = (1.0, 1.0)) -> int:
        """Factors of keyframe ``kf`` seeing landmarks ``lm`` at pixels ``uv`` with depth ``z``;
        ``body`` (4x4): the observing camera's pose relative to the keyframe (a frame hanging from it);
        ``scale``: the keyframe's (pixel, disparity) noise scale (:func:`noise_scales`)."""
        sd = self.disparity_sigma(z) * scale[1]
        spx = float(self.cfg.sigma_px * scale[0])
        extra = (False, False) if body is None else (False, False, gtsam.Pose3(body))
        for j in range(len(lm)):
            meas = gtsam.StereoPoint2(uv[j, 0], uv[j, 0] - self.fb / z[j], uv[j, 1])
            graph.add(gtsam.GenericStereoFactor3D(meas, self._model(sd[j], spx), X(kf), L(lm[j]), self.K, *extra))
        return len(lm)


NOISE_SCALE_CLIP = (0.25, 4.0)  # the range of a keyframe's noise scale (as the map pose's adaptive_noise)


def noise_scales(cfg: LandmarksConfig, factors: StereoFactors, p) -> dict:
    """Each keyframe's own noise level in the problem ``p``: {keyframe: (k_px, k_d)}, the robust scale
    (1.4826 · median |r|, clipped to ``NOISE_SCALE_CLIP``) of its observations' whitened pixel and
    disparity residuals at the start — what the map pose's ``adaptive_noise`` measures per frame, so the
    BA weighs a blurred keyframe's key points as the tracking did (``ba_adaptive_noise``; all 1 without)."""
    if not cfg.ba_adaptive_noise:
        return {o[0]: (1.0, 1.0) for o in p.obs}
    cam, lm_of = factors.camera, {int(i): j for j, i in enumerate(p.use)}
    out = {}
    for kf, lm, uv, z in p.obs:
        P = p.poses[kf]
        Pc = (p.pos[[lm_of[int(i)] for i in lm]] - P[:3, 3]) @ P[:3, :3]
        zc = np.maximum(Pc[:, 2], 1e-6)
        e_px = np.concatenate([cam.fx * Pc[:, 0] / zc + cam.cx - uv[:, 0], cam.fy * Pc[:, 1] / zc + cam.cy - uv[:, 1]])
        e_d = (factors.fb / z - factors.fb / zc) / factors.disparity_sigma(z)
        k = [1.4826 * np.median(np.abs(e_px)) / cfg.sigma_px, 1.4826 * np.median(np.abs(e_d))]
        out[kf] = tuple(float(np.clip(v, *NOISE_SCALE_CLIP)) for v in k)
    return out


SEARCH_GATE = 14.16  # χ² (3 dof) of a searched observation against its landmark: 99.73 %, a 3σ gate


def keyframe_search(cfg: LandmarksConfig, lmap, feats, pose: np.ndarray, camera: Camera,
                    allowed: np.ndarray | None, have_feat: np.ndarray, have_lm: np.ndarray):
    """Every landmark of the local map (``allowed``: a mask over landmark ids, None = every one) that the
    keyframe ``feats`` sees at its ``pose``, beyond the observations it has (features ``have_feat`` of
    landmarks ``have_lm``): projected, matched by descriptor within ``search_radius`` px under
    ``max_hamming`` (:func:`~rgbdslam.landmarks.tracking.match_to_map`, as tracking), kept where the
    feature's world point agrees with the landmark within the χ² gate ``SEARCH_GATE`` of the
    observation's and the landmark's covariances together. Returns (feature indices, landmark ids)."""
    none = np.zeros(0, np.int64), np.zeros(0, np.int64)
    if lmap.size == 0:
        return none
    m = match_to_map(lmap, feats, pose, camera, cfg.search_radius, cfg.max_hamming, cfg.max_depth, allowed=allowed)
    if not len(m.lm):
        return none
    taken_lm = np.zeros(lmap.n, bool)
    taken_lm[have_lm] = True
    taken_f = np.zeros(len(feats.valid), bool)
    taken_f[have_feat] = True
    ok = ~taken_lm[m.lm] & ~taken_f[m.feat]
    f, lm = m.feat[ok].astype(np.int64), m.lm[ok].astype(np.int64)
    if not len(f):
        return none
    P = feats.pts[f]
    d = P @ pose[:3, :3].T + pose[:3, 3] - lmap.pos[lm]
    S = observation_covariance(P, pose[:3, :3], camera.fx, cfg.sigma_px, cfg.depth_noise_a, cfg.depth_noise_b) + \
        lmap.cov[lm]
    chi2 = np.einsum("ni,ni->n", d, np.linalg.solve(S, d[:, :, None])[..., 0])
    keep = chi2 <= SEARCH_GATE
    return f[keep], lm[keep]


RELATIVE_ERROR_TOL = 1e-4  # LM stops when an iteration lowers the error by less than this share


def solve(graph, values, pose_ids, iterations: int):
    """Levenberg–Marquardt with the landmarks eliminated first and the poses last (the Schur
    complement of BA: ~10x faster than plain COLAMD); None when the system is indeterminate."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    params.setRelativeErrorTol(RELATIVE_ERROR_TOL)
    poses = gtsam.KeyVector([X(kf) for kf in pose_ids])
    params.setOrdering(gtsam.Ordering.ColamdConstrainedLastNonlinearFactorGraph(graph, poses))
    try:
        return gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except RuntimeError:
        return None


@dataclass
class BAProblem:
    """One local BA, as plain arrays (built on the tracking thread, solved anywhere: it pickles)."""

    obs: list  # (keyframe, landmark ids, uv (n,2), z (n,)): the observations of the optimised landmarks
    use: np.ndarray  # (L,) the optimised landmark ids
    pos: np.ndarray  # (L, 3) their positions when the problem was made (the snapshot)
    cov: np.ndarray  # (L, 3, 3) their Kalman covariances (the prior)
    poses: dict  # {keyframe: 4x4} every keyframe in the graph, at its pose then
    fixed: set  # keyframes held
    window: set  # the window's keyframes (the ones that may move)


@dataclass
class BAResult:
    poses: dict  # {keyframe: refined pose} of the window's moved keyframes (empty: dropped)
    use: np.ndarray  # the optimised landmark ids
    before: np.ndarray  # (L, 3) their positions in the problem
    after: np.ndarray  # (L, 3) their refined positions
    error: tuple  # graph error before / after
    fixed: list  # the held keyframes
    rejected: bool = False  # a keyframe moved further than ba_max_move: nothing is written
    seconds: float = 0.0  # the solve's wall time (where it ran)


def make_problem(cfg: LandmarksConfig, lmap, keyframes: list, kf_pose: dict[int, np.ndarray]) -> BAProblem | None:
    """The local BA over the last ``ba_window`` keyframes of ``keyframes`` (module doc): which
    landmarks, which observations, which keyframes are held; None when there is nothing to optimise."""
    c = cfg
    if len(keyframes) < 2:
        return None
    window = keyframes[-c.ba_window:]
    older = keyframes[:-c.ba_window]
    win_ids = np.unique(np.concatenate([k.lm for k in window]))
    win_ids = win_ids[lmap.alive[win_ids]]
    if not len(win_ids):
        return None
    # observations: (keyframe, landmark id, u, v, z) of window + older keyframes on those landmarks
    in_win = np.zeros(lmap.n, bool)  # membership by lookup (ids < lmap.n): what np.isin gives, cheaper
    in_win[win_ids] = True
    obs = []
    for k in window + older:
        sel = in_win[k.lm]
        if sel.any():
            obs.append((k.index, k.lm[sel], k.uv[sel], k.z[sel]))
    counts = np.bincount(np.concatenate([o[1] for o in obs]), minlength=lmap.n)
    use = win_ids[counts[win_ids] >= 2]
    if len(use) > c.ba_max_landmarks:  # the best-observed ones (the cost is Python-side factor building)
        use = use[np.argsort(-counts[use], kind="stable")[: c.ba_max_landmarks]]
    if len(use) < 10:
        return None
    # a keyframe with few observations of the optimised landmarks is left out: it would be
    # barely constrained (on fr1/rpy such a keyframe swung by metres)
    in_use = np.zeros(lmap.n, bool)
    in_use[use] = True
    n_obs = {o[0]: int(in_use[o[1]].sum()) for o in obs}
    obs = [o for o in obs if n_obs[o[0]] >= c.ba_min_observations]
    win_idx = {k.index for k in window if n_obs.get(k.index, 0) >= c.ba_min_observations}
    fixed = {o[0] for o in obs if o[0] not in win_idx}
    if not fixed:
        fixed = {min(win_idx)} if win_idx else set()
    if len(win_idx - fixed) == 0:
        return None
    used = []
    for kf, lm, uv, z in obs:
        sel = in_use[lm]
        if sel.any():
            used.append((kf, lm[sel], uv[sel], z[sel]))
    poses_used = set()  # (in this order, as before the split: the factor graph's order is kept)
    for o in used:
        poses_used.add(o[0])
    poses = {kf: np.array(kf_pose[kf]) for kf in poses_used}
    return BAProblem(used, use, lmap.pos[use].astype(np.float64), lmap.cov[use].copy(), poses, fixed, win_idx)


def solve_problem(cfg: LandmarksConfig, factors: StereoFactors, p: BAProblem) -> BAResult | None:
    """Solve ``p`` (``ba_solver``: 'schur' = NumPy, :mod:`rgbdslam.landmarks.schur_ba`; 'gtsam' = the
    factor graph; the same LM, the same result to rounding); None when the system is indeterminate."""
    import time

    t0 = time.perf_counter()
    solved = (_solve_schur if cfg.ba_solver == "schur" else _solve_gtsam)(cfg, factors, p)
    if solved is None:  # an indeterminate system: keep the map as it is
        return None
    out, after, error = solved
    res = BAResult(out, p.use, p.pos, after, error, sorted(p.fixed & set(p.poses)),
                   seconds=time.perf_counter() - t0)
    for kf, P in out.items():  # a keyframe moved further than a tracking error: a bad solution, dropped
        d = np.linalg.inv(p.poses[kf]) @ P
        if np.linalg.norm(d[:3, 3]) > cfg.ba_max_move or \
                np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1))) > cfg.ba_max_move_deg:
            res.poses, res.rejected = {}, True
            break
    return res


def _prior_covariance(cfg: LandmarksConfig, C: np.ndarray) -> np.ndarray:
    """The landmark prior's covariance: the Kalman one plus ``ba_prior_floor`` in quadrature."""
    return C + (cfg.ba_prior_floor ** 2 + 1e-12) * np.eye(3)


def _solve_gtsam(cfg: LandmarksConfig, factors: StereoFactors, p: BAProblem):
    """GTSAM: (refined free poses {kf: 4x4}, refined landmarks (L, 3), (error before, after)) or None."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    scales = noise_scales(cfg, factors, p)
    for kf, lm, uv, z in p.obs:
        factors.add(graph, kf, lm, uv, z, scale=scales[kf])
    for kf, P in p.poses.items():
        values.insert(X(kf), gtsam.Pose3(P))
        if kf in p.fixed:
            graph.add(gtsam.NonlinearEqualityPose3(X(kf), gtsam.Pose3(P)))
    for i, x, C in zip(p.use, p.pos, p.cov):
        values.insert(L(i), x)
        if cfg.ba_landmark_prior:  # the Kalman estimate (every frame's observations, not only keyframes')
            graph.add(gtsam.PriorFactorPoint3(L(i), x, gtsam.noiseModel.Gaussian.Covariance(_prior_covariance(cfg, C))))
    result = solve(graph, values, sorted(p.poses), cfg.ba_iterations)
    if result is None:
        return None
    error = (graph.error(values), graph.error(result))
    out = {kf: result.atPose3(X(kf)).matrix() for kf in p.poses if kf in p.window and kf not in p.fixed}
    after = np.array([result.atPoint3(L(i)) for i in p.use]).reshape(-1, 3)
    return out, after, error


def schur_problem(cfg: LandmarksConfig, factors: StereoFactors, p: BAProblem):
    """``p`` as a :class:`~rgbdslam.landmarks.schur_ba.SchurBA` and the keyframe of each of its poses."""
    from rgbdslam.landmarks.schur_ba import SchurBA

    kfs = list(p.poses)
    pose_of = {kf: i for i, kf in enumerate(kfs)}
    lm_of = np.full(int(p.use.max()) + 1, -1, np.int64)
    lm_of[p.use] = np.arange(len(p.use))
    op = np.concatenate([np.full(len(o[1]), pose_of[o[0]], np.int64) for o in p.obs])
    ol = lm_of[np.concatenate([o[1] for o in p.obs])]
    uv = np.concatenate([o[2] for o in p.obs]).reshape(-1, 2)
    z = np.concatenate([o[3] for o in p.obs])
    meas = np.stack([uv[:, 0], uv[:, 1], z], axis=1).astype(float)
    scales = noise_scales(cfg, factors, p)
    k = np.concatenate([np.tile(scales[o[0]], (len(o[1]), 1)) for o in p.obs]).reshape(-1, 2)
    sd = factors.binned(factors.disparity_sigma(z) * k[:, 1])
    spx = cfg.sigma_px * k[:, 0]
    prior = np.linalg.inv(_prior_covariance(cfg, p.cov)) if cfg.ba_landmark_prior else None
    free = np.array([kf not in p.fixed for kf in kfs])
    cam = factors.camera
    ba = SchurBA(np.array([p.poses[kf] for kf in kfs]), free, op, ol, meas, sd, p.pos, prior,
                 cam.fx, cam.fy, cam.cx, cam.cy, factors.fb, spx, cfg.ba_huber)
    return ba, kfs


def _solve_schur(cfg: LandmarksConfig, factors: StereoFactors, p: BAProblem):
    """NumPy Schur-complement LM: the same (poses, landmarks, errors) as :func:`_solve_gtsam`."""
    ba, kfs = schur_problem(cfg, factors, p)
    poses, Xs, e0, e1, _ = ba.optimize(cfg.ba_iterations, RELATIVE_ERROR_TOL)
    out = {kf: poses[i] for i, kf in enumerate(kfs) if kf in p.window and kf not in p.fixed}
    return out, Xs, (e0, e1)


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
        p = make_problem(self.cfg, lmap, keyframes, kf_pose)
        if p is None:
            return {}
        return self.apply(lmap, solve_problem(self.cfg, self.factors, p))

    def apply(self, lmap, res: BAResult | None) -> dict[int, np.ndarray]:
        """Write a solved BA into ``lmap``: each landmark still alive moves by what the BA moved it
        (its position now + (refined − position in the problem): the Kalman updates since the problem
        was made are kept; exactly the refined position when there were none). Returns the refined poses."""
        if res is None:
            return {}
        self.last_error = res.error
        if res.rejected:
            self.rejected += 1
            return {}
        alive = lmap.alive[res.use]
        ids, before, after = res.use[alive], res.before[alive], res.after[alive]
        now = lmap.pos[ids]
        lmap.pos[ids] = np.where(now == before, after, now + (after - before))
        self.last_moved = sorted(res.poses)
        self.last_fixed = res.fixed
        self.last_landmarks = res.use
        return res.poses
