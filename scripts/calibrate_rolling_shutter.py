"""Rolling-shutter readout time of an RGB-D camera from its own frames, without ground truth.

A rolling shutter reads the image rows one after the other; under rotation the key points of
the rows read later are displaced (``features.rolling_shutter``, docs/slam.md "Rolling shutter").
Undone with the right readout time, consecutive frames' 3-D key points agree better under one rigid
motion. For each candidate readout the front end tracks the sequence with it, and every frame's
registration against the previous one is scored by the RMS reprojection error (pixels, each
capped at 10 px) of its inliers: the previous frame's 3-D points moved by the registration and
projected, against the current key points (the rolling shutter displaces pixels; the 3-D residual
is dominated by the depth noise along the rays); the readout with the smallest median residual is the estimate. Only the
images are used (no ground truth): it can run on a camera's own recording.

Usage::

    .venv/bin/python scripts/calibrate_rolling_shutter.py SEQUENCE [--readouts 0,0.01,...] [--set K=V ...]
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
from rgbdslam.frontend.odometry import build_frontend  # noqa: E402
from rgbdslam.frontend.pairwise import build_pair_registration  # noqa: E402
from rgbdslam.geometry.se3 import inv  # noqa: E402


def score(frames, cfg, readout: float) -> tuple[float, float, int]:
    """(median over frames of the RMS inlier reprojection error in px, mean inliers, frames scored) with the
    front end's key points for ``readout`` seconds."""
    c = load_config(None, [f"features.rolling_shutter={readout}"])
    c.features, c.matching, c.registration = (type(cfg.features)(**{**vars(cfg.features), "rolling_shutter": readout}),
                                              cfg.matching, cfg.registration)
    fe = build_frontend(c, frames[0].camera)
    pair = build_pair_registration(c)
    res, inl = [], []
    prev = None
    for f in frames:
        tr = fe.track(f)
        if tr.lost:
            prev = None
            continue
        if prev is not None:
            r = pair(prev[0], tr.features, inv(tr.pose) @ prev[1])
            if r is not None and r.n_inliers >= 10:
                a, b = r.pairs[:, 0], r.pairs[:, 1]
                P = prev[0].pts[a] @ r.T[:3, :3].T + r.T[:3, 3]  # reference points in the current frame
                px = np.linalg.norm(f.camera.project(P) - tr.features.uv[b], axis=1)
                res.append(float(np.sqrt(np.mean(np.minimum(px, 10.0) ** 2))))
                inl.append(r.n_inliers)
        prev = (tr.features, tr.pose)
    return float(np.median(res)), float(np.mean(inl)), len(res)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--readouts", default="0,0.01,0.02,0.03,0.04")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args(argv)
    cfg = load_config(None, list(a.set))
    seq = open_sequence(a.sequence, cfg.dataset)
    n = len(seq) if a.max_frames is None else min(len(seq), a.max_frames)
    frames = [seq.load(i) for i in range(n)]
    best = None
    for r in [float(x) for x in a.readouts.split(",")]:
        med, inl, k = score(frames, cfg, r)
        print(f"readout {1e3 * r:5.1f} ms: median inlier RMS reprojection error {med:.4f} px, mean inliers {inl:.0f} "
              f"({k} frame pairs)", flush=True)
        if best is None or med < best[1]:
            best = (r, med)
    print(f"smallest residual at a readout of {1e3 * best[0]:.1f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
