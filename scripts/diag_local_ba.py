"""Audit of the landmark map's bundle adjustment against exact ground truth (issue 17).

Usage::

    .venv/bin/python scripts/diag_local_ba.py [--motion xyz] [--seed 0] [--frames 150] [--work DIR]
        [--set KEY=VALUE ...]

Runs the SLAM chain (``landmarks.enabled=true landmarks.local_ba=true`` plus ``--set``) over a
synthetic sequence with Kinect-like noise and records, around every local BA:

* the window keyframes' pose error before and after the solve, (a) relative to the window's
  newest held (fixed) keyframe — the error the BA can remove, independent of the drift before
  the window — and (b) absolute, under one SE(3) alignment of the run's final keyframe poses
  (before the pose graph) to the ground truth;
* the optimised landmarks' position error before and after, under the same two alignments.

Landmark ground truth: the mean over the landmark's keyframe observations (>= 2) of the pixel
back-projected with the noise-free depth of the same frame (the generator rendered without
noise, same seed: same geometry) and the ground-truth pose (depth bilinearly interpolated;
pixels on a depth edge, the four neighbours differing by > 1 cm, left out). It keeps the key
points' own detection noise, averaged over the observations. Prints medians per solve and over the run; the final trajectory's ATE and RPE too.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def _gt_by_frame(seq) -> dict[int, np.ndarray]:
    gt = seq.groundtruth()
    out = {}
    for i in range(len(seq)):
        t = seq[i].timestamp
        out[i] = gt.poses[int(np.argmin(np.abs(gt.timestamps - t)))]
    return out


def _align(est: list[np.ndarray], gt: list[np.ndarray]) -> np.ndarray:
    """SE(3) (4x4) taking the estimated positions onto the ground truth's (Umeyama, no scale)."""
    from rgbdslam.evaluation.ate import umeyama_alignment

    R, t, _ = umeyama_alignment(np.array([P[:3, 3] for P in est]).T, np.array([P[:3, 3] for P in gt]).T, "se3")
    A = np.eye(4)
    A[:3, :3], A[:3, 3] = R, t
    return A


def _terr(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.linalg.norm(A[:3, 3] - B[:3, 3]))


def landmark_truth(clean_depth, gt: dict[int, np.ndarray], camera, kf_obs: dict) -> dict[int, np.ndarray]:
    """Ground-truth world point of every landmark (see the module doc): the mean over its keyframe
    observations of pixel + noise-free depth taken to the world with the true pose."""
    pts: dict[int, list] = {}
    for k, o in kf_obs.items():
        if not len(o.lm):
            continue
        D = clean_depth(k)
        uv = o.uv
        u0 = np.clip(np.floor(uv[:, 0]).astype(int), 0, D.shape[1] - 2)
        v0 = np.clip(np.floor(uv[:, 1]).astype(int), 0, D.shape[0] - 2)
        fu, fv = uv[:, 0] - u0, uv[:, 1] - v0
        q = np.stack([D[v0, u0], D[v0, u0 + 1], D[v0 + 1, u0], D[v0 + 1, u0 + 1]], 1)
        z = (q[:, 0] * (1 - fu) + q[:, 1] * fu) * (1 - fv) + (q[:, 2] * (1 - fu) + q[:, 3] * fu) * fv
        ok = (q.min(1) > 0) & (q.max(1) - q.min(1) < 0.01)  # bilinear, off depth edges
        x = (uv[:, 0] - camera.cx) / camera.fx * z
        y = (uv[:, 1] - camera.cy) / camera.fy * z
        P = np.stack([x, y, z], 1) @ gt[k][:3, :3].T + gt[k][:3, 3]
        for i, p in zip(o.lm[ok], P[ok]):
            pts.setdefault(int(i), []).append(p)
    return {i: np.mean(v, axis=0) for i, v in pts.items() if len(v) >= 2}


