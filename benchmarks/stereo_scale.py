"""Is a stereo rig's depth to scale with its ground truth? (docs/stereo.md, "The noise model")

For consecutive pairs (i, i+1) of a stereo sequence with ground truth, the sparse stereo points of the
left key points (the product's own ``detect`` + ``sparse_matches`` with the ``kitti`` preset) are
matched by descriptor (cross-checked; ``benchmarks.stereo.consecutive_stereo_matches``) and kept within 3 px of their ground-truth reprojection
(evaluation only: the ground truth measures here, it sets nothing). If every depth were off by one
factor 1/s, the points would obey ``s Pb = R (s Pa) + t`` with the ground-truth motion (R, t), so each
match gives ``s_i = (v_i . t) / (v_i . v_i)``, ``v_i = Pb_i - R Pa_i``. Medians per disparity band:
s < 1 means the stereo depths are too long (the disparities too small by the share 1 - s). Below
~20 px the ratio is dominated by the disparity noise (and biased low by it); the 20-130 px band is
the measurement.

Usage::

    .venv/bin/python -m benchmarks.stereo_scale ../shared/data/kitti/odometry_06_head51
    .venv/bin/python -m benchmarks.stereo_scale runs/highway0   # rgbdslam synth --motion highway
"""

from __future__ import annotations

import argparse

import numpy as np

from benchmarks.stereo import consecutive_stereo_matches

BANDS = ((4, 10), (10, 20), (20, 40), (40, 130), (20, 130))


def scale_ratios(path: str) -> tuple[np.ndarray, np.ndarray, float]:
    """Per-match scale ratios s_i, the matches' disparities (px) in the later frame, and fx * B."""
    *pairs, fb = consecutive_stereo_matches(path, [])
    ratios = []
    for T, Pa, Pb, _, _ in pairs:
        v = Pb - Pa @ T[:3, :3].T
        ratios.append((v @ T[:3, 3]) / np.einsum("ij,ij->i", v, v))
    return np.concatenate(ratios), np.concatenate([pb for _, _, _, pb, _ in pairs]), fb


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
