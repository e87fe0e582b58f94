"""Small noise-free 2-D pose graphs with known poses, for tests and reference recordings."""

from __future__ import annotations

import numpy as np

from rgbdslam.posegraph.graph import PoseGraphData, se2_between


def manhattan_world(n: int = 150, seed: int = 0) -> tuple[PoseGraphData, np.ndarray]:
    """A seeded grid walk (unit steps, 90° turns) with loop closures between revisited places.

    Odometry edges ``k -> k+1`` plus an edge ``i -> j`` (j > i + 2) whenever pose j is within one
    grid step of pose i, capped at ``3n`` edges; measurements are exact, information identity.
    Returns ``(graph, poses)``."""
    rng = np.random.default_rng(seed)
    poses = np.zeros((n, 3))
    for k in range(1, n):
        th = poses[k - 1, 2] + rng.choice([0.0, np.pi / 2, -np.pi / 2], p=[0.7, 0.15, 0.15])
        poses[k] = [poses[k - 1, 0] + np.cos(th), poses[k - 1, 1] + np.sin(th), th]
    poses[:, :2] = np.round(poses[:, :2])
    poses[:, 2] = (poses[:, 2] + np.pi) % (2 * np.pi) - np.pi
    pairs = [(k, k + 1) for k in range(n - 1)]
    d = np.linalg.norm(poses[:, None, :2] - poses[None, :, :2], axis=2)
    for i in range(n):
        for j in np.flatnonzero(d[i] < 1.01):
            if j > i + 2 and len(pairs) < 3 * n:
                pairs.append((i, int(j)))
    ei = np.array([p[0] for p in pairs])
    ej = np.array([p[1] for p in pairs])
    g = PoseGraphData(2, np.arange(n), poses.copy(), ei, ej, se2_between(poses[ei], poses[ej]),
                  np.tile(np.eye(3), (len(ei), 1, 1)), True, "synthetic")
    return g, poses
