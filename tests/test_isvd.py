"""Exact maths of the rigid fit, ISVD, the ISLAM gate/weights and the candidate fusion."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rgbdslam.frontend.islam import chordal_mean, fuse_candidates, gate_threshold, inverse_mean_l1, islam_pair
from rgbdslam.frontend.isvd import isvd
from rgbdslam.frontend.ransac import ransac_rigid
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


def test_svd_fit_reflection_case():
    # Planar points mirrored through the plane z=0: the unconstrained least-squares answer
    # is a reflection (det -1); the fix must return a proper rotation.
    S = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0.5, 0.2, 0]], float)
    D = S * np.array([1, 1, -1]) + np.array([0.0, 0.0, 0.0])
    T = fit_rigid(S, D)
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)
    # For coplanar points on z=0, the mirrored set equals the set: identity is the best rotation.
    assert np.allclose(T, np.eye(4), atol=1e-12)
    # Non-planar mirrored set: still a rotation (det +1), never the reflection diag(1,1,-1).
    S2 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0], [1, 1, 1]])
    R = fit_rigid(S2, S2 * np.array([1, 1, -1]))[:3, :3]
    assert np.isclose(np.linalg.det(R), 1.0)
    assert not np.allclose(R, np.diag([1, 1, -1.0]))


def test_isvd_with_30_percent_outliers():
    rng, T, S, D = _known(seed=2, n=300)
    bad = rng.choice(len(S), size=90, replace=False)
    D[bad] += rng.uniform(-0.5, 0.5, size=(90, 3)) + np.sign(rng.uniform(-1, 1, size=(90, 3))) * 0.1
    res = isvd(D, S, max_it=10, e_start=0.5, e_min=0.01)
    assert res is not None
    assert np.abs(res.T - T).max() < 1e-6
    assert not res.inliers[bad].any()
    assert res.inliers.sum() == 300 - 90


def test_isvd_collapse_returns_none():
    rng = np.random.default_rng(3)
    S = rng.uniform(-1, 1, (30, 3))
    D = rng.uniform(-1, 1, (30, 3))  # no consistent transform
    assert isvd(D, S, max_it=10, e_start=0.2, e_min=0.01, min_points=12) is None


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
    res = islam_pair(D, S, max_it=20, alpha=0.2, beta=-1.0, min_error=0.01, min_points=12)
    assert res is not None
    assert not res.inliers[:20].any()
    # gates 0.2, 0.1, ... ; th_j = 0.2/j < 0.01 first at j = 21 -> capped by max_it = 20
    assert res.iterations == 20
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
    assert out1[1][50:].all()
