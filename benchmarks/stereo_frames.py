"""Where a stereo run's error is made, frame by frame, against exact ground truth (docs/stereo_measured.md, "Where
the highway error is made").

The chain runs with the ``kitti`` preset (plus ``--set``) and, per frame, records whether the stereo
fallback placed it (``registration.stereo_fallback``), the registration's inliers, the key points with
a depth in the tracking range split at 40 baselines (ORB-SLAM's near/far ``ThDepth``; 21.6 m for a
0.54 m baseline), the key points with a stereo depth beyond the range, and whether the landmark map
placed it (``landmarks.enabled``). The error of each frame's **own** step is the relative-motion error
against the ground truth, ``(G_{k-1}^-1 G_k)^-1 (E_{k-1}^-1 E_k)``: its translation (m, camera axes x right,
y down, z forward) and rotation (deg), so a bias shows as a constant sign. ``--orb DIR`` adds the same
per-frame errors of an ORB-SLAM3 run on the same pairs (its ``CameraTrajectory_kitti.txt``, e.g. from
``python -m benchmarks.stereo --parts orb --work W``: ``W/orb_highway_seed_S_0``). The summary sums the
step errors over the fallback frames and over the registered ones.

Usage::

    .venv/bin/python -m benchmarks.stereo_frames runs/highway1 [--set KEY=VALUE ...] [--orb DIR] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from rgbdslam.geometry.se3 import inv, rotation_angle

NEAR_BASELINES = 40.0  # ORB-SLAM's ThDepth, in baselines


def step_errors(E: np.ndarray, G: np.ndarray) -> np.ndarray:
    """(N, 8) per frame: the step's translation error (x, y, z in the camera, m), its norm (m), rotation error (deg),
    and that rotation error as a rotation vector (x, y, z in the camera, deg); frame 0 zeros."""
    from scipy.spatial.transform import Rotation

    out = np.zeros((len(E), 8))
    for k in range(1, len(E)):
        e = inv(inv(G[k - 1]) @ G[k]) @ (inv(E[k - 1]) @ E[k])
        out[k, :3] = e[:3, 3]
        out[k, 3] = np.linalg.norm(e[:3, 3])
        out[k, 4] = np.degrees(rotation_angle(e[:3, :3]))
        out[k, 5:] = np.degrees(Rotation.from_matrix(e[:3, :3]).as_rotvec())
    return out


def ate_se3(E: np.ndarray, G: np.ndarray) -> float:
    """ATE RMSE (m) of the positions after the best rigid alignment (Umeyama without scale)."""
    return _umeyama(E, G)[0]


def sim3_scale(E: np.ndarray, G: np.ndarray) -> float:
    """The scale of the best similarity alignment of the positions (Umeyama): > 1 = the estimate is too short."""
    return _umeyama(E, G)[1]


def _umeyama(E: np.ndarray, G: np.ndarray) -> tuple[float, float]:
    X, Y = E[:, :3, 3], G[:, :3, 3]
    mx, my = X.mean(0), Y.mean(0)
    U, S, Vt = np.linalg.svd((Y - my).T @ (X - mx))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    ate = float(np.sqrt(np.mean(np.sum(((X - mx) @ R.T + my - Y) ** 2, axis=1))))
    var = float(np.mean(np.sum((X - mx) ** 2, axis=1)))
    return ate, float(np.trace(np.diag(S) @ D) / len(X) / var) if var > 0 else 1.0


def run_frames(path: str, sets: list[str]) -> dict:
    """The chain over the sequence with the per-frame record (see the module doc)."""
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.frontend.features import with_detections
    from rgbdslam.frontend.odometry import detection_features
    from rgbdslam.slam import SLAM

    cfg = load_config("kitti", sets)
    seq = open_sequence(path, cfg)
    gt = seq.groundtruth()
    slam = SLAM(cfg, seq.camera)
    fe, lm = slam.frontend, slam.landmarks
    fc = detection_features(cfg.features, cfg.landmarks.n_features if lm is not None and not seq.own_key_points else 0)
    rows, index = [], []
    for i, pending in seq.prefetched(2, then=lambda f: with_detections(f, fc), workers=1):
        frame = pending.result()
        nf, mp = fe.n_fallback, lm.stats.map_poses if lm is not None else 0
        res = slam.track(frame)
        if res.lost or res.pose is None:
            continue
        f = res.features
        split = NEAR_BASELINES * f.depth_noise.baseline if f.depth_noise is not None else np.inf
        z = f.pts[f.valid, 2]
        rows.append({"frame": i, "fallback": fe.n_fallback > nf, "inliers": int(res.n_inliers or 0),
                     "near": int((z < split).sum()), "far": int((z >= split).sum()),
                     "beyond_range": int(((f.depth_raw > 0) & ~f.valid).sum()),
                     "map_pose": (lm.stats.map_poses > mp) if lm is not None else False})
        index.append(i)
    E = slam.finish().poses
    G = gt.poses[np.array(index)]
    err = step_errors(E, G)
    for r, e in zip(rows, err):
        r.update(ex=float(e[0]), ey=float(e[1]), ez=float(e[2]), dt=float(e[3]), dr=float(e[4]),
                 rx=float(e[5]), ry=float(e[6]), rz=float(e[7]))
    fb = np.array([r["fallback"] for r in rows])
    summary = {"ate": ate_se3(E, G), "sim3_scale": sim3_scale(E, G), "lost": len(slam.state.lost), "fallback_frames": int(fb.sum()),
               "map_poses": int(sum(r["map_pose"] for r in rows)),
               "step_m_fallback": float(err[fb, 3].sum()), "step_m_registered": float(err[~fb, 3].sum()),
               "step_deg_fallback": float(err[fb, 4].sum()), "step_deg_registered": float(err[~fb, 4].sum())}
    return {"rows": rows, "summary": summary, "gt": G, "index": index}


def orb_steps(orb_dir: str, G_all: np.ndarray) -> np.ndarray:
    from rgbdslam.io.kitti import read_kitti_poses

    E = np.asarray(read_kitti_poses(Path(orb_dir) / "CameraTrajectory_kitti.txt"), dtype=np.float64).reshape(-1, 4, 4)
    n = min(len(E), len(G_all))
    return step_errors(E[:n], G_all[:n])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sequence")
    ap.add_argument("--set", action="append", default=[], dest="sets", metavar="KEY=VALUE")
    ap.add_argument("--orb", default=None, help="an ORB-SLAM3 run folder on the same pairs (CameraTrajectory_kitti.txt)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    out = run_frames(args.sequence, args.sets)
    orb = None
    if args.orb:
        from rgbdslam.config import load_config
        from rgbdslam.datasets import open_sequence

        orb = orb_steps(args.orb, open_sequence(args.sequence, load_config("kitti")).groundtruth().poses)
    print(" frame fb inliers near far beyond map |  dx     dy     dz   step m  deg (rotation error x y z)" + ("  | ORB step m  deg" if orb is not None else ""))
    for r in out["rows"]:
        line = (f"{r['frame']:6d} {'F' if r['fallback'] else '.':>2} {r['inliers']:7d} {r['near']:4d} {r['far']:3d} "
                f"{r['beyond_range']:6d} {'M' if r['map_pose'] else '.':>3} | {r['ex']:+.3f} {r['ey']:+.3f} {r['ez']:+.3f} "
                f"{r['dt']:.3f} {r['dr']:.3f} ({r['rx']:+.3f} {r['ry']:+.3f} {r['rz']:+.3f})")
        if orb is not None and r["frame"] < len(orb):
            line += f"  | {orb[r['frame'], 3]:.3f} {orb[r['frame'], 4]:.3f}"
        print(line)
    s = out["summary"]
    if orb is not None:
        fb = np.zeros(len(orb), bool)
        fb[[r["frame"] for r in out["rows"] if r["fallback"] and r["frame"] < len(orb)]] = True
        s.update(orb_step_m_fallback=float(orb[fb, 3].sum()), orb_step_m_registered=float(orb[~fb, 3].sum()),
                 orb_step_deg_fallback=float(orb[fb, 4].sum()), orb_step_deg_registered=float(orb[~fb, 4].sum()))
    print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in s.items()}))
    if args.json:
        args.json.write_text(json.dumps({"rows": out["rows"], "summary": s}, indent=1))


if __name__ == "__main__":
    main()
