"""Timestamp association with the semantics of TUM's ``associate.py``.

Every pair (a, b) with ``|t_a - (t_b + offset)| < max_difference`` is a candidate; the
candidates are taken greedily by increasing difference (ties by t_a, then t_b), each
timestamp used at most once. The result is ordered by ``t_a``.
"""

from __future__ import annotations

import numpy as np


def associate(
    ts_a: np.ndarray, ts_b: np.ndarray, max_difference: float = 0.02, offset: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Greedy one-to-one matching of two timestamp lists.

    Returns ``(idx_a, idx_b)``: integer index arrays into ``ts_a`` and ``ts_b`` of the
    matched pairs, sorted by ``ts_a``.
    """
    a = np.asarray(ts_a, dtype=np.float64).reshape(-1)
    b = np.asarray(ts_b, dtype=np.float64).reshape(-1) + offset
    empty = np.zeros(0, dtype=np.int64)
    if len(a) == 0 or len(b) == 0:
        return empty, empty
    order_b = np.argsort(b, kind="stable")
    bs = b[order_b]
    # Candidate window of b for every a (sorted b, so a contiguous range).
    lo = np.searchsorted(bs, a - max_difference, side="left")
    hi = np.searchsorted(bs, a + max_difference, side="right")
    counts = hi - lo
    if counts.sum() == 0:
        return empty, empty
    ia = np.repeat(np.arange(len(a)), counts)
    starts = np.repeat(lo - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    jb = order_b[np.arange(len(ia)) + starts]
    diff = np.abs(a[ia] - b[jb])
    keep = diff < max_difference
    ia, jb, diff = ia[keep], jb[keep], diff[keep]
    # Sort candidates like Python sorts (diff, a, b) tuples.
    order = np.lexsort((b[jb], a[ia], diff))
    used_a = np.zeros(len(a), dtype=bool)
    used_b = np.zeros(len(b), dtype=bool)
    out_a, out_b = [], []
    for i, j in zip(ia[order].tolist(), jb[order].tolist()):
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            out_a.append(i)
            out_b.append(j)
    out_a = np.asarray(out_a, dtype=np.int64)
    out_b = np.asarray(out_b, dtype=np.int64)
    s = np.lexsort((b[out_b], a[out_a]))
    return out_a[s], out_b[s]
