"""Do a sequence's colour pixels and depth agree about the camera pose? A ground-truth-free check (issue 17)

Runs the pipeline with the landmark map on (``landmarks.enabled=true`` plus ``--set`` overrides) and, for
every map pose with at least 30 inliers, estimates the pose twice from the same inliers: from their **pixels
alone** (the reprojection refine with the depth sigma x100 and the landmarks' covariance left out: a PnP) and
from their **3-D points alone** (the weighted rigid fit, 1/sigma_z^2). Their disagreement
eta = Log(P_pixels^-1 P_points) (camera frame; rotation deg, translation mm) is summarised by its median size
and by |mean| / RMS per part (near 1: a systematic bias, near 0: noise). With an exact camera model (the
synthetic generator) the two agree to the noise; a colour camera model or a depth registration that is off
makes them disagree. No ground truth is read.

Usage::

    .venv/bin/python scripts/diag_colour_depth.py SEQUENCE [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from rgbdslam.config import load_config  # noqa: E402
from rgbdslam.geometry.rigid import fit_rigid  # noqa: E402
from rgbdslam.geometry.se3 import inv  # noqa: E402


def pixel_and_point_poses(lmap, feats, res, camera, cfg):
    """(pose from the inliers' pixels alone, pose from their 3-D points alone) of map pose ``res``."""
    from rgbdslam.landmarks.tracking import refine_reprojection

    S, D, uv = feats.pts[res.feat], lmap.pos[res.lm], feats.uv[res.feat]
    sig = cfg.depth_noise_a + cfg.depth_noise_b * S[:, 2] ** 2
    Tp, _, _ = refine_reprojection(res.pose, D, uv, S[:, 2], camera, 1.0, sig * 100.0, np.zeros(len(D)), 10)
    return Tp, fit_rigid(S, D, 1.0 / sig**2)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args(argv)
    import gtsam

    from rgbdslam.datasets import open_sequence
    from rgbdslam.landmarks import stage
    from rgbdslam.slam import SLAM

    cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", "landmarks.enabled=true", *a.set])
    seq = open_sequence(a.sequence, cfg)
    rec = []
    orig = stage.estimate_pose

    def estimate(lmap, feats, match, *args, **kw):
        res = orig(lmap, feats, match, *args, **kw)
        if res is not None and len(res.lm) >= 30:
            Tp, Td = pixel_and_point_poses(lmap, feats, res, seq.camera, cfg.landmarks)
            rec.append(gtsam.Pose3.Logmap(gtsam.Pose3(inv(Tp) @ Td)))
        return res

    stage.estimate_pose = estimate
    try:
        slam = SLAM(cfg, seq.camera)
        for i in range(len(seq)):
            slam.track(seq[i])
    finally:
        stage.estimate_pose = orig
    if not rec:
        print("no map pose with 30 inliers")
        return 1
    e = np.array(rec)
    e[:, :3], e[:, 3:] = np.degrees(e[:, :3]), 1e3 * e[:, 3:]
    ratio = [np.linalg.norm(e[:, k].mean(0)) / np.sqrt((e[:, k] ** 2).sum(1).mean()) for k in (slice(0, 3), slice(3, 6))]
    print(f"{a.sequence.name}: {len(e)} map-pose estimates; pixels vs points: median rotation "
          f"{np.median(np.linalg.norm(e[:, :3], axis=1)):.2f} deg, translation {np.median(np.linalg.norm(e[:, 3:], axis=1)):.1f} mm; "
          f"|mean| / RMS rotation {ratio[0]:.2f}, translation {ratio[1]:.2f}")
    print("  mean (deg x3, mm x3):", np.array2string(e.mean(0), precision=3, suppress_small=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
