"""Fusion of the candidate poses of a multi-reference registration (ISLAM,
docs/references.md §2).

The candidates (one camera-to-world pose per reference frame, each the reference's pose chained
with its registration) are fused into one pose: ``'thesis'`` weighted mean of translations,
rotation of the best-weighted candidate; ``'chordal'`` the same translation mean plus the
weighted chordal rotation mean (project ``sum W_f R_f`` onto SO(3)), after dropping candidates
that disagree with the weighted consensus by more than the rejection thresholds.
"""

from __future__ import annotations

import numpy as np

from rgbdslam.geometry.se3 import project_to_so3, rotation_angle


def chordal_mean(rotations: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted chordal L2 mean of rotations (K, 3, 3): SO(3) projection of sum w R."""
    w = np.asarray(weights, dtype=np.float64)
    return project_to_so3(np.einsum("k,kij->ij", w / w.sum(), rotations))


def fuse_candidates(
    poses: np.ndarray,
    weights: np.ndarray,
    mode: str = "chordal",
    reject_translation: float = np.inf,
    reject_rotation: float = np.inf,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Fuse candidate poses (K, 4, 4) with weights (K,).

    Returns (pose, kept mask, agreeing weight fraction). In 'chordal' mode the consensus is
    the candidate whose agreeing set (within both thresholds) holds the largest weight; the
    others are rejected. 'thesis' mode keeps every candidate (fraction 1).
    """
    poses = np.asarray(poses, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    k = len(poses)
    if mode == "thesis":
        keep = np.ones(k, bool)
        frac = 1.0
    else:
        t = poses[:, :3, 3]
        dt = np.linalg.norm(t[:, None] - t[None], axis=2)
        rel = np.einsum("aji,bjk->abik", poses[:, :3, :3], poses[:, :3, :3])  # R_a^T R_b
        dr = rotation_angle(rel)
        agree = (dt <= reject_translation) & (dr <= reject_rotation)
        support = agree.astype(float) @ w
        best = int(np.lexsort((-w, -support))[0])
        keep = agree[best]
        frac = float(support[best] / w.sum())
    wk = w[keep]
    out = np.eye(4)
    out[:3, 3] = (wk[:, None] * poses[keep, :3, 3]).sum(axis=0) / wk.sum()
    if mode == "thesis":
        out[:3, :3] = poses[int(np.argmax(w)), :3, :3]
    else:
        out[:3, :3] = chordal_mean(poses[keep, :3, :3], wk)
    return out, keep, frac
