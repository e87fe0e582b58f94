"""Rigid alignment of point pairs with per-point covariances (anisotropic, e.g. stereo).

Stereo depth is far noisier along the viewing ray than across it (``DepthNoise.covariance``):
a least-squares fit in metres lets the distant points' depth errors pull the pose and biases
the scale. :func:`refine_pose_mahalanobis` minimises instead

    sum_i rho( r_i^T (R S_c,i R^T + S_w,i)^-1 r_i ),    r_i = R c_i + t - w_i

over the camera-to-world pose ``X = (R, t)`` (c_i: current camera points, w_i: their world
partners with covariance S_w,i; S_c,i: covariance of c_i in the camera frame), by Gauss-Newton
with a left perturbation ``X <- Exp(xi) X`` and Huber weights on the Mahalanobis distance.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from rgbdslam.geometry.se3 import skew_batch


def refine_pose_mahalanobis(X: np.ndarray, C: np.ndarray, cov_c: np.ndarray, W: np.ndarray, cov_w: np.ndarray,
                            iterations: int = 8, huber: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refine the pose ``X`` (4x4 camera-to-world) from pairs (C (N,3) camera, W (N,3) world) with
    covariances cov_c (N,3,3, camera frame) and cov_w (N,3,3, world frame).

    Returns (X, H, inlier mask): H is the 6x6 Gauss-Newton information of the left perturbation
    (rotation, translation) at the solution; inliers have a Mahalanobis distance within ``huber``
    * 2 (chi-square 3 dof, beyond that a pair is most likely a wrong match)."""
    X = np.array(X, dtype=np.float64)
    n = len(C)
    H = np.zeros((6, 6))
    if n < 3:
        return X, H, np.zeros(n, bool)
    for _ in range(iterations):
        R, t = X[:3, :3], X[:3, 3]
        y = C @ R.T + t  # current points in the world
        r = y - W
        cov = R @ cov_c @ R.T + cov_w
        info = np.linalg.inv(cov)
        m2 = np.einsum("ni,nij,nj->n", r, info, r)
        m = np.sqrt(np.maximum(m2, 0.0))
        w = np.where(m <= huber, 1.0, huber / np.maximum(m, 1e-12))
        J = np.concatenate([-skew_batch(y), np.broadcast_to(np.eye(3), (n, 3, 3))], axis=2)  # (N,3,6)
        JtI = np.einsum("nki,nkl->nil", J, info) * w[:, None, None]  # (N,6,3)
        H = np.einsum("nil,nlj->ij", JtI, J)
        g = np.einsum("nil,nl->i", JtI, r)
        try:
            xi = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        dX = np.eye(4)
        dX[:3, :3] = Rotation.from_rotvec(xi[:3]).as_matrix()
        dX[:3, 3] = xi[3:]
        X = dX @ X
        if np.linalg.norm(xi) < 1e-7:  # 0.1 micro-rad / 0.1 micro-m: converged
            break
    R, t = X[:3, :3], X[:3, 3]
    r = C @ R.T + t - W
    info = np.linalg.inv(R @ cov_c @ R.T + cov_w)
    m = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", r, info, r), 0.0))
    return X, H, m <= 2.0 * huber
