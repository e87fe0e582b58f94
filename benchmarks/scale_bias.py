"""Translation-scale bias of the frame-to-frame registration, per stage choice, against ground truth.

For every consecutive frame pair of a sequence (the synthetic ``orbit`` motion has exact ground truth;
TUM fr3/teddy frames 0-119 motion capture), the estimated camera translation of a plain SVD fit on the
pre-filtered descriptor matches is compared with the true one; the ratio
``sum(t_est . t_true) / sum(|t_true|^2)`` (1 = no bias) is printed for: all matches, and matches without
key points at depth edges (window radius fixed, scaled with the ORB pyramid level, or only at coarse
or fine levels), matches without the edge points whose own pixel lies on the far surface, and all matches
with every far-side edge point given the near surface's depth. See docs/frontend.md "Scale bias" for
the findings.

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


def edge_flags(feats, depth, radius_of_level, jump: float = 0.05) -> np.ndarray:
    """Depth-edge flags of every key point (a ``jump`` relative depth step), the window radius a function of its
    ORB level."""
    h, w = depth.shape
    u = np.clip(np.rint(feats.uv_raw[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(feats.uv_raw[:, 1]).astype(int), 0, h - 1)
    radius = np.array([radius_of_level(o) for o in feats.octave], np.int64)
    return depth_edges(depth, u, v, radius, jump)


def near_depth(depth: np.ndarray, u: np.ndarray, v: np.ndarray, radius: np.ndarray, jump: float) -> np.ndarray:
    """(N,) depth of the near surface in each pixel's (2r+1)² window: of the pixels within ``jump`` of
    the window's least depth, the one closest to the centre (NaN: no depth in the window)."""
    h, w = depth.shape
    out = np.full(len(u), np.nan)
    for r in np.unique(radius):
        m = radius == r
        k = np.arange(-r, r + 1)
        vv = np.clip(v[m][:, None, None] + k[None, :, None], 0, h - 1)
        uu = np.clip(u[m][:, None, None] + k[None, None, :], 0, w - 1)
        nb = depth[vv, uu].reshape(int(m.sum()), -1).astype(np.float64)
        nb = np.where(np.isfinite(nb) & (nb > 0), nb, np.inf)
        near = nb <= nb.min(axis=1, keepdims=True) * (1 + jump)
        dist = (k[:, None] ** 2 + k[None, :] ** 2).ravel()
        z = nb[np.arange(len(nb)), np.argmin(np.where(near, dist, np.inf), axis=1)]
        out[m] = np.where(np.isfinite(z), z, np.nan)
    return out


def far_side(feats, depth, radius_of_level) -> tuple[np.ndarray, np.ndarray]:
    """Depth-edge key points whose own pixel is on the far surface (its depth more than 5 % beyond the
    window's near surface), and the near surface's depth for each key point."""
    h, w = depth.shape
    u = np.clip(np.rint(feats.uv_raw[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(feats.uv_raw[:, 1]).astype(int), 0, h - 1)
    radius = np.array([radius_of_level(o) for o in feats.octave], np.int64)
    z_near = near_depth(depth, u, v, radius, 0.05)
    z = feats.pts[:, 2]
    with np.errstate(invalid="ignore"):
        far = edge_flags(feats, depth, radius_of_level) & (z > z_near * 1.05)
    return far, z_near


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
    def level_radius(r0):
        return lambda o: int(np.ceil(r0 * s ** o - 1e-9))

    for r0 in (1, 2, 3):
        rules[f"no depth edge, r = {r0}·{s}^level"] = level_radius(r0)
    rules[f"no depth edge, r = 1·{s}^level at levels 0-2, 3·{s}^level above"] = lambda o: level_radius(1 if o < 3 else 3)(o)
    rules[f"no depth edge, r = 3·{s}^level at levels 0-2, 1·{s}^level above"] = lambda o: level_radius(3 if o < 3 else 1)(o)
    flags = {k: [edge_flags(f, fr.depth, rule) for f, fr in zip(feats, loaded)] for k, rule in rules.items()}
    mc = cfg.matching  # the default's window and jump
    flags[f"no depth edge, r = {mc.depth_edge_radius}·{s}^level, {mc.depth_edge_jump:.0%} jump (the default)"] = [
        edge_flags(f, fr.depth, level_radius(mc.depth_edge_radius), mc.depth_edge_jump) for f, fr in zip(feats, loaded)]
    # edge points on the far surface only (r = 2·s^level), and all points with those given the near depth
    sides = [far_side(f, fr.depth, level_radius(2)) for f, fr in zip(feats, loaded)]
    far_only = f"no far-side depth edge, r = 2·{s}^level"
    flags[far_only] = [far for far, _ in sides]
    near_pts = []
    for f, (far, z_near) in zip(feats, sides):
        p = f.pts.copy()
        p[far] *= (z_near[far] / p[far, 2])[:, None]  # the same ray at the near surface's depth
        near_pts.append(p)
    near_rule = f"all matches, far-side edge points at the near depth (r = 2·{s}^level)"
    flags[near_rule] = [np.zeros(len(f.uv), bool) for f in feats]
    feats_near = [f.with_points(p) for f, p in zip(feats, near_pts)]
    est = {k: [] for k in flags}
    used = {k: [] for k in flags}
    true = []
    for i in range(n - 1):
        if stamps[i] < gt.timestamps[0] or stamps[i + 1] > gt.timestamps[-1]:
            continue
        true.append((inv(G[i]) @ G[i + 1])[:3, 3])
        for k in flags:
            a, b = (feats_near if k == near_rule else feats)[i:i + 2]  # the pre-filter sees the near depths too
            ia, ib = match_pairs(a, b, cfg.matching)
            keep = prefilter(a, b, ia, ib, cfg.matching)
            ia, ib = ia[keep], ib[keep]
            ok = ~flags[k][i][ia] & ~flags[k][i + 1][ib]
            est[k].append(inv(fit_rigid(a.pts[ia[ok]], b.pts[ib[ok]]))[:3, 3])
            used[k].append(int(ok.sum()))
    g = np.array(true)
    out = {}
    for k in flags:
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
