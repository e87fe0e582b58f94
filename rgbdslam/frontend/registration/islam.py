"""ISLAM — the per-reference registration of the weighted multi-frame method
(docs/references.md §2).

:func:`islam_pair` is the loop for one reference: SVD fit, gate ``th_j = alpha * j**beta``
(shrinking for beta < 0), weight ``W = 1 / (mean L1 residual)``, stop when ``th < minError``
or fewer than ``minPoint`` pairs survive. The front end registers against the last
``registration.mp`` tracked frames (:attr:`IslamRegistration.multi_reference`) and fuses the
candidates (:mod:`rgbdslam.frontend.pose_fusion`). The refit on the survivors is shared
with every strategy (:class:`~rgbdslam.frontend.registration.base.Registration`).
"""

from __future__ import annotations

import numpy as np

from rgbdslam.frontend.registration.base import Registration
from rgbdslam.geometry.rigid import fit_rigid_stacked, residuals, row_norms


def gate_threshold(alpha: float, beta: float, j: int) -> float:
    """The gate of iteration ``j`` (1-based): ``alpha * j**beta``."""
    return alpha * float(j) ** beta


def inverse_mean_l1(r: np.ndarray) -> float:
    """ISLAM weight of residual vectors r (N, 3): ``1 / (sum_i |r_i|_1 / N)``."""
    e = float(np.abs(r).sum())
    return len(r) / e if e > 0 else np.inf


def islam_pair(S: np.ndarray, D: np.ndarray, keep: np.ndarray, max_it: int, alpha: float, beta: float,
               min_error: float, min_points: int) -> tuple[np.ndarray, float, int] | None:
    """The loop above from the pairs ``keep``: (surviving pairs, weight W, iterations), None when
    fewer than ``min_points`` pairs survive."""
    need = max(3, min_points)
    W = 0.0
    it = 0
    SD = np.concatenate((S, D), axis=1)  # the pairs as rows [s | d]: one compress and one sum per refit
    for j in range(1, max_it + 1):  # compress / count_nonzero: boolean indexing's and sum's numbers, faster
        it = j
        T = fit_rigid_stacked(SD.compress(keep, axis=0))
        th = gate_threshold(alpha, beta, j)
        r = residuals(T, S, D)
        W = inverse_mean_l1(r.compress(keep, axis=0))
        keep = keep & (row_norms(r) <= th)
        if th < min_error or np.count_nonzero(keep) < need:
            break
    if np.count_nonzero(keep) < need:
        return None
    return keep, W, it


class IslamRegistration(Registration):
    """``registration.method = islam`` (the default)."""

    name = "islam"
    multi_reference = True

    def select(self, S, D, keep):
        rc = self.rc
        out = islam_pair(S, D, keep, rc.max_iterations, rc.alpha, rc.beta, rc.min_error, self.min_points)
        return None if out is None else (out[0], out[1])
