"""Chordal initial guess for SE(2) pose graphs: rotations first, then positions, two linear solves.

The 2-D counterpart of GTSAM's ``InitializePose3`` (Carlone et al., "Initialization techniques
for 3D SLAM", ICRA 2015, and "A fast and accurate approximation for planar pose graph
optimization", IJRR 2014 — LAGO), written for this project:

1. **Chordal rotations.** Each heading is written as ``(c_k, s_k) = (cos θ_k, sin θ_k)`` and the
   rotation constraint of an edge, ``R_j = R_i R(z_θ)``, is linear in them (two rows per edge).
   Weighted linear least squares (weight ``Ω_θθ``) with vertex 0 held at ``(1, 0)``; each
   ``(c_k, s_k)`` is then projected back onto the circle (``atan2``). No angle unwrapping, so
   unlike LAGO's 2kπ regularisation along a spanning tree it does not break when the heading
   noise accumulated along tree paths is large.
2. **Heading refinement** (LAGO's second step, optional, on by default): each edge's relative
   angle is unwrapped against the chordal headings (``k = round((θ_j − θ_i − z_θ) / 2π)``) and the
   headings are re-solved as a linear least-squares problem on the angles themselves.
3. **Positions.** With the headings fixed, ``t_j − t_i = R(θ_i) z_t`` is linear in the positions:
   weighted least squares with the translation information rotated into the world frame,
   vertex 0 at the origin.

Every step is one sparse factorisation whose pattern depends only on the graph, so the cost does
not depend on the noise (City10k ≈ 0.3 s here). Measured against MASAT in docs/benchmarks.md.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from rgbdslam.posegraph.gn2d import factor_spd
from rgbdslam.posegraph.graph import PoseGraphData, wrap_angle
from rgbdslam.posegraph.masat import bfs_order
from rgbdslam.errors import InputError


def _solve_anchored(A: sp.spmatrix, b: np.ndarray, n_unknowns: int, fixed: np.ndarray, source: str) -> np.ndarray:
    """Least squares ``min |A x − b|²`` (rows already whitened) with the ``fixed`` unknowns held at 0.

    Normal equations, SuperLU in symmetric mode (the matrix is SPD once the gauge is fixed);
    several right-hand sides may be passed as the columns of ``b``."""
    keep = np.ones(n_unknowns, bool)
    keep[fixed] = False
    A = A.tocsc()[:, keep]
    H = (A.T @ A).tocsc()
    rhs = A.T @ b
    try:
        sol = factor_spd(H).solve(np.asarray(rhs, float))
    except RuntimeError:
        raise InputError(f"{source}: the linear system of the chordal initial guess is singular "
                         "(is the graph connected?); try --method masat") from None
    out = np.zeros((n_unknowns,) + np.shape(b)[1:])
    out[keep] = sol
    return out


def chordal_headings(graph: PoseGraphData) -> np.ndarray:
    """Step 1: headings from the chordal relaxation (vertex 0 at 0)."""
    n, m = graph.n_vertices, graph.n_edges
    i, j = graph.edges_i, graph.edges_j
    w = np.sqrt(np.maximum(graph.info[:, 2, 2], 0.0))
    cz, sz = np.cos(graph.meas[:, 2]), np.sin(graph.meas[:, 2])
    # unknowns: c_k at 2k, s_k at 2k+1.  c_j − (c_i cz − s_i sz) = 0 ; s_j − (s_i cz + c_i sz) = 0
    r = np.arange(m)
    rows = np.concatenate([r, r, r, m + r, m + r, m + r])
    cols = np.concatenate([2 * j, 2 * i, 2 * i + 1, 2 * j + 1, 2 * i + 1, 2 * i])
    vals = np.concatenate([w, -w * cz, w * sz, w, -w * cz, -w * sz])
    A = sp.coo_matrix((vals, (rows, cols)), shape=(2 * m, 2 * n)).tocsc()
    # vertex 0 is held at (c, s) = (1, 0): its c column moves to the right-hand side
    b = -np.asarray(A[:, 0].todense()).ravel()
    x = _solve_anchored(A, b, 2 * n, np.array([0, 1]), graph.source or "pose graph")
    x[0], x[1] = 1.0, 0.0
    return np.arctan2(x[1::2], x[0::2])


def _incidence(graph: PoseGraphData, w: np.ndarray) -> sp.csc_matrix:
    m, n = graph.n_edges, graph.n_vertices
    r = np.arange(m)
    return sp.coo_matrix((np.concatenate([-w, w]), (np.concatenate([r, r]),
                                                      np.concatenate([graph.edges_i, graph.edges_j]))),
                         shape=(m, n)).tocsc()


def refine_headings(graph: PoseGraphData, theta: np.ndarray) -> np.ndarray:
    """Step 2: unwrap every edge's relative angle against ``theta``, re-solve the headings linearly."""
    i, j = graph.edges_i, graph.edges_j
    k = np.round((theta[j] - theta[i] - graph.meas[:, 2]) / (2.0 * np.pi))
    w = np.sqrt(np.maximum(graph.info[:, 2, 2], 0.0))
    A = _incidence(graph, w)
    b = w * (graph.meas[:, 2] + 2.0 * np.pi * k)
    return _solve_anchored(A, b, graph.n_vertices, np.array([0]), graph.source or "pose graph")


