"""Rigid alignment of point pairs with per-point covariances (anisotropic, e.g. stereo).

Stereo depth is far noisier along the viewing ray than across it (``DepthNoise.covariance``):
a least-squares fit in metres lets the distant points' depth errors pull the pose and biases
the scale. :func:`refine_pose_near_far` minimises instead (its near pairs; the far ones as bearings)

    sum_i rho( r_i^T (R S_c,i R^T + S_w,i)^-1 r_i ),    r_i = R c_i + t - w_i

over the camera-to-world pose ``X = (R, t)`` (c_i: current camera points, w_i: their world
partners with covariance S_w,i; S_c,i: covariance of c_i in the camera frame), by Gauss-Newton
with a left perturbation ``X <- Exp(xi) X`` and Huber weights on the Mahalanobis distance.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from rgbdslam.geometry.se3 import skew_batch


def solve_translation_mahalanobis(X: np.ndarray, C: np.ndarray, cov_c: np.ndarray, W: np.ndarray,
                                  cov_w: np.ndarray, iterations: int = 8, huber: float = 3.0
                                  ) -> tuple[np.ndarray, np.ndarray]:
    """The translation of the pose ``X`` (4x4 camera-to-world) re-solved from the pairs (C (N,3) camera,
    W (N,3) world; covariances cov_c camera frame, cov_w world frame) with its rotation ``R`` held: the
    minimiser of ``sum_i rho(r_i^T I_i r_i)``, ``r_i = R c_i + t - w_i``, ``I_i = (R S_c,i R^T + S_w,i)^-1``,
    is the weighted mean ``t = (sum h_i I_i)^-1 sum h_i I_i (w_i - R c_i)`` (exact for fixed weights), iterated
    with Huber weights ``h_i`` on the Mahalanobis distance at the current ``t``.

    Returns (X with the new translation, inlier mask: Mahalanobis distance within 2 * ``huber``); ``X``
    unchanged when there are fewer than 3 pairs."""
    X = np.array(X, dtype=np.float64)
    n = len(C)
    if n < 3:
        return X, np.zeros(n, bool)
    R = X[:3, :3]
    try:
        info = np.linalg.inv(R @ cov_c @ R.T + cov_w)  # fixed: depends on R only
    except np.linalg.LinAlgError:  # a degenerate covariance: no translation from these pairs
        return X, np.zeros(n, bool)
    a = W - C @ R.T  # w_i - R c_i: each pair's own translation
    t = X[:3, 3]
    for _ in range(iterations):
        r = t - a
        m = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", r, info, r), 0.0))
        wI = info * np.where(m <= huber, 1.0, huber / np.maximum(m, 1e-12))[:, None, None]
        try:
            t_new = np.linalg.solve(wI.sum(axis=0), np.einsum("nij,nj->i", wI, a))
        except np.linalg.LinAlgError:
            break
        done = np.linalg.norm(t_new - t) < 1e-7
        t = t_new
        if done:
            break
    X[:3, 3] = t
    r = t - a
    return X, np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", r, info, r), 0.0)) <= 2.0 * huber


def project_jacobian(q: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """(N, 2, 3) Jacobians of the pinhole projection ``(fx x/z + cx, fy y/z + cy)`` at camera points ``q``."""
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    J = np.zeros((len(q), 2, 3))
    J[:, 0, 0] = fx / z
    J[:, 0, 2] = -fx * x / z ** 2
    J[:, 1, 1] = fy / z
    J[:, 1, 2] = -fy * y / z ** 2
    return J


def bearing_residuals(X: np.ndarray, W: np.ndarray, cov_w: np.ndarray, uv: np.ndarray, intrinsics: tuple,
                      sigma_pixel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reprojection residuals of world points ``W`` (N,3; covariance ``cov_w`` (N,3,3)) seen at pixels
    ``uv`` (N,2) by the camera at pose ``X`` (camera-to-world), ``intrinsics = (fx, fy, cx, cy)``.

    Returns (r (N,2) = projection - uv, their covariances (N,2,2) = sigma_pixel^2 I + the world
    point's covariance carried into the image, Jacobians (N,2,6) w.r.t. the left perturbation
    ``X <- Exp(xi) X``, xi = (rotation, translation)). Points at or behind the camera get r = 0
    and no Jacobian (they take no part)."""
    fx, fy, cx, cy = intrinsics
    R, t = X[:3, :3], X[:3, 3]
    q = (W - t) @ R  # R^T (w - t)
    ahead = q[:, 2] > 1e-6
    qs = np.where(ahead[:, None], q, [0.0, 0.0, 1.0])
    r = np.stack([fx * qs[:, 0] / qs[:, 2] + cx, fy * qs[:, 1] / qs[:, 2] + cy], axis=1) - uv
    r[~ahead] = 0.0
    Jp = project_jacobian(qs, fx, fy)  # (N,2,3)
    JpRt = Jp @ R.T  # d r / d w
    cov = JpRt @ cov_w @ JpRt.transpose(0, 2, 1) + sigma_pixel ** 2 * np.eye(2)
    # q(xi) = R^T (w - t) - R^T (phi x w) - R^T rho  =>  dq/dphi = R^T [w]x, dq/drho = -R^T
    J = np.concatenate([JpRt @ skew_batch(W), -JpRt], axis=2)
    J[~ahead] = 0.0
    return r, cov, J


