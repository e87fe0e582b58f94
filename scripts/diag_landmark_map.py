"""Where the landmark map loses accuracy on a sequence with exact ground truth (issue 17).

Usage::

    .venv/bin/python scripts/diag_landmark_map.py SEQ_DIR [SEQ_DIR ...] [--set KEY=VALUE ...]
        [--compare KEY=VALUE[,KEY=VALUE...]] [--block 15] [--json FILE]

Runs ``rgbdslam.slam.SLAM`` frame by frame (landmark map on unless a ``--set`` turns it off) and
records per frame:

* ``final``: the final trajectory's error (the ATE's SE(3) alignment over the whole run), ``odo``:
  the odometry's (the poses before the pose graph) with its first frame on the truth;
* the map step: descriptor matches, inliers, the share of inliers first seen ``>= old`` frames
  earlier, and the inliers' reprojection residual (px) under the **true** pose: a landmark that sits
  where the truth puts it projects onto its key point (~0.5 px of key point noise), one that
  drifted does not — per age class (old / young), so it says whether the map's landmarks or the
  registration are off;
* ``map`` / ``reg``: the map pose's and the registration's 1-frame error against the truth, taken
  from the previous frame's output (what each would add on its own).

* after the run: the odometry's ATE beside the final one, and every pose-graph edge (odometry, loop)
  against the truth: translation rms and the median Mahalanobis² under the edge's information
  (calibrated: 5.35), so it says whether the pose graph helps or hurts the map-tracked odometry.

``--compare`` runs the same sequence once more with those settings added and prints both side by
side per block of ``--block`` frames. The synthetic generator's sequences only (TUM layout with the
generator's ground truth, one pose per frame).
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
from rgbdslam.geometry.se3 import inv  # noqa: E402


def true_reprojection(G: np.ndarray, X: np.ndarray, uv: np.ndarray, camera) -> np.ndarray:
    """Pixel distance (N,) between landmarks ``X`` (N, 3) projected with the true camera-to-world
    pose ``G`` and their measured key points ``uv`` (N, 2)."""
    Tcw = inv(G)
    P = X @ Tcw[:3, :3].T + Tcw[:3, 3]
    z = np.maximum(P[:, 2], 1e-6)
    pr = np.stack([camera.fx * P[:, 0] / z + camera.cx, camera.fy * P[:, 1] / z + camera.cy], axis=1)
    return np.linalg.norm(pr - uv, axis=1)


def _trans_err(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.linalg.norm((inv(A) @ B)[:3, 3]))


def run(seq_dir: Path, sets: list[str], old_age: int) -> dict:
    from rgbdslam.datasets import open_sequence
    from rgbdslam.evaluation.ate import ate
    from rgbdslam.landmarks import stage
    from rgbdslam.slam import SLAM

    cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", "landmarks.enabled=true", *sets])
    seq = open_sequence(seq_dir, cfg)
    gt = seq.groundtruth()
    G = gt.poses
    cam = seq.camera
    trace: dict[int, dict] = {}
    orig_track, orig_fuse, orig_accept = stage.LandmarkTracker.track, stage.fuse_poses, stage.LandmarkTracker._accept
    cur = [0]

    def fuse(P1, H1, P2, H2):
        trace[cur[0]]["map"] = P2.copy()
        return orig_fuse(P1, H1, P2, H2)

    def accept(self, index, feats, res):
        t = trace[index]
        t.setdefault("map", res.pose.copy())
        age = index - self.map.first[res.lm]
        # the run's world is its first frame's camera (the first pose is the identity): the truth in it
        r = true_reprojection(inv(G[0]) @ G[index], self.map.pos[res.lm], feats.uv[res.feat], cam)
        Gi = inv(G[0]) @ G[index]
        t["abs_map"] = _trans_err(Gi, res.pose)
        t["abs_reg"] = _trans_err(Gi, t["reg"])
        m = self._last_matches
        if m is not None:  # the map pose from the old and from the young matches alone
            from rgbdslam.landmarks.tracking import MapMatch, estimate_pose

            c = self.cfg
            mold = index - self.map.first[m.lm] >= old_age
            for name, sel in (("old", mold), ("young", ~mold)):
                if sel.sum() >= c.min_inliers:
                    sub = MapMatch(m.feat[sel], m.lm[sel], m.n_candidates, m.cand_uv)
                    rr = estimate_pose(self.map, feats, sub, t["reg"], self._sigma(feats.pts[sub.feat, 2]),
                                       c.ransac_threshold, c.ransac_iterations, c.min_inliers, c.sampling,
                                       c.old_fraction, np.random.default_rng(0), c.refine, self.camera,
                                       c.sigma_px, c.chi_gate, c.landmark_cov == "full", c.adaptive_noise)
                    if rr is not None:
                        t["abs_map_" + name] = _trans_err(Gi, rr.pose)
        t.update(inliers=len(res.lm), matches=res.n_matches, old=int((age >= old_age).sum()),
                 rp_old=float(np.median(r[age >= old_age])) if (age >= old_age).any() else np.nan,
                 rp_young=float(np.median(r[age < old_age])) if (age < old_age).any() else np.nan,
                 rp_all=float(np.median(r)))
        return orig_accept(self, index, feats, res)

    def track(self, index, feats, pose, information=None):
        cur[0] = index
        trace[index] = {"reg": pose.copy()}
        out = orig_track(self, index, feats, pose, information)
        trace[index]["out"] = out.copy()
        return out

    stage.LandmarkTracker.track, stage.fuse_poses, stage.LandmarkTracker._accept = track, fuse, accept
    try:
        slam = SLAM(cfg, cam)
        for i in range(len(seq)):
            slam.track(seq[i])
        final = slam.finish()
    finally:
        stage.LandmarkTracker.track, stage.fuse_poses, stage.LandmarkTracker._accept = orig_track, orig_fuse, orig_accept
    a = ate(gt, final)
    odo = {r.index: r.pose for r in slam.state.records}
    n = len(seq)
    rows = []
    A0 = G[0] @ inv(odo[0])  # the odometry with its first frame on the truth
    for i in range(n):
        t = trace.get(i, {})
        if "out" in t:
            t["abs_out"] = _trans_err(inv(G[0]) @ G[i], t["out"])
        row = {"i": i, "final": float(a.errors[i]) if i < len(a.errors) else np.nan,
               "odo": _trans_err(G[i], A0 @ odo[i]) if i in odo else np.nan}
        if i > 0 and (i - 1) in odo and "map" in t:
            gt_rel = inv(G[i - 1]) @ G[i]
            row["map1"] = _trans_err(gt_rel, inv(odo[i - 1]) @ t["map"])
            row["reg1"] = _trans_err(gt_rel, inv(odo[i - 1]) @ t["reg"])
        for k in ("inliers", "matches", "old", "rp_old", "rp_young", "rp_all", "abs_map", "abs_reg", "abs_out",
                  "abs_map_old", "abs_map_young"):
            if k in t:
                row[k] = t[k]
        rows.append(row)
    out_edges = {}
    if slam.graph is not None:  # the pose graph's edges against the truth: error and Mahalanobis²
        import gtsam

        Gw = {i: inv(G[0]) @ G[i] for i in range(n)}
        for kind, edges in (("odometry", slam.graph.odometry),
                            ("loop", [(e.i, e.j, e.T_ij, e.information) for e in slam.graph.loops])):
            errs, chi = [], []
            for i, j, T, H in edges:
                E = inv(inv(Gw[i]) @ Gw[j]) @ T
                eta = gtsam.Pose3.Logmap(gtsam.Pose3(E))
                errs.append(float(np.linalg.norm(E[:3, 3])))
                chi.append(float(eta @ H @ eta))
            if errs:
                out_edges[kind] = {"n": len(errs), "t_mm_rms": 1e3 * float(np.sqrt(np.mean(np.square(errs)))),
                                   "chi2_median": float(np.median(chi)),
                                   "each": [(int(e[0]), int(e[1]), round(1e3 * t, 2), round(x, 1))
                                            for e, t, x in zip(edges, errs, chi)]}
    out = {"sequence": str(seq_dir), "sets": sets, "ate": a.rmse, "rows": rows, "edges": out_edges,
           "ate_odometry": ate(gt, slam.odometry()).rmse,
           "loops": [list(map(int, x)) for x in slam.state.loops],
           "keyframes": [r.index for r in slam.state.records if r.index == r.keyframe]}
    if slam.landmarks is not None:
        out["summary"] = slam.landmarks.summary()
    return out


def _block_table(runs: list[dict], block: int) -> str:
    n = len(runs[0]["rows"])
    head = ["frames"]
    for k, _ in enumerate(runs):
        head += [f"final{k}", f"odo{k}", f"inl{k}", f"old{k}", f"rp_old{k}", f"rp_yng{k}", f"map1_{k}", f"reg1_{k}"]
    lines = ["  ".join(f"{h:>8s}" for h in head)]
    nanmed = lambda v: float(np.nanmedian(v)) if np.isfinite(v).any() else np.nan  # noqa: E731
    for b0 in range(0, n, block):
        cells = [f"{b0}-{min(n, b0 + block) - 1}"]
        for r in runs:
            rs = r["rows"][b0:b0 + block]
            g = lambda k: np.array([x.get(k, np.nan) for x in rs], float)  # noqa: E731
            rms = lambda v: float(1e3 * np.sqrt(np.nanmean(v**2))) if np.isfinite(v).any() else np.nan  # noqa: E731
            cells += [f"{rms(g('final')):.2f}", f"{rms(g('odo')):.2f}", f"{nanmed(g('inliers')):.0f}",
                      f"{nanmed(g('old')):.0f}", f"{nanmed(g('rp_old')):.2f}", f"{nanmed(g('rp_young')):.2f}",
                      f"{rms(g('map1')):.2f}", f"{rms(g('reg1')):.2f}"]
        lines.append("  ".join(f"{c:>8s}" for c in cells))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("seqs", type=Path, nargs="+")
    ap.add_argument("--set", dest="sets", action="append", default=[])
    ap.add_argument("--compare", action="append", default=[],
                    help="another run with these settings added (KEY=VALUE[,KEY=VALUE...]); repeatable")
    ap.add_argument("--old-age", type=int, default=50, help="frames: an inlier first seen this long ago is 'old'")
    ap.add_argument("--block", type=int, default=15)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    out = []
    for d in a.seqs:
        runs = [run(d, a.sets, a.old_age)] + [run(d, a.sets + c.split(","), a.old_age) for c in a.compare]
        print(f"== {d.name}: " + "; ".join(
            f"[{k}] {' '.join(r['sets']) or 'landmarks'}: ATE {r['ate']:.4f}, loops {len(r['loops'])}, "
            f"keyframes {len(r['keyframes'])}" for k, r in enumerate(runs)))
        print("   (mm: final / odo = error per frame, rms over the block; map1 / reg1 = 1-frame error of the map pose "
              "/ registration; px: median reprojection of the inliers under the true pose)")
        for k, r in enumerate(runs):
            sm = r.get("summary") or {}
            print(f"   [{k}] ATE odometry {r['ate_odometry']:.4f}, edges vs truth: " + ", ".join(
                f"{kind} {e['n']} rms {e['t_mm_rms']:.2f} mm chi2 med {e['chi2_median']:.1f}" for kind, e in r["edges"].items()))
            print(f"   [{k}] map poses {sm.get('map_poses')}, old share {sm.get('old_share')}, stale left out "
                  f"{sm.get('stale_left_out')}, stale joined {sm.get('stale_joined')}, consistency {sm.get('consistency_median')}")
        print(_block_table(runs, a.block), flush=True)
        out.append(runs)
    if a.json is not None:
        a.json.write_text(json.dumps(out, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
