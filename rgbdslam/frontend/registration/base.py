"""The registration interface: matched 3-D points -> rigid pose + inliers + information.

Every strategy (``ransac.py``, ``isvd.py``, ``islam.py``; a new one goes next to them) is a
subclass of :class:`Registration` that implements one step, :meth:`Registration.select`:
which of the matched pairs are inliers (and, optionally, the pair set's weight). The shared
parts run around it in :meth:`Registration.fit`, the same for every strategy:

1. ``select`` (the strategy);
2. refit: one least-squares fit on the inliers (:func:`rgbdslam.geometry.rigid.fit_with_stats`),
   its residuals, and the information of the pose from the inlier points
   (:func:`fit_information`: one formula and one noise floor, also for loop edges).

Convention: the source points ``S`` are the reference frame's, the destination points ``D``
the current frame's, and ``RigidFit.T`` maps the first onto the second: ``D ~ T @ S``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from rgbdslam.frontend.config import RegistrationConfig
from rgbdslam.geometry.rigid import fit_with_stats, residuals, row_norms

# Lower bound (metres) of the per-axis point noise behind the information of a rigid fit: a fit
# with a tiny residual (few, perfectly consistent points) must not become overconfident.
SIGMA_FLOOR = 0.003


@dataclass
class RigidFit:
    """What a registration strategy returns for one set of matched pairs."""

    T: np.ndarray  # 4x4, D ~ T @ S
    inliers: np.ndarray  # (N,) bool over the pairs given to fit
    residual_l1: float  # mean L1 residual of the inliers (m)
    residual_l2: float  # RMS Euclidean residual of the inliers (m)
    weight: float  # quality weight (ISLAM's inverse mean L1 residual, 1/m)
    information: np.ndarray  # 6x6 information of inv(T) (rotation, translation), right perturbation

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))


def point_information(P: np.ndarray, sigma: float) -> np.ndarray:
    """Gauss–Newton information of a pose from points P (N,3) in its own frame, iid noise sigma/axis.

    Residual Jacobian of ``X Exp(xi) p`` w.r.t. xi = (omega, v) is ``R_X [-[p]x, I]``.
    """
    P = np.asarray(P, dtype=np.float64)
    n = len(P)
    s = P.sum(axis=0)
    # sum [p]x^T [p]x = sum (|p|^2 I - p p^T)
    A = np.eye(3) * np.einsum("ij,ij->", P, P) - P.T @ P
    sx = np.array([[0, -s[2], s[1]], [s[2], 0, -s[0]], [-s[1], s[0], 0]])
    H = np.zeros((6, 6))
    H[:3, :3] = A
    H[:3, 3:] = sx  # (-[p]x)^T I summed = [s]x
    H[3:, :3] = sx.T
    H[3:, 3:] = n * np.eye(3)
    return H / (sigma * sigma)


def fit_information(points: np.ndarray, residual_l2: float, sigma_floor: float = SIGMA_FLOOR) -> np.ndarray:
    """Information of a rigid fit on ``points`` (the inliers, in the frame whose pose it is) whose
    RMS Euclidean residual is ``residual_l2``: per-axis noise ``max(residual_l2 / sqrt(3), floor)``."""
    return point_information(points, max(residual_l2 / np.sqrt(3.0), sigma_floor))


class Registration:
    """A registration strategy, built from the ``registration`` config section.

    Subclasses set :attr:`name` (the ``registration.method`` that selects them), implement
    :meth:`select` and may override :attr:`multi_reference` and
    :attr:`replaces_prefilter`; :func:`rgbdslam.frontend.registration.get_registration` builds them.
    """

    name: ClassVar[str] = ""
    # the front end registers against the last registration.mp frames and fuses the candidates
    multi_reference: ClassVar[bool] = False
    # a matching.prefilter this strategy makes redundant (it is skipped when configured)
    replaces_prefilter: ClassVar[str | None] = None

    def __init__(self, rc: RegistrationConfig):
        self.rc = rc
        self.min_points = max(3, rc.min_points)

    def select(self, S: np.ndarray, D: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, float | None] | None:
        """The strategy: inlier mask over all pairs (starting from ``keep``, every pair) and the
        pair set's weight (None: the inverse mean L1 residual of the refit); None = no fit."""
        raise NotImplementedError

    def fit(self, S: np.ndarray, D: np.ndarray) -> RigidFit | None:
        """Rigid fit of the matched points ``S`` (reference) onto ``D`` (current), ``D ~ T @ S``.
        None when fewer than ``registration.min_points`` pairs are given."""
        S = np.asarray(S, dtype=np.float64)
        D = np.asarray(D, dtype=np.float64)
        if len(D) < self.min_points:
            return None
        out = self.select(S, D, np.ones(len(D), bool))
        if out is None:
            return None
        inliers, weight = out
        T, l1, l2 = fit_with_stats(S[inliers], D[inliers])  # the refit on the survivors
        return RigidFit(T=T, inliers=inliers, residual_l1=l1, residual_l2=l2,
                        weight=float(1.0 / max(l1, 1e-12) if weight is None else weight),
                        information=fit_information(D[inliers], l2))
