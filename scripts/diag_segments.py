"""Where do runs depart from the ground truth (and from each other)? Per-segment errors (issue 17, 7-Scenes)

For each RUN (a run folder: ``odometry.tum`` = the chain before the pose graph, ``trajectory.tum`` =
the final one) and each block of ``--block`` frames:

* ``abs``: RMS position error of the block under one SE(3) alignment of the whole trajectory (ATE's);
* ``rot0``: rotation error (deg) of the pose relative to frame 0, T_0k, against the ground truth's, at
  the block's last frame — accumulated rotation drift, no alignment;
* ``seg``: rotation (deg) / translation (mm) error of the block's own relative pose (first to last
  frame) — the drift the block adds.

With two or more runs, ``--pairs`` also prints the rotation between the runs' relative poses of each
block (where they disagree, without the ground truth). The ground truth is used for evaluation only.

Usage::

    .venv/bin/python scripts/diag_segments.py SEQUENCE RUN [RUN ...] [--set dataset.camera_file=...] [--block 30]
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
from rgbdslam.io.trajectory import read_tum  # noqa: E402


def matched(gt, traj) -> tuple[np.ndarray, np.ndarray]:
    """(ground-truth poses, estimated poses) at the estimate's stamps (nearest ground-truth stamp)."""
    k = np.clip(np.searchsorted(gt.timestamps, traj.timestamps), 1, len(gt.timestamps) - 1)
    k = np.where(np.abs(gt.timestamps[k - 1] - traj.timestamps) < np.abs(gt.timestamps[k] - traj.timestamps), k - 1, k)
    return gt.poses[k], traj.poses


def segment_table(G: np.ndarray, E: np.ndarray, block: int) -> list[tuple[int, int, float, float, float, float]]:
    """Per block [a, b]: (a, b, abs RMS position error m, rot0 deg, seg rotation deg, seg translation m)."""
    R, t, _ = umeyama_alignment(E[:, :3, 3].T, G[:, :3, 3].T, "se3")
    Ea = E[:, :3, 3] @ R.T + t
    out = []
    for a in range(0, len(G) - 1, block):
        b = min(a + block, len(G) - 1)
        err = np.linalg.norm(Ea[a:b + 1] - G[a:b + 1, :3, 3], axis=1)
        D0 = inv(inv(G[0]) @ G[b]) @ (inv(E[0]) @ E[b])
        Ds = inv(inv(G[a]) @ G[b]) @ (inv(E[a]) @ E[b])
        out.append((a, b, float(np.sqrt(np.mean(err**2))), float(np.degrees(rotation_angle(D0[:3, :3]))),
                    float(np.degrees(rotation_angle(Ds[:3, :3]))), float(np.linalg.norm(Ds[:3, 3]))))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--block", type=int, default=30)
    ap.add_argument("--pairs", action="store_true", help="rotation between the runs' block relative poses")
    a = ap.parse_args(argv)
    cfg = load_config(None, list(a.set))
    gt = open_sequence(a.sequence, cfg.dataset).groundtruth()
    trajs = {}
    for run in a.runs:
        for name in ("odometry", "trajectory"):
            p = run / f"{name}.tum"
            if p.exists():
                G, E = matched(gt, read_tum(p))
                trajs[f"{run.name}:{name}"] = E
                rows = segment_table(G, E, a.block)
                R, t, _ = umeyama_alignment(E[:, :3, 3].T, G[:, :3, 3].T, "se3")
                ate = float(np.sqrt(np.mean(np.sum((E[:, :3, 3] @ R.T + t - G[:, :3, 3]) ** 2, axis=1))))
                print(f"\n{run.name} {name}: ATE {ate:.4f} m")
                print("  frames     abs mm  rot0 deg  seg deg  seg mm")
                for x in rows:
                    print(f"  {x[0]:3d}-{x[1]:3d}  {1e3 * x[2]:7.1f}  {x[3]:8.2f}  {x[4]:7.2f}  {1e3 * x[5]:6.1f}")
    if a.pairs and len(trajs) >= 2:
        names = list(trajs)
        print("\nrotation (deg) between runs' block relative poses:")
        print("  frames   " + "  ".join(f"{n[-28:]:>28s}" for n in names[1:]))
        base = trajs[names[0]]
        n = len(base)
        for s in range(0, n - 1, a.block):
            e = min(s + a.block, n - 1)
            vals = []
            for nm in names[1:]:
                E = trajs[nm]
                D = inv(inv(base[s]) @ base[e]) @ (inv(E[s]) @ E[e])
                vals.append(np.degrees(rotation_angle(D[:3, :3])))
            print(f"  {s:3d}-{e:3d}  " + "  ".join(f"{v:28.2f}" for v in vals))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
