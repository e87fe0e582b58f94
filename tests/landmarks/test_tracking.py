"""Tracking against the landmark map: the reprojection refine's noise model (exact, hand-built scenes)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import inv
from rgbdslam.landmarks.tracking import refine_reprojection, reprojection_residuals

CAM = Camera(525.0, 525.0, 319.5, 239.5, 640, 480)


def _pose(rotvec, t):
    P = np.eye(4)
    P[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    P[:3, 3] = t
    return P


def _scene(n=300, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(1.0, 4.0, n)])


def _seen(P, X):
    Tcw = inv(P)
    Pc = X @ Tcw[:3, :3].T + Tcw[:3, 3]
    return Pc, CAM.project(Pc), Pc[:, 2]


def _ray_covariance(X, centre, along, across):
    """World covariances with sigma ``along`` the ray from ``centre`` and ``across`` it."""
    d = X - centre
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return across**2 * np.eye(3) + (along**2 - across**2) * d[:, :, None] * d[:, None, :]


def _err(A, B):
    return np.linalg.norm((inv(A) @ B)[:3, 3])


def test_landmark_uncertainty_along_the_ray_does_not_reach_the_pixels():
    # hand-worked: a landmark straight ahead (x = y = 0) with covariance only along z has no pixel
    # variance from it, only the key point's; its inverse depth gets (sigma_z_lm / z^2)^2 added
    X = np.array([[0.0, 0.0, 2.0]])
    cov = np.diag([0.0, 0.0, 0.05**2])[None]
    r, J = reprojection_residuals(np.eye(3), np.zeros(3), X, np.array([[CAM.cx + 1.5, CAM.cy - 3.0]]),
                                  np.array([1 / 0.51]), CAM, 1.5, np.array([0.01]), cov)
    # pixels whitened by sigma_px = 1.5 alone; the 1/z residual 0.51 - 0.5 by sqrt(frame² + landmark²):
    # frame 0.01 m at z = 1/0.51 -> 0.01 * 0.51², landmark 0.05 m at z = 2 -> 0.05 / 4
    assert np.allclose(r[0, :2], [1.0, -2.0])
    assert np.isclose(r[0, 2], 0.01 / np.hypot(0.01 * 0.51**2, 0.05 / 4))
    # a landmark off-axis: its ray uncertainty still leaves the pixels alone (the ray projects to one pixel)
    X = np.array([[1.0, -0.5, 2.0]])
    cov = _ray_covariance(X, np.zeros(3), 0.05, 0.0)
    Pc, uv, z = _seen(np.eye(4), X)
    r, _ = reprojection_residuals(np.eye(3), np.zeros(3), X, uv + [0.7, 0.0], z, CAM, 0.7, np.array([0.01]), cov)
    assert np.isclose(r[0, 0], 1.0) and np.isclose(r[0, 1], 0.0)


def test_full_landmark_covariance_keeps_depth_errors_of_the_map_out_of_the_pose():
    # landmarks displaced along the rays of the camera that mapped them (depth noise, 3 cm), with a
    # covariance saying so; a camera 20 cm away sees them with exact pixels and exact depths: the refine
    # with the full covariance recovers its pose to sub-mm, the isotropic sigma sqrt(trace/3) does not
    rng = np.random.default_rng(1)
    X = _scene(400)
    mapper = np.eye(4)
    d = X - mapper[:3, 3]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    Xn = X + d * rng.normal(scale=0.03, size=(len(X), 1))
    cov = _ray_covariance(Xn, mapper[:3, 3], 0.03, 0.0005)
    P = _pose([0.02, -0.05, 0.01], [0.2, -0.05, 0.05])
    _, uv, z = _seen(P, X)
    start = P @ _pose([0.005, -0.004, 0.002], [0.01, 0.01, -0.01])
    sz = np.full(len(X), 0.002)
    full, _, H = refine_reprojection(start, Xn, uv, z, CAM, 0.5, sz, cov, 10)
    iso, _, _ = refine_reprojection(start, Xn, uv, z, CAM, 0.5, sz, np.sqrt(np.trace(cov, axis1=1, axis2=2) / 3), 10)
    assert _err(full, P) < 5e-4
    assert _err(iso, P) > 3 * _err(full, P)
    assert np.all(np.linalg.eigvalsh(H) > 0)


def test_sigma_by_octave_weights_the_sharp_key_points():
    # half the key points (pyramid level 0) are exact, the other half (level 7) off by ~3 px: with
    # sigma = sigma_px * 1.2^octave the pose comes from the sharp ones; with one sigma for all it does not
    rng = np.random.default_rng(2)
    X = _scene(300)
    P = _pose([0.01, 0.03, -0.02], [0.05, 0.02, -0.1])
    _, uv, z = _seen(P, X)
    octave = np.where(np.arange(len(X)) % 2 == 0, 0, 7)
    uv_n = uv + (octave == 7)[:, None] * rng.normal(scale=3.0, size=uv.shape)
    sz, cov = np.full(len(X), 0.02), np.zeros(len(X))
    by_octave, _, _ = refine_reprojection(P, X, uv_n, z, CAM, 1.2 ** octave, sz, cov, 10, huber=100.0)
    flat, _, _ = refine_reprojection(P, X, uv_n, z, CAM, 1.0, sz, cov, 10, huber=100.0)
    assert _err(by_octave, P) < 0.25 * _err(flat, P)


def test_tracker_sigma_px_follows_the_orb_octave():
    from types import SimpleNamespace

    from rgbdslam.config import LandmarksConfig
    from rgbdslam.landmarks.stage import LandmarkTracker

    t = LandmarkTracker(LandmarksConfig(sigma_px=0.8, sigma_px_scale=1.2), CAM)
    feats = SimpleNamespace(uv=np.zeros((3, 2)), octave=np.array([0, 1, 3], np.int8))
    assert np.allclose(t._sigma_px(feats), [0.8, 0.96, 0.8 * 1.728])
    t = LandmarkTracker(LandmarksConfig(sigma_px=0.8), CAM)  # scale 1: one sigma
    assert t._sigma_px(feats) == 0.8
