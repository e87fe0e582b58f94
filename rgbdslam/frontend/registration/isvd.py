"""ISVD — iterative SVD registration with a shrinking outlier gate (docs/references.md §1).

```
T = T0 ; e = e_start
for j = 0 .. maxIt:
    T = SVD_FIT(D, S)  on the surviving pairs
    remove pairs with ||d_i - T s_i|| > e
    if e_min > e: stop
    else: e = e / 2
```

One addition, shared by every strategy
(:class:`~rgbdslam.frontend.registration.base.Registration`): a final refit on the surviving
pairs (the thesis' last fit was made before the last removal). The thesis' ``T = T0`` is
overwritten by the first fit, so the prediction is not used here.
"""

from __future__ import annotations

import numpy as np

from rgbdslam.frontend.registration.base import Registration
from rgbdslam.geometry.rigid import fit_rigid, residuals, row_norms


def isvd(S: np.ndarray, D: np.ndarray, keep: np.ndarray, max_it: int, e_start: float, e_min: float,
         min_points: int = 3) -> tuple[np.ndarray, int] | None:
    """The loop above from the pairs ``keep``: (surviving pairs, iterations), None when fewer than
    ``min_points`` pairs survive."""
    need = max(3, min_points)
    e = e_start
    it = 0
    for j in range(max_it + 1):
        it = j + 1
        T = fit_rigid(S[keep], D[keep])
        err = row_norms(residuals(T, S, D))
        new = keep & (err <= e)
        if new.sum() < need:
            return None
        keep = new
        if e_min > e:
            break
        e = e / 2
    return keep, it


class IsvdRegistration(Registration):
    """``registration.method = isvd``: against the previous frame only."""

    name = "isvd"

    def select(self, S, D, keep):
        rc = self.rc
        out = isvd(S, D, keep, rc.max_iterations, rc.e_start, rc.e_min, self.min_points)
        return None if out is None else (out[0], None)
