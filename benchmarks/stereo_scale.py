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

The same matches give the **disparity consistency**: each point's disparity in frame i+1 against the
one predicted from frame i moved by the ground truth; the difference holds two measurements' errors,
so the per-measurement sigma is the difference's robust sd / sqrt(2) (also the sd of the differences
below 3 px, tails included, and the share beyond 1 px). ``--set`` changes the stereo matching (e.g.
``stereo.subpixel=centre_parabola``, ``stereo.sparse_search=row``): a bias of the sub-pixel refinement
would change the scale with it.

Usage::

    .venv/bin/python -m benchmarks.stereo_scale ../shared/data/kitti/odometry_06_head51 [--set KEY=VALUE ...]
    .venv/bin/python -m benchmarks.stereo_scale runs/highway0   # rgbdslam synth --motion highway
"""

from __future__ import annotations

import argparse

import numpy as np

from benchmarks.stereo import consecutive_stereo_matches

BANDS = ((4, 10), (10, 20), (20, 40), (40, 70), (70, 130), (40, 130), (20, 130))


def scale_ratios(path: str, sets: list[str] | tuple[str, ...] = ()) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Per-match scale ratios s_i, the matches' disparities (px) in the later frame, their differences
    to the disparities predicted from the earlier frame by the ground-truth motion (px), and fx * B."""
    *pairs, fb = consecutive_stereo_matches(path, list(sets))
    ratios = []
    for T, Pa, Pb, _, _ in pairs:
        v = Pb - Pa @ T[:3, :3].T
        ratios.append((v @ T[:3, 3]) / np.einsum("ij,ij->i", v, v))
    diff = np.concatenate([pb - fb / Q[:, 2] for _, _, _, pb, Q in pairs])
    return np.concatenate(ratios), np.concatenate([pb for _, _, _, pb, _ in pairs]), diff, fb


def consistency(diff: np.ndarray) -> dict:
    """Disparity consistency of consecutive frames (px): median difference, robust sd, per measurement
    (robust sd / sqrt 2), sd of the differences below 3 px (/ sqrt 2) and the share beyond 1 px."""
    med = float(np.median(diff))
    dev = np.abs(diff - med)
    robust = 1.4826 * float(np.median(dev))
    return {"n": int(len(diff)), "median_px": med, "robust_sd_px": robust, "per_measurement_px": robust / np.sqrt(2),
            "sd_below_3px_per_measurement_px": float(np.std(diff[dev < 3.0])) / np.sqrt(2),
            "share_beyond_1px": float(np.mean(dev > 1.0))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence", help="a stereo sequence folder with ground truth (KITTI, EuRoC or plain layout)")
    ap.add_argument("--set", action="append", default=[], dest="sets", metavar="KEY=VALUE",
                    help="config settings on top of the kitti preset (stereo matching)")
    a = ap.parse_args()
    s, d, diff, fb = scale_ratios(a.sequence, a.sets)
    c = consistency(diff)
    print(f"fx*B {fb:.2f} px*m, {len(s)} matches")
    print(f"disparity consistency: median {c['median_px']:+.3f} px, robust sd {c['robust_sd_px']:.3f} px, per measurement "
          f"{c['per_measurement_px']:.3f} px (sd below 3 px: {c['sd_below_3px_per_measurement_px']:.3f} px), "
          f"beyond 1 px {100 * c['share_beyond_1px']:.1f} %")
    print("| disparity (px) | matches | median s | quartiles |")
    print("|---|---|---|---|")
    for lo, hi in BANDS:
        k = (d >= lo) & (d < hi)
        if k.sum() >= 10:
            q1, q2, q3 = np.percentile(s[k], [25, 50, 75])
            print(f"| {lo}-{hi} | {k.sum()} | {q2:.4f} | {q1:.4f}-{q3:.4f} |")


if __name__ == "__main__":
    main()
