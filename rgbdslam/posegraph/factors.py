"""GTSAM factor graphs of a :class:`~rgbdslam.posegraph.graph.PoseGraphData`, and its χ².

χ² is ``sum_ij e_ij^T Ω_ij e_ij`` = ``2 * NonlinearFactorGraph.error`` (GTSAM's error is half
the squared Mahalanobis norm).  The gauge is fixed by a tight prior on the root vertex (the
paper's g2o runs fix vertex 0); its residual is ~0 and it is not counted in the degrees of
freedom ``dof = (residual dimensions of the edges) - (pose dimensions of the free vertices)``.
"""

from __future__ import annotations

import gtsam
import numpy as np

from rgbdslam.posegraph.graph import PoseGraphData, info6_g2o_to_gtsam

PRIOR_SIGMA = 1e-6


def values_from_poses(dim: int, poses: np.ndarray) -> gtsam.Values:
    v = gtsam.Values()
    poses = np.asarray(poses, float)
    if dim == 2:
        for k, (x, y, t) in enumerate(poses):
            v.insert(k, gtsam.Pose2(float(x), float(y), float(t)))
    else:
        for k, T in enumerate(poses):
            v.insert(k, gtsam.Pose3(T))
    return v


def poses_from_values(dim: int, values: gtsam.Values, n: int) -> np.ndarray:
    if dim == 2:
        out = np.empty((n, 3))
        for k in range(n):
            p = values.atPose2(k)
            out[k] = (p.x(), p.y(), p.theta())
        return out
    return np.array([values.atPose3(k).matrix() for k in range(n)])


def _dense_models(info: np.ndarray) -> list:
    """GTSAM noise models for full information matrices (n, d, d).

    ``Gaussian.Information`` factors Ω by Cholesky and silently returns a wrong square root when
    Ω is singular or has a rounding-size negative eigenvalue (a valid, rank-deficient edge; the
    reader's PSD projection of indefinite edges). Those get ``SqrtInformation(R)`` with
    R = diag(√max(w, 0)) Vᵀ from Ω = V diag(w) Vᵀ, so that ‖R e‖² = eᵀΩe exactly; positive
    definite ones keep ``Information``."""
    w, V = np.linalg.eigh(info)
    pd = w[:, 0] > 1e-9 * np.abs(w).max(axis=1)
    out = []
    for k in range(len(info)):
        if pd[k]:
            out.append(gtsam.noiseModel.Gaussian.Information(info[k]))
        else:
            R = np.sqrt(np.maximum(w[k], 0.0))[:, None] * V[k].T
            out.append(gtsam.noiseModel.Gaussian.SqrtInformation(R, False))  # not "smart": a diagonal R may hold 0 or signs
    return out


def build_factor_graph(graph: PoseGraphData, prior_pose=None, root: int = 0) -> gtsam.NonlinearFactorGraph:
    """Between factors for every edge (Gaussian with the edge's information) + a tight prior on ``root``.

    ``prior_pose`` is ``(x, y, theta)`` / 4x4 (default: origin / identity); ``None``-prior graphs
    (for GTSAM's own initialisers) are made with ``root=-1``.
    """
    fg = gtsam.NonlinearFactorGraph()
    ei, ej = graph.edges_i.tolist(), graph.edges_j.tolist()
    if graph.dim == 2:
        info = graph.info
        diag = np.all(info[:, [0, 0, 1, 1, 2, 2], [1, 2, 0, 2, 0, 1]] == 0, axis=1)
        dense = dict(zip(np.flatnonzero(~diag).tolist(), _dense_models(info[~diag]))) if (~diag).any() else {}
        for k in range(graph.n_edges):
            x, y, t = graph.meas[k]
            if diag[k]:
                model = gtsam.noiseModel.Diagonal.Precisions(np.diagonal(info[k]).copy())
            else:
                model = dense[k]
            fg.add(gtsam.BetweenFactorPose2(ei[k], ej[k], gtsam.Pose2(float(x), float(y), float(t)), model))
        if root >= 0:
            p = (0.0, 0.0, 0.0) if prior_pose is None else tuple(float(v) for v in prior_pose)
            fg.add(gtsam.PriorFactorPose2(root, gtsam.Pose2(*p), gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_SIGMA)))
    else:
        info = info6_g2o_to_gtsam(graph.info)
        for k, model in enumerate(_dense_models(info)):
            fg.add(gtsam.BetweenFactorPose3(ei[k], ej[k], gtsam.Pose3(graph.meas[k]), model))
        if root >= 0:
            p = np.eye(4) if prior_pose is None else np.asarray(prior_pose, float)
            fg.add(gtsam.PriorFactorPose3(root, gtsam.Pose3(p), gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA)))
    return fg


def degrees_of_freedom(graph: PoseGraphData) -> int:
    d = graph.dof_per_vertex
    return d * graph.n_edges - d * (graph.n_vertices - 1)


def chi2(graph: PoseGraphData, poses: np.ndarray, fg: gtsam.NonlinearFactorGraph | None = None) -> float:
    """χ² of ``poses`` (prior on the root at ``poses[0]``, so it adds nothing)."""
    fg = fg or build_factor_graph(graph, prior_pose=np.asarray(poses)[0])
    return 2.0 * fg.error(values_from_poses(graph.dim, poses))
