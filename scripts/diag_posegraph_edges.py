"""How well do a run's pose-graph edges agree with the ground truth, and is their information calibrated?

For every edge of RUN/posegraph.g2o (vertex ids = frame indices): the error of the measured relative pose
against the ground truth's (evaluation only), E = inv(T_gt) · T_meas, as a 6-vector (translation, rotation)
and its Mahalanobis² e'Λe with the edge's information Λ (calibrated information: mean 6, median 5.35).
Odometry edges (consecutive keyframes) and loop edges are reported apart; a graph whose loop edges are
over-confident or biased against their odometry pulls the trajectory away from a good odometry.

Usage::

    .venv/bin/python scripts/diag_posegraph_edges.py SEQUENCE RUN [--set dataset.camera_file=...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from rgbdslam.config import load_config  # noqa: E402
from rgbdslam.datasets import open_sequence  # noqa: E402
from rgbdslam.geometry.se3 import inv  # noqa: E402
from rgbdslam.posegraph.graph_io import read_graph  # noqa: E402


def edge_errors(graph, gt_poses: dict[int, np.ndarray]):
    """Per edge: (i, j, translation error m, rotation error deg, Mahalanobis², is_odometry)."""
    ids = graph.ids
    order = {int(v): k for k, v in enumerate(sorted(int(x) for x in ids))}
    out = []
    for k in range(graph.n_edges):
        i, j = int(ids[graph.edges_i[k]]), int(ids[graph.edges_j[k]])
        if i not in gt_poses or j not in gt_poses:
            continue
        T_gt = inv(gt_poses[i]) @ gt_poses[j]
        E = inv(T_gt) @ graph.meas[k]
        e = np.concatenate([E[:3, 3], Rotation.from_matrix(E[:3, :3]).as_rotvec()])  # g2o order: t, r
        m2 = float(e @ graph.info[k] @ e)
        out.append((i, j, float(np.linalg.norm(e[:3])), float(np.degrees(np.linalg.norm(e[3:]))), m2,
                    abs(order[j] - order[i]) == 1))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("run", type=Path)
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args(argv)
    cfg = load_config(None, list(a.set))
    seq = open_sequence(a.sequence, cfg.dataset)
    gt = seq.groundtruth()
    graph = read_graph(a.run / "posegraph.g2o")
    from scripts.diag_depth_delay import pose_at

    ts = seq.timestamps
    ids = [int(x) for x in graph.ids]
    P = pose_at(gt, ts[ids])
    rows = edge_errors(graph, dict(zip(ids, P)))
    for name, sel in (("odometry", True), ("loop", False)):
        r = np.array([x[2:5] for x in rows if x[5] == sel])
        if len(r) == 0:
            continue
        print(f"{name:8s} edges {len(r):3d}: translation error median {1e3 * np.median(r[:, 0]):.1f} mm "
              f"(max {1e3 * r[:, 0].max():.1f}), rotation median {np.median(r[:, 1]):.2f} deg "
              f"(max {r[:, 1].max():.2f}), Mahalanobis² median {np.median(r[:, 2]):.1f} (mean {r[:, 2].mean():.1f})")
    worst = sorted((x for x in rows if not x[5]), key=lambda x: -x[4])[:8]
    for i, j, t, rdeg, m2, _ in worst:
        print(f"  loop {i:4d}-{j:4d}: {1e3 * t:6.1f} mm {rdeg:5.2f} deg  Mahalanobis² {m2:9.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
