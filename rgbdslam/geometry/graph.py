"""Graph helpers shared by the SLAM back end and the saved-map code (pure maths, no state)."""

from __future__ import annotations

import numpy as np


def components(n: int, edges) -> np.ndarray:
    """Connected component label (0..c-1) of each of ``n`` nodes joined by undirected ``edges``
    (pairs of node numbers); a component's label is the order of its lowest-numbered node."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if n == 0:
        return np.zeros(0, np.int64)
    e = np.asarray(list(edges), np.int64).reshape(-1, 2)
    A = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, labels = connected_components(A, directed=False)
    # scipy numbers components in the order its traversal meets them; renumber by lowest node
    _, first = np.unique(labels, return_index=True)
    order = np.empty(len(first), np.int64)
    order[np.argsort(first, kind="stable")] = np.arange(len(first))
    return order[labels]
