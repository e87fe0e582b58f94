"""Tracking against the landmark map: the reprojection refine's noise model (exact, hand-built scenes)."""

from __future__ import annotations

import numpy as np

from rgbdslam.geometry.se3 import inv
from rgbdslam.landmarks.map import LandmarkMap
from rgbdslam.landmarks.tracking import refine_reprojection, reprojection_residuals
from tests.landmarks.scenes import CAM
from tests.landmarks.scenes import pose as _pose
from tests.landmarks.scenes import scene as _scene
from tests.landmarks.scenes import seen as _seen


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


def test_isotropic_landmark_sigma_is_the_earlier_model():
    # hand-worked: f·σ_lm/z added to the pixels' sigma, nothing to the inverse depth's
    X = np.array([[0.5, 0.2, 2.0]])
    Pc, uv, z = _seen(np.eye(4), X)
    r, _ = reprojection_residuals(np.eye(3), np.zeros(3), X, uv + [1.0, 2.0], np.array([1 / 0.51]), CAM, 1.0,
                                  np.array([0.01]), np.array([0.004]))
    s_px = np.hypot(1.0, 525.0 * 0.004 / 2.0)
    assert np.allclose(r[0], [1.0 / s_px, 2.0 / s_px, 0.01 / (0.01 * 0.51**2)])


def test_map_observe_can_count_without_moving_and_move_without_counting():
    m = LandmarkMap("single", kalman=True, process_noise=0.0)
    ids = m.add(np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1)), np.zeros((2, 32), np.uint8), 0, 0)
    m.observe(ids, None, None, 5)  # seen at frame 5, positions kept
    assert np.all(m.seen[ids] == 2) and np.all(m.last[ids] == 5) and np.allclose(m.pos[ids], 0)
    m.observe(ids, np.ones((2, 3)), np.tile(np.eye(3), (2, 1, 1)), 6, count=False)  # Kalman only: the mean
    assert np.all(m.seen[ids] == 2) and np.all(m.last[ids] == 5) and np.allclose(m.pos[ids], 0.5)


def test_adaptive_noise_follows_the_frames_own_pixel_noise():
    # pixels with 0.3 px noise, sigma_px configured 1: the adaptive refine finds the scale of its
    # whitened residuals (~0.3) and its information grows accordingly; the pose stays as good
    from types import SimpleNamespace

    from rgbdslam.landmarks.tracking import MapMatch, estimate_pose

    rng = np.random.default_rng(4)
    X = _scene(400, seed=5)
    m = LandmarkMap("single")
    ids = m.add(X, np.tile(np.eye(3) * 1e-8, (len(X), 1, 1)), np.zeros((len(X), 32), np.uint8), 0, 0)
    P = _pose([0.02, 0.01, -0.03], [0.1, 0.0, 0.05])
    Pc, uv, z = _seen(P, X)
    dz = rng.normal(scale=0.01, size=len(X))  # depth noise as configured (sigma 1 cm): its scale stays ~1
    feats = SimpleNamespace(uv=uv + rng.normal(scale=0.3, size=uv.shape), pts=Pc * (1 + dz / Pc[:, 2])[:, None])
    match = MapMatch(np.arange(len(X)), ids, len(X))
    sig = np.full(len(X), 0.01)
    out = {}
    for adaptive in (False, True):
        out[adaptive] = estimate_pose(m, feats, match, P, sig, 0.03, 50, 10, "uniform", 1.0, np.random.default_rng(0),
                                      "reprojection", CAM, 1.0, 3.0, True, adaptive)
    gain = np.trace(out[True].information) / np.trace(out[False].information)
    assert 5.0 < gain < 15.0  # (1 / 0.3)² ≈ 11 on the pixel-dominated directions
    assert _err(out[True].pose, P) < 2e-3 and _err(out[False].pose, P) < 2e-3