def replay(a) -> int:
    """Re-solve dumped BA problems with another configuration; keyframe errors relative to the
    newest held keyframe and landmark errors, before and after."""
    import pickle
    from types import SimpleNamespace

    from rgbdslam.config import load_config
    from rgbdslam.geometry.se3 import inv
    from rgbdslam.landmarks.local_ba import LocalBA

    d = pickle.loads(a.replay.read_bytes())
    gt, truth = d["gt"], d["truth"]
    cfg = load_config(None, ["landmarks.enabled=true", "landmarks.local_ba=true", *a.set]).landmarks
    ba = LocalBA(cfg, d["camera"])
    rb, ra, lb, la, better, axes = [], [], [], [], 0, []
    rng = np.random.default_rng(0)
    cam = d["camera"]
    for kfs, poses, pos, cov, alive in d["problems"]:
        lmap = SimpleNamespace(pos=pos.copy(), cov=cov, alive=alive, n=len(pos))
        if a.ideal_obs is not None:  # the measurements as the model assumes them (same geometry, same ids)
            sp, ds = a.ideal_obs
            ideal = []
            for k in kfs:
                keep = np.array([int(i) in truth for i in k.lm], bool)
                T = np.array([truth[int(i)] for i in k.lm[keep]]).reshape(-1, 3)
                Pc = (T - gt[k.index][:3, 3]) @ gt[k.index][:3, :3]
                z = Pc[:, 2]
                uv = np.stack([cam.fx * Pc[:, 0] / z + cam.cx, cam.fy * Pc[:, 1] / z + cam.cy], 1)
                uv += rng.normal(scale=sp, size=uv.shape)
                z = z + ds * (0.0012 + 0.0019 * (z - 0.4) ** 2) * rng.standard_normal(len(z))
                ideal.append(SimpleNamespace(index=k.index, lm=k.lm[keep], uv=uv, z=z))
            kfs = ideal
        poses = {k: P.copy() for k, P in poses.items()}
        if a.oracle_fixed:  # window keyframes keep their tracked poses, the rest go to the truth
            win = {k.index for k in kfs[-cfg.ba_window:]}
            held = [k for k in poses if k not in win]
            if not held:
                continue
            f0 = max(held)
            A = poses[f0] @ inv(gt[f0])
            for k in poses:
                if k not in win:
                    poses[k] = A @ gt[k]
        before = {k: P.copy() for k, P in poses.items()}
        out = ba.run(lmap, kfs, poses)
        if not out:
            continue
        f = max(ba.last_fixed) if ba.last_fixed else min(out)
        L = gt[f] @ inv(before[f])
        b = [_terr(L @ before[k], gt[k]) for k in out]
        c = [_terr(L @ out[k], gt[k]) for k in out]
        rb += b
        ra += c
        for k in out:  # the error's direction in the true camera frame
            axes.append(gt[k][:3, :3].T @ ((L @ out[k])[:3, 3] - gt[k][:3, 3]))
        better += sum(x < y for x, y in zip(c, b))
        ids = [int(i) for i in ba.last_landmarks if int(i) in truth]
        T = np.array([truth[i] for i in ids]).reshape(-1, 3)
        lb += list(np.linalg.norm(pos[ids] @ L[:3, :3].T + L[:3, 3] - T, axis=1))
        la += list(np.linalg.norm(lmap.pos[ids] @ L[:3, :3].T + L[:3, 3] - T, axis=1))
    med = lambda x: 1e3 * float(np.median(x)) if len(x) else float("nan")  # noqa: E731
    rms = lambda x: 1e3 * float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")  # noqa: E731
    print(f"replay {a.replay.name} {' '.join(a.set) or '(defaults)'}{' oracle-fixed' if a.oracle_fixed else ''}: "
          f"kf err rel (mm) median {med(rb):.2f} -> {med(ra):.2f}, rms {rms(rb):.2f} -> {rms(ra):.2f}, "
          f"better {better}/{len(rb)}; landmarks median {med(lb):.2f} -> {med(la):.2f}; after, rms per camera axis "
          f"x/y/z (mm) {' / '.join(f'{v:.2f}' for v in 1e3 * np.sqrt(np.mean(np.square(axes), axis=0)))}")
    return 0


