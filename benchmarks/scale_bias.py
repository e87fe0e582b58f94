"""Translation-scale bias of the frame-to-frame registration, per stage choice, against ground truth.

For every consecutive frame pair of a sequence (the synthetic ``orbit`` motion has exact ground truth;
TUM fr3/teddy frames 0-119 motion capture), the estimated camera translation of a plain SVD fit on the
pre-filtered descriptor matches is compared with the true one; the ratio
``sum(t_est . t_true) / sum(|t_true|^2)`` (1 = no bias) is printed for: all matches, and matches without
key points at depth edges (window radius fixed, or scaled with the ORB pyramid level). See
docs/frontend.md "Scale bias" for the findings.

Run from the repository root:  python -m benchmarks.scale_bias [SEQUENCE ...] [--frames N]
(default: a 60-frame synthetic orbit rendered into a temporary folder, and TUM fr3/teddy 0-119 from
$RGBDSLAM_DATA, default ../shared/data).
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from rgbdslam.config import Config
from rgbdslam.datasets import open_sequence
from rgbdslam.datasets.synthetic import generate_sequence
from rgbdslam.frontend.features import depth_edges, extract_features
from rgbdslam.frontend.matching import match_pairs, prefilter
from rgbdslam.geometry.rigid import fit_rigid
from rgbdslam.geometry.se3 import inv

TEDDY = "tum/rgbd_dataset_freiburg3_teddy_frames_0000_0119"


def poses_at(gt, stamps: np.ndarray) -> np.ndarray:
    """Ground-truth camera-to-world poses at ``stamps`` (linear / slerp interpolation, clamped)."""
    t = np.clip(stamps, gt.timestamps[0], gt.timestamps[-1])
    out = np.tile(np.eye(4), (len(t), 1, 1))
    out[:, :3, :3] = Slerp(gt.timestamps, Rotation.from_matrix(gt.poses[:, :3, :3]))(t).as_matrix()
    out[:, :3, 3] = np.stack([np.interp(t, gt.timestamps, gt.poses[:, k, 3]) for k in range(3)], axis=1)
    return out


def edge_flags(feats, depth, radius_of_level) -> np.ndarray:
    """Depth-edge flags (5 % jump) of every key point, the window radius a function of its ORB level."""
    h, w = depth.shape
    u = np.clip(np.rint(feats.uv_raw[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(feats.uv_raw[:, 1]).astype(int), 0, h - 1)
    radius = np.array([radius_of_level(o) for o in feats.octave], np.int64)
    return depth_edges(depth, u, v, radius, 0.05)


def measure(path: Path, frames: int) -> dict[str, tuple[float, float, float]]:
    """{rule: (scale ratio, median translation error mm, mean pairs used)} over consecutive frame pairs."""
    cfg = Config()
    seq = open_sequence(path, cfg)
    n = min(frames, len(seq))
    loaded = [seq.load(i) for i in range(n)]
    gt = seq.groundtruth()
    stamps = np.array([f.timestamp for f in loaded])
    G = poses_at(gt, stamps)
    feats = [extract_features(f, cfg.features, cfg.matching) for f in loaded]
    s = cfg.features.scale_factor
    rules = {"all matches": lambda o: 0, "no depth edge, r = 4 px": lambda o: 4, "no depth edge, r = 8 px": lambda o: 8}
    for r0 in (1, 2, 3):
        rules[f"no depth edge, r = {r0}·{s}^level"] = (lambda r0: lambda o: int(np.ceil(r0 * s ** o - 1e-9)))(r0)
    flags = {k: [edge_flags(f, fr.depth, rule) for f, fr in zip(feats, loaded)] for k, rule in rules.items()}
    est = {k: [] for k in rules}
    used = {k: [] for k in rules}
    true = []
    for i in range(n - 1):
        if stamps[i] < gt.timestamps[0] or stamps[i + 1] > gt.timestamps[-1]:
            continue
        a, b = feats[i], feats[i + 1]
        ia, ib = match_pairs(a, b, cfg.matching)
        keep = prefilter(a, b, ia, ib, cfg.matching)
        ia, ib = ia[keep], ib[keep]
        true.append((inv(G[i]) @ G[i + 1])[:3, 3])
        for k in rules:
            ok = ~flags[k][i][ia] & ~flags[k][i + 1][ib]
            est[k].append(inv(fit_rigid(a.pts[ia[ok]], b.pts[ib[ok]]))[:3, 3])
            used[k].append(int(ok.sum()))
    g = np.array(true)
    out = {}
    for k in rules:
        e = np.array(est[k])
        out[k] = (float((e * g).sum() / (g * g).sum()), float(np.median(np.linalg.norm(e - g, axis=1)) * 1000),
                  float(np.mean(used[k])))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequences", nargs="*", help="sequence folders with ground truth (default: orbit + teddy)")
    ap.add_argument("--frames", type=int, default=120, help="frames per sequence (from the first)")
    args = ap.parse_args()
    paths = [Path(p) for p in args.sequences]
    with tempfile.TemporaryDirectory() as tmp:
        if not paths:
            orbit = Path(tmp) / "orbit_seed0"
            generate_sequence(orbit, frames=60, motion="orbit", noise=True, seed=0)
            paths = [orbit, Path(os.environ.get("RGBDSLAM_DATA", "../shared/data")) / TEDDY]
        for p in paths:
            if not p.exists():
                print(f"{p}: not found, skipped (set RGBDSLAM_DATA to the shared data folder)")
                continue
            print(f"\n{p.name}: estimated / true frame-to-frame translation (SVD on pre-filtered matches)")
            print("| key points used | scale ratio | median error (mm) | pairs per frame |\n|---|---|---|---|")
            for k, (ratio, err, n) in measure(p, args.frames).items():
                print(f"| {k} | {ratio:.3f} | {err:.2f} | {n:.0f} |")


if __name__ == "__main__":
    main()
