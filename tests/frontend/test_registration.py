"""Exact maths of the rigid fit, ISVD, the ISLAM gate/weights and the candidate fusion."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rgbdslam.config import RegistrationConfig
from rgbdslam.frontend.pose_fusion import chordal_mean, fuse_candidates
from rgbdslam.frontend.registration import STRATEGIES, get_registration
from rgbdslam.frontend.registration.islam import IslamRegistration, gate_threshold, inverse_mean_l1, islam_pair
from rgbdslam.frontend.registration.isvd import IsvdRegistration
from rgbdslam.geometry.ransac import ransac_rigid
from rgbdslam.geometry.rigid import fit_rigid, fit_rigid_batch
from rgbdslam.geometry.se3 import make_pose, rotation_angle, transform_points


def _known(seed=1, n=200):
    rng = np.random.default_rng(seed)
    T = make_pose(Rotation.from_rotvec([0.1, -0.2, 0.15]).as_matrix(), [0.05, -0.1, 0.2])
    S = rng.uniform([-1, -1, 0.5], [1, 1, 4], size=(n, 3))
    return rng, T, S, transform_points(T, S)


def test_svd_fit_exact():
    _, T, S, D = _known()
    assert np.abs(fit_rigid(S, D) - T).max() < 1e-9
    # weighted variant with arbitrary positive weights is exact too
    w = np.linspace(0.1, 3, len(S))
    assert np.abs(fit_rigid(S, D, w) - T).max() < 1e-9
    # batched minimal samples
    Tb = fit_rigid_batch(np.stack([S[:3], S[3:6]]), np.stack([D[:3], D[3:6]]))
    assert np.abs(Tb - T).max() < 1e-9


def _naive_rotation(S, D):
    """Arun's SVD answer without the reflection fix: V U^T for H = sum (s - p)(d - q)^T."""
    U, _, Vt = np.linalg.svd((S - S.mean(0)).T @ (D - D.mean(0)))
    return Vt.T @ U.T


def test_svd_fit_reflection_case_planar_points():
    # Coplanar points (z = 0) moved by a proper rotation: H has rank 2, the sign of its third
    # singular vectors is arbitrary, and the naive V U^T is then a reflection for some rotations.
    # The fix must recover every rotation and translation exactly.
    rng = np.random.default_rng(0)
    S = np.c_[rng.uniform(-1, 1, (8, 2)), np.zeros(8)]
    t = np.array([0.3, -0.2, 1.0])
    naive_dets = []
    for R in Rotation.random(20, random_state=1).as_matrix():
        D = S @ R.T + t
        naive_dets.append(np.linalg.det(_naive_rotation(S, D)))
        T = fit_rigid(S, D)
        assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)
        np.testing.assert_allclose(T[:3, :3], R, atol=1e-9)
        np.testing.assert_allclose(T[:3, 3], t, atol=1e-9)
        Tb = fit_rigid_batch(S[None], D[None])[0]
        np.testing.assert_allclose(Tb[:3, :3], R, atol=1e-9)
    # precondition: the naive SVD did produce reflections here, so the fix was exercised
    assert sum(np.isclose(d, -1.0) for d in naive_dets) >= 3, np.round(naive_dets)