def replay_final(a) -> int:
    """Re-solve a --dump-final global BA problem with --set; the trajectory as ``SLAM.finish``
    makes it (frames follow their keyframe), evaluated after the pose graph and after the BA."""
    import pickle
    from types import SimpleNamespace

    from rgbdslam.config import load_config
    from rgbdslam.evaluation.report import evaluate_trajectories
    from rgbdslam.geometry.se3 import inv
    from rgbdslam.io.trajectory import Trajectory
    from rgbdslam.landmarks.global_ba import global_bundle_adjustment

    d = pickle.loads(a.replay_final.read_bytes())
    cfg = load_config(None, ["landmarks.enabled=true", "landmarks.global_ba=true", *d["cfg_sets"], *a.set]).landmarks
    lmap = SimpleNamespace(pos=d["pos"].copy(), alive=d["alive"], n=len(d["pos"]))
    recs = d["records"]
    kf_pose = {i: P for i, _, P, k in recs if i == k}

    def traj(opt):
        return Trajectory(np.array([t for _, t, _, _ in recs]),
                          np.array([opt[k] @ inv(kf_pose[k]) @ P if k in opt else P for _, _, P, k in recs]))

    before = evaluate_trajectories(d["gt"], traj(d["poses"]))
    import time

    t0 = time.perf_counter()
    res = global_bundle_adjustment(cfg, d["camera"], lmap, d["keyframes"], d["poses"], d["loops"], d["odometry"])
    took = time.perf_counter() - t0
    after = evaluate_trajectories(d["gt"], traj({**d["poses"], **(res.poses if res else {})}))
    print(f"replay-final {a.replay_final.name} {' '.join(a.set) or '(defaults)'}: ATE {before.ate.rmse:.4f} -> "
          f"{after.ate.rmse:.4f}, RPE {before.rpe.trans.rmse:.4f} -> {after.rpe.trans.rmse:.4f}; "
          f"{len(res.poses) if res else 0} keyframes, {res.landmarks if res else 0} landmarks, "
          f"{res.observations if res else 0} observations, {res.between if res else 0} relative-pose factors, {took:.1f} s")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--motion", default="xyz")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--work", type=Path, default=Path("/tmp/diag_local_ba"))
    ap.add_argument("--set", action="append", default=[], help="config KEY=VALUE (repeatable)")
    ap.add_argument("--quiet", action="store_true", help="only the run's summary lines")
    ap.add_argument("--dump", type=Path, default=None, help="save every BA problem (inputs + truth) here")
    ap.add_argument("--sequence", type=Path, default=None,
                    help="a recorded sequence instead of the synthetic one (no landmark truth; for --dump-final)")
    ap.add_argument("--dump-final", type=Path, default=None,
                    help="save the global BA's problem (the run after the pose graph) here (needs landmarks.global_ba=true)")
    ap.add_argument("--replay-final", type=Path, default=None,
                    help="re-solve a --dump-final problem with --set; ATE / RPE after the pose graph and after it")
    ap.add_argument("--replay", type=Path, default=None,
                    help="re-solve the problems of a --dump offline with --set (no tracking feedback)")
    ap.add_argument("--oracle-fixed", action="store_true", help="replay: the held keyframes at their true poses")
    ap.add_argument("--ideal-obs", type=float, nargs=2, default=None, metavar=("SIGMA_PX", "DEPTH_SCALE"),
                    help="replay: every observation replaced by the true landmark projected with the true pose "
                         "+ Gaussian noise (SIGMA_PX pixels; depth noise the Kinect model times DEPTH_SCALE)")
    a = ap.parse_args(argv)
    if a.replay is not None:
        return replay(a)
    if a.replay_final is not None:
        return replay_final(a)

    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.datasets.synthetic import generate_sequence
    from rgbdslam.evaluation.report import evaluate_trajectories
    from rgbdslam.geometry.se3 import inv
    from rgbdslam.slam import SLAM

    noisy = a.work / f"{a.motion}_s{a.seed}_{a.frames}"
    clean = a.work / f"{a.motion}_s{a.seed}_{a.frames}_clean"
    if a.sequence is None:
        for d, n in ((noisy, True), (clean, False)):
            if not (d / "groundtruth.txt").exists():
                generate_sequence(d, frames=a.frames, motion=a.motion, noise=n, seed=a.seed)
    else:
        noisy = a.sequence
    cfg = load_config(None, ["landmarks.enabled=true", "landmarks.local_ba=true", *a.set])
    seq = open_sequence(noisy, cfg.dataset)
    cseq = open_sequence(clean, cfg.dataset) if a.sequence is None else None
    gt = _gt_by_frame(seq)
    cam = seq.camera
    slam = SLAM(cfg, cam)
    tr = slam.landmarks
    kf_obs: dict[int, object] = {}
    problems = []  # --dump: (keyframes, poses, landmark positions, covariances, alive) per solve
    solves = []  # (fixed, moved, poses before, poses after, landmark ids, pos before, pos after)
    ba = tr.ba
    if ba is not None:
        run0 = ba.run

        def run(lmap, keyframes, kf_pose):
            for k in keyframes:
                kf_obs.setdefault(k.index, k)
            before = {k: P.copy() for k, P in kf_pose.items()}
            pos0 = lmap.pos.copy()
            if a.dump is not None:
                problems.append((list(keyframes), before, pos0[:lmap.n].copy(), lmap.cov[:lmap.n].copy(),
                                 lmap.alive[:lmap.n].copy()))
            out = run0(lmap, keyframes, kf_pose)
            if out:
                ids = ba.last_landmarks
                solves.append((list(ba.last_fixed), dict(out), before, pos0[ids], lmap.pos[ids].copy(), ids))
            return out

        ba.run = run
    if a.dump_final is not None:  # the global BA's inputs, saved before it runs
        gba0 = tr.global_ba

        def gba(poses, loops=(), odometry=()):
            import pickle

            m = tr.map
            state = {"cfg_sets": a.set, "camera": cam, "keyframes": tr.all_keyframes, "poses": poses,
                     "loops": loops, "odometry": odometry, "pos": m.pos[:m.n].copy(), "alive": m.alive[:m.n].copy(),
                     "records": [(r.index, r.timestamp, r.pose.copy(), r.keyframe) for r in slam.state.records],
                     "gt": seq.groundtruth()}
            a.dump_final.write_bytes(pickle.dumps(state))
            return gba0(poses, loops, odometry)

        tr.global_ba = gba
    for i in range(len(seq)):
        slam.track(seq[i])
    for k in tr.keyframes:
        kf_obs.setdefault(k.index, k)
    kf_final = {r.index: r.pose.copy() for r in slam.state.records if r.index == r.keyframe}
    traj = slam.finish()
    rep = evaluate_trajectories(seq.groundtruth(), traj)

    ks = sorted(kf_final)
    G = _align([kf_final[k] for k in ks], [gt[k] for k in ks])  # one alignment, the run's keyframes
    truth = {} if cseq is None else landmark_truth(lambda k: cseq[k].depth, gt, cam, kf_obs)
    rel_b, rel_a, abs_b, abs_a, lrel_b, lrel_a, labs_b, labs_a = ([] for _ in range(8))
    better = 0
    for fixed, out, before, p0, p1, ids in solves:
        f = max(fixed) if fixed else min(out)
        L = gt[f] @ inv(before[f])  # local alignment: the newest held keyframe on its truth
        rb = [_terr(L @ before[k], gt[k]) for k in out]
        ra = [_terr(L @ out[k], gt[k]) for k in out]
        ab = [_terr(G @ before[k], gt[k]) for k in out]
        aa = [_terr(G @ out[k], gt[k]) for k in out]
        rel_b += rb
        rel_a += ra
        abs_b += ab
        abs_a += aa
        better += sum(x < y for x, y in zip(ra, rb))
        have = np.array([int(i) in truth for i in ids], bool)
        if have.any():
            T = np.array([truth[int(i)] for i in ids[have]])
            for A, store_b, store_a in ((L, lrel_b, lrel_a), (G, labs_b, labs_a)):
                store_b += list(np.linalg.norm(p0[have] @ A[:3, :3].T + A[:3, 3] - T, axis=1))
                store_a += list(np.linalg.norm(p1[have] @ A[:3, :3].T + A[:3, 3] - T, axis=1))
        if not a.quiet:
            print(f"BA fixed {fixed} moved {sorted(out)}: rel kf err {1e3 * np.median(rb):.2f} -> "
                  f"{1e3 * np.median(ra):.2f} mm, abs {1e3 * np.median(ab):.2f} -> {1e3 * np.median(aa):.2f} mm; "
                  f"{len(ids)} landmarks")
    if a.dump is not None:
        import pickle

        with open(a.dump, "wb") as fh:
            pickle.dump({"problems": problems, "gt": gt, "truth": truth, "G": G, "camera": cam}, fh)
    med = lambda x: 1e3 * float(np.median(x)) if len(x) else float("nan")  # noqa: E731
    rms = lambda x: 1e3 * float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")  # noqa: E731
    n = len(rel_b)
    print(f"{a.motion} s{a.seed} {' '.join(a.set) or '(defaults)'}: {len(solves)} solves, {n} keyframe updates, "
          f"better in {better}/{n}")
    print(f"  keyframe err rel. newest fixed (mm): median {med(rel_b):.2f} -> {med(rel_a):.2f}, "
          f"rms {rms(rel_b):.2f} -> {rms(rel_a):.2f}")
    print(f"  keyframe err abs (one SE3, mm):      median {med(abs_b):.2f} -> {med(abs_a):.2f}, "
          f"rms {rms(abs_b):.2f} -> {rms(abs_a):.2f}")
    print(f"  landmark err rel (mm):               median {med(lrel_b):.2f} -> {med(lrel_a):.2f} ({len(lrel_b)} obs)")
    print(f"  landmark err abs (mm):               median {med(labs_b):.2f} -> {med(labs_a):.2f}")
    print(f"  final ATE {rep.ate.rmse:.4f}  RPE(1f) {rep.rpe.trans.rmse:.4f}  keyframes {len(ks)}  "
          f"BA rejected {getattr(ba, 'rejected', 0)}")
    if tr.global_ba_stats:
        print(f"  global BA {tr.global_ba_stats}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
