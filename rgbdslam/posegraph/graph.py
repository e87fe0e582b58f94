"""One in-memory pose graph for SE(2) and SE(3), plus the small Lie-group helpers it needs.

Conventions (used by every module in ``rgbdslam.posegraph``):

* vertices are stored densely, ``0..n-1``; ``PoseGraphData.ids`` maps a dense index to the id used
  in the file (files may skip ids);
* SE(2) poses and measurements are ``(x, y, theta)`` rows; SE(3) ones are 4x4 matrices
  (camera/robot-to-world for poses, ``T_ij = T_i^-1 T_j`` for measurements);
* an edge ``(i, j, z_ij, info)`` says "seen from i, j is at z_ij"; ``info`` is the information
  (inverse covariance) of the measurement: 3x3 in ``(x, y, theta)`` order for SE(2), 6x6 in
  **g2o order** ``(tx, ty, tz, rx, ry, rz)`` (translation first) for SE(3).  GTSAM's Pose3
  tangent is rotation first; :func:`info6_g2o_to_gtsam` swaps the blocks.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np



def wrap_angle(a):
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


# ------------------------------------------------------------------------------------------ SE(2)


def se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a ∘ b for (..., 3) arrays of (x, y, theta)."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    out[..., 1] = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    out[..., 2] = wrap_angle(a[..., 2] + b[..., 2])
    return out


def se2_inverse(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    out = np.empty_like(a)
    out[..., 0] = -(c * a[..., 0] + s * a[..., 1])
    out[..., 1] = -(-s * a[..., 0] + c * a[..., 1])
    out[..., 2] = wrap_angle(-a[..., 2])
    return out


def se2_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a^-1 ∘ b."""
    return se2_compose(se2_inverse(a), b)


# ------------------------------------------------------------------------------------------ SE(3)


def info6_g2o_to_gtsam(info: np.ndarray) -> np.ndarray:
    """Reorder 6x6 information from (t, r) blocks (g2o) to (r, t) blocks (GTSAM Pose3 tangent)."""
    p = np.array([3, 4, 5, 0, 1, 2])
    info = np.asarray(info, float)
    return info[..., p[:, None], p[None, :]]


# ------------------------------------------------------------------------------------- the graph


@dataclass
class PoseGraphData:
    """A pose graph (SE(2) if ``dim == 2`` else SE(3)).

    ``poses`` holds the vertex estimates from the file (zeros / identity when a format stores
    none, e.g. iSAM; ``has_poses`` tells).  ``edges_i/edges_j`` are dense vertex indices.
    """

    dim: int
    ids: np.ndarray  # (n,) original vertex ids
    poses: np.ndarray  # (n, 3) or (n, 4, 4)
    edges_i: np.ndarray  # (m,) int
    edges_j: np.ndarray  # (m,) int
    meas: np.ndarray  # (m, 3) or (m, 4, 4)
    info: np.ndarray  # (m, 3, 3) or (m, 6, 6); SE(3) in g2o (t, r) order
    has_poses: bool = False
    source: str = ""
    notes: list[str] = field(default_factory=list)

    @property
    def n_vertices(self) -> int:
        return len(self.ids)

    @property
    def n_edges(self) -> int:
        return len(self.edges_i)

    @property
    def dof_per_vertex(self) -> int:
        return 3 if self.dim == 2 else 6

    def copy(self) -> "PoseGraphData":
        return PoseGraphData(self.dim, self.ids.copy(), self.poses.copy(), self.edges_i.copy(),
                         self.edges_j.copy(), self.meas.copy(), self.info.copy(), self.has_poses,
                         self.source, list(self.notes))

    def with_poses(self, poses: np.ndarray) -> "PoseGraphData":
        g = self.copy()
        g.poses = np.asarray(poses, float).copy()
        g.has_poses = True
        return g

    def edge_list3(self) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
        """SE(3) edges as ``(i, j, T_ij, info_gtsam_order)`` tuples (the SLAM back end's form)."""
        info = info6_g2o_to_gtsam(self.info)
        return [(int(a), int(b), self.meas[k], info[k]) for k, (a, b) in enumerate(zip(self.edges_i, self.edges_j))]

    def summary(self) -> str:
        kind = "SE(2)" if self.dim == 2 else "SE(3)"
        return (f"{kind} pose graph from {self.source or '<memory>'}: {self.n_vertices} vertices, "
                f"{self.n_edges} edges" + (" (with vertex estimates)" if self.has_poses else ""))


def empty_poses(dim: int, n: int) -> np.ndarray:
    return np.zeros((n, 3)) if dim == 2 else np.tile(np.eye(4), (n, 1, 1))
