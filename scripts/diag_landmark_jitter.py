"""Where the per-frame jitter of landmark tracking comes from (issue 17): every stage's 1-frame error.

Usage::

    .venv/bin/python scripts/diag_landmark_jitter.py SEQ_DIR [SEQ_DIR ...] [--set KEY=VALUE ...]
        [--frames N] [--json FILE]

Runs ``rgbdslam.slam.SLAM`` frame by frame over each sequence (with exact ground truth: the
synthetic generator's) and records, for every frame i that the landmark map tracked, the poses of
the stages of ``LandmarkTracker.track``: the frame-to-frame registration's (``reg``), the map
pose before fusing (``map``), the pose the tracker returns (``out``, fused or replaced), and the
final trajectory after the pose graph (``final``). Each stage's error is its 1-frame relative error
against the truth, taken from the previous frame's *output* pose (what the stage started from):
E_X(i) = (gt_{i-1}⁻¹ gt_i)⁻¹ · (out_{i-1}⁻¹ X_i). Reported: RMS translation (mm) and rotation (deg)
of each stage over the frames where the map placed the frame; ``map_chain``: consecutive map poses
against each other (the map pose's own jitter); ``odo``/``final``: the odometry's and the final
trajectory's 1-frame RPE over all frames; ``chi2med``: median Mahalanobis² of the registration's
and the map pose's 1-frame error under the information the fusion gives them (a calibrated 6-dof
information: 5.35); ``sigma_t``: the translation sigma (mm) that information predicts; ``abs``:
RMS absolute error with the first frame aligned (drift included); ATE of the final trajectory.
``--set`` takes config overrides as ``rgbdslam run --set``; the landmark map is on
(``landmarks.enabled=true``) unless a ``--set landmarks.enabled=false`` says otherwise. Real
sequences (TUM) work too: their ground truth is interpolated to the frame time stamps (its own
accuracy, ~1 mm and a few ms of sync, limits the per-stage numbers there).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from rgbdslam.config import load_config  # noqa: E402
from rgbdslam.geometry.se3 import inv, rotation_angle  # noqa: E402


def rel_error(gt0: np.ndarray, gt1: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of (gt0⁻¹ gt1)⁻¹ (p0⁻¹ p1)."""
    E = inv(inv(gt0) @ gt1) @ (inv(p0) @ p1)
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(rotation_angle(E[:3, :3])))


def interpolate_poses(gt, stamps: np.ndarray) -> np.ndarray:
    """Ground-truth poses at ``stamps``: translation linear, rotation slerp between the two
    neighbouring samples (exact for the synthetic generator, which writes one pose per frame)."""
    from scipy.spatial.transform import Rotation, Slerp

    t = np.clip(stamps, gt.timestamps[0], gt.timestamps[-1])
    out = np.tile(np.eye(4), (len(t), 1, 1))
    out[:, :3, :3] = Slerp(gt.timestamps, Rotation.from_matrix(gt.poses[:, :3, :3]))(t).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(t, gt.timestamps, gt.poses[:, k, 3])
    return out


