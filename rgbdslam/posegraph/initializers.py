"""Initial guesses for pose-graph optimisation (SE(2) and SE(3)).

* ``odometry`` — chain the consecutive edges i -> i+1 from vertex 0 (an edge stored i+1 -> i is
  inverted); a missing odometry edge is an InputError.
* ``spanning_tree`` — BFS from vertex 0; every vertex is placed from its BFS parent through
  one edge joining them (as g2o's ``computeInitialGuess`` with unit edge costs).
* ``masat`` / ``weighted_masat`` — see :mod:`rgbdslam.posegraph.masat`.
* ``lago`` (SE(2)) — GTSAM's LAGO (``gtsam.lago.initialize(graph, useOdometricPath=False)``: its
  2kπ angle unwrapping along a spanning tree instead of the odometry chain, which was better on
  M3500 at σθ = 0.05–0.2 — both fail often at the paper's noise levels, see docs/posegraph.md);
  ``chordal`` — SE(3): GTSAM's chordal relaxation (``gtsam.InitializePose3.initialize``; on a
  tree, which it cannot solve, the exact chained poses that are the relaxation's optimum); SE(2):
  this project's chordal relaxation of the headings + linear positions
  (:mod:`rgbdslam.posegraph.chordal2d`). ``lago`` is SE(2) only: on an SE(3) graph it is an
  InputError that points to ``chordal``.

All return poses with vertex 0 at the origin / identity: ``(n, 3)`` rows ``(x, y, theta)`` for
SE(2), ``(n, 4, 4)`` matrices for SE(3).
"""

from __future__ import annotations

import numpy as np

from rgbdslam.errors import InputError
from rgbdslam.geometry.se3 import inv
from rgbdslam.posegraph.chordal2d import chordal_se2
from rgbdslam.posegraph.convergence import error_summary, name_vertices
from rgbdslam.posegraph.factors import build_factor_graph, poses_from_values
from rgbdslam.posegraph.graph import PoseGraphData, se2_compose, se2_inverse, wrap_angle
from rgbdslam.posegraph.masat import bfs_order, masat

METHODS = ("odometry", "spanning_tree", "masat", "weighted_masat", "lago", "chordal")


def _chain(graph: PoseGraphData, parent: np.ndarray, order: np.ndarray, edge_of: np.ndarray, fwd: np.ndarray) -> np.ndarray:
    """Place vertices (``order``: root first, parents before children) from their ``parent``
    through edge ``edge_of``; all vertices of one tree depth are composed in one vectorised step."""
    n = graph.n_vertices
    depth = np.zeros(n, np.int64)
    par = parent.tolist()
    dl = depth.tolist()
    for v in order[1:].tolist():
        dl[v] = dl[par[v]] + 1
    depth = np.asarray(dl, np.int64)
    by_depth = np.argsort(depth, kind="stable")
    bounds = np.searchsorted(depth[by_depth], np.arange(1, depth.max() + 2))
    if graph.dim == 2:
        z = np.where(fwd[:, None], graph.meas[edge_of], se2_inverse(graph.meas[edge_of]))
        out = np.zeros((n, 3))
        for d in range(len(bounds) - 1):
            vs = by_depth[bounds[d]:bounds[d + 1]]
            out[vs] = se2_compose(out[parent[vs]], z[vs])
        return out
    z = graph.meas[edge_of].copy()
    z[~fwd] = inv(z[~fwd])
    out = np.tile(np.eye(4), (n, 1, 1))
    for d in range(len(bounds) - 1):
        vs = by_depth[bounds[d]:bounds[d + 1]]
        out[vs] = out[parent[vs]] @ z[vs]
    return out


def _edge_lookup(graph: PoseGraphData) -> dict[tuple[int, int], int]:
    """First edge index for each (i, j) pair (either direction, key as stored)."""
    lut: dict[tuple[int, int], int] = {}
    for k, (a, b) in enumerate(zip(graph.edges_i.tolist(), graph.edges_j.tolist())):
        lut.setdefault((a, b), k)
    return lut


