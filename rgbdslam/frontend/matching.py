"""Descriptor matching between two frames and the geometric pre-filter of the matches.

Only features with valid depth take part (the 3-D registration cannot use the others), which
also makes the brute-force Hamming matcher cheaper. The pre-filter keeps the matches that
agree with one RANSAC model: 'homography' (the thesis), 'fundamental', 'rigid3d' (3-D rigid
RANSAC, seeded) or 'none'.
"""

from __future__ import annotations

import cv2
import numpy as np

from rgbdslam.config import Config
from rgbdslam.frontend.features import FrameFeatures
from rgbdslam.frontend.ransac import ransac_rigid

_MATCHERS: dict[bool, cv2.BFMatcher] = {}


def _matcher(cross_check: bool) -> cv2.BFMatcher:
    m = _MATCHERS.get(cross_check)
    if m is None:
        m = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=cross_check)
        _MATCHERS[cross_check] = m
    return m


def match_descriptors(desc_a: np.ndarray, desc_b: np.ndarray, cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    """Index arrays (ia, ib) of matched descriptors, sorted by ia.

    Cross-check (mutual nearest neighbour) and/or Lowe's ratio test, then a Hamming cap.
    """
    mc = cfg.matching
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    if mc.ratio is None:
        ms = _matcher(mc.cross_check).match(desc_a, desc_b)
        ia = np.fromiter((m.queryIdx for m in ms), int, len(ms))
        ib = np.fromiter((m.trainIdx for m in ms), int, len(ms))
        dist = np.fromiter((m.distance for m in ms), float, len(ms))
    else:
        knn = _matcher(False).knnMatch(desc_a, desc_b, k=2)
        rows = [(p[0].queryIdx, p[0].trainIdx, p[0].distance) for p in knn
                if len(p) == 2 and p[0].distance < mc.ratio * p[1].distance]
        arr = np.array(rows, dtype=float).reshape(-1, 3)
        ia, ib, dist = arr[:, 0].astype(int), arr[:, 1].astype(int), arr[:, 2]
        if mc.cross_check and len(ia):
            back = _matcher(False).match(desc_b, desc_a)
            best_a = np.full(len(desc_b), -1)
            best_a[[m.queryIdx for m in back]] = [m.trainIdx for m in back]
            keep = best_a[ib] == ia
            ia, ib, dist = ia[keep], ib[keep], dist[keep]
    keep = dist <= mc.max_hamming
    ia, ib = ia[keep], ib[keep]
    order = np.argsort(ia, kind="stable")
    return ia[order], ib[order]


def prefilter(
    ref: FrameFeatures,
    cur: FrameFeatures,
    ia: np.ndarray,
    ib: np.ndarray,
    cfg: Config,
    T0: np.ndarray | None = None,
) -> np.ndarray:
    """Boolean mask over the matches (ia into ref, ib into cur) that pass the geometric model."""
    mc = cfg.matching
    n = len(ia)
    if mc.prefilter == "none" or n == 0:
        return np.ones(n, bool)
    if mc.prefilter == "rigid3d":
        rng = np.random.default_rng(cfg.registration.seed)
        out = ransac_rigid(ref.pts[ia], cur.pts[ib], mc.prefilter_threshold, mc.prefilter_iterations, rng)
        return np.zeros(n, bool) if out is None else out[1]
    a = ref.uv[ia].astype(np.float32)
    b = cur.uv[ib].astype(np.float32)
    cv2.setRNGSeed(cfg.registration.seed)
    if mc.prefilter == "homography":
        if n < 4:
            return np.zeros(n, bool)
        _, mask = cv2.findHomography(a, b, cv2.RANSAC, mc.prefilter_threshold, maxIters=mc.prefilter_iterations * 10)
    else:  # fundamental
        if n < 8:
            return np.zeros(n, bool)
        _, mask = cv2.findFundamentalMat(a, b, cv2.FM_RANSAC, mc.prefilter_threshold, 0.999, mc.prefilter_iterations * 10)
    if mask is None:
        return np.zeros(n, bool)
    return mask.reshape(-1).astype(bool)


def match_pairs(ref: FrameFeatures, cur: FrameFeatures, cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    """Descriptor matches between the depth-valid features of ``ref`` and ``cur``.

    Returns (ia, ib): indices into ref's and cur's full feature arrays.
    """
    va = np.flatnonzero(ref.valid)
    vb = np.flatnonzero(cur.valid)
    ia, ib = match_descriptors(ref.desc[va], cur.desc[vb], cfg)
    return va[ia], vb[ib]
