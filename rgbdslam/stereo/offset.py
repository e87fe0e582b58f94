"""A stereo rig's disparity offset, measured from the sequence itself (no ground truth).

A disparity measured as ``d = d_true - delta`` (a calibration error of the principal points, a bias of
the sub-pixel refinement) puts every point at depth ``fx B / d`` instead of ``fx B / (d + delta)``:
the relative depth error ``delta / d`` grows with the distance, so near and far points disagree about
a rigid motion. (A wrong baseline or focal length scales every depth alike and is unobservable
without ground truth; an offset is not.)

:func:`fit_disparity_offset` fits, for frame pairs (i, j) at gaps 1..``max_gap``, one motion per pair
and ONE shared correction ``delta`` (added to every measured disparity) jointly: a frame-i key point
(u, v, d + delta) is triangulated, moved by the pair's motion and projected into frame j, where its
descriptor match measured (u, v, d + delta); the residuals are :mod:`rgbdslam.geometry.stereo_pose`'s
(the frame-j key point's octave pixel and the pair's disparity noise, the frame-i point's own
covariance carried into frame j). Gauss-Newton over [6 per pair + 1], the pairs' 6x6 blocks
eliminated (Schur complement on delta), in rounds like the pose refit: Huber at the chi-square gate
in the first two rounds, every residual re-classified by its chi-square (95 %, 3 dof) after each round.
The first motions and inliers come from PnP RANSAC at delta = 0.

:func:`estimate_disparity_offset` gathers the observations of a sequence (the product's ``detect`` +
``sparse_matches`` with the config's stereo settings, so a configured ``stereo.disparity_offset`` is
already applied and the result is what to add on top) and fits. ``rgbdslam calibrate stereo-offset``
prints it and writes it as ``stereo.disparity_offset``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from rgbdslam.geometry.stereo_pose import CHI2_STEREO, stereo_projection

MIN_PAIR_POINTS = 20  # PnP inliers a pair needs to take part
MAX_STEP = 0.1  # px: the largest change of delta per Gauss-Newton step


@dataclass
class StereoObservations:
    """One frame's sparse stereo key points: left pixel (N,2), disparity (N,) px, ORB octave (N,), descriptors."""

    uv: np.ndarray
    disparity: np.ndarray
    octave: np.ndarray
    desc: np.ndarray


@dataclass
class OffsetFit:
    """The fitted disparity correction ``delta`` (px, to add to every measured disparity), its standard
    error (px, from the Gauss-Newton information at the solution), the pairs and inlier residuals used."""

    delta: float
    se: float
    pairs: int
    inliers: int
    residuals: int

    @property
    def significant(self) -> bool:
        """Distinguishable from no offset: more than two standard errors from 0."""
        return abs(self.delta) > 2.0 * self.se


def observe(seq, cfg, frames) -> list[StereoObservations]:
    """The sparse stereo key points of ``frames`` of the stereo sequence ``seq`` (config ``cfg``)."""
    from rgbdslam.frontend.features import detect
    from rgbdslam.stereo.depth import sparse_matches

    out = []
    for i in frames:
        left, right = seq.rectified_pair(i)
        det = detect(left, cfg.features)
        m = sparse_matches(left, right, seq.rig, det.uv_raw, det.desc, cfg.stereo, cfg.features)
        k = m.left_index
        out.append(StereoObservations(det.uv_raw[k].astype(np.float64), m.disparity.astype(np.float64),
                                      det.octave[k].astype(np.float64), det.desc[k]))
    return out


def backproject(uv: np.ndarray, d: np.ndarray, intrinsics: tuple, baseline: float) -> np.ndarray:
    """Points (N,3) of left pixels ``uv`` at disparities ``d`` (px)."""
    fx, fy, cx, cy = intrinsics
    z = fx * baseline / d
    return np.column_stack([(uv[:, 0] - cx) * z / fx, (uv[:, 1] - cy) * z / fy, z])