def test_svd_fit_reflection_case_mirrored_points():
    # Non-planar points mirrored through z = 0, with the largest spread along z: the best
    # orthogonal matrix is the mirror diag(1, 1, -1) itself, the best rotation is not identity.
    # Centred S with S^T S = diag(2, 8, 18) (x, y, z spreads 1, 2, 3 in +- pairs):
    S = np.array([[1, 0, 0], [-1, 0, 0], [0, 2, 0], [0, -2, 0], [0, 0, 3], [0, 0, -3]], float)
    D = S * np.array([1, 1, -1])
    # Maximise tr(R H), H = sum s d^T = diag(2, 8, -18): over diagonal sign rotations
    # I -> -8, diag(1,-1,-1) -> 12, diag(-1,1,-1) -> 24, diag(-1,-1,1) -> -28. The optimum over
    # SO(3) is sigma1 + sigma2 - sigma3 = 18 + 8 - 2 = 24, reached by diag(-1, 1, -1)
    # (180 deg about y), leaving residual only along x: d - R s = (2 x, 0, 0).
    assert np.isclose(np.linalg.det(_naive_rotation(S, D)), -1.0)  # naive: the mirror
    T = fit_rigid(S, D)
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)
    np.testing.assert_allclose(T[:3, :3], np.diag([-1.0, 1.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], 0.0, atol=1e-12)
    # weighted (uniform weights) and batched variants agree
    np.testing.assert_allclose(fit_rigid(S, D, np.full(6, 0.5)), T, atol=1e-12)
    np.testing.assert_allclose(fit_rigid_batch(S[None], D[None])[0], T, atol=1e-12)


def test_isvd_with_30_percent_outliers():
    rng, T, S, D = _known(seed=2, n=300)
    bad = rng.choice(len(S), size=90, replace=False)
    D[bad] += rng.uniform(-0.5, 0.5, size=(90, 3)) + np.sign(rng.uniform(-1, 1, size=(90, 3))) * 0.1
    res = IsvdRegistration(RegistrationConfig(max_iterations=10, e_start=0.5, e_min=0.01, min_points=3)).fit(S, D)
    assert res is not None
    assert np.abs(res.T - T).max() < 1e-6
    assert not res.inliers[bad].any()
    assert res.inliers.sum() == 300 - 90


def test_isvd_collapse_returns_none():
    rng = np.random.default_rng(3)
    S = rng.uniform(-1, 1, (30, 3))
    D = rng.uniform(-1, 1, (30, 3))  # no consistent transform
    rc = RegistrationConfig(max_iterations=10, e_start=0.2, e_min=0.01, min_points=12)
    assert IsvdRegistration(rc).fit(S, D) is None


def test_gate_schedule_and_weight_hand_checked():
    assert gate_threshold(0.2, -1.0, 1) == pytest.approx(0.2)
    assert gate_threshold(0.2, -1.0, 4) == pytest.approx(0.05)
    assert gate_threshold(0.1, -0.5, 4) == pytest.approx(0.05)
    assert gate_threshold(0.3, -2.0, 3) == pytest.approx(0.3 / 9)
    # residuals (0.01, -0.02, 0.03) and (0, 0, -0.02): L1 sums 0.06 and 0.02 -> mean 0.04 -> W = 25
    r = np.array([[0.01, -0.02, 0.03], [0.0, 0.0, -0.02]])
    assert inverse_mean_l1(r) == pytest.approx(25.0)


def test_islam_pair_gates_outliers_and_weights():
    rng, T, S, D = _known(seed=4, n=100)
    D = D + rng.normal(0, 0.002, D.shape)
    D[:20] += 0.3  # 20 gross outliers
    rc = RegistrationConfig(max_iterations=20, alpha=0.2, beta=-1.0, min_error=0.01, min_points=12)
    res = IslamRegistration(rc).fit(S, D)
    assert res is not None
    assert not res.inliers[:20].any()
    # gates 0.2, 0.1, ... ; th_j = 0.2/j < 0.01 first at j = 21 -> capped by max_it = 20
    keep, weight, iterations = islam_pair(S, D, np.ones(len(S), bool), 20, 0.2, -1.0, 0.01, 12)
    assert iterations == 20 and np.array_equal(keep, res.inliers) and weight == res.weight
    assert rotation_angle(res.T[:3, :3].T @ T[:3, :3]) < 2e-3
    assert np.linalg.norm(res.T[:3, 3] - T[:3, 3]) < 3e-3
    # the weight is the inverse mean L1 residual of the pairs alive in the last iteration (~ 1/(3*0.0016))
    assert 100 < res.weight < 400


def test_chordal_mean_is_midpoint():
    R1 = Rotation.from_rotvec([0, 0, 0.2]).as_matrix()
    R2 = Rotation.from_rotvec([0, 0, 0.6]).as_matrix()
    Rm = chordal_mean(np.stack([R1, R2]), np.array([1.0, 1.0]))
    assert np.allclose(Rm, Rotation.from_rotvec([0, 0, 0.4]).as_matrix(), atol=1e-12)


def test_fusion_rejects_disagreeing_candidate():
    P = [make_pose(Rotation.from_rotvec([0, 0.1, 0]).as_matrix(), [1.0, 0, 0]),
         make_pose(Rotation.from_rotvec([0, 0.1, 0]).as_matrix(), [1.02, 0, 0]),
         make_pose(Rotation.from_rotvec([0, 0.5, 0]).as_matrix(), [1.5, 0, 0])]  # outlier
    w = np.array([1.0, 3.0, 2.0])
    pose, keep, frac = fuse_candidates(np.stack(P), w, "chordal", 0.05, 0.05)
    assert keep.tolist() == [True, True, False]
    assert frac == pytest.approx(4 / 6)
    assert pose[0, 3] == pytest.approx((1.0 * 1 + 1.02 * 3) / 4)
    assert np.allclose(pose[:3, :3], P[0][:3, :3])
    # thesis mode: every translation averaged, rotation of the heaviest candidate
    pose_t, keep_t, _ = fuse_candidates(np.stack(P), w, "thesis")
    assert keep_t.all()
    assert pose_t[0, 3] == pytest.approx((1.0 + 3.06 + 3.0) / 6)
    assert np.allclose(pose_t[:3, :3], P[1][:3, :3])


def test_ransac_rigid_seeded():
    rng, T, S, D = _known(seed=5, n=150)
    D[:50] += rng.uniform(-1, 1, (50, 3))
    out1 = ransac_rigid(S, D, 0.01, 100, np.random.default_rng(0))
    out2 = ransac_rigid(S, D, 0.01, 100, np.random.default_rng(0))
    assert out1 is not None
    assert np.array_equal(out1[0], out2[0])
    assert np.abs(out1[0] - T).max() < 1e-9
    mask = out1[1]
    # every displaced pair is more than the 1 cm threshold off (precondition), and all are rejected
    assert (np.linalg.norm(transform_points(T, S[:50]) - D[:50], axis=1) > 0.01).all()
    assert not mask[:50].any()
    assert mask[50:].all() and mask.sum() == 100
    assert np.array_equal(out2[1], mask)


def test_strategies_share_the_refit():
    """Every strategy rejects the gross outliers itself, and the pose is the least-squares refit on
    the inliers it selects."""
    rng, T, S, D = _known(seed=6, n=120)
    D = D + rng.normal(0, 0.001, D.shape)
    D[:30] += rng.uniform(0.2, 0.4, (30, 3))  # outliers
    for method in ("ransac", "isvd", "islam"):
        rc = RegistrationConfig(method=method, min_points=12, ransac_threshold=0.01)
        strategy = get_registration(rc)
        assert type(strategy) is STRATEGIES[method]
        fit = strategy.fit(S, D)
        assert fit is not None and not fit.inliers[:30].any() and fit.n_inliers > 80, method
        np.testing.assert_allclose(fit.T, fit_rigid(S[fit.inliers], D[fit.inliers]), atol=1e-12)
        assert np.abs(fit.T - T).max() < 5e-3
        # information of the refit: the inliers' points, per-axis sigma from the RMS residual
        from rgbdslam.frontend.registration import fit_information

        np.testing.assert_allclose(fit.information, fit_information(D[fit.inliers], fit.residual_l2))


def test_fit_information_has_one_noise_floor():
    from rgbdslam.frontend.registration import fit_information, point_information
    from rgbdslam.frontend.registration.base import SIGMA_FLOOR

    P = np.array([[0.0, 0, 1], [1, 0, 2], [0, 1, 3], [1, 1, 1]])
    # a residual below the floor (RMS 1 mm -> 0.58 mm per axis) is raised to it
    np.testing.assert_allclose(fit_information(P, 0.001), point_information(P, SIGMA_FLOOR))
    np.testing.assert_allclose(fit_information(P, 0.03), point_information(P, 0.03 / np.sqrt(3)))
    # translation block: n / sigma^2 on the diagonal
    assert fit_information(P, 0.03)[3, 3] == pytest.approx(4 / (0.03**2 / 3))


def test_seeded_rigid_refits_the_predictions_inliers():
    """No samples: the prediction's inliers (3 cm) refitted give the exact motion when the prediction
    is 1 cm off, the same answer as RANSAC; a prediction 10 cm off has no consensus (None)."""
    from rgbdslam.geometry.ransac import seeded_rigid

    rng = np.random.default_rng(8)
    S = rng.normal(size=(150, 3)) + [0, 0, 2]
    T = np.eye(4)
    T[:3, 3] = [0.05, 0.01, -0.02]
    D = S @ T[:3, :3].T + T[:3, 3]
    D[:30] += rng.normal(0, 0.5, (30, 3))
    near, far = T.copy(), T.copy()
    near[0, 3] += 0.01
    far[0, 3] += 0.1
    est, mask = seeded_rigid(S, D, 0.03, near, 30)
    assert np.allclose(est, T, atol=1e-9) and mask[30:].all() and mask.sum() <= 122
    ran = ransac_rigid(S, D, 0.03, 100, np.random.default_rng(0), 30, T0=near)
    assert np.allclose(ran[0], est, atol=1e-9) and np.array_equal(ran[1], mask)
    assert seeded_rigid(S, D, 0.03, far, 30) is None
