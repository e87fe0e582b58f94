"""Closed-form least-squares rigid fit (Arun, Huang & Blostein 1987; Umeyama 1991 reflection fix).

``fit_rigid(S, D)`` returns the 4x4 ``T`` minimising ``sum_i w_i ||d_i - (R s_i + t)||^2``:
it maps the source points ``S`` onto the destination points ``D``. ``fit_rigid_batch`` does the
same for a stack of small point sets at once (used by RANSAC on minimal samples).
"""

from __future__ import annotations

import numpy as np


def _rotation_from_cov(H: np.ndarray) -> np.ndarray:
    """R = V diag(1, 1, det(V U^T)) U^T for cross-covariances H = U S V^T, shape (..., 3, 3)."""
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    Ut = np.swapaxes(U, -1, -2)
    d = np.sign(np.linalg.det(V @ Ut))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros(H.shape[:-2] + (3,))
    D[..., 0] = 1.0
    D[..., 1] = 1.0
    D[..., 2] = d
    return (V * D[..., None, :]) @ Ut


def _det3_sign(M: np.ndarray) -> float:
    """Sign (+-1.0) of the determinant of an orthogonal 3x3 matrix (its cofactor expansion in Python
    floats: no LAPACK call; the determinant is +-1 to rounding, so its sign is never in doubt)."""
    (a, b, c), (d, e, f), (g, h, i) = M.tolist()
    return 1.0 if a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) >= 0.0 else -1.0


def _rotation_from_cov3(H: np.ndarray) -> np.ndarray:
    """:func:`_rotation_from_cov` of one 3x3 ``H``, the same numbers: the reflection sign
    det(V U^T) = det(V) det(U) from two cofactor expansions instead of a product and LAPACK's
    determinant, and V diag(1, 1, d) as V itself (a C-ordered copy, as the product makes it) or
    with its last column negated. Less than half the call overhead (``fit_rigid`` runs ~60 times
    per frame)."""
    U, _, Vt = np.linalg.svd(H)
    V = Vt.T
    if _det3_sign(U) * _det3_sign(Vt) > 0.0:
        VD = np.array(V, order="C")
    else:
        VD = V * _FLIP_LAST
    return VD @ U.T


_FLIP_LAST = np.array([1.0, 1.0, -1.0])
_EYE4 = np.eye(4)


def fit_rigid(S: np.ndarray, D: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """4x4 rigid transform T with ``D ~ T * S`` in the (weighted) least-squares sense.

    S, D: (N, 3) matched points, N >= 3 and not all collinear for a unique answer.
    weights: optional (N,) non-negative weights.
    """
    S = np.asarray(S, dtype=np.float64).reshape(-1, 3)
    D = np.asarray(D, dtype=np.float64).reshape(-1, 3)
    n = len(S)
    if n != len(D):
        raise ValueError("fit_rigid needs the same number of source and destination points")
    if n < 3:
        raise ValueError("fit_rigid needs at least 3 point pairs")
    if weights is None:
        p = np.add.reduce(S, axis=0) / n  # = S.mean(axis=0) (the same sum and division), without its wrapper
        q = np.add.reduce(D, axis=0) / n
        H = (S - p).T @ (D - q)
    else:
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        w = w / w.sum()
        p = w @ S
        q = w @ D
        H = ((S - p) * w[:, None]).T @ (D - q)
    R = _rotation_from_cov3(H)
    T = _EYE4.copy()
    T[:3, :3] = R
    T[:3, 3] = q - R @ p
    return T


def fit_rigid_stacked(SD: np.ndarray) -> np.ndarray:
    """:func:`fit_rigid` (unweighted) of the pairs stacked as rows ``[s | d]`` of ``SD`` (N, 6), the
    same bits: both means from one sum down the rows (NumPy adds the rows of a C-ordered array one by
    one, column by column, whatever their width), the centred source and destination as column views
    of one difference into the same covariance product. For loops that refit subsets of the same
    pairs (ISLAM): one ``compress`` and one sum per fit instead of two each."""
    n = len(SD)
    if n < 3:
        raise ValueError("fit_rigid needs at least 3 point pairs")
    m = np.add.reduce(SD, axis=0) / n
    C = SD - m
    R = _rotation_from_cov3(C[:, :3].T @ C[:, 3:])
    T = _EYE4.copy()
    T[:3, :3] = R
    T[:3, 3] = m[3:] - R @ m[:3]
    return T


def fit_rigid_batch(S: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Unweighted fits for a batch: S, D of shape (B, k, 3) -> T of shape (B, 4, 4)."""
    S = np.asarray(S, dtype=np.float64)
    D = np.asarray(D, dtype=np.float64)
    p = S.mean(axis=1)
    q = D.mean(axis=1)
    H = np.einsum("bki,bkj->bij", S - p[:, None], D - q[:, None])
    R = _rotation_from_cov(H)
    T = np.zeros((len(S), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = q - np.einsum("bij,bj->bi", R, p)
    T[:, 3, 3] = 1.0
    return T


def row_norms(r: np.ndarray) -> np.ndarray:
    """Euclidean norms of the rows of ``r`` (N, k): ``np.linalg.norm(r, axis=1)``'s own expression
    (the same numbers) without its dispatch, which costs more than the sums at a few hundred rows."""
    return np.sqrt(np.add.reduce(r * r, axis=1))


def residuals(T: np.ndarray, S: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Per-pair residual vectors ``d_i - T s_i``, shape (N, 3)."""
    return D - (S @ T[:3, :3].T + T[:3, 3])


def fit_with_stats(S: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, float, float]:
    """``fit_rigid(S, D)`` plus the fit's mean L1 and RMS Euclidean residuals (metres)."""
    T = fit_rigid(S, D)
    r = residuals(T, S, D)
    return T, float(np.abs(r).sum(axis=1).mean()), float(np.sqrt((r**2).sum(axis=1).mean()))