def test_whitened_residuals_match_the_dense_model_and_their_jacobian_the_finite_differences():
    """The per-entry residuals equal the dense model written plainly — S = J_p R Σ Rᵀ J_pᵀ +
    diag(σ_px², σ_px², (σ_z/z²)²), whitened by Lᵀ with L = cholesky(S⁻¹) (LAPACK) — and the
    whitened Jacobian equals finite differences of the whitened residual under p ← p + ω×p + v
    (the whitening held at the linearisation point, as Gauss–Newton uses it)."""
    from scipy.spatial.transform import Rotation

    from rgbdslam.geometry.whitening import whitening

    rng = np.random.default_rng(5)
    n = 40
    R = Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix()
    t = np.array([0.05, -0.02, 0.1])
    X = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(1, 3, n)])
    P = X @ R.T + t
    uv = CAM.project(P) + rng.normal(size=(n, 2))
    z = P[:, 2] + rng.normal(scale=0.01, size=n)
    A = rng.normal(scale=0.004, size=(n, 3, 3))
    cov = A @ A.transpose(0, 2, 1) + 1e-6 * np.eye(3)
    spx, sz = rng.uniform(0.7, 2.0, n), 0.001 + 0.002 * z * z
    r, J = reprojection_residuals(R, t, X, uv, z, CAM, spx, sz, cov)

    def dense(Pc):
        a = 1.0 / Pc[:, 2]
        e = np.stack([uv[:, 0] - (CAM.fx * Pc[:, 0] * a + CAM.cx), uv[:, 1] - (CAM.fy * Pc[:, 1] * a + CAM.cy),
                      1.0 / z - a], axis=1)
        return e, a

    e, a = dense(P)
    Jp = np.zeros((n, 3, 3))
    Jp[:, 0, 0], Jp[:, 0, 2] = CAM.fx * a, -CAM.fx * P[:, 0] * a * a
    Jp[:, 1, 1], Jp[:, 1, 2] = CAM.fy * a, -CAM.fy * P[:, 1] * a * a
    Jp[:, 2, 2] = -a * a
    S = Jp @ (R @ cov @ R.T) @ Jp.transpose(0, 2, 1) + np.array([np.diag([s * s, s * s, (q / (zz * zz)) ** 2])
                                                                 for s, q, zz in zip(spx, sz, z)])
    Lt = np.linalg.cholesky(np.linalg.inv(S)).transpose(0, 2, 1)
    assert np.allclose(whitening(S), Lt, rtol=1e-12, atol=0)
    assert np.allclose(r, np.einsum("nij,nj->ni", Lt, e), rtol=1e-11, atol=1e-12)
    h = 1e-7
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = h
        Pp = P + np.cross(xi[:3], P) + xi[3:]
        Pm = P - np.cross(xi[:3], P) - xi[3:]
        num = np.einsum("nij,nj->ni", Lt, (dense(Pp)[0] - dense(Pm)[0]) / (2 * h))
        assert np.allclose(J[:, :, k], -num, rtol=1e-5, atol=1e-6 * np.abs(J).max())


def _pixels_off_their_depth():
    """(map, features, matches, true pose): 300 exact landmarks seen with exact 3-D points whose colour
    pixels are shifted 3 px (a colour image misregistered against its depth)."""
    from types import SimpleNamespace

    from rgbdslam.landmarks.tracking import MapMatch

    X = _scene(300, seed=6)
    m = LandmarkMap("single")
    ids = m.add(X, np.tile(np.eye(3) * 1e-8, (len(X), 1, 1)), np.zeros((len(X), 32), np.uint8), 0, 0)
    P = _pose([0.01, -0.02, 0.03], [0.05, 0.02, -0.04])
    Pc, uv, z = _seen(P, X)
    feats = SimpleNamespace(uv=uv + [3.0, 0.0], pts=Pc)
    match = MapMatch(np.arange(len(X)), ids, len(X))
    return m, feats, match, P


def test_points_refine_follows_the_depth_where_the_pixels_disagree():
    # the colour pixels shifted 3 px against exact 3-D points (a misregistered colour image): the
    # reprojection refine follows the pixels (the pose turns by ~0.3 deg), refine 'points' keeps the
    # 3-D fit (exact pose) and carries the registration's information formula (RMS 0 -> the 3 mm floor)
    from rgbdslam.frontend.registration.base import SIGMA_FLOOR, point_information
    from rgbdslam.geometry.se3 import rotation_angle
    from rgbdslam.landmarks.tracking import estimate_pose

    m, feats, match, P = _pixels_off_their_depth()
    Pc = feats.pts
    sig = np.full(len(Pc), 0.01)
    out = {r: estimate_pose(m, feats, match, P, sig, 0.03, 50, 10, "uniform", 1.0, np.random.default_rng(0), r, CAM,
                            1.0, 10.0, True, False) for r in ("reprojection", "points")}
    assert _err(out["points"].pose, P) < 1e-6
    turn = np.degrees(rotation_angle((inv(P) @ out["reprojection"].pose)[:3, :3]))
    # 3 px at f = 525 is 0.33 deg: taken as a turn (0.1 deg) and a sideways shift (7 mm)
    assert turn > 0.05 and _err(out["reprojection"].pose, P) > 4e-3
    assert np.allclose(out["points"].information, point_information(Pc, SIGMA_FLOOR))


def test_map_pose_fits_3d_points_when_the_depth_is_not_registered_to_the_colour():
    """``map_pose`` (the one map-pose call of the landmarks section): a camera whose depth comes from a
    second camera (``Camera.depth_registered`` false, 7-Scenes) gets the 3-D refit ('points') in place
    of the configured reprojection refine, so pixels 3 px off their depth (the calibration's error) do
    not turn the pose; a registered camera keeps the reprojection refine, its pose bit for bit."""
    from dataclasses import replace

    from rgbdslam.landmarks.config import LandmarksConfig
    from rgbdslam.landmarks.tracking import estimate_pose, map_pose

    m, feats, match, P = _pixels_off_their_depth()
    z = feats.pts[:, 2]
    cfg = LandmarksConfig(min_inliers=10)
    assert cfg.refine == "reprojection"
    unregistered = replace(CAM, depth_registered=False)
    two = map_pose(m, feats, match, P, cfg, unregistered, np.random.default_rng(0))
    one = map_pose(m, feats, match, P, cfg, CAM, np.random.default_rng(0))
    assert _err(two.pose, P) < 1e-6 and _err(one.pose, P) > 4e-3  # the pixels' 3 px shift turns only the latter
    sig = cfg.depth_noise_a + cfg.depth_noise_b * z * z  # map_pose's depth noise, operation for operation
    by_hand = estimate_pose(m, feats, match, P, sig, cfg.ransac_threshold, cfg.ransac_iterations, cfg.min_inliers,
                            cfg.sampling, cfg.old_fraction, np.random.default_rng(0), "reprojection", CAM,
                            cfg.sigma_px, cfg.chi_gate, True, cfg.adaptive_noise)
    assert np.array_equal(one.pose, by_hand.pose)