def run(seq_dir: Path, sets: list[str], frames: int | None) -> dict:
    from rgbdslam.datasets import open_sequence
    from rgbdslam.landmarks import stage
    from rgbdslam.slam import SLAM

    cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", "landmarks.enabled=true", *sets])
    seq = open_sequence(seq_dir, cfg)
    gt = seq.groundtruth()
    trace: dict[int, dict] = {}
    orig_track, orig_fuse = stage.LandmarkTracker.track, stage.fuse_poses

    def fuse(P1, H1, P2, H2):
        trace[cur[0]].update(map=P2.copy(), H_reg=H1.copy(), H_map=H2.copy())
        return orig_fuse(P1, H1, P2, H2)

    def track(self, index, feats, pose, information=None):
        cur[0] = index
        trace[index] = {"reg": pose.copy()}
        out = orig_track(self, index, feats, pose, information)
        trace[index]["out"] = out.copy()
        if "map" not in trace[index] and out is not pose:
            trace[index]["map"] = out.copy()  # replace mode
        return out

    cur = [0]
    stage.LandmarkTracker.track, stage.fuse_poses = track, fuse
    try:
        slam = SLAM(cfg, seq.camera)
        n = len(seq) if frames is None else min(frames, len(seq))
        for i in range(n):
            slam.track(seq[i])
        final = slam.finish()
    finally:
        stage.LandmarkTracker.track, stage.fuse_poses = orig_track, orig_fuse
    G = interpolate_poses(gt, final.timestamps)
    odo = {r.index: r.pose for r in slam.state.records}
    idx = [r.index for r in slam.state.records]
    pos = {k: j for j, k in enumerate(idx)}
    errs = {k: [] for k in ("reg", "map", "out", "map_chain", "odo", "final_map", "final")}
    absd = {k: [] for k in ("reg", "map", "out")}  # absolute error, the first frame aligned
    # Mahalanobis² of each stage's 1-frame error under its information; the sigma it predicts
    chi2, sig_t = {"reg": [], "map": []}, {"reg": [], "map": []}
    for j in range(1, len(idx)):
        i, p = idx[j], idx[j - 1]
        e = rel_error(G[j - 1], G[j], final.poses[j - 1], final.poses[j])
        errs["final"].append(e)
        errs["odo"].append(rel_error(G[j - 1], G[j], odo[p], odo[i]))
        t = trace.get(i)
        if t is None or "map" not in t:
            continue
        for k in ("reg", "map", "out"):
            errs[k].append(rel_error(G[j - 1], G[j], odo[p], t[k]))
        errs["final_map"].append(e)
        tp = trace.get(p)
        if tp is not None and "map" in tp:
            errs["map_chain"].append(rel_error(G[j - 1], G[j], tp["map"], t["map"]))
        if "H_reg" in t:
            import gtsam

            for k in ("reg", "map"):
                E = inv(inv(G[j - 1]) @ G[j]) @ (inv(odo[p]) @ t[k])
                eta = gtsam.Pose3.Logmap(gtsam.Pose3(E))
                chi2[k].append(float(eta @ t["H_" + k] @ eta))
                sig_t[k].append(1e3 * np.sqrt(np.trace(np.linalg.inv(t["H_" + k])[3:, 3:])))
        for k in absd:
            absd[k].append(rel_error(G[0], G[j], odo[idx[0]], t[k]))
    from rgbdslam.evaluation.ate import ate

    out = {"sequence": str(seq_dir), "frames": len(idx), "map_frames": len(errs["map"]), "ate": ate(gt, final).rmse}
    for k, v in errs.items():
        a = np.array(v) if v else np.zeros((0, 2))
        out[k] = {"t_mm": float(1e3 * np.sqrt(np.mean(a[:, 0] ** 2))) if len(a) else float("nan"),
                  "r_deg": float(np.sqrt(np.mean(a[:, 1] ** 2))) if len(a) else float("nan"),
                  "t_med_mm": float(1e3 * np.median(a[:, 0])) if len(a) else float("nan")}
    for k, v in absd.items():
        a = np.array(v) if v else np.zeros((0, 2))
        out["abs_" + k] = {"t_mm": float(1e3 * np.sqrt(np.mean(a[:, 0] ** 2))) if len(a) else float("nan"),
                           "r_deg": float(np.sqrt(np.mean(a[:, 1] ** 2))) if len(a) else float("nan")}
    for k, v in chi2.items():
        out["chi2_" + k] = float(np.median(v)) if v else float("nan")
        out["sigma_t_mm_" + k] = float(np.median(sig_t[k])) if v else float("nan")
    if slam.landmarks is not None:
        out["summary"] = slam.landmarks.summary()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("seqs", type=Path, nargs="+")
    ap.add_argument("--set", dest="sets", action="append", default=[])
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    rows = []
    for d in a.seqs:
        r = run(d, a.sets, a.frames)
        rows.append(r)
        line = "  ".join(f"{k} {r[k]['t_mm']:.2f}mm/{r[k]['r_deg']:.3f}°" for k in
                         ("reg", "map", "out", "map_chain", "odo", "final"))
        line += (f"  chi2med reg {r['chi2_reg']:.1f} map {r['chi2_map']:.1f}  sigma_t reg {r['sigma_t_mm_reg']:.2f}"
                 f" map {r['sigma_t_mm_map']:.2f}")
        line += "  abs " + " ".join(f"{k} {r['abs_' + k]['t_mm']:.2f}" for k in ("reg", "map", "out"))
        print(f"{d.name:20s} ATE {r['ate']:.4f} map {r['map_frames']}/{r['frames']}  {line}", flush=True)
    if a.json is not None:
        a.json.write_text(json.dumps({"sets": a.sets, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
