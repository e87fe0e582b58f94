"""Which image agrees with a run's loop edges: the colour or the depth? (issue 17, 7-Scenes)

For every loop edge of RUN/posegraph.g2o (frames i, j; the measured pose of j in i's frame) the two
frames are aligned again by three dense methods that do not use the run's features, each started
once from the ground truth's relative pose and once from the loop edge:

* ``depth``: point-to-plane ICP of the two depth clouds alone (Open3D; 1 cm voxels, 3 cm gate) —
  what a depth-only tracker such as KinectFusion (7-Scenes' reference poses) measures;
* ``colour``: Open3D's RGB-D odometry with the photometric term only (the depth only lifts the
  pixels) — what the colour image says;
* ``hybrid``: the same with the photometric and the depth term.

Printed per edge and method: the rotation (deg) between where the method converged and the ground
truth, and the loop edge. When both starts converge to the same pose the method has one answer;
where the colour and the depth answers differ, the sequence's colour and depth images disagree
about the relative pose under the camera model (intrinsics, depth-to-colour registration), and a
trajectory from colour features is measured against a depth-only reference with that bias. The
ground truth is used for the comparison only.

Usage::

    .venv/bin/python scripts/diag_loop_dense.py SEQUENCE RUN [--set dataset.camera_file=...] [--max-edges 9]
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
from rgbdslam.geometry.se3 import inv, rotation_angle  # noqa: E402
from rgbdslam.posegraph.graph_io import read_graph  # noqa: E402


def loop_edges(run: Path) -> list[tuple[int, int, np.ndarray]]:
    """(i, j, T_ij) of every edge of ``run``'s pose graph between keyframes that are not neighbours."""
    g = read_graph(run / "posegraph.g2o")
    ids = [int(x) for x in g.ids]
    rank = {v: k for k, v in enumerate(sorted(ids))}
    return [(ids[g.edges_i[k]], ids[g.edges_j[k]], g.meas[k]) for k in range(g.n_edges)
            if abs(rank[ids[g.edges_i[k]]] - rank[ids[g.edges_j[k]]]) != 1]


def dense_aligners(camera, max_depth: float = 4.0):
    """{name: align(frame_i, frame_j, T0) -> pose of j in i's frame or None}."""
    import open3d as o3d

    intr = o3d.camera.PinholeCameraIntrinsic(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)

    def rgbd(f):
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(f.rgb)), o3d.geometry.Image(f.depth.astype(np.float32)),
            depth_scale=1.0, depth_trunc=max_depth, convert_rgb_to_intensity=True)

    def cloud(f):
        pc = o3d.geometry.PointCloud.create_from_rgbd_image(rgbd(f), intr).voxel_down_sample(0.01)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.05, max_nn=30))
        return pc

    def icp(fi, fj, T0):
        reg = o3d.pipelines.registration
        r = reg.registration_icp(cloud(fj), cloud(fi), 0.03, T0, reg.TransformationEstimationPointToPlane(),
                                 reg.ICPConvergenceCriteria(max_iteration=60))
        return np.asarray(r.transformation)

    def odometry(jacobian):
        opt = o3d.pipelines.odometry.OdometryOption()
        opt.iteration_number_per_pyramid_level = o3d.utility.IntVector([40, 20, 10])

        def align(fi, fj, T0):
            ok, T, _ = o3d.pipelines.odometry.compute_rgbd_odometry(rgbd(fj), rgbd(fi), intr, T0, jacobian, opt)
            return np.asarray(T) if ok else None
        return align

    od = o3d.pipelines.odometry
    return {"depth": icp, "colour": odometry(od.RGBDOdometryJacobianFromColorTerm()),
            "hybrid": odometry(od.RGBDOdometryJacobianFromHybridTerm())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("run", type=Path)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--max-edges", type=int, default=9)
    a = ap.parse_args(argv)
    seq = open_sequence(a.sequence, load_config(None, list(a.set)).dataset)
    gt = seq.groundtruth()
    from scripts.diag_depth_delay import pose_at

    deg = lambda T: float(np.degrees(rotation_angle(T[:3, :3])))  # noqa: E731
    aligners = dense_aligners(seq.camera)
    summary: dict[str, list[tuple[float, float]]] = {k: [] for k in aligners}
    for i, j, T_loop in loop_edges(a.run)[: a.max_edges]:
        Pi, Pj = pose_at(gt, seq.timestamps[[i, j]])
        T_gt = inv(Pi) @ Pj
        fi, fj = seq.load(i), seq.load(j)
        parts = [f"loop {i:4d}-{j:4d}: loop edge vs truth {deg(inv(T_gt) @ T_loop):.2f} deg"]
        for name, align in aligners.items():
            for start, T0 in (("truth", T_gt), ("loop", T_loop)):
                T = align(fi, fj, T0)
                if T is None:
                    parts.append(f"{name} from {start}: failed")
                    continue
                d_gt, d_loop = deg(inv(T_gt) @ T), deg(inv(T_loop) @ T)
                summary[name].append((d_gt, d_loop))
                parts.append(f"{name} from {start}: {d_gt:.2f} / {d_loop:.2f}")
        print("  ".join(parts), flush=True)
    print("median rotation (deg) of the dense result from the truth / from the loop edge, both starts:")
    for name, v in summary.items():
        if v:
            r = np.array(v)
            print(f"  {name:7s} {np.median(r[:, 0]):.2f} / {np.median(r[:, 1]):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
