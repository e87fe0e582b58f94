"""Is a stereo rig's depth to scale with its ground truth? (docs/stereo_measured.md, "The noise model")

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

``--gaps 1,3,5`` also fits the disparity error model ``d = (1 + k) d_true + delta`` to frame pairs (i, i+g)
(:func:`disparity_error_fit`): an offset ``delta`` (px; a calibration or sub-pixel bias: relative depth error
``delta / d``, largest for far points) against a scale ``k`` (of ``fx B`` or of the ground truth: the same
relative error at every depth). Longer gaps give far points more parallax and dilute the ground truth's
per-frame error.

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


def disparity_error_fit(pairs: list[tuple], fb: float) -> dict:
    """Fit ``d = (1 + k) d_true + delta`` on ``pairs`` (``benchmarks.stereo.consecutive_stereo_matches``: T, Pa,
    Pb, ...): each frame-i point keeps its bearing, its depth is ``fx B / d_true`` with ``d = fx B / Pa_z``, and
    moved by the ground-truth T it must fall on its match's bearing in the later frame (residual in normalised
    image coordinates, soft-L1 at twice the residuals' robust sd at delta = k = 0). Returns {"n", "offset_scale":
    (delta px, k, se delta, se k), "offset": (delta, se), "scale": (k, se)} and each fit's robust cost
    ("offset_scale_cost", ...: lower fits better; the offset and the scale alone have one parameter each)."""
    from scipy.optimize import least_squares

    T = np.concatenate([np.repeat(p[0][None], len(p[1]), 0) for p in pairs])
    Pa = np.concatenate([p[1] for p in pairs])
    Pb = np.concatenate([p[2] for p in pairs])
    xa, d = Pa[:, :2] / Pa[:, 2:], fb / Pa[:, 2]
    xb = Pb[:, :2] / Pb[:, 2:]

    def residuals(delta: float, k: float) -> np.ndarray:
        z = fb / np.maximum((d - delta) / (1.0 + k), 1e-3)
        Q = np.einsum("nij,nj->ni", T[:, :3, :3], np.column_stack([xa * z[:, None], z])) + T[:, :3, 3]
        return (Q[:, :2] / Q[:, 2:] - xb).ravel()

    r0 = residuals(0.0, 0.0)
    f_scale = 2.0 * 1.4826 * float(np.median(np.abs(r0 - np.median(r0)))) + 1e-12
    out = {"n": len(d)}
    for name, fun, n in (("offset_scale", lambda q: residuals(q[0], q[1]), 2), ("offset", lambda q: residuals(q[0], 0.0), 1),
                         ("scale", lambda q: residuals(0.0, q[0]), 1)):
        sol = least_squares(fun, np.zeros(n), loss="soft_l1", f_scale=f_scale, x_scale=np.full(n, 0.01))
        s2 = (1.4826 * np.median(np.abs(sol.fun))) ** 2
        se = np.sqrt(np.diag(np.linalg.pinv(sol.jac.T @ sol.jac)) * s2)
        out[name] = tuple(float(v) for v in sol.x) + tuple(float(v) for v in se)
        out[name + "_cost"] = float(sol.cost / f_scale ** 2)  # in units of the soft-L1 scale squared
    return out


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
    ap.add_argument("--gaps", default="", help="also fit the disparity offset and scale on frame pairs (i, i+g), e.g. 1,3,5")
    a = ap.parse_args()
    for g in (int(x) for x in a.gaps.split(",") if x):
        *pairs, fb = consecutive_stereo_matches(a.sequence, a.sets, gap=g)
        f = disparity_error_fit(pairs, fb)
        (od, ok, sd, sk), (oo, so), (ss, sss) = f["offset_scale"], f["offset"], f["scale"]
        print(f"gap {g}: {f['n']} matches; offset and scale: delta {od:+.3f} +- {sd:.3f} px, k {100 * ok:+.2f} +- "
              f"{100 * sk:.2f} %; offset only: {oo:+.3f} +- {so:.3f} px; scale only: k {100 * ss:+.2f} +- {100 * sss:.2f} %; "
              f"costs {f['offset_scale_cost']:.1f} / {f['offset_cost']:.1f} / {f['scale_cost']:.1f}")
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