def pair_matches(obs: list[StereoObservations], intrinsics: tuple, baseline: float, max_gap: int
                 ) -> list[tuple[int, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Descriptor matches (cross-checked) of frame pairs (i, i+g), g = 1..max_gap, with a first motion:
    (i, j, index in i, index in j, X = 4x4 pose of frame j in frame i's coordinates, the PnP inliers) from PnP
    RANSAC on frame i's points at the measured disparities (seeded); pairs with fewer than MIN_PAIR_POINTS inliers
    are left out."""
    fx, fy, cx, cy = intrinsics
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    out = []
    for g in range(1, max_gap + 1):
        for i in range(len(obs) - g):
            a, b = obs[i], obs[i + g]
            if len(a.desc) < MIN_PAIR_POINTS or len(b.desc) < MIN_PAIR_POINTS:
                continue
            ms = bf.match(a.desc, b.desc)
            ia = np.array([m.queryIdx for m in ms], int)
            ib = np.array([m.trainIdx for m in ms], int)
            if len(ia) < MIN_PAIR_POINTS:
                continue
            P = backproject(a.uv[ia], a.disparity[ia], intrinsics, baseline)
            cv2.setRNGSeed(0)
            ok, rvec, tvec, inl = cv2.solvePnPRansac(P, b.uv[ib], K, None, iterationsCount=200,
                                                     reprojectionError=2.0, confidence=0.999)
            if not ok or inl is None or len(inl) < MIN_PAIR_POINTS:
                continue
            T = np.eye(4)  # frame i -> frame j
            T[:3, :3] = cv2.Rodrigues(rvec)[0]
            T[:3, 3] = tvec.ravel()
            X = np.eye(4)
            X[:3, :3] = T[:3, :3].T
            X[:3, 3] = -T[:3, :3].T @ T[:3, 3]
            first = np.zeros(len(ia), bool)
            first[inl.ravel()] = True
            out.append((i, i + g, ia, ib, X, first))
    return out


def fit_disparity_offset(obs: list[StereoObservations], intrinsics: tuple, baseline: float, sigma_d: float,
                         sigma_pixel: float = 0.5, pyramid_scale: float = 1.2, max_gap: int = 5,
                         rounds: int = 4, iterations: int = 20, robust_rounds: int = 2) -> OffsetFit | None:
    """The joint fit of the module doc on the frames' observations ``obs``; None without any usable pair."""
    from rgbdslam.geometry.stereo import DepthNoise

    pairs = pair_matches(obs, intrinsics, baseline, max_gap)
    if not pairs:
        return None
    fx, fy, cx, cy = intrinsics
    noise = DepthNoise(fx, baseline, sigma_d, fy, cx, cy)
    pid = np.concatenate([np.full(len(p[2]), k) for k, p in enumerate(pairs)])
    uv_i = np.concatenate([obs[i].uv[ia] for i, _, ia, *_ in pairs])
    d_i = np.concatenate([obs[i].disparity[ia] for i, _, ia, *_ in pairs])
    s_i = np.concatenate([sigma_pixel * pyramid_scale ** obs[i].octave[ia] for i, _, ia, *_ in pairs])
    obs_j = np.concatenate([np.column_stack([obs[j].uv[ib], obs[j].disparity[ib]]) for _, j, _, ib, *_ in pairs])
    s_j = np.concatenate([sigma_pixel * pyramid_scale ** obs[j].octave[ib] for _, j, _, ib, *_ in pairs])
    Xs = np.stack([p[4] for p in pairs])
    n, npair = len(pid), len(pairs)
    S_meas = np.zeros((n, 3, 3))
    S_meas[:, 0, 0] = S_meas[:, 1, 1] = s_j ** 2
    S_meas[:, 2, 2] = sigma_d ** 2
    delta = 0.0
    inl = np.concatenate([p[5] for p in pairs])  # the first inliers: PnP's
    e3 = np.array([0.0, 0.0, 1.0])

    def model(Xs, delta):
        """Predicted (u, v, d) in frame j, dz/dxi (N,3,6), dz/dW (N,3,3), dW/ddelta (N,3), ahead, W."""
        dd = d_i + delta
        W = backproject(uv_i, np.maximum(dd, 1e-3), intrinsics, baseline)
        z = np.zeros((n, 3))
        J = np.zeros((n, 3, 6))
        Jw = np.zeros((n, 3, 3))
        ahead = np.zeros(n, bool)
        for k in range(npair):  # one projection per pair (vectorised over its points)
            s = pid == k
            z[s], J[s], Jw[s], ahead[s] = stereo_projection(Xs[k], W[s], intrinsics, baseline)
        ahead &= dd > 1e-3
        return z, J, Jw, -W / np.maximum(dd, 1e-3)[:, None], ahead, W

    def residual(z, delta):
        return z - obs_j - delta * e3

    def update(Xs, xi):
        dX = np.tile(np.eye(4), (npair, 1, 1))
        dX[:, :3, :3] = Rotation.from_rotvec(xi[:, :3]).as_matrix()
        dX[:, :3, 3] = xi[:, 3:]
        return dX @ Xs

    def cost(Lt, Xs, delta, use, huber):
        """Robust cost of the residuals in ``use`` (Huber at the gate, or squares); infinite when one of them
        went behind a camera (a step may not get rid of a residual that way)."""
        z, _, _, _, ahead, _ = model(Xs, delta)
        e = (Lt @ residual(z, delta)[:, :, None])[:, :, 0]
        c2 = np.where(ahead, np.sum(e * e, axis=1), np.inf)[use]
        if huber:
            k = np.sqrt(CHI2_STEREO)
            m = np.sqrt(c2)
            c2 = np.where(m <= k, c2, 2.0 * k * m - CHI2_STEREO)
        return float(np.sum(c2))

    info_dd = 0.0
    for rnd in range(rounds):
        z, J, Jw, dW, ahead, W = model(Xs, delta)
        S = S_meas + Jw @ noise.covariance(W, s_i) @ Jw.transpose(0, 2, 1)
        S = 0.5 * (S + S.transpose(0, 2, 1)) + 1e-9 * np.eye(3)
        Lt = np.linalg.inv(np.linalg.cholesky(S))  # e = L^-1 r: e.e = r^T S^-1 r
        for _ in range(iterations):
            z, J, Jw, dW, ahead, W = model(Xs, delta)
            e = (Lt @ residual(z, delta)[:, :, None])[:, :, 0]
            A = Lt @ J  # (N,3,6)
            a = (Lt @ ((Jw @ dW[:, :, None])[:, :, 0] - e3)[:, :, None])[:, :, 0]  # (N,3)
            c2 = np.sum(e * e, axis=1)
            use = inl & ahead
            w = np.ones(n)
            if rnd < robust_rounds:
                m = np.sqrt(c2)
                w = np.where(m <= np.sqrt(CHI2_STEREO), 1.0, np.sqrt(CHI2_STEREO) / np.maximum(m, 1e-12))
            w = np.where(use, w, 0.0)
            Hpp = np.zeros((npair, 6, 6))
            np.add.at(Hpp, pid, np.einsum("nki,n,nkj->nij", A, w, A))
            bp = np.zeros((npair, 6))
            np.add.at(bp, pid, np.einsum("nki,n,nk->ni", A, w, a))
            gp = np.zeros((npair, 6))
            np.add.at(gp, pid, np.einsum("nki,n,nk->ni", A, w, e))
            c = float(np.einsum("nk,n,nk->", a, w, a))
            gd = float(np.einsum("nk,n,nk->", a, w, e))
            Hpp += np.eye(6) * 1e-9
            Hi_b = np.linalg.solve(Hpp, bp[:, :, None])[:, :, 0]
            Hi_g = np.linalg.solve(Hpp, gp[:, :, None])[:, :, 0]
            info_dd = c - float(np.sum(bp * Hi_b))
            if info_dd <= 1e-12:
                return None
            step_d = float(np.clip(-(gd - float(np.sum(bp * Hi_g))) / info_dd, -MAX_STEP, MAX_STEP))
            xi = -(Hi_g + Hi_b * step_d)  # the motions' best step given delta's (clamped) one
            now = cost(Lt, Xs, delta, use, rnd < robust_rounds)
            for _ in range(8):  # halve the step until the robust cost goes down
                trial = update(Xs, xi)
                if cost(Lt, trial, delta + step_d, use, rnd < robust_rounds) < now:
                    break
                xi, step_d = 0.5 * xi, 0.5 * step_d
            else:
                break
            Xs, delta = trial, delta + step_d
            if abs(step_d) < 1e-6 and np.max(np.abs(xi)) < 1e-8:
                break
        z, _, _, _, ahead, _ = model(Xs, delta)
        e = (Lt @ residual(z, delta)[:, :, None])[:, :, 0]
        inl = ahead & (np.sum(e * e, axis=1) <= CHI2_STEREO)
        inl &= (np.bincount(pid, inl, npair) >= MIN_PAIR_POINTS)[pid]  # a pair with too few inliers leaves
    return OffsetFit(float(delta), float(1.0 / np.sqrt(info_dd)), npair, int(inl.sum()), n)


def estimate_disparity_offset(seq, cfg, frames=None, max_gap: int = 5) -> OffsetFit | None:
    """The disparity correction (px) of the stereo sequence ``seq`` opened with config ``cfg`` (its
    ``stereo`` and ``features`` sections), from ``frames`` (default: the first 50), without ground truth."""
    frames = list(range(min(50, len(seq)))) if frames is None else list(frames)
    obs = observe(seq, cfg, frames)
    cam = seq.rig.camera
    return fit_disparity_offset(obs, (cam.fx, cam.fy, cam.cx, cam.cy), seq.rig.baseline,
                                cfg.stereo.sigma_disparity_sparse, seq.depth_noise.sigma_pixel
                                if getattr(seq, "depth_noise", None) is not None else 0.5,
                                cfg.features.scale_factor, max_gap)
