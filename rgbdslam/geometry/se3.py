"""Small SE(3)/SO(3) helpers on 4x4 / 3x3 NumPy arrays.

Quaternions <-> matrices are NumPy here (not SciPy's ``Rotation``): every command reads or writes
a trajectory before its first frame, and ``scipy.spatial`` costs 0.3-0.7 s to import on the
2-core machine (docs/benchmarks.md "End cost"); SciPy is imported where it is needed."""

from __future__ import annotations

import math

import numpy as np


def skew_batch(p: np.ndarray) -> np.ndarray:
    """(N, 3) vectors -> (N, 3, 3) cross-product matrices ([p]x q = p x q)."""
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    S = np.zeros((len(p), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -p[:, 2], p[:, 1]
    S[:, 1, 0], S[:, 1, 2] = p[:, 2], -p[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -p[:, 1], p[:, 0]
    return S


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation matrix of the rotation vector ``w``."""
    th = math.sqrt(float(w.dot(w)))  # np.linalg.norm's own sqrt(w·w), without its dispatch
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / th**2 * (K @ K)


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t).reshape(3)
    return T


def look_along(position: np.ndarray, forward: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes: x right, y down, z forward) at ``position`` looking along
    ``forward``, no roll about it: x is ``forward x up`` (``up`` must not be parallel to ``forward``)."""
    z = np.asarray(forward, dtype=np.float64)
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_pose(np.stack([x, y, z], axis=1), position)


def inv(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (or a stack of them, shape (..., 4, 4))."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    Ti[..., 3, 3] = 1.0
    return Ti


def transform_points(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points."""
    return P @ T[:3, :3].T + T[:3, 3]


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle (rad) of rotation matrices, shape (..., 3, 3)."""
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def motion_between(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """(translation metres, rotation degrees) of ``inv(A) @ B``: how far pose B is from pose A."""
    rel = inv(A) @ B
    return float(np.linalg.norm(rel[:3, 3])), float(np.degrees(rotation_angle(rel[:3, :3])))


def scale_motion(V: np.ndarray, factor: float) -> np.ndarray:
    """The rigid motion V scaled on SE(3) by ``factor`` (rotation vector and translation scaled
    alike): the constant-velocity motion over ``factor`` times V's time span."""
    if factor == 1.0:
        return V
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(Rotation.from_matrix(V[:3, :3]).as_rotvec() * factor).as_matrix()
    out[:3, 3] = V[:3, 3] * factor
    return out


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Closest rotation to a 3x3 matrix in the Frobenius norm (chordal projection)."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def pose_from_tum(t: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """4x4 poses from TUM translation (N,3) and quaternion (N,4) in x y z w order."""
    t = np.atleast_2d(t)
    q = np.atleast_2d(q_xyzw)
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, :3] = quat_to_matrix(q)
    T[:, :3, 3] = t
    return T


def quat_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of quaternions (N, 4; x y z w; normalised here)."""
    q = np.asarray(q_xyzw, dtype=np.float64).reshape(-1, 4)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.stack([x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw),
                     2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw),
                     2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2], axis=1).reshape(-1, 3, 3)


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (N, 4; x y z w) of rotation matrices (N, 3, 3), by the largest of the four
    (Shepperd's method: the trace or the largest diagonal element picks the component computed
    from a square root, the others follow from sums and differences of the off-diagonal terms)."""
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    d = np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2], R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]], axis=1)
    pick = d.argmax(axis=1)
    q = np.empty((len(R), 4))
    for i in range(3):  # x, y or z the largest
        m = pick == i
        j, k = (i + 1) % 3, (i + 2) % 3
        Rm = R[m]
        q[m, i] = 1 - d[m, 3] + 2 * Rm[:, i, i]
        q[m, j] = Rm[:, j, i] + Rm[:, i, j]
        q[m, k] = Rm[:, k, i] + Rm[:, i, k]
        q[m, 3] = Rm[:, k, j] - Rm[:, j, k]
    m = pick == 3  # w the largest
    Rm = R[m]
    q[m, 0] = Rm[:, 2, 1] - Rm[:, 1, 2]
    q[m, 1] = Rm[:, 0, 2] - Rm[:, 2, 0]
    q[m, 2] = Rm[:, 1, 0] - Rm[:, 0, 1]
    q[m, 3] = 1 + d[m, 3]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def pose_to_tum(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (N,3) and unit quaternion (N,4, x y z w, w >= 0) of poses (N,4,4)."""
    T = np.asarray(T).reshape(-1, 4, 4)
    q = matrix_to_quat(T[:, :3, :3])
    q[q[:, 3] < 0] *= -1
    return T[:, :3, 3].copy(), q