def odometry(graph: PoseGraphData) -> np.ndarray:
    n = graph.n_vertices
    lut = _edge_lookup(graph)
    edge_of = np.zeros(n, np.int64)
    fwd = np.ones(n, bool)
    for v in range(1, n):
        k = lut.get((v - 1, v))
        if k is None:
            k = lut.get((v, v - 1))
            fwd[v] = False
        if k is None:
            raise InputError(
                f"{graph.source or 'pose graph'}: no odometry edge between vertices {graph.ids[v - 1]} and "
                f"{graph.ids[v]}; use --method spanning_tree or masat")
        edge_of[v] = k
    # chaining is a prefix product: SE(2) can be done in closed form, vectorised
    if graph.dim == 2:
        z = np.where(fwd[:, None], graph.meas[edge_of], se2_inverse(graph.meas[edge_of]))
        z[0] = 0.0
        th = np.cumsum(z[:, 2])
        c, s = np.cos(th - z[:, 2]), np.sin(th - z[:, 2])  # heading of the previous vertex
        dx = c * z[:, 0] - s * z[:, 1]
        dy = s * z[:, 0] + c * z[:, 1]
        return np.column_stack([np.cumsum(dx), np.cumsum(dy), wrap_angle(th)])
    parent = np.arange(-1, n - 1)
    return _chain(graph, parent, np.arange(n), edge_of, fwd)


