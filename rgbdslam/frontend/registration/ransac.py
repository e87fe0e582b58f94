"""The simple frame-to-frame baseline: seeded 3-D rigid RANSAC on the matched pairs.

The sampling itself is :func:`rgbdslam.geometry.ransac.ransac_rigid` (also the rigid-3-D
pre-filter of the matches, which this strategy therefore replaces).
"""

from __future__ import annotations

import numpy as np

from rgbdslam.frontend.registration.base import Registration
from rgbdslam.geometry.ransac import ransac_rigid


class RansacRegistration(Registration):
    """``registration.method = ransac``: inliers of the best rigid hypothesis
    (``registration.ransac_threshold``, ``ransac_iterations``, ``seed``)."""

    name = "ransac"
    replaces_prefilter = "rigid3d"

    def select(self, S, D, keep):
        rc = self.rc
        idx = np.flatnonzero(keep)
        out = ransac_rigid(S[idx], D[idx], rc.ransac_threshold, rc.ransac_iterations,
                           np.random.default_rng(rc.seed), self.min_points)
        if out is None:
            return None
        inliers = np.zeros(len(S), bool)
        inliers[idx[out[1]]] = True
        return inliers, None