def test_residuals_without_jacobians_and_the_rotated_covariance():
    """``jacobian=False`` gives the same residuals bit for bit; the landmark covariance rotated into
    the camera (the (N, 9) @ (9, 6) product) is R Σ Rᵀ: with Σ along the camera's z after the rotation
    (a landmark straight ahead) no pixel variance reaches the residuals, as hand-worked in
    test_landmark_uncertainty_along_the_ray_does_not_reach_the_pixels."""
    rng = np.random.default_rng(2)
    X = _scene(200, 3)
    R = _pose([0.05, -0.1, 0.2], [0, 0, 0])[:3, :3]
    t = np.array([0.1, -0.05, 0.2])
    P = X @ R.T + t
    uv = np.stack([CAM.fx * P[:, 0] / P[:, 2] + CAM.cx, CAM.fy * P[:, 1] / P[:, 2] + CAM.cy], axis=1)
    uv += rng.normal(0, 1, uv.shape)
    z = P[:, 2] + rng.normal(0, 0.01, len(P))
    A = rng.normal(0, 0.01, (len(X), 3, 3))
    cov = A @ A.transpose(0, 2, 1)
    r, J = reprojection_residuals(R, t, X, uv, z, CAM, 1.0, np.full(len(X), 0.01), cov)
    r2, J2 = reprojection_residuals(R, t, X, uv, z, CAM, 1.0, np.full(len(X), 0.01), cov, jacobian=False)
    assert J2 is None and np.array_equal(r, r2)
    # the same residuals from the covariance rotated by hand and handed over as the camera's (R = I)
    Cc = np.einsum("ij,njk,lk->nil", R, cov, R)
    r3, _ = reprojection_residuals(np.eye(3), np.zeros(3), P, uv, z, CAM, 1.0, np.full(len(X), 0.01), Cc)
    assert np.allclose(r, r3, rtol=1e-10, atol=1e-12)
    # a landmark straight ahead of the rotated camera with world covariance along its ray: pixels untouched
    ahead = R.T @ (np.array([0.0, 0.0, 2.0]) - t)
    ray = R.T @ np.array([0.0, 0.0, 1.0])
    c1 = (0.05**2 * np.outer(ray, ray))[None]
    r4, _ = reprojection_residuals(R, t, ahead[None], np.array([[CAM.cx + 1.5, CAM.cy - 3.0]]), np.array([2.0]),
                                   CAM, 1.5, np.array([0.01]), c1)
    assert np.allclose(r4[0, :2], [1.0, -2.0])


def test_refine_iterations_sets_the_gauss_newton_steps_of_each_pass():
    """``refine_iterations`` (landmarks.refine_iterations): 5, the default, gives the pose of the call
    without it bit for bit; one step per pass stops short of the converged pose, many steps reach it."""
    from types import SimpleNamespace

    from rgbdslam.landmarks.tracking import MapMatch, estimate_pose

    rng = np.random.default_rng(8)
    X = _scene(300, seed=9)
    m = LandmarkMap("single")
    ids = m.add(X, np.tile(np.eye(3) * 1e-6, (len(X), 1, 1)), np.zeros((len(X), 32), np.uint8), 0, 0)
    P = _pose([0.02, -0.01, 0.03], [0.1, 0.02, -0.05])
    Pc, uv, z = _seen(P, X)
    dz = rng.normal(scale=0.01, size=len(X))
    feats = SimpleNamespace(uv=uv + rng.normal(scale=1.0, size=uv.shape), pts=Pc * (1 + dz / Pc[:, 2])[:, None])
    match = MapMatch(np.arange(len(X)), ids, len(X))
    sig = np.full(len(X), 0.01)

    def run(**kw):
        return estimate_pose(m, feats, match, P, sig, 0.03, 50, 10, "uniform", 1.0, np.random.default_rng(0),
                             "reprojection", CAM, 1.0, 3.0, True, True, **kw).pose

    default, five, one, many = run(), run(refine_iterations=5), run(refine_iterations=1), run(refine_iterations=30)
    assert np.array_equal(default, five)
    assert _err(five, many) < 1e-6  # five steps per pass: converged to a micrometre
    assert _err(one, many) > 10 * _err(five, many)  # one step per pass: not
