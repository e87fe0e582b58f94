"""Does the colour/depth time offset of an RGB-D sequence show in its 3-D key points? (issue 17)

For consecutive frames (i-1, i) the ORB key points are lifted to 3-D with the frame's depth, matched by
descriptor, and the matched points compared under the ground-truth relative motion (evaluation only: the
ground truth measures here, it sets nothing): residual r = T_gt · p_{i-1} - p_i. Each frame's depth is
read either at the key point's own pixel (``ignore``) or, with the camera's motion over the frame's
colour-to-depth delay taken from the ground truth (``gt``, the best a compensation could do) or from the
constant-velocity model of the previous ground-truth poses (``cv``, what the tracker's ``predict`` does with
its own poses), where the scene point was at the depth time (geometry/depth_time.py). A scan of an
extra offset added to every delay shows where the residual is smallest: if the stamps are right, at 0.

The residual's component along the current key point's viewing ray is reported (the depth's share;
across the ray the key points' pixel error dominates): median and RMS over the inliers (|r| < gate).
Per frame: |ω|·Δt (the rotation over the frame's own delay, deg) against the median inlier residual.

Usage::

    .venv/bin/python scripts/diag_depth_delay.py ../shared/data/tum/rgbd_dataset_freiburg1_rpy_head200 \
        [--offsets -0.02,-0.01,0,0.01,0.02] [--gate 0.03]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from rgbdslam.config import load_config  # noqa: E402
from rgbdslam.datasets import open_sequence  # noqa: E402
from rgbdslam.frontend.features import extract_features  # noqa: E402
from rgbdslam.frontend.matching import match_pairs  # noqa: E402
from rgbdslam.geometry.se3 import inv, rotation_angle, scale_motion  # noqa: E402


def pose_at(gt, t: np.ndarray) -> np.ndarray:
    """Ground-truth poses at times ``t`` (linear translation, slerp rotation)."""
    ts = gt.timestamps
    t = np.clip(np.asarray(t, float), ts[0], ts[-1])
    out = np.tile(np.eye(4), (len(t), 1, 1))
    out[:, :3, :3] = Slerp(ts, Rotation.from_matrix(gt.poses[:, :3, :3]))(t).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(t, ts, gt.poses[:, k, 3])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--offsets", default="-0.03,-0.02,-0.01,-0.005,0,0.005,0.01,0.02,0.03")
    ap.add_argument("--gate", type=float, default=0.03, help="inlier residual (m)")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args(argv)
    cfg = load_config(None, list(a.set))
    seq = open_sequence(a.sequence, cfg.dataset)
    gt = seq.groundtruth()
    n = len(seq) if a.max_frames is None else min(len(seq), a.max_frames)
    frames = [seq.load(i) for i in range(n)]
    tc = np.array([f.timestamp for f in frames])
    delay = np.array([f.depth_delay for f in frames])
    Pc = pose_at(gt, tc)
    print(f"{a.sequence.name}: {n} frames; delay ms median {1e3 * np.median(delay):.1f}, max {1e3 * delay.max():.1f}")
    # angular speed from the ground truth (deg/s) and the rotation over each frame's own delay
    Pn = pose_at(gt, tc + 0.005)
    Pp = pose_at(gt, tc - 0.005)
    omega = np.degrees(rotation_angle(np.einsum("nji,njk->nik", Pp[:, :3, :3], Pn[:, :3, :3]))) / 0.01
    rot_delay = omega * np.abs(delay)
    print(f"angular speed deg/s: median {np.median(omega):.1f}, max {omega.max():.1f}; rotation over the delay deg: "
          f"median {np.median(rot_delay):.2f}, max {rot_delay.max():.2f}")

    def lifted(mode: str, extra: float):
        out = []
        for i, f in enumerate(frames):
            d = f.depth_delay + extra
            D = None
            if mode == "gt" and d != 0:
                D = inv(Pc[i]) @ pose_at(gt, [tc[i] + d])[0]
            elif mode == "cv" and d != 0 and i >= 2:
                D = scale_motion(inv(Pc[i - 2]) @ Pc[i - 1], d / (tc[i - 1] - tc[i - 2]))
            out.append(extract_features(f, cfg.features, cfg.matching, D))
        return out

    def residuals(feats):
        per_frame = np.full(n, np.nan)
        allr = []
        ninl = 0
        for i in range(1, n):
            ia, ib = match_pairs(feats[i - 1], feats[i], cfg.matching)
            T = inv(Pc[i]) @ Pc[i - 1]
            r = feats[i - 1].pts[ia] @ T[:3, :3].T + T[:3, 3] - feats[i].pts[ib]
            e = np.linalg.norm(r, axis=1)
            ray = np.abs(np.einsum("ij,ij->i", r, feats[i].pts[ib]) / np.linalg.norm(feats[i].pts[ib], axis=1))
            inl = e < a.gate
            if inl.sum() >= 10:
                per_frame[i] = np.median(ray[inl])
            allr.append(ray[inl])
            ninl += int(inl.sum())
        allr = np.concatenate(allr)
        return per_frame, np.median(allr), np.sqrt(np.mean(allr ** 2)), ninl

    base, med0, rms0, n0 = residuals(lifted("ignore", 0.0))
    print(f"ignore (depth at the key point's pixel):  along the ray: median {1e3 * med0:.2f} mm  RMS {1e3 * rms0:.2f} mm  "
          f"inliers {n0}")
    ok = np.isfinite(base)
    c = np.corrcoef(rot_delay[ok], base[ok])[0, 1]
    print(f"  correlation of the per-frame median residual with |w|*dt: {c:+.2f}")
    for mode in ("gt", "cv"):
        for extra in [float(x) for x in a.offsets.split(",")]:
            pf, med, rms, ni = residuals(lifted(mode, extra))
            ok2 = np.isfinite(pf) & ok
            print(f"{mode:3s} extra offset {1e3 * extra:+6.1f} ms: median {1e3 * med:.2f} mm  RMS {1e3 * rms:.2f} mm  "
                  f"inliers {ni}  frames better {np.mean(pf[ok2] < base[ok2]):.2f}")
            if mode == "cv":
                break
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
