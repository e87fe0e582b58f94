"""One frame registered against another: descriptor matches -> pre-filter -> registration strategy.

:class:`PairRegistration` is what the front end (against each reference frame) and the loop
closer (against a candidate keyframe) call. Conventions: ``RegistrationResult.T`` maps
**reference-frame points into the current frame**, ``p_cur = T @ p_ref``; with
camera-to-world poses ``T = inv(P_cur) @ P_ref`` and the current frame's pose chained from
the reference is ``P_cur = P_ref @ inv(T)``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from rgbdslam.frontend.config import MatchingConfig
from rgbdslam.frontend.features import FrameFeatures
from rgbdslam.frontend.matching import guided_match, match_pairs, prefilter
from rgbdslam.frontend.registration import Registration, get_registration
from rgbdslam.geometry.rigid import fit_rigid

if TYPE_CHECKING:
    from rgbdslam.config import Config

# least share of a registration's inliers off depth edges for its pose to be fitted on them alone
EDGE_FREE_SHARE = 0.3


@dataclass
class RegistrationResult:
    """Pairwise registration of ``cur`` against ``ref``: ``p_cur = T @ p_ref``."""

    T: np.ndarray
    n_matches: int  # descriptor matches between depth-valid features
    n_inliers: int  # pairs surviving pre-filter and registration
    residual_l1: float  # mean L1 residual of the inliers (m)
    residual_l2: float  # RMS Euclidean residual of the inliers (m)
    weight: float  # ISLAM weight: inverse mean L1 residual (1/m)
    pairs: np.ndarray  # (n_inliers, 2) int: (index into ref features, index into cur features)
    information: np.ndarray  # 6x6 information of inv(T) (rotation, translation), right perturbation
    timings: dict[str, float] = field(default_factory=dict)
    matches: np.ndarray | None = None  # (n_matches, 2) every descriptor match, before any geometric filter


class PairRegistration:
    """Matching (``matching`` section) + the registration strategy; ``seed`` seeds the pre-filter."""

    def __init__(self, mc: MatchingConfig, strategy: Registration, seed: int = 0):
        self.mc = mc
        self.strategy = strategy
        self.seed = seed

    def __call__(self, ref: FrameFeatures, cur: FrameFeatures, T0: np.ndarray | None = None,
                 gate: float | None = None) -> RegistrationResult | None:
        """Register ``cur`` against ``ref``; None when too few pairs are left (``registration.min_points``).

        ``T0`` is a prediction of ``T`` (``p_cur = T0 @ p_ref``), e.g. from constant velocity.
        With ``gate`` (metres) and a trusted ``T0``, matching is guided (only 3-D neighbours
        within ``gate`` of the prediction are candidates) and the RANSAC pre-filter is skipped;
        used for the older ISLAM references, whose ``T0`` comes from the newest reference.
        """
        need = self.strategy.min_points
        t0 = time.perf_counter()
        guided = gate is not None and T0 is not None
        ia, ib = guided_match(ref, cur, T0, gate, self.mc) if guided else match_pairs(ref, cur, self.mc)
        n_matches = len(ia)
        if n_matches < need:
            return None
        all_matches = np.stack([ia, ib], axis=1)
        if not guided and self.mc.prefilter != self.strategy.replaces_prefilter:
            m = prefilter(ref, cur, ia, ib, self.mc, self.seed, T0)
            ia, ib = ia[m], ib[m]
            if len(ia) < need:
                return None
        t1 = time.perf_counter()
        fit = self.strategy.fit(ref.pts[ia], cur.pts[ib])
        if fit is None:
            return None
        keep = fit.inliers
        if len(ref.edge) == len(ref.uv) and len(cur.edge) == len(cur.uv):
            # key points at depth edges (matching.depth_edge_radius) helped choose the
            # inliers; the pose is fitted without them when enough others are left: their depth may
            # be the other surface's, which shortens the translation (docs/frontend.md "Scale bias")
            clean = keep & ~ref.edge[ia] & ~cur.edge[ib]
            if clean.sum() < keep.sum() and clean.sum() >= max(need, EDGE_FREE_SHARE * keep.sum()):
                fit.T = fit_rigid(ref.pts[ia[clean]], cur.pts[ib[clean]])
        return RegistrationResult(
            T=fit.T,
            n_matches=n_matches,
            n_inliers=fit.n_inliers,
            residual_l1=fit.residual_l1,
            residual_l2=fit.residual_l2,
            weight=fit.weight,
            pairs=np.stack([ia[keep], ib[keep]], axis=1),
            information=fit.information,
            timings={"matching": t1 - t0, "registration": time.perf_counter() - t1},
            matches=all_matches,
        )


def build_pair_registration(cfg: Config) -> PairRegistration:
    """Matching from ``cfg.matching``, the strategy from ``cfg.registration``."""
    return PairRegistration(cfg.matching, get_registration(cfg.registration), cfg.registration.seed)
