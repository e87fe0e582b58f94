"""Quaternions and rotation matrices (rgbdslam.geometry.se3), against hand-worked cases and SciPy."""

from __future__ import annotations

import numpy as np

from rgbdslam.geometry.se3 import matrix_to_quat, pose_from_tum, pose_to_tum, quat_to_matrix


def test_quaternions_of_hand_worked_rotations():
    s = np.sqrt(0.5)
    cases = [  # (x y z w), the matrix
        ((0, 0, 0, 1), np.eye(3)),
        ((1, 0, 0, 0), np.diag([1.0, -1.0, -1.0])),  # 180 deg about x
        ((0, 0, s, s), np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])),  # 90 deg about z
        ((0, s, 0, s), np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])),  # 90 deg about y
        ((0, 0, 2, 0), np.diag([-1.0, -1.0, 1.0])),  # not unit: normalised first
    ]
    for q, R in cases:
        np.testing.assert_allclose(quat_to_matrix(np.array([q], float))[0], R, atol=1e-15)
        back = matrix_to_quat(R[None])[0]
        want = np.asarray(q, float) / np.linalg.norm(q)
        np.testing.assert_allclose(back * np.sign(back @ want), want, atol=1e-15)


def test_quaternions_agree_with_scipy_on_every_branch():
    """Random rotations, and ones near 180 degrees about each axis (where x, y or z is the largest
    component): the same matrices and (up to sign) quaternions as SciPy's Rotation."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(4)
    q = rng.normal(size=(400, 4))
    near = np.zeros((3, 4))
    near[np.arange(3), np.arange(3)] = 1.0
    near[:, 3] = 1e-3
    q = np.concatenate([q, near, -q[:5]])
    np.testing.assert_allclose(quat_to_matrix(q), Rotation.from_quat(q).as_matrix(), atol=1e-14)
    R = Rotation.from_quat(q).as_matrix()
    ours, theirs = matrix_to_quat(R), Rotation.from_matrix(R).as_quat()
    np.testing.assert_allclose(ours * np.sign(np.sum(ours * theirs, axis=1))[:, None], theirs, atol=1e-14)


def test_tum_poses_round_trip_with_w_not_negative():
    rng = np.random.default_rng(5)
    t, q = rng.normal(size=(20, 3)), rng.normal(size=(20, 4))
    T = pose_from_tum(t, q)
    t2, q2 = pose_to_tum(T)
    np.testing.assert_allclose(t2, t)
    assert (q2[:, 3] >= 0).all()
    unit = q / np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.sum(q2 * unit, axis=1)), 1.0, atol=1e-14)
    np.testing.assert_allclose(pose_from_tum(t2, q2), T, atol=1e-14)


def test_skew_batch_is_the_cross_product_worked_by_hand():
    from rgbdslam.geometry.se3 import skew_batch

    S = skew_batch(np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 1.0]]))
    assert np.array_equal(S[0], [[0, -3, 2], [3, 0, -1], [-2, 1, 0]])
    assert np.array_equal(S[0] @ [4.0, 5.0, 6.0], [-3.0, 6.0, -3.0])  # (1,2,3) x (4,5,6)
    assert np.array_equal(S[1] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])  # z x x = y