def _psd_cholesky(omega: np.ndarray) -> np.ndarray:
    """Cholesky factors of a stack of symmetric 2x2 matrices after clipping negative eigenvalues
    (plus a relative 1e-12 of the largest, so every factor exists)."""
    w, V = np.linalg.eigh(omega)
    top = np.maximum(np.abs(w).max(axis=1, keepdims=True), 1e-300)
    w = np.maximum(w, 1e-12 * top)
    return np.linalg.cholesky((V * w[:, None, :]) @ np.transpose(V, (0, 2, 1)))


def positions_given_headings(graph: PoseGraphData, theta: np.ndarray) -> np.ndarray:
    """Step 3: positions by weighted linear least squares with the headings fixed; returns (n, 3)."""
    n, m = graph.n_vertices, graph.n_edges
    i, j = graph.edges_i, graph.edges_j
    c, s = np.cos(theta[i]), np.sin(theta[i])
    R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # (m, 2, 2) world <- frame i
    zt = graph.meas[:, :2]
    b_world = np.einsum("mab,mb->ma", R, zt)
    # translation information in the world frame, whitened by its Cholesky factor: L^T (t_j - t_i - b)
    omega = R @ graph.info[:, :2, :2] @ np.transpose(R, (0, 2, 1))
    omega = 0.5 * (omega + np.transpose(omega, (0, 2, 1))) + 1e-12 * np.eye(2)
    try:
        L = np.linalg.cholesky(omega)  # omega = L L^T; residual weight L^T
    except np.linalg.LinAlgError:
        # a singular block rounded slightly indefinite (the readers accept eigenvalues down to
        # -1e-5 of the largest): clip its negative eigenvalues, then factor it
        L = _psd_cholesky(omega)
    Lt = np.transpose(L, (0, 2, 1))
    # unknowns x_k at 2k, y_k at 2k+1; row (2e + a) = sum_b Lt[e, a, b] (t_j[b] − t_i[b])
    e = np.arange(m)
    rows, cols, vals = [], [], []
    for a in range(2):
        for bb in range(2):
            rows += [2 * e + a, 2 * e + a]
            cols += [2 * j + bb, 2 * i + bb]
            vals += [Lt[:, a, bb], -Lt[:, a, bb]]
    A = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(2 * m, 2 * n)).tocsc()
    rhs = np.einsum("mab,mb->ma", Lt, b_world).ravel()
    x = _solve_anchored(A, rhs, 2 * n, np.array([0, 1]), graph.source or "pose graph")
    return np.column_stack([x[0::2], x[1::2], wrap_angle(theta)])


def chordal_se2(graph: PoseGraphData, refine: bool = True) -> np.ndarray:
    """Chordal initial guess of an SE(2) graph, ``(n, 3)`` poses with vertex 0 at the origin."""
    if graph.dim != 2:
        raise InputError("chordal_se2 needs an SE(2) graph")
    bfs_order(graph.n_vertices, graph.edges_i, graph.edges_j)  # a disconnected graph is a clear error
    theta = chordal_headings(graph)
    if refine:
        theta = refine_headings(graph, theta)
    theta = theta - theta[0]
    return positions_given_headings(graph, theta)
