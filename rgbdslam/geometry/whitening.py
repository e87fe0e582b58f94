"""Whitening of 3x3 covariances: for each symmetric positive definite S (as arrays of its six entries), the
rows of Lᵀ with S⁻¹ = L Lᵀ, so that ``Lᵀ r`` is a residual with the identity covariance. Closed forms for whole
arrays at once (the landmark map's reprojection refine, the stereo pose refit), not one LAPACK call per matrix."""

from __future__ import annotations

import numpy as np


def whitening_rows(a, b, c, d, e, f):
    """The rows of Lᵀ, L the Cholesky factor of S⁻¹ (S⁻¹ = L Lᵀ), for symmetric positive definite
    3x3 matrices S = [[a, b, c], [b, d, e], [c, e, f]] given as arrays of their entries: the
    adjugate inverse, then the 3x3 Cholesky recurrences (``cholesky(inv(S))`` to rounding, without
    LAPACK's per-matrix calls). Returns (l00, l10, l20, l11, l21, l22): Lᵀ = [[l00, l10, l20],
    [0, l11, l21], [0, 0, l22]]."""
    A00, A01, A02 = d * f - e * e, c * e - b * f, b * e - c * d
    A11, A12, A22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A00 + b * A01 + c * A02
    l00 = np.sqrt(A00 / det)
    l10, l20 = A01 / det / l00, A02 / det / l00
    l11 = np.sqrt(A11 / det - l10 * l10)
    l21 = (A12 / det - l20 * l10) / l11
    l22 = np.sqrt(A22 / det - l20 * l20 - l21 * l21)
    return l00, l10, l20, l11, l21, l22


def whitening(S: np.ndarray) -> np.ndarray:
    """Lᵀ (N, 3, 3) with S⁻¹ = L Lᵀ (L lower triangular) for symmetric positive definite ``S`` (N, 3, 3)."""
    l00, l10, l20, l11, l21, l22 = whitening_rows(S[:, 0, 0], S[:, 0, 1], S[:, 0, 2], S[:, 1, 1], S[:, 1, 2], S[:, 2, 2])
    Lt = np.zeros_like(S)
    Lt[:, 0, 0], Lt[:, 0, 1], Lt[:, 0, 2] = l00, l10, l20
    Lt[:, 1, 1], Lt[:, 1, 2], Lt[:, 2, 2] = l11, l21, l22
    return Lt
