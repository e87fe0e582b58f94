"""ISVD — iterative SVD registration with a shrinking outlier gate (spec §1, thesis 1).

```
T = T0 ; e = e_start
for j = 0 .. maxIt:
    T = SVD_FIT(D, S)  on the surviving pairs
    remove pairs with ||d_i - T s_i|| > e
    if e_min > e: stop
    else: e = e / 2
```

Additions, both documented in docs/frontend.md: an optional pre-gate with ``T0`` (pairs
further than ``e_start`` from the prediction are dropped before the first fit, which is
how ``T0`` can matter at all, since the first fit overwrites it), and a final refit on the
surviving pairs (the spec's last fit was made before the last removal).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgbdslam.geometry.rigid import fit_rigid, fit_with_stats, residuals


@dataclass
class IsvdResult:
    T: np.ndarray  # 4x4, D ~ T * S
    inliers: np.ndarray  # (N,) bool, surviving pairs
    iterations: int
    residual_l1: float  # mean L1 residual of the survivors (metres)
    residual_l2: float  # RMS Euclidean residual of the survivors (metres)


def isvd(
    D: np.ndarray,
    S: np.ndarray,
    max_it: int,
    e_start: float,
    e_min: float,
    T0: np.ndarray | None = None,
    min_points: int = 3,
    pregate: bool = False,
) -> IsvdResult | None:
    """Iterative SVD fit of ``S`` onto ``D``; None if fewer than ``min_points`` pairs survive."""
    D = np.asarray(D, dtype=np.float64)
    S = np.asarray(S, dtype=np.float64)
    keep = np.ones(len(D), bool)
    need = max(3, min_points)
    if pregate and T0 is not None:
        gated = np.linalg.norm(residuals(T0, S, D), axis=1) <= e_start
        if gated.sum() >= need:
            keep = gated
    if keep.sum() < need:
        return None
    e = e_start
    T = np.eye(4) if T0 is None else np.asarray(T0, dtype=np.float64)
    it = 0
    for j in range(max_it + 1):
        it = j + 1
        T = fit_rigid(S[keep], D[keep])
        err = np.linalg.norm(residuals(T, S, D), axis=1)
        new = keep & (err <= e)
        if new.sum() < need:
            return None
        keep = new
        if e_min > e:
            break
        e = e / 2
    T, l1, l2 = fit_with_stats(S[keep], D[keep])
    return IsvdResult(T=T, inliers=keep, iterations=it, residual_l1=l1, residual_l2=l2)