def refine_pose_near_far(X: np.ndarray, C: np.ndarray, cov_c: np.ndarray, W: np.ndarray, cov_w: np.ndarray,
                         far: np.ndarray, uv: np.ndarray, intrinsics: tuple, sigma_pixel: float,
                         iterations: int = 8, huber: float = 3.0,
                         rotation_only: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pose refit above for a stereo frame whose points are split into near and far
    (the stereo fallback: far = a pair without depth in the tracking range): the near pairs (``~far``)
    as 3-D residuals with the stereo covariances, the far pairs as bearing-only residuals (:func:`bearing_residuals` of their world partner at the
    current frame's pixel ``uv``; the current point's own depth is not used). Huber on each pair's
    Mahalanobis distance (2 dof for a bearing, 3 for a 3-D pair).

    ``rotation_only``: keep the translation, refine the rotation alone (a frame with too few near
    points: far bearings fix the rotation, not the translation). Returns (X, H 6x6 information,
    inlier mask: Mahalanobis distance within 2 * ``huber``)."""
    X = np.array(X, dtype=np.float64)
    far = np.asarray(far, bool)
    near = ~far
    n = len(C)
    H = np.zeros((6, 6))
    if n < 3:
        return X, H, np.zeros(n, bool)
    Cn, Sn, Wn, SWn = C[near], cov_c[near], W[near], cov_w[near]
    Wf, SWf, uvf = W[far], cov_w[far], uv[far]

    def terms(X):
        R, t = X[:3, :3], X[:3, 3]
        y = Cn @ R.T + t
        r3 = y - Wn
        info3 = np.linalg.inv(R @ Sn @ R.T + SWn)
        J3 = np.concatenate([-skew_batch(y), np.broadcast_to(np.eye(3), (len(y), 3, 3))], axis=2)
        r2, cov2, J2 = bearing_residuals(X, Wf, SWf, uvf, intrinsics, sigma_pixel)
        info2 = np.linalg.inv(cov2)
        return (r3, info3, J3), (r2, info2, J2)

    def mahalanobis(r, info):
        return np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", r, info, r), 0.0))

    for _ in range(iterations):
        H = np.zeros((6, 6))
        g = np.zeros(6)
        for r, info, J in terms(X):
            m = mahalanobis(r, info)
            w = np.where(m <= huber, 1.0, huber / np.maximum(m, 1e-12))
            JtI = np.einsum("nki,nkl->nil", J, info) * w[:, None, None]
            H += np.einsum("nil,nlj->ij", JtI, J)
            g += np.einsum("nil,nl->i", JtI, r)
        # rotation_only: a rotation phi about the camera centre is xi = A phi, A = [I; [t]x]
        A = np.vstack([np.eye(3), skew_batch(X[None, :3, 3])[0]]) if rotation_only else np.eye(6)
        try:
            step = -np.linalg.solve(A.T @ H @ A, A.T @ g)
        except np.linalg.LinAlgError:
            break
        dX = np.eye(4)
        dX[:3, :3] = Rotation.from_rotvec(step[:3]).as_matrix()
        dX[:3, 3] = X[:3, 3] - dX[:3, :3] @ X[:3, 3] if rotation_only else step[3:]
        X = dX @ X
        if np.linalg.norm(step) < 1e-7:
            break
    (r3, info3, _), (r2, info2, _) = terms(X)
    inl = np.zeros(n, bool)
    inl[near] = mahalanobis(r3, info3) <= 2.0 * huber
    inl[far] = mahalanobis(r2, info2) <= 2.0 * huber
    return X, H, inl
