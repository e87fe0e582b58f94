"""ISLAM — weighted multi-frame registration (spec §2, thesis 2).

Two pieces:

* :func:`islam_pair` — the per-reference loop: SVD fit, gate ``th_j = alpha * j**beta``
  (shrinking for beta < 0), weight ``W = 1 / (mean L1 residual)``, stop when
  ``th < minError`` or fewer than ``minPoint`` pairs survive.
* :func:`fuse_candidates` — the candidates (one camera-to-world pose per reference, each
  the reference's pose chained with its registration) fused into one pose:
  ``'thesis'`` weighted mean of translations, rotation of the best-weighted candidate;
  ``'chordal'`` the same translation mean plus the weighted chordal rotation mean
  (project ``sum W_f R_f`` onto SO(3)), after dropping candidates that disagree with the
  weighted consensus by more than the rejection thresholds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgbdslam.geometry.rigid import fit_rigid, fit_with_stats, residuals
from rgbdslam.geometry.se3 import project_to_so3, rotation_angle


def gate_threshold(alpha: float, beta: float, j: int) -> float:
    """The gate of iteration ``j`` (1-based): ``alpha * j**beta``."""
    return alpha * float(j) ** beta


def inverse_mean_l1(r: np.ndarray) -> float:
    """ISLAM weight of residual vectors r (N, 3): ``1 / (sum_i |r_i|_1 / N)``."""
    e = float(np.abs(r).sum())
    return len(r) / e if e > 0 else np.inf


@dataclass
class PairResult:
    T: np.ndarray  # 4x4, D ~ T * S
    inliers: np.ndarray  # (N,) bool
    weight: float  # inverse mean L1 residual (1/m)
    iterations: int
    residual_l1: float  # mean L1 residual of the survivors (m)
    residual_l2: float  # RMS residual of the survivors (m)


def islam_pair(
    D: np.ndarray,
    S: np.ndarray,
    max_it: int,
    alpha: float,
    beta: float,
    min_error: float,
    min_points: int,
    T0: np.ndarray | None = None,
    pregate: float | None = None,
) -> PairResult | None:
    """Spec §2's loop for one reference; None when fewer than ``min_points`` pairs survive.

    ``pregate`` (metres): drop pairs further than this from the prediction ``T0`` first.
    After the loop the transform is refitted on the survivors (documented addition).
    """
    need = max(3, min_points)
    keep = np.ones(len(D), bool)
    if pregate is not None and T0 is not None:
        g = np.linalg.norm(residuals(T0, S, D), axis=1) <= pregate
        if g.sum() >= need:
            keep = g
    if keep.sum() < need:
        return None
    W = 0.0
    it = 0
    for j in range(1, max_it + 1):
        it = j
        T = fit_rigid(S[keep], D[keep])
        th = gate_threshold(alpha, beta, j)
        r = residuals(T, S, D)
        W = inverse_mean_l1(r[keep])
        keep = keep & (np.linalg.norm(r, axis=1) <= th)
        if th < min_error or keep.sum() < need:
            break
    if keep.sum() < need:
        return None
    T, l1, l2 = fit_with_stats(S[keep], D[keep])
    return PairResult(T=T, inliers=keep, weight=W, iterations=it, residual_l1=l1, residual_l2=l2)


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
