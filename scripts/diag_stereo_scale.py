"""Is a stereo rig's depth to scale with its ground truth? (docs/stereo.md, "The noise model")

For consecutive pairs (i, i+1) of a stereo sequence with ground truth, the sparse stereo points of the
left key points (the product's own ``detect`` + ``sparse_matches`` with the ``kitti`` preset) are
matched by descriptor (cross-checked) and kept within 3 px of their ground-truth reprojection
(evaluation only: the ground truth measures here, it sets nothing). If every depth were off by one
factor 1/s, the points would obey ``s Pb = R (s Pa) + t`` with the ground-truth motion (R, t), so each
match gives ``s_i = (v_i . t) / (v_i . v_i)``, ``v_i = Pb_i - R Pa_i``. Medians per disparity band:
s < 1 means the stereo depths are too long (the disparities too small by the share 1 - s). Below
~20 px the ratio is dominated by the disparity noise (and biased low by it); the 20-130 px band is
the measurement.

Usage::

    .venv/bin/python scripts/diag_stereo_scale.py ../shared/data/kitti/odometry_06_head51
    .venv/bin/python scripts/diag_stereo_scale.py runs/highway0   # rgbdslam synth --motion highway
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np

from rgbdslam.config import load_config
from rgbdslam.datasets import open_sequence
from rgbdslam.frontend.features import detect
from rgbdslam.geometry.se3 import inv
from rgbdslam.stereo.depth import sparse_matches

BANDS = ((4, 10), (10, 20), (20, 40), (40, 130), (20, 130))


def scale_ratios(path: str) -> tuple[np.ndarray, np.ndarray, float]:
    """Per-match scale ratios s_i and the current disparities (px) of the matches, and fx * B."""
    cfg = load_config("kitti", [])
    seq = open_sequence(path, cfg)
    G = seq.groundtruth().poses
    cam = seq.camera
    per = []
    for i in range(len(seq)):
        left, right = seq.rectified_pair(i)
        det = detect(left, cfg.features)
        m = sparse_matches(left, right, seq.rig, det.uv_raw, det.desc, cfg.stereo, cfg.features)
        per.append((det.uv_raw[m.left_index], det.desc[m.left_index], m.disparity, m.points))
    bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    ratios, disparities = [], []
    for i in range(len(per) - 1):
        (_, da, _, Pa), (ub, db, pb, Pb) = per[i], per[i + 1]
        ms = bf.match(da, db)
        ia = np.array([x.queryIdx for x in ms], int)
        ib = np.array([x.trainIdx for x in ms], int)
        T = inv(G[i + 1]) @ G[i]
        Q = Pa[ia] @ T[:3, :3].T + T[:3, 3]
        proj = np.stack([cam.fx * Q[:, 0] / Q[:, 2] + cam.cx, cam.fy * Q[:, 1] / Q[:, 2] + cam.cy], axis=1)
        ok = (Q[:, 2] > 0) & np.all(np.abs(proj - ub[ib]) < 3.0, axis=1)
        v = Pb[ib][ok] - Pa[ia][ok] @ T[:3, :3].T
        ratios.append((v @ T[:3, 3]) / np.einsum("ij,ij->i", v, v))
        disparities.append(pb[ib][ok])
    return np.concatenate(ratios), np.concatenate(disparities), cam.fx * seq.rig.baseline


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence", help="a stereo sequence folder with ground truth (KITTI, EuRoC or plain layout)")
    a = ap.parse_args()
    s, d, fb = scale_ratios(a.sequence)
    print(f"fx*B {fb:.2f} px*m, {len(s)} matches")
    print("| disparity (px) | matches | median s | quartiles |")
    print("|---|---|---|---|")
    for lo, hi in BANDS:
        k = (d >= lo) & (d < hi)
        if k.sum() >= 10:
            q1, q2, q3 = np.percentile(s[k], [25, 50, 75])
            print(f"| {lo}-{hi} | {k.sum()} | {q2:.4f} | {q1:.4f}-{q3:.4f} |")


if __name__ == "__main__":
    main()
