"""Timestamp association with the exact semantics of TUM's ``associate.py``.

TUM's script forms every candidate pair ``(a, b)`` with ``|a - (b + offset)| < max_difference``,
sorts the candidates by ``(difference, a, b)`` and accepts them greedily, each stamp at most once.
This module reproduces that result without the quadratic candidate list: a sorted-window search
(``searchsorted``) finds the candidates, and the greedy pass is done in vectorised rounds.

Why the rounds are exact: greedy acceptance in sorted order accepts every candidate that comes
first (in the sort order) among all candidates sharing its ``a`` or its ``b`` — nothing before it
can have used either stamp.  Accepting all such "locally first" candidates at once, dropping the
candidates that conflict with them and repeating therefore gives the greedy result.  Chains of
conflicts can need many rounds, so after a few rounds the rest is finished by a plain sequential
pass over the (already sorted, already thinned) remaining candidates.
"""

from __future__ import annotations

import numpy as np

_VECTOR_ROUNDS = 16


def _candidates(ts_a: np.ndarray, ts_b: np.ndarray, max_difference: float, offset: float):
    """All index pairs with ``|a - (b + offset)| < max_difference`` and their differences."""
    b_shift = ts_b + offset
    order_b = np.argsort(b_shift, kind="stable")
    b_sorted = b_shift[order_b]
    # The window is widened by one position on each side, then filtered with the exact test,
    # so floating-point rounding of ``a +- max_difference`` can never drop a true candidate.
    lo = np.maximum(np.searchsorted(b_sorted, ts_a - max_difference, side="left") - 1, 0)
    hi = np.minimum(np.searchsorted(b_sorted, ts_a + max_difference, side="right") + 1, len(b_sorted))
    counts = np.maximum(hi - lo, 0)
    ia = np.repeat(np.arange(len(ts_a)), counts)
    # Position inside each a's window: global running index minus the window's start offset.
    starts = np.cumsum(counts) - counts
    pos = np.arange(counts.sum()) - np.repeat(starts, counts) + np.repeat(lo, counts)
    ib = order_b[pos]
    diff = np.abs(ts_a[ia] - (ts_b[ib] + offset))
    keep = diff < max_difference
    return ia[keep], ib[keep], diff[keep]


def associate(
    ts_a, ts_b, max_difference: float = 0.02, offset: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Associate two timestamp lists one-to-one, like TUM's ``associate.py``.

    Args:
        ts_a, ts_b: timestamps in seconds (any order; indices refer to the given order).
        max_difference: a pair needs ``|a - (b + offset)| < max_difference`` (strict).
        offset: added to every ``ts_b`` stamp before comparing.

    Returns:
        ``(idx_a, idx_b)`` integer arrays of equal length, sorted by ``ts_a[idx_a]``.
    """
    ts_a = np.asarray(ts_a, dtype=np.float64).reshape(-1)
    ts_b = np.asarray(ts_b, dtype=np.float64).reshape(-1)
    empty = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    if len(ts_a) == 0 or len(ts_b) == 0 or max_difference <= 0:
        return empty
    ia, ib, diff = _candidates(ts_a, ts_b, float(max_difference), float(offset))
    if len(ia) == 0:
        return empty
    # TUM sorts tuples (difference, a, b): ties broken by the stamp values, then by index.
    order = np.lexsort((ib, ia, ts_b[ib], ts_a[ia], diff))
    ia, ib = ia[order], ib[order]

    acc_a: list[np.ndarray] = []
    acc_b: list[np.ndarray] = []
    for _ in range(_VECTOR_ROUNDS):
        if len(ia) == 0:
            break
        rank = np.arange(len(ia))
        first_a = np.full(len(ts_a), len(ia))
        first_b = np.full(len(ts_b), len(ia))
        np.minimum.at(first_a, ia, rank)
        np.minimum.at(first_b, ib, rank)
        win = (first_a[ia] == rank) & (first_b[ib] == rank)
        acc_a.append(ia[win])
        acc_b.append(ib[win])
        used_a = np.zeros(len(ts_a), dtype=bool)
        used_b = np.zeros(len(ts_b), dtype=bool)
        used_a[ia[win]] = True
        used_b[ib[win]] = True
        alive = ~(used_a[ia] | used_b[ib])
        ia, ib = ia[alive], ib[alive]

    if len(ia):  # long conflict chains: finish sequentially, the order is still the greedy one
        free_a = np.ones(len(ts_a), dtype=bool)
        free_b = np.ones(len(ts_b), dtype=bool)
        rest_a, rest_b = [], []
        for a, b in zip(ia.tolist(), ib.tolist()):
            if free_a[a] and free_b[b]:
                free_a[a] = free_b[b] = False
                rest_a.append(a)
                rest_b.append(b)
        acc_a.append(np.array(rest_a, dtype=np.int64))
        acc_b.append(np.array(rest_b, dtype=np.int64))

    idx_a = np.concatenate(acc_a).astype(np.int64)
    idx_b = np.concatenate(acc_b).astype(np.int64)
    order = np.lexsort((ts_b[idx_b], ts_a[idx_a]))
    return idx_a[order], idx_b[order]