def bfs_tree_ordered(n: int, ei: np.ndarray, ej: np.ndarray, tie_break="index",
                     root: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """BFS from ``root`` with a chosen order of each vertex's neighbours, which decides the parent
    whenever several vertices one level up are adjacent (the first one dequeued wins).

    ``tie_break``: ``"index"`` — neighbours by increasing vertex index (:func:`bfs_order`);
    ``"edge_order"`` — by the position of the joining edge in the file, the order in which g2o
    allocates edges and so (usually) the pointer order of its ``std::set`` of a vertex's edges;
    an ``int`` — a random neighbour order seeded by it.  Returns ``(order, parent, edge_of)`` with
    ``edge_of[v]`` the index of the edge that placed ``v`` (the first in the chosen order).
    """
    ei = np.asarray(ei, np.int64)
    ej = np.asarray(ej, np.int64)
    m = len(ei)
    k = np.concatenate([np.arange(m), np.arange(m)])
    a = np.concatenate([ei, ej])
    b = np.concatenate([ej, ei])
    if tie_break == "index":
        key = b
    elif tie_break == "edge_order":
        key = k
    elif isinstance(tie_break, (int, np.integer)) and not isinstance(tie_break, bool):
        key = np.random.default_rng(int(tie_break)).permutation(2 * m)
    else:
        raise InputError(f"unknown spanning-tree tie break {tie_break!r}; use index, edge_order or an integer seed")
    srt = np.lexsort((k, key, a))  # per vertex a: its incident edges in the chosen order
    nbr, edge = b[srt].tolist(), k[srt].tolist()
    ptr = np.searchsorted(a[srt], np.arange(n + 1)).tolist()
    parent = [-1] * n
    edge_of = [0] * n
    seen = [False] * n
    seen[root] = True
    order = [root]
    head = 0
    while head < len(order):
        u = order[head]
        head += 1
        for t in range(ptr[u], ptr[u + 1]):
            v = nbr[t]
            if not seen[v]:
                seen[v] = True
                parent[v] = u
                edge_of[v] = edge[t]
                order.append(v)
    if len(order) < n:
        raise InputError(f"pose graph is not connected: {n - len(order)} of {n} vertices cannot be reached "
                         f"from vertex {root}; add edges to them or drop them")
    return np.asarray(order, np.int64), np.asarray(parent, np.int64), np.asarray(edge_of, np.int64)


def spanning_tree(graph: PoseGraphData, tie_break="index") -> np.ndarray:
    """BFS spanning-tree initial guess; ``tie_break`` as in :func:`bfs_tree_ordered` (the default
    ``"index"`` is the benchmark's tree)."""
    order, parent, edge_of = bfs_tree_ordered(graph.n_vertices, graph.edges_i, graph.edges_j, tie_break)
    fwd = np.asarray(graph.edges_i)[edge_of] == parent
    return _chain(graph, parent, order, edge_of, fwd)


def _gtsam_init(graph: PoseGraphData) -> np.ndarray:
    """GTSAM's LAGO (SE(2)) or chordal ``InitializePose3`` (SE(3)); a failure is one line."""
    import gtsam

    bfs_order(graph.n_vertices, graph.edges_i, graph.edges_j)  # connectivity check, clear error
    fg = build_factor_graph(graph, root=0)
    name = "LAGO" if graph.dim == 2 else "chordal initialiser (InitializePose3)"
    try:
        if graph.dim == 2:
            vals = gtsam.lago.initialize(fg, False)  # BFS spanning tree for the 2kπ unwrapping
        else:
            vals = gtsam.InitializePose3.initialize(fg)
    except (RuntimeError, ValueError) as e:
        why = name_vertices(error_summary(e), graph)
        hint = "use --method masat"
        if "Indeterminate" in why:
            hint = "check that the information of that vertex's edges constrains its rotation, or " + hint
        raise InputError(f"{graph.source or 'pose graph'}: GTSAM's {name} failed ({why}); {hint}") from None
    poses = poses_from_values(graph.dim, vals, graph.n_vertices)
    if not np.all(np.isfinite(poses)):
        raise InputError(f"{graph.source or 'pose graph'}: GTSAM's {name} returned non-finite poses; "
                         f"use --method masat")
    return poses


def lago(graph: PoseGraphData) -> np.ndarray:
    """GTSAM's LAGO; SE(2) only (an SE(3) graph is an InputError pointing to ``chordal``)."""
    if graph.dim != 2:
        raise InputError(f"{graph.source or 'pose graph'}: LAGO is for 2-D (SE(2)) graphs only and this graph is "
                         f"3-D (SE(3)); use --method chordal (GTSAM's chordal initialiser) or masat")
    full = np.flatnonzero(np.any(graph.info[:, [0, 0, 1, 1, 2, 2], [1, 2, 0, 2, 0, 1]] != 0, axis=1))
    if len(full):
        k = int(full[0])
        raise InputError(f"{graph.source or 'pose graph'}: GTSAM's LAGO needs diagonal information matrices, and "
                         f"{len(full)} edge(s) have off-diagonal terms (the first joins vertices "
                         f"{graph.ids[graph.edges_i[k]]} and {graph.ids[graph.edges_j[k]]}); use --method chordal "
                         f"(our SE(2) chordal relaxation uses the full information) or masat")
    return _gtsam_init(graph)


def chordal(graph: PoseGraphData) -> np.ndarray:
    if graph.dim == 2:
        return chordal_se2(graph)
    bfs_order(graph.n_vertices, graph.edges_i, graph.edges_j)  # connected (a clear error otherwise)
    if graph.n_edges == graph.n_vertices - 1:
        # A tree: every constraint can be met exactly, so the chordal relaxation's optimum is the
        # tree's chained poses (GTSAM 4.3's InitializePose3 throws IndeterminantLinearSystem on any
        # graph without a loop).
        return spanning_tree(graph)
    return _gtsam_init(graph)


def initialize(graph: PoseGraphData, method: str) -> np.ndarray:
    """Initial poses by ``method`` (one of :data:`METHODS`)."""
    if method == "masat":
        return masat(graph, weighted=False)
    if method == "weighted_masat":
        return masat(graph, weighted=True)
    if method == "odometry":
        return odometry(graph)
    if method == "spanning_tree":
        return spanning_tree(graph)
    if method == "chordal":
        return chordal(graph)
    if method == "lago":
        return lago(graph)
    raise InputError(f"unknown initialisation method {method!r}; use one of {', '.join(METHODS)}")
