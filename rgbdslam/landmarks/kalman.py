"""Static Kalman filter of landmark positions (spec §6: F = H = I, B = 0), vectorised over landmarks.

A landmark is a static point: the prediction only adds the process noise ``Q = q² I`` (a config
value: how far a "static" point may wander, e.g. through depth bias), and a re-observation ``z``
(the frame's point taken to the world with the frame's pose) with covariance ``R`` updates

    K = P (P + R)⁻¹,   x ← x + K (z − x),   P ← (I − K) P.

``R`` comes from the depth noise model (:func:`observation_covariance`): along the viewing ray the
depth noise grows with z² (Kinect: σ_z = a + b z²), across it with the pixel noise z σ_px / f; the
camera-frame covariance is rotated into the world with the pose.
"""

from __future__ import annotations

import numpy as np


def observation_covariance(P_cam: np.ndarray, R_wc: np.ndarray, fx: float, sigma_px: float, depth_a: float,
                           depth_b: float) -> np.ndarray:
    """World-frame covariances (N, 3, 3) of camera points ``P_cam`` (N, 3) seen from rotation ``R_wc``.

    Along the ray σ = depth_a + depth_b z²; across it σ = z σ_px / fx. The ray direction is the
    point's own direction (not the optical axis), so the ellipsoid points at the camera.
    """
    P = np.asarray(P_cam, dtype=np.float64).reshape(-1, 3)
    z = np.maximum(P[:, 2], 1e-3)
    d = P / np.linalg.norm(P, axis=1, keepdims=True)
    s_ray = depth_a + depth_b * z * z
    s_lat = z * sigma_px / fx
    # C = s_lat² I + (s_ray² - s_lat²) d dᵀ, then rotated: R C Rᵀ
    C = (s_lat**2)[:, None, None] * np.eye(3) + (s_ray**2 - s_lat**2)[:, None, None] * d[:, :, None] * d[:, None, :]
    return np.einsum("ij,njk,lk->nil", R_wc, C, R_wc)


def kalman_update(x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray, q: float) -> tuple[np.ndarray, np.ndarray]:
    """One static-Kalman step for N landmarks at once: x (N,3), P (N,3,3), z (N,3), R (N,3,3).

    Returns the updated (x, P). ``q`` is the process noise (metres, per step of the landmark).
    """
    Pp = P + (q * q) * np.eye(3)
    S = Pp + R
    K = Pp @ np.linalg.inv(S)
    x_new = x + np.einsum("nij,nj->ni", K, z - x)
    P_new = Pp - K @ Pp
    P_new = 0.5 * (P_new + np.swapaxes(P_new, 1, 2))  # keep it symmetric
    return x_new, P_new
