"""Would depth-consistent loop edges bring a run closer to a depth-only reference? (issue 17, 7-Scenes)

For each RUN (a run folder with ``posegraph.g2o``), offline: the keyframe chain from the graph's odometry
edges, then GTSAM Levenberg-Marquardt on (a) the graph as it is, (b) the graph with every loop edge replaced by a
point-to-plane ICP of the two frames' depth images started from the edge (``diag_loop_dense.py``'s depth
aligner), (c) no loop edges (the chain itself). Printed: the keyframes' ATE RMSE against the ground truth for
each, and the loop edges' median rotation from the ground truth's relative pose, as measured and after ICP.
The graph's informations are kept; the pipeline's robust kernels are not used, so (a) is close to, not the
same as, the run's own result — compare (a) with (b).

Usage::

    .venv/bin/python scripts/diag_loop_icp_graph.py SEQUENCE RUN [RUN ...] [--set dataset.camera_file=...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from rgbdslam.config import load_config  # noqa: E402
from rgbdslam.datasets import open_sequence  # noqa: E402
from rgbdslam.evaluation.ate import umeyama_alignment  # noqa: E402
from rgbdslam.geometry.se3 import inv, rotation_angle  # noqa: E402
from rgbdslam.posegraph.graph_io import read_graph  # noqa: E402
from rgbdslam.posegraph.optimize import run_gauss_newton  # noqa: E402


def odometry_chain(g, ids: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Vertex poses (in ``ids`` order) composed from the odometry edges, the smallest id at the identity."""
    order = np.argsort(ids)
    od = {(ids[a], ids[b]): g.meas[k] for k, (a, b) in enumerate(zip(g.edges_i, g.edges_j)) if not loop[k]}
    P = {ids[order[0]]: np.eye(4)}
    for k in range(1, len(order)):
        a, b = ids[order[k - 1]], ids[order[k]]
        P[b] = P[a] @ od[(a, b)] if (a, b) in od else P[a] @ inv(od[(b, a)])
    return np.array([P[i] for i in ids])


def keyframe_ate(poses: np.ndarray, G: np.ndarray) -> float:
    R, t, _ = umeyama_alignment(poses[:, :3, 3].T, G[:, :3, 3].T, "se3")
    return float(np.sqrt(np.mean(np.sum((poses[:, :3, 3] @ R.T + t - G[:, :3, 3]) ** 2, axis=1))))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args(argv)
    from scripts.diag_depth_delay import pose_at
    from scripts.diag_loop_dense import dense_aligners

    seq = open_sequence(a.sequence, load_config(None, list(a.set)).dataset)
    gt = seq.groundtruth()
    icp = dense_aligners(seq.camera)["depth"]
    deg = lambda T: float(np.degrees(rotation_angle(T[:3, :3])))  # noqa: E731
    for run in a.runs:
        g = read_graph(run / "posegraph.g2o")
        ids = np.array([int(x) for x in g.ids])
        rank = {v: k for k, v in enumerate(sorted(ids))}
        loop = np.array([abs(rank[ids[i]] - rank[ids[j]]) != 1 for i, j in zip(g.edges_i, g.edges_j)])
        init = odometry_chain(g, ids, loop)
        G = pose_at(gt, seq.timestamps[ids])
        g_icp = g.copy()
        dev = []
        for k in np.flatnonzero(loop):
            i, j = ids[g.edges_i[k]], ids[g.edges_j[k]]
            T = icp(seq.load(i), seq.load(j), g.meas[k])
            g_icp.meas[k] = T
            T_gt = inv(pose_at(gt, seq.timestamps[[i]])[0]) @ pose_at(gt, seq.timestamps[[j]])[0]
            dev.append((deg(inv(T_gt) @ g.meas[k]), deg(inv(T_gt) @ T)))
        measured = run_gauss_newton(g, init, "lm", max_iter=100).poses
        by_icp = run_gauss_newton(g_icp, init, "lm", max_iter=100).poses
        d = np.array(dev) if dev else np.full((1, 2), np.nan)
        print(f"{run.name}: keyframe ATE odometry {keyframe_ate(init, G):.4f}, loops as measured "
              f"{keyframe_ate(measured, G):.4f}, loops by depth ICP {keyframe_ate(by_icp, G):.4f} m; {int(loop.sum())} loop "
              f"edges, median rotation from the truth {np.median(d[:, 0]):.2f} deg as measured, {np.median(d[:, 1]):.2f} by ICP",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
