"""Tracking a frame against the landmark map (spec §6).

1. Candidates: the landmarks the store returns within ``max_depth / 2`` (+ margin) of the point
   ``max_depth / 2`` ahead of the predicted camera, kept when they project into the image in
   front of the camera.
2. Matching: every depth-valid frame feature is compared (Hamming) with the ``k`` projected
   landmarks nearest to it within ``search_radius`` pixels; the best under ``max_hamming`` wins,
   one frame feature per landmark (the closest descriptor).
3. Pose: 3-D rigid RANSAC (:func:`rgbdslam.geometry.ransac.ransac_rigid`) of the frame's camera
   points onto the landmarks' world points, with minimal samples drawn from the **oldest**
   matched landmarks first (the thesis' rule; ``sampling='uniform'`` for the ablation), the
   prediction scored as one more hypothesis; then a weighted refit on the inliers (weights
   1 / (σ²_observation + σ²_landmark), re-gated twice).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rgbdslam.frontend.features import map_valid
from rgbdslam.frontend.matching import pair_hamming
from rgbdslam.frontend.registration.base import fit_information
from rgbdslam.geometry.ransac import ransac_rigid, seeded_rigid
from rgbdslam.geometry.rigid import fit_rigid, row_norms
from rgbdslam.geometry.se3 import inv, so3_exp
from rgbdslam.geometry.whitening import whitening_rows


@dataclass
class MapMatch:
    feat: np.ndarray  # (M,) frame feature indices
    lm: np.ndarray  # (M,) landmark ids
    n_candidates: int  # landmarks projected into the frame
    cand_uv: np.ndarray | None = None  # (K, 2) pixels of the projected candidates
    cand_ids: np.ndarray | None = None  # (K,) their landmark ids

    def subset(self, keep: np.ndarray, keep_cand: np.ndarray | None = None) -> "MapMatch":
        """The matches ``keep`` (boolean (M,)), and the candidates ``keep_cand`` (boolean (K,); all if None)."""
        uv, ids = self.cand_uv, self.cand_ids
        if keep_cand is not None and uv is not None and ids is not None:
            uv, ids = uv[keep_cand], ids[keep_cand]
        return MapMatch(self.feat[keep], self.lm[keep], self.n_candidates, uv, ids)


@dataclass
class MapPose:
    pose: np.ndarray  # camera-to-world
    feat: np.ndarray  # inlier frame feature indices
    lm: np.ndarray  # inlier landmark ids
    n_matches: int
    n_candidates: int
    rms: float  # RMS 3-D residual of the inliers (m)
    information: np.ndarray | None = None  # 6x6, right perturbation (rotation, translation); reprojection refine


def project_candidates(lmap, pose: np.ndarray, camera, max_depth: float, margin: float = 0.2,
                       allowed: np.ndarray | None = None):
    """(ids, uv (K,2), depth (K,)) of live landmarks in front of the camera and inside the image
    (``allowed``: a boolean mask over landmark ids, only those set; applied before the projection,
    which is the same for each landmark whichever others are projected with it)."""
    c = pose[:3, 3]
    ahead = c + pose[:3, 2] * (0.5 * max_depth)
    ids = lmap.near(ahead, 0.5 * max_depth + margin, allowed)
    if not len(ids):
        return ids, np.zeros((0, 2)), np.zeros(0)
    Tcw = inv(pose)
    P = lmap.pos[ids] @ Tcw[:3, :3].T + Tcw[:3, 3]
    z = P[:, 2]
    ok = (z > 0.1) & (z < max_depth)
    ids, P, z = ids[ok], P[ok], z[ok]
    uv = np.stack([camera.fx * P[:, 0] / z + camera.cx, camera.fy * P[:, 1] / z + camera.cy], axis=1)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    return ids[inside], uv[inside], z[inside]


def match_to_map(lmap, feats, pose: np.ndarray, camera, search_radius: float, max_hamming: int,
                 max_depth: float, k: int = 6, first_before: int | None = None,
                 first_after: int | None = None, allowed: np.ndarray | None = None) -> MapMatch:
    """Frame features matched to projected landmarks by descriptor inside ``search_radius`` px
    (``first_before``: only landmarks first seen before that frame, ``first_after``: only those first
    seen at or after that frame — together a loop's older end, ``landmarks.loop_refine``;
    ``allowed``: a boolean mask over landmark ids, only those set — the local map, ``landmarks.local_map_shared``)."""
    if first_before is not None or first_after is not None:  # one mask with the local map's, before projecting
        f = lmap.first[: lmap.n]
        old = (f < (first_before if first_before is not None else np.inf)) & \
            (f >= (first_after if first_after is not None else -np.inf))
        allowed = old if allowed is None else allowed[: lmap.n] & old
    ids, uv, _ = project_candidates(lmap, pose, camera, max_depth, allowed=allowed)
    fi = np.flatnonzero(map_valid(feats))
    empty = MapMatch(np.zeros(0, np.int64), np.zeros(0, np.int64), len(ids), uv, ids)
    if len(ids) == 0 or len(fi) == 0:
        return empty
    from scipy.spatial import cKDTree  # here: SciPy's import is not on the way to the first frame

    kk = min(k, len(ids))
    # a tree built once per frame and queried once: unbalanced (built in half the time, same answers)
    d, nn = cKDTree(uv, balanced_tree=False, compact_nodes=False).query(feats.uv[fi], k=kk,
                                                                        distance_upper_bound=search_radius)
    if kk == 1:
        d, nn = d[:, None], nn[:, None]
    has = np.isfinite(d)
    nn_safe = np.where(has, nn, 0)
    # Hamming distances of every feature to its k candidates (F, k): word by word, gathered with 1-D takes
    ham = pair_hamming(feats.words, lmap.words(ids), fi[:, None], nn_safe).astype(np.int32)
    ham = np.where(has, ham, 1 << 20)
    best = ham.argmin(axis=1)
    hb = ham[np.arange(len(fi)), best]
    ok = hb <= max_hamming
    f_idx, l_idx, hb = fi[ok], nn_safe[np.arange(len(fi)), best][ok], hb[ok]
    # one feature per landmark: the smallest Hamming distance wins
    order = np.lexsort((f_idx, hb))
    _, first = np.unique(l_idx[order], return_index=True)
    sel = order[first]
    return MapMatch(f_idx[sel], ids[l_idx[sel]], len(ids), uv, ids)


def estimate_pose(lmap, feats, match: MapMatch, pred: np.ndarray, sigma_obs: np.ndarray, threshold: float,
                  iterations: int, min_inliers: int, sampling: str, old_fraction: float,
                  rng: np.random.Generator, refine: str = "rigid", camera=None, sigma_px=1.0,
                  chi2_gate: float = 3.0, full_cov: bool = True, adaptive: bool = False,
                  refine_iterations: int = 5) -> MapPose | None:
    """Pose from the matches: RANSAC (old landmarks first) + weighted refit on the inliers.

    ``sigma_obs`` (M,) is each frame point's depth noise (m); the landmark's own is sqrt(trace(P)/3)
    in the 3-D refit, its full covariance in the reprojection refine (``full_cov``; else the same
    isotropic sigma). ``sigma_px``: key point noise (px), a scalar or one per frame feature.
    ``adaptive``: after the refine, the key point and depth noise are rescaled by the robust scale
    (1.4826 · median |r|, clipped to [0.25, 4]) of the inliers' whitened residuals and the refine is
    run once more: the frame's own noise level sets the weights and the information.
    ``refine_iterations``: Gauss–Newton iterations of each reprojection refine pass.
    ``iterations`` 0: no RANSAC — the prediction's inliers start the refits
    (:func:`rgbdslam.geometry.ransac.seeded_rigid`; for a prediction that is another estimate of the pose).
    """
    m = len(match.lm)
    if m < max(3, min_inliers):
        return None
    S = feats.pts[match.feat]
    D = lmap.pos[match.lm]
    if sampling == "old_first":  # sort by first sighting: the minimal samples come from the oldest part
        order = np.argsort(lmap.first[match.lm], kind="stable")
        S, D, feat, lm, sig = S[order], D[order], match.feat[order], match.lm[order], sigma_obs[order]
        n_sample = max(min(m, 12), int(np.ceil(old_fraction * m)))
    else:
        feat, lm, sig = match.feat, match.lm, sigma_obs
        n_sample = m
    if iterations > 0:
        out = ransac_rigid(S, D, threshold, iterations, rng, min_inliers, T0=pred, sample_from=n_sample)
    else:
        out = seeded_rigid(S, D, threshold, pred, min_inliers)
    if out is None:
        return None
    T, mask = out
    s_lm2 = np.trace(lmap.cov[lm], axis1=1, axis2=2) / 3.0
    w = 1.0 / (sig**2 + s_lm2)
    for _ in range(2):
        if mask.sum() < max(3, min_inliers):
            return None
        T = fit_rigid(S[mask], D[mask], w[mask])
        r = row_norms(D - (S @ T[:3, :3].T + T[:3, 3]))
        mask = r < threshold
    if mask.sum() < max(3, min_inliers):
        return None
    T = fit_rigid(S[mask], D[mask], w[mask])
    info = None
    if refine == "reprojection":  # motion-only GN on pixels + inverse depth, re-gated once
        uv, z = feats.uv[feat], S[:, 2]
        cov = lmap.cov[lm] if full_cov else np.sqrt(s_lm2)
        spx = sigma_px if np.ndim(sigma_px) == 0 else np.asarray(sigma_px, float)[feat]  # per frame feature
        reproj = Reprojection(D, uv, z, camera, spx, sig, cov)  # every match's; the refine takes the inliers'
        for _ in range(2):
            T, e, info = gauss_newton(T, reproj.subset(mask), refine_iterations)
            Tcw = inv(T)
            r, _ = reproj(Tcw[:3, :3], Tcw[:3, 3], jacobian=False)
            new = row_norms(r) < chi2_gate
            if new.sum() < max(3, min_inliers):
                break
            mask = new
        if adaptive:  # the frame's own noise: robust scale of the inliers' whitened pixel and depth residuals
            k_px = 1.4826 * np.median(np.abs(r[mask, :2]))
            k_z = 1.4826 * np.median(np.abs(r[mask, 2]))
            spx, sig = spx * np.clip(k_px, 0.25, 4.0), sig * np.clip(k_z, 0.25, 4.0)
            T, e, info = gauss_newton(T, Reprojection(D, uv, z, camera, spx, sig, cov).subset(mask), refine_iterations)
    r = row_norms(D[mask] - (S[mask] @ T[:3, :3].T + T[:3, 3]))
    rms = float(np.sqrt(np.mean(r**2)))
    if refine == "points":  # the weighted 3-D refit kept, with the registration's information formula
        info = fit_information(S[mask], rms)
    return MapPose(T, feat[mask], lm[mask], m, match.n_candidates, rms, info)


_UPPER = np.array([0, 1, 2, 4, 5, 8])  # the entries (0,0) (0,1) (0,2) (1,1) (1,2) (2,2) of a flattened 3x3


def map_pose(lmap, feats, match: MapMatch, pred: np.ndarray, cfg, camera, rng: np.random.Generator,
             seeded: bool = False) -> MapPose | None:
    """:func:`estimate_pose` with the settings of the ``landmarks`` config section ``cfg`` (the landmark
    stage's map pose, and a localising run's pose against a saved map); ``seeded``: no RANSAC, the refine
    starts from ``pred``'s inliers.

    A camera whose depth is not registered to its colour (``Camera.depth_registered`` false: depth from a
    second camera, re-projected) gets the 3-D refit (``refine='points'``) instead of the reprojection
    refine: a key point's pixel and its depth then disagree by the depth-to-colour calibration's error,
    and the pixel refine would trust the colour bearing at ``sigma_px`` against it (docs/landmarks.md
    "Why 7-Scenes is worse")."""
    z = feats.pts[match.feat, 2]
    refine = "points" if cfg.refine == "reprojection" and not camera.depth_registered else cfg.refine
    return estimate_pose(lmap, feats, match, pred, cfg.depth_noise_a + cfg.depth_noise_b * z * z,
                         cfg.ransac_threshold, 0 if seeded else cfg.ransac_iterations, cfg.min_inliers, cfg.sampling,
                         cfg.old_fraction, rng, refine, camera, cfg.sigma_px, cfg.chi_gate,
                         cfg.landmark_cov == "full", cfg.adaptive_noise, refine_iterations=cfg.refine_iterations)


def reprojection_residuals(R: np.ndarray, t: np.ndarray, X: np.ndarray, uv: np.ndarray, z: np.ndarray, camera,
                           sigma_px, sigma_z: np.ndarray, cov_lm: np.ndarray, jacobian: bool = True):
    """Whitened residuals (N, 3) of the measured (u, v, 1/z) against landmarks X (N, 3) seen by the
    world-to-camera (R, t), and their whitened Jacobians (N, 3, 6) w.r.t. ξ = (ω, v), the left
    perturbation of world-to-camera (p ← p + ω×p + v).

    The covariance of each residual is diag(σ_px², σ_px², (σ_z/z²)²) (the frame's key point and
    depth noise; ``sigma_px`` scalar or (N,), e.g. by ORB octave) plus the landmark's own 3x3
    covariance ``cov_lm`` (N, 3, 3) carried through the projection, J_p Σ_lm J_pᵀ: the part of its
    uncertainty along the viewing ray goes into the inverse depth, not into the pixels. With an
    isotropic sigma ``cov_lm`` (N,) instead (the earlier model): f·σ/z added to each pixel's sigma,
    nothing to the inverse depth's. Whitening: Lᵀ with S⁻¹ = L Lᵀ (:func:`rgbdslam.geometry.whitening.whitening_rows`).
    ``jacobian`` False: the residuals alone (the same numbers), the Jacobians None (the inlier gates).
    The work is :class:`Reprojection`'s (the measured side prepared once, for a refine's iterations).
    """
    return Reprojection(X, uv, z, camera, sigma_px, sigma_z, cov_lm)(R, t, jacobian)


class Reprojection:
    """:func:`reprojection_residuals` of fixed measurements at any pose: what does not depend on the
    pose — the measured pixels as two contiguous rows, the inverse depths, the frame's noise terms,
    the landmark covariances as (N, 9) rows — is prepared once (a refine evaluates 5 poses), and
    the last operation of each residual and Jacobian entry writes into its place (no temporary
    copied in). Every entry is the same operations in the same order as the plain expression, so
    the same bits (``tests/landmarks/test_tracking.py`` holds it against that expression on real
    frames). ``subset(mask)``: the same for the measurements ``mask`` selects (a refine's inliers)."""

    def __init__(self, X: np.ndarray, uv: np.ndarray, z: np.ndarray, camera, sigma_px, sigma_z: np.ndarray,
                 cov_lm: np.ndarray, _parts: tuple | None = None):
        self.camera = camera
        if _parts is not None:
            self.X, self.u, self.v, self.inv_z, self.s_px2, self.s_z2, self.cov = _parts
            return
        self.X = X
        self.u, self.v = np.ascontiguousarray(uv[:, 0]), np.ascontiguousarray(uv[:, 1])
        self.inv_z = 1.0 / z
        self.s_px2 = np.asarray(sigma_px, float) ** 2
        self.s_z2 = (sigma_z / (z * z)) ** 2
        cov_lm = np.asarray(cov_lm, float)
        self.cov = cov_lm.reshape(-1, 9) if cov_lm.ndim == 3 else np.broadcast_to(cov_lm, (len(X),))

    def __len__(self) -> int:
        return len(self.X)

    def subset(self, mask: np.ndarray) -> "Reprojection":
        s_px2 = self.s_px2 if self.s_px2.ndim == 0 else self.s_px2[mask]
        return Reprojection(None, None, None, self.camera, None, None, None,
                            (self.X[mask], self.u[mask], self.v[mask], self.inv_z[mask], s_px2, self.s_z2[mask],
                             self.cov[mask]))

    def __call__(self, R: np.ndarray, t: np.ndarray, jacobian: bool = True):
        cam = self.camera
        fx, fy, cx, cy = cam.fx, cam.fy, cam.cx, cam.cy
        n = len(self.X)
        P = self.X @ R.T + t
        x, y = P[:, 0], P[:, 1]
        a = 1.0 / np.maximum(P[:, 2], 1e-3)  # inverse depth of the prediction
        xa, ya = x * a, y * a
        r0, r1, r2 = self.u - (fx * xa + cx), self.v - (fy * ya + cy), self.inv_z - a
        # d(u, v, 1/z)/dP = [[p, 0, q], [0, p2, q2], [0, 0, s]]
        p, q = fx * a, -fx * xa * a
        p2, q2 = fy * a, -fy * ya * a
        s = -a * a
        if self.cov.ndim == 2:  # S = J_p (R Σ Rᵀ) J_pᵀ
            # the landmark covariance in the camera frame, R Σ Rᵀ: its six distinct entries at once as one
            # (N, 9) @ (9, 6) product with the rows of R ⊗ R (3x cheaper than N stacked 3x3 products)
            C = self.cov @ (R[:, None, :, None] * R[None, :, None, :]).reshape(9, 9)[_UPPER].T
            c00, c01, c02, c11, c12, c22 = C.T
            u0, u2 = p * c02 + q * c22, p2 * c12 + q2 * c22
            S00 = p * (p * c00 + q * c02) + q * u0
            S01 = p * (p2 * c01 + q2 * c02) + q * u2
            S02 = s * u0
            S11 = p2 * (p2 * c11 + q2 * c12) + q2 * u2
            S12 = s * u2
            S22 = s * s * c22
        else:
            S00 = S11 = (fx * self.cov * a) ** 2
            S01 = S02 = S12 = S22 = np.zeros(n)
        s_px2 = self.s_px2
        l00, l10, l20, l11, l21, l22 = whitening_rows(S00 + s_px2, S01, S02, S11 + s_px2, S12, S22 + self.s_z2)
        r = np.empty((n, 3))
        add, mul = np.add, np.multiply
        add(l00 * r0 + l10 * r1, l20 * r2, out=r[:, 0])
        add(l11 * r1, l21 * r2, out=r[:, 1])
        mul(l22, r2, out=r[:, 2])
        if not jacobian:
            return r, None
        # d(u, v, 1/z)/dξ = Jp · [-[P]x | I], rows J0, J1, J2 (J0[4] = J1[3] = J2[2:5] = 0)
        J0 = (-xa * ya * fx, (1 + xa * xa) * fx, -ya * fx, p, -xa * p)
        J1 = (-(1 + ya * ya) * fy, xa * ya * fy, xa * fy, p2, -ya * p2)
        J2 = (-ya * a, xa * a, s)
        J = np.empty((n, 3, 6))
        add(l00 * J0[0] + l10 * J1[0], l20 * J2[0], out=J[:, 0, 0])
        add(l00 * J0[1] + l10 * J1[1], l20 * J2[1], out=J[:, 0, 1])
        add(l00 * J0[2], l10 * J1[2], out=J[:, 0, 2])
        mul(l00, J0[3], out=J[:, 0, 3])
        mul(l10, J1[3], out=J[:, 0, 4])
        add(l00 * J0[4] + l10 * J1[4], l20 * J2[2], out=J[:, 0, 5])
        add(l11 * J1[0], l21 * J2[0], out=J[:, 1, 0])
        add(l11 * J1[1], l21 * J2[1], out=J[:, 1, 1])
        mul(l11, J1[2], out=J[:, 1, 2])
        J[:, 1, 3] = 0.0
        mul(l11, J1[3], out=J[:, 1, 4])
        add(l11 * J1[4], l21 * J2[2], out=J[:, 1, 5])
        mul(l22, J2[0], out=J[:, 2, 0])
        mul(l22, J2[1], out=J[:, 2, 1])
        J[:, 2, 2:5] = 0.0
        mul(l22, J2[2], out=J[:, 2, 5])
        return r, J


def refine_reprojection(pose: np.ndarray, X: np.ndarray, uv: np.ndarray, z: np.ndarray, camera, sigma_px,
                        sigma_z: np.ndarray, cov_lm: np.ndarray, iterations: int = 5,
                        huber: float = 1.345) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Motion-only Gauss–Newton on pixel and inverse-depth residuals (vectorised, Huber-weighted).

    pose: camera-to-world start; X (N,3) landmark world points; uv (N,2) measured (undistorted)
    pixels with noise ``sigma_px`` (px, scalar or (N,)); z (N,) measured depths with noise sigma_z
    (N,); ``cov_lm`` the landmarks' world covariances (N,3,3) or an isotropic sigma (N,) (m).
    Residuals per point: (u, v) in pixels and 1/z in 1/m, whitened by their full 3x3 covariance
    (:func:`reprojection_residuals`) — the RGB-D analogue of a stereo reprojection error, so the
    depth's larger noise no longer pulls the pose as the 3-D point distance does. Returns (pose,
    whitened error norm per point, 6x6 information of the pose: right perturbation pose·Exp(η),
    η = (ω, v), GTSAM's Pose3 order).
    """
    return gauss_newton(pose, Reprojection(X, uv, z, camera, sigma_px, sigma_z, cov_lm), iterations, huber)


def gauss_newton(pose: np.ndarray, reproj: Reprojection, iterations: int = 5,
                 huber: float = 1.345) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`refine_reprojection` of the measurements ``reproj`` (a :class:`Reprojection`)."""
    Tcw = inv(pose)
    R, t = Tcw[:3, :3].copy(), Tcw[:3, 3].copy()
    e = np.zeros(len(reproj))
    H = np.zeros((6, 6))
    for _ in range(iterations):
        r, J = reproj(R, t)
        e = row_norms(r)
        w = np.where(e <= huber, 1.0, huber / np.maximum(e, 1e-12))
        Jw = (J * w[:, None, None]).reshape(-1, 6)
        H = Jw.T @ J.reshape(-1, 6)
        g = Jw.T @ r.reshape(-1)
        try:
            xi = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        dR = so3_exp(xi[:3])
        R, t = dR @ R, dR @ t + xi[3:]
        if math.sqrt(float(xi.dot(xi))) < 1e-8:
            break
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, t
    # Tcw <- Exp(xi) Tcw is pose <- pose Exp(-xi): the same information for the pose's right perturbation
    return inv(out), e, H
