"""Stereo input: accuracy and speed of the two depth methods, on real KITTI and on synthetic
stereo with exact ground truth.

Usage::

    python -m benchmarks.stereo [--seeds 0,1,2] [--frames 150] [--motions loop,circle]
        [--work DIR] [--json FILE] [--parts depth,disparity,kitti,synthetic,oracle,orb,speed] [--repeats 3]
        [--methods sparse,...] [--set KEY=VALUE ...] [--tag NAME] [--reuse-rgbd] [--oracle-modes ...]
        [--orb-rounds 2] [--highway-seeds 0,1,2,3,4]

1. Depth accuracy: synthetic stereo pairs (0.12 m baseline, 640x480, image noise) against the
   exact rendered depth: disparity error (median = bias, 1.4826 * MAD = sigma, share > 1 px) and
   the share of pixels / key points that get depth, for ``sparse`` and ``sgbm``.
2. KITTI 06 frames 0-50 (../shared/data/kitti/odometry_06_head51), config ``kitti``, with each
   depth method: ATE RMSE, KITTI's relative metric (short segments: 5-50 m, the path is 60 m),
   end-point drift, frames/s of the whole run (mapping off).
3. Synthetic loop-type sequences (``--motions``, ``--seeds``): the same trajectory rendered as
   RGB-D (``rgbdslam synth``) and as stereo (``--stereo 0.12``, KITTI layout), both run with the
   default config: ATE of each and the ratio stereo / RGB-D (target <= 1.5), for each stereo
   variant of ``--methods`` (sparse with the ORB or the row search, SGBM).
   ``--set`` adds config settings to every stereo run (``--tag`` keeps their run folders apart).
   Parts 1-5 are run by default; ``disparity`` and ``oracle`` only when asked for:
   * ``disparity``: per-point sparse disparity error against the exact rendered depth for each
     ``stereo.subpixel`` method (bias, spread, mean error by the true sub-pixel fraction, by depth, by
     image column), and on KITTI the consistency of consecutive frames' disparities moved by the
     ground-truth poses (no true disparity there).
   * ``oracle``: the synthetic stereo runs again with the depth at the stereo key points replaced by
     the exact depth, the exact depth + Kinect noise, or the exact disparity + Gaussian noise, with
     and without ``registration.stereo_reprojection``: what the depth errors cost, and what the rest does.
4. ``orb``: ORB-SLAM3 stereo (../shared/peers/orbslam3/run_orb_stereo.py, its own venv) and rgbdslam's
   ``kitti`` preset on the same pairs in the same run, interleaved for ``--orb-rounds`` rounds: KITTI 06 0-50
   and the synthetic highway (``rgbdslam synth --stereo 0.54 --motion highway --size 1241 376 -n 51 --noise``,
   ``--highway-seeds``; ORB-SLAM3 gets the KITTI 04-12 settings with the folder's calib.txt). ATE, lost frames,
   ATE / distance driven, and the ratios: ATE rgbdslam / ORB-SLAM3 (median of its rounds; < 1 better) and CPU
   time per pair ORB-SLAM3 / rgbdslam (> 1: rgbdslam cheaper). CPU time is of the whole process, every
   thread; ORB-SLAM3's start-up (vocabulary) is taken out by a run on the first two pairs. Skipped with a
   message when the peer is not installed.
5. Speed: the whole pipeline on KITTI-sized pairs (1226x370) with each depth method, next to the
   RGB-D pipeline on TUM fr1/rpy (640x480) in the same process, so that a ratio survives a
   shared machine: frames/s are quoted with the fr1/rpy frames/s measured in the same run.
   The ``speed`` part interleaves KITTI (sparse) with one and two reader threads and fr1/rpy for
   ``--repeats`` rounds (frames/s, frames/s without waiting for images, CPU ms per frame of the
   whole process) and times each step of preparing a pair in one thread.

Prints a Markdown report (and writes JSON with ``--json``). All runs are seeded.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import DATA, sequence_view

KITTI = DATA / "kitti" / "odometry_06_head51"
RPY = DATA / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
# stereo depth variants of the synthetic comparison
METHODS = {"sparse": ["stereo.depth=sparse"], "row": ["stereo.depth=sparse", "stereo.sparse_search=row"],
           "sgbm": ["stereo.depth=sgbm"],
           # the sub-pixel refinement before (patch minus its centre pixel, parabola), for comparison
           "sparse_parabola": ["stereo.depth=sparse", "stereo.subpixel=centre_parabola"]}


def depth_accuracy(work: Path, seed: int = 0, frames: int = 30) -> dict:
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.datasets.synthetic import Rays, Scene, make_trajectory
    from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence

    seq_dir = work / f"depthacc_s{seed}"
    if not (seq_dir / "synthetic.yaml").exists():
        generate_stereo_sequence(seq_dir, 0.12, "kitti", frames=frames, motion="loop", noise=True, seed=seed)
    out = {}
    for method, sets in METHODS.items():  # sparse (ORB search), row (sparse, row search), sgbm
        cfg = load_config(None, sets)
        seq = open_sequence(seq_dir, cfg)
        world = make_trajectory("loop", frames)  # KITTI layout poses start at the identity: render from the world's
        scene, rays = Scene(seed), Rays(seq.camera)
        fb = seq.camera.fx * seq.rig.baseline
        errs, cover, t = [], [], []
        for i in range(0, len(seq), max(1, len(seq) // 6)):
            t0 = time.perf_counter()
            f = seq.load(i)
            t.append(time.perf_counter() - t0)
            true = scene.render(rays, world[i])[1]
            ok = (f.depth > 0) & (true > 0)
            errs.append(fb / f.depth[ok] - fb / true[ok])
            cover.append(int(np.count_nonzero(f.depth > 0)))
        e = np.concatenate(errs)
        med = float(np.median(e))
        out[method] = {"bias_px": med, "sigma_px": float(1.4826 * np.median(np.abs(e - med))),
                       "gross_share": float(np.mean(np.abs(e) > 1.0)), "depth_pixels_median": float(np.median(cover)),
                       "load_ms_median": 1e3 * float(np.median(t))}
    return out


SUBPIXEL = ("centre_parabola", "zsad_v")


def _error_stats(e: np.ndarray) -> dict:
    """Disparity errors (px): bias = mean of |e| < 1 px, median, robust sigma, sd of |e| < 1, share > 1 px."""
    core = np.abs(e) < 1.0
    med = float(np.median(e))
    return {"n": int(len(e)), "bias_px": float(np.mean(e[core])), "median_px": med,
            "sigma_robust_px": float(1.4826 * np.median(np.abs(e - med))), "sd_core_px": float(np.std(e[core])),
            "gross_share": float(np.mean(~core))}


def disparity_errors(motions: list[str], seeds: list[int], frames: int = 150, step: int = 10) -> dict:
    """Per-point sparse disparity error against the renderer's exact depth (``disparity`` part).

    Every ``step``-th pair of the synthetic sequence (0.12 m baseline, image noise) is rendered in memory,
    the product's ``sparse_matches`` gives disparities at the left key points and the truth is
    ``fx B / z`` of the rendered depth at the same integer pixel (the right image is an exact render of the
    shifted camera, so this is exact). For each ``stereo.subpixel`` method: overall statistics, the mean
    error by the true disparity's sub-pixel fraction (pixel locking shows as a sine-like pattern), by depth
    and by image column third."""
    from rgbdslam.config import load_config
    from rgbdslam.datasets.synthetic import Rays, Scene, make_trajectory, scaled_camera
    from rgbdslam.datasets.synthetic_stereo import render_pairs
    from rgbdslam.frontend.features import detect
    from rgbdslam.geometry.stereo import StereoRig
    from rgbdslam.stereo.depth import sparse_matches

    cam = scaled_camera("ros_default", 640, 480)
    rig = StereoRig(cam, 0.12)
    fb = cam.fx * rig.baseline
    out = {}
    for motion in motions:
        for seed in seeds:
            poses = make_trajectory(motion, max(2, frames // step))  # the same path, every step-th frame's spacing
            scene, rays = Scene(seed), Rays(cam)
            rows: dict[str, list] = {m: [] for m in SUBPIXEL}
            pairs = render_pairs(cam, poses, rig.baseline, True, seed, False, {"motion": motion}, [])
            for k, left, right in pairs:
                z_true = scene.render(rays, poses[k])[1]
                for method in SUBPIXEL:
                    cfg = load_config(None, [f"stereo.subpixel={method}"])
                    det = detect(left, cfg.features)
                    m = sparse_matches(left, right, rig, det.uv_raw, det.desc, cfg.stereo, cfg.features)
                    u, v = m.uv[:, 0].astype(int), m.uv[:, 1].astype(int)
                    z = z_true[v, u]
                    rows[method].append(np.stack([m.disparity - fb / z, fb / z, z, u], axis=1))
            res = {}
            for method, r in rows.items():
                a = np.concatenate(r)
                e, frac, z, u = a[:, 0], a[:, 1] % 1.0, a[:, 2], a[:, 3]
                core = np.abs(e) < 1.0
                d = _error_stats(e)
                d["by_fraction"] = [float(np.mean(e[core & (frac >= f) & (frac < f + 0.1)])) for f in np.arange(0, 1, 0.1)]
                d["by_depth"] = {f"{lo}-{hi} m": _error_stats(e[(z >= lo) & (z < hi)])
                                 for lo, hi in ((0.0, 2.0), (2.0, 2.5), (2.5, 3.0), (3.0, 3.5), (3.5, 9.0))
                                 if np.count_nonzero((z >= lo) & (z < hi)) >= 30}
                third = np.minimum((3 * u / cam.width).astype(int), 2)
                d["by_column_third"] = [_error_stats(e[third == t]) for t in range(3)]
                res[method] = d
            out[f"{motion} seed {seed}"] = res
            print("disparity", motion, seed, json.dumps({m: {k: v for k, v in d.items() if not k.startswith("by_")}
                                                         for m, d in res.items()}), flush=True)
    return out


def consecutive_stereo_matches(path, sets: list[str], gap: int = 1) -> list[tuple]:
    """For each pair (i, i+gap) (consecutive: gap 1) of the stereo sequence at ``path`` (with ground truth; ``kitti``
    preset plus ``sets``): the sparse stereo points of the left key points (``detect`` + ``sparse_matches``)
    matched by descriptor (cross-checked) and kept within 3 px of their ground-truth reprojection.
    Returns (T = ground-truth motion from i to i+gap, Pa (K,3) frame i points, Pb (K,3) frame i+gap points,
    pb (K,) frame i+gap disparities, Q (K,3) = T Pa) per pair, and fx * B as the last element."""
    import cv2

    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.frontend.features import detect
    from rgbdslam.geometry.se3 import inv
    from rgbdslam.stereo.depth import sparse_matches

    cfg = load_config("kitti", sets)
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
    out = []
    for i in range(len(per) - gap):
        (_, da, _, Pa), (ub, db, pb, Pb) = per[i], per[i + gap]
        ms = bf.match(da, db)
        ia = np.array([x.queryIdx for x in ms], int)
        ib = np.array([x.trainIdx for x in ms], int)
        T = inv(G[i + gap]) @ G[i]
        Q = Pa[ia] @ T[:3, :3].T + T[:3, 3]
        proj = np.stack([cam.fx * Q[:, 0] / Q[:, 2] + cam.cx, cam.fy * Q[:, 1] / Q[:, 2] + cam.cy], axis=1)
        ok = (Q[:, 2] > 0) & np.all(np.abs(proj - ub[ib]) < 3.0, axis=1)
        out.append((T, Pa[ia][ok], Pb[ib][ok], pb[ib][ok], Q[ok]))
    return out + [cam.fx * seq.rig.baseline]


def kitti_disparity_consistency() -> dict:
    """KITTI 06 0-50 (no true disparity): each key point's disparity in frame i+1 against the one predicted
    from its partner in frame i (descriptor match, cross-checked, within 3 px of the ground-truth
    reprojection) moved by the ground-truth relative pose. The difference holds the error of both
    measurements (and of the ground truth): per-measurement sigma ~ robust sd / sqrt(2)."""
    out = {}
    for method in SUBPIXEL:
        *pairs, fb = consecutive_stereo_matches(KITTI, [f"stereo.subpixel={method}"])
        a = np.concatenate([np.stack([pb - fb / Q[:, 2], pb], axis=1) for _, _, _, pb, Q in pairs])
        d = _error_stats(a[:, 0])
        d["sigma_per_measurement_px"] = d["sigma_robust_px"] / np.sqrt(2.0)
        d["by_disparity"] = {f"{lo}-{hi} px": _error_stats(a[(a[:, 1] >= lo) & (a[:, 1] < hi), 0])
                             for lo, hi in ((4, 10), (10, 20), (20, 40), (40, 130))}
        out[method] = d
        print("kitti disparity consistency", method, json.dumps({k: v for k, v in d.items() if k != "by_disparity"}),
              flush=True)
    return out


def with_oracle_depth(seq, motion: str, seed: int, mode: str):
    """``seq`` (a synthetic stereo sequence, sparse depth) with the depth at its key points replaced, to
    separate what the depth's errors cost from what the rest of the stereo pipeline costs (``oracle``
    part): ``exact`` = the renderer's depth; ``kinect`` = exact + the RGB-D rendering's Kinect noise;
    ``dispS`` = exact disparity + Gaussian noise of S px (independent per point and frame); ``stereo`` =
    unchanged. The same key points get depth in every mode."""
    from rgbdslam.datasets.synthetic import Rays, Scene, kinect_noise, make_trajectory

    if mode == "stereo":
        return seq
    world = make_trajectory(motion, len(seq))  # KITTI layout poses start at the identity: render from the world's
    scene, rays = Scene(seed), Rays(seq.camera)
    fb = seq.camera.fx * seq.rig.baseline
    def oracle_load(seq, i: int):
        f = seq.load(i)
        true = scene.render(rays, world[i])[1]
        rng = np.random.default_rng([seed, i, 777])
        has = f.depth > 0
        if mode == "exact":
            z = true[has]
        elif mode == "kinect":
            z = kinect_noise(true, rng)[has]
        elif mode.startswith("disp"):
            d = fb / true[has] + float(mode[4:]) * rng.standard_normal(int(has.sum()))
            z = np.where(d > 0, fb / np.maximum(d, 1e-9), 0.0)
        else:
            raise ValueError(f"unknown oracle mode {mode!r}")
        depth = np.zeros_like(f.depth)
        depth[has] = z
        f.depth = depth
        return f

    return sequence_view(seq, oracle_load)


def run(seq, cfg_name: str | None, sets: list[str], out: Path) -> dict:
    from rgbdslam.config import load_config
    from rgbdslam.pipeline import run_sequence

    cfg = load_config(cfg_name, ["mapping.enabled=false", "output.plots=false", *sets])
    cpu, main = time.process_time(), time.thread_time()
    s = run_sequence(seq, out, cfg, progress=False)
    cpu = time.process_time() - cpu  # every thread of the process, evaluation included
    main = time.thread_time() - main  # this thread: tracking, pose graph, evaluation
    ev = s.get("evaluation") or {}
    k = ev.get("kitti") or {}
    return {"ate": (ev.get("ate") or {}).get("rmse"), "fps": s["fps"], "processing_fps": s["processing_fps"],
            "cpu_ms_per_frame": 1e3 * cpu / max(1, s["frames"]), "load_time_s": s["load_time_s"],
            "main_thread_cpu_ms_per_frame": 1e3 * main / max(1, s["frames"]),
            "frames": s["frames"], "lost": s["lost"], "t_err_pct": k.get("t_err_pct"),
            "r_err_deg_per_m": k.get("r_err_deg_per_m"), "end_drift_pct": k.get("end_drift_pct"),
            "kitti_note": k.get("note")}


def reader_breakdown(frames: int = 51) -> dict:
    """CPU time (thread_time, medians over the pairs) of each step of preparing a KITTI pair with
    sparse depth, in this thread, by the product's own functions: reading both PNGs
    (``rectified_pair``), left ORB (``detect``, the front end's key points), and the stereo matching
    (``sparse_matches``: right ORB + row matching, or the row search, then refinement and
    triangulation) with each ``stereo.sparse_search``."""
    import cv2

    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.frontend.features import detect
    from rgbdslam.stereo.depth import sparse_matches

    cfg = load_config("kitti", [])
    seq = open_sequence(KITTI, cfg)
    fc = cfg.features
    searches = {k: load_config("kitti", [f"stereo.sparse_search={k}"]).stereo for k in ("orb", "row")}
    # the sub-pixel refinement before (centre pixel subtracted, parabola), for the ratio in one run
    searches["orb_centre_parabola"] = load_config("kitti", ["stereo.subpixel=centre_parabola"]).stereo
    steps: dict[str, list[float]] = {k: [] for k in ("read", "left_orb", *(f"stereo_{s}" for s in searches))}
    for i in range(min(frames, len(seq))):
        t = time.thread_time()
        left, right = seq.rectified_pair(i)
        t1 = time.thread_time()
        det = detect(left, fc)
        steps["read"].append(t1 - t)
        steps["left_orb"].append(time.thread_time() - t1)
        for k, sc in searches.items():
            t2 = time.thread_time()
            sparse_matches(left, right, seq.rig, det.uv_raw, det.desc, sc, fc)
            steps[f"stereo_{k}"].append(time.thread_time() - t2)
    out = {k: 1e3 * float(np.median(v)) for k, v in steps.items()}
    out["total_orb"] = out["read"] + out["left_orb"] + out["stereo_orb"]
    out["total_row"] = out["read"] + out["left_orb"] + out["stereo_row"]
    out["opencv_threads"] = cv2.getNumThreads()
    return out


def orb_stereo_settings(seq_dir: Path, out: Path) -> Path:
    """ORB-SLAM3 stereo settings for a KITTI-layout sequence folder (``sequences/NN``): the peer's KITTI
    04-12 file with the folder's ``calib.txt`` (fx, fy, cx, cy, baseline) and image size, written to ``out``."""
    import re

    import cv2

    from benchmarks.common import orb_settings
    from rgbdslam.io.kitti import read_kitti_calib

    P = read_kitti_calib(seq_dir / "calib.txt")
    P0, P1 = P["P0"], P["P1"]
    b = -(P1[0, 3] - P0[0, 3]) / P1[0, 0]
    h, w = cv2.imread(str(sorted((seq_dir / "image_0").glob("*.png"))[0]), cv2.IMREAD_GRAYSCALE).shape
    text = orb_settings("kitti").read_text()
    for key, v in {"fx": P0[0, 0], "fy": P0[1, 1], "cx": P0[0, 2], "cy": P0[1, 2]}.items():
        text = re.sub(rf"^(Camera[12]\.{key}): .*$", rf"\g<1>: {v:.6f}", text, flags=re.M)
    text = re.sub(r"^Camera\.width: .*$", f"Camera.width: {w}", text, flags=re.M)
    text = re.sub(r"^Camera\.height: .*$", f"Camera.height: {h}", text, flags=re.M)
    text = re.sub(r"^Stereo\.b: .*$", f"Stereo.b: {b:.6f}", text, flags=re.M)
    text = re.sub(r"(data: \[1\.0, 0\.0, 0\.0, )[-0-9.e]+,", rf"\g<1>{b:.6f},", text)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return out


def orb_stereo_run(seq_dir: Path, settings: Path, out: Path, gt) -> dict:
    """One ORB-SLAM3 stereo run on ``seq_dir`` (``sequences/NN``): ATE, lost frames, median
    ``track_stereo`` ms, and the CPU seconds of its process (every thread, start-up included)."""
    import resource

    from benchmarks.common import run_orbslam3

    def children_cpu() -> float:
        r = resource.getrusage(resource.RUSAGE_CHILDREN)
        return r.ru_utime + r.ru_stime

    c0 = children_cpu()
    m = run_orbslam3(seq_dir, settings, out, gt, stereo=True)
    return {"ate": m.ate, "lost": m.lost, "frames": m.frames, "track_ms": m.ms, "cpu_s": children_cpu() - c0}


def orb_startup_cpu(seq_dir: Path, settings: Path, work: Path, gt) -> float:
    """CPU seconds of an ORB-SLAM3 stereo run on the first two pairs of ``seq_dir`` (its start-up:
    vocabulary, threads; subtracted from a whole run to get its CPU time per pair)."""
    short = work / "orb_startup" / f"{seq_dir.parent.parent.name}_{seq_dir.name}"
    for cam in ("image_0", "image_1"):
        (short / cam).mkdir(parents=True, exist_ok=True)
        for f in sorted((seq_dir / cam).glob("*.png"))[:2]:
            if not (short / cam / f.name).exists():
                (short / cam / f.name).symlink_to(f.resolve())
    return orb_stereo_run(short, settings, short.with_name(short.name + "_run"), gt)["cpu_s"]


def orb_comparison(work: Path, rounds: int, seeds: list[int]) -> dict:
    """rgbdslam (``kitti`` preset) and ORB-SLAM3 stereo on KITTI 06 0-50 and the synthetic highway seeds,
    the same pairs, interleaved rounds (rgbdslam is deterministic: its rounds agree; ORB-SLAM3's vary)."""
    from benchmarks.common import orbslam3_missing
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence

    why = orbslam3_missing()
    if why:
        print(why, flush=True)
        return {"skipped": why}
    cases = [("KITTI 06 0-50", KITTI)]
    for s in seeds:
        path = work / f"highway_s{s}"
        if not (path / "synthetic.yaml").exists():
            generate_stereo_sequence(path, 0.54, "kitti", frames=51, motion="highway", width=1241, height=376,
                                     noise=True, seed=s)
        cases.append((f"highway seed {s}", path))
    out = {}
    for name, path in cases:
        seq = open_sequence(path, load_config("kitti", []))
        seq_dir = sorted((path / "sequences").iterdir())[0]  # KITTI layout: sequences/NN
        gt = seq.groundtruth()
        settings = orb_stereo_settings(seq_dir, work / "orb_settings" / f"{name.replace(' ', '_')}.yaml")
        startup = orb_startup_cpu(seq_dir, settings, work, gt)
        row = {"rgbdslam": [], "orb": [], "orb_startup_cpu_s": startup,
               "distance_m": float(np.linalg.norm(np.diff(gt.positions, axis=0), axis=1).sum())}
        for k in range(rounds):
            row["rgbdslam"].append(run(path, "kitti", [], work / f"orbcmp_{name.replace(' ', '_')}_{k}"))
            row["orb"].append(orb_stereo_run(seq_dir, settings, work / f"orb_{name.replace(' ', '_')}_{k}", gt))
            print("orb comparison", name, k, json.dumps(row["rgbdslam"][-1]), json.dumps(row["orb"][-1]), flush=True)
        out[name] = row
    return out


def speed(work: Path, repeats: int) -> dict:
    """Whole pipeline (mapping off) on KITTI 06 0-50 with sparse depth, one and two reader threads,
    and fr1/rpy 200 (RGB-D, tum_fr1) as the machine's reference, interleaved ``repeats`` times so
    that the ratios of one round share the load; plus the reader's per-step CPU breakdown."""
    run(KITTI, "kitti", [], work / "speed_warmup")  # imports, caches
    rounds = []
    for k in range(repeats):
        row = {"load_average": os.getloadavg()[0]}
        for threads in (1, 2):
            row[f"kitti_threads{threads}"] = run(KITTI, "kitti", [f"dataset.reader_threads={threads}"],
                                                 work / f"speed_k{threads}_{k}")
        row["kitti_row"] = run(KITTI, "kitti", ["stereo.sparse_search=row"], work / f"speed_krow_{k}")
        row["rpy"] = run(RPY, "tum_fr1", [], work / f"speed_rpy_{k}")
        rounds.append(row)
        print("speed round", k, json.dumps(row), flush=True)
    return {"rounds": rounds, "reader_breakdown_ms": reader_breakdown()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--motions", default="loop,circle")
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--skip-synthetic", action="store_true")
    ap.add_argument("--parts", default="depth,kitti,orb,synthetic,speed",
                    help="comma list of the parts to run: depth (accuracy), disparity (per-point sparse disparity "
                         "errors by sub-pixel method, synthetic exact and KITTI consistency), kitti (+ fr1/rpy), "
                         "synthetic, oracle (synthetic stereo with exact / noisy true depth), orb (rgbdslam against "
                         "ORB-SLAM3 stereo on KITTI 06 0-50 and the highway seeds), speed")
    ap.add_argument("--repeats", type=int, default=3, help="rounds of the speed part")
    ap.add_argument("--orb-rounds", type=int, default=2, help="rounds of the orb part (ORB-SLAM3 varies per run)")
    ap.add_argument("--highway-seeds", default="0,1,2,3,4", help="synthetic highway seeds of the orb part")
    ap.add_argument("--methods", default="sparse,row,sgbm", help="stereo depth variants of the synthetic part: "
                    + ", ".join(f"{k} ({' '.join(v)})" for k, v in METHODS.items()))
    ap.add_argument("--set", action="append", default=[], dest="sets", metavar="KEY=VALUE",
                    help="extra config setting for every stereo run of the synthetic part (repeatable)")
    ap.add_argument("--reuse-rgbd", action="store_true",
                    help="synthetic part: take the RGB-D ATE from an earlier run in --work (the runs are deterministic)")
    ap.add_argument("--oracle-modes", default="exact,kinect,disp0.12,stereo",
                    help="oracle part (needs the synthetic part's RGB-D runs in --work): depth at the stereo key "
                         "points replaced by exact / kinect / dispS (exact disparity + S px noise) / stereo "
                         "(unchanged), each run with and without registration.stereo_reprojection")
    ap.add_argument("--oracle-refit", default="true,false", help="oracle part: registration.stereo_reprojection values to run")
    ap.add_argument("--tag", default="", help="suffix of the synthetic part's stereo run folders (to keep variants)")
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_stereo_"))
    work.mkdir(parents=True, exist_ok=True)
    from rgbdslam.datasets.synthetic import generate_sequence
    from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence

    report: dict = {"machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} CPUs, load average "
                               f"{os.getloadavg()[0]:.1f} at start", "command": " ".join(sys.argv)}
    parts = set(args.parts.split(","))
    if args.skip_synthetic:
        parts.discard("synthetic")
    report["depth_accuracy"] = depth_accuracy(work) if "depth" in parts else {}
    if "disparity" in parts:
        report["disparity"] = disparity_errors(args.motions.split(","), [int(s) for s in args.seeds.split(",")])
        report["kitti_disparity"] = kitti_disparity_consistency()
    print("depth accuracy", json.dumps(report["depth_accuracy"]), flush=True)

    # KITTI with both methods, and fr1/rpy (RGB-D) in between for the speed ratio
    kitti = {}
    if "kitti" in parts:
        for method in ("sparse", "sgbm"):
            kitti[method] = run(KITTI, "kitti", [f"stereo.depth={method}"], work / f"kitti_{method}")
            print("kitti", method, kitti[method], flush=True)
        kitti["rgbd_fr1_rpy"] = run(RPY, "tum_fr1", [], work / "rpy")
        print("fr1/rpy", kitti["rgbd_fr1_rpy"], flush=True)
    report["kitti"] = kitti
    if "orb" in parts:
        report["orb"] = orb_comparison(work, args.orb_rounds, [int(s) for s in args.highway_seeds.split(",")])

    synth = []
    if "synthetic" in parts:
        for motion in args.motions.split(","):
            for seed in [int(s) for s in args.seeds.split(",")]:
                rg, st = work / f"{motion}_s{seed}_rgbd", work / f"{motion}_s{seed}_stereo"
                if not (rg / "groundtruth.txt").exists():
                    generate_sequence(rg, frames=args.frames, motion=motion, noise=True, seed=seed)
                if not (st / "synthetic.yaml").exists():
                    generate_stereo_sequence(st, 0.12, "kitti", frames=args.frames, motion=motion, noise=True,
                                             seed=seed)
                ra = work / f"run_{motion}_{seed}_rgbd"
                if args.reuse_rgbd and (ra / "evaluation.json").is_file():  # deterministic: an earlier run's ATE
                    a = {"ate": json.loads((ra / "evaluation.json").read_text())["ate"]["rmse"]}
                else:
                    a = run(rg, None, [], ra)
                row = {"motion": motion, "seed": seed, "rgbd": a["ate"]}
                for method in args.methods.split(","):
                    b = run(st, None, METHODS[method] + args.sets, work / f"run_{motion}_{seed}_{method}{args.tag}")
                    row[method] = b["ate"]
                    row[f"{method}_lost"] = b["lost"]
                    row[f"{method}_ratio"] = b["ate"] / a["ate"] if a["ate"] and b["ate"] is not None else None
                synth.append(row)
                print("synthetic", row, flush=True)
    report["synthetic"] = synth
    oracle = []
    if "oracle" in parts:
        from rgbdslam.config import load_config
        from rgbdslam.datasets import open_sequence

        for motion in args.motions.split(","):
            for seed in [int(s) for s in args.seeds.split(",")]:
                st = work / f"{motion}_s{seed}_stereo"
                if not (st / "synthetic.yaml").exists():
                    generate_stereo_sequence(st, 0.12, "kitti", frames=args.frames, motion=motion, noise=True,
                                             seed=seed)
                rgbd = json.loads((work / f"run_{motion}_{seed}_rgbd" / "evaluation.json").read_text())["ate"]["rmse"]
                for mode in args.oracle_modes.split(","):
                    for refit in args.oracle_refit.split(","):
                        sets = [*args.sets, f"registration.stereo_reprojection={refit}"]
                        seq = with_oracle_depth(open_sequence(st, load_config(None, sets)), motion, seed, mode)
                        b = run(seq, None, sets, work / f"oracle_{motion}_{seed}_{mode}_{refit}{args.tag}")
                        row = {"motion": motion, "seed": seed, "mode": mode, "refit": refit == "true",
                               "ate": b["ate"], "lost": b["lost"], "rgbd": rgbd, "ratio": b["ate"] / rgbd}
                        oracle.append(row)
                        print("oracle", row, flush=True)
    report["oracle"] = oracle
    report["speed"] = speed(work, args.repeats) if "speed" in parts else {}
    report["load_average_end"] = os.getloadavg()[0]
    print_markdown(report)
    if args.json:
        from rgbdslam.io.atomic import atomic_write_text

        atomic_write_text(args.json, json.dumps(report, indent=2))


def print_markdown(r: dict) -> None:
    print(f"\nmachine: {r['machine']}; load average at the end {r['load_average_end']:.1f}\n")
    if r["depth_accuracy"]:
        print("| method | disparity bias (px) | sigma (px) | errors > 1 px | pixels with depth | read + depth ms |")
        print("|---|---|---|---|---|---|")
        for m, d in r["depth_accuracy"].items():
            print(f"| {m} | {d['bias_px']:+.3f} | {d['sigma_px']:.3f} | {100 * d['gross_share']:.1f} % | "
                  f"{d['depth_pixels_median']:.0f} | {d['load_ms_median']:.0f} |")
    if r.get("disparity"):
        print_disparity(r["disparity"], r["kitti_disparity"])
    if r["kitti"]:
        print_kitti(r["kitti"])
    if r.get("orb") and "skipped" not in r["orb"]:
        print_orb(r["orb"])
    if r["synthetic"]:
        print_synthetic(r["synthetic"])
    if r.get("oracle"):
        print("\n| sequence | depth at the stereo key points | stereo refit | ATE (m) | RGB-D ATE (m) | ratio | lost |")
        print("|---|---|---|---|---|---|---|")
        for o in r["oracle"]:
            print(f"| {o['motion']} seed {o['seed']} | {o['mode']} | {'on' if o['refit'] else 'off'} | {o['ate']:.4f} | "
                  f"{o['rgbd']:.4f} | {o['ratio']:.2f} | {o['lost']} |")
    if r["speed"]:
        print_speed(r["speed"])


def print_disparity(syn: dict, kitti: dict) -> None:
    print("\n| sequence | sub-pixel | points | bias (px) | median | robust sigma | sd of |e|<1 | > 1 px | "
          "mean error by true fraction 0.0 ... 0.9 (px) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, res in syn.items():
        for m, d in res.items():
            print(f"| {name} | {m} | {d['n']} | {d['bias_px']:+.3f} | {d['median_px']:+.3f} | {d['sigma_robust_px']:.3f} | "
                  f"{d['sd_core_px']:.3f} | {100 * d['gross_share']:.1f} % | "
                  + " ".join(f"{x:+.2f}" for x in d["by_fraction"]) + " |")
    print("\nby depth (bias / robust sigma px): " + "; ".join(
        f"{name} {m}: " + ", ".join(f"{k} {v['bias_px']:+.3f}/{v['sigma_robust_px']:.3f}" for k, v in d["by_depth"].items())
        for name, res in syn.items() for m, d in res.items()))
    print("\nby image column third (bias / robust sigma px): " + "; ".join(
        f"{name} {m}: " + ", ".join(f"{v['bias_px']:+.3f}/{v['sigma_robust_px']:.3f}" for v in d["by_column_third"])
        for name, res in syn.items() for m, d in res.items()))
    print("\n| KITTI 06 consistency | pairs | median diff (px) | robust sd of diff | per measurement | > 1 px | "
          "median diff by disparity 4-10 / 10-20 / 20-40 / 40-130 px |")
    print("|---|---|---|---|---|---|---|")
    for m, d in kitti.items():
        print(f"| {m} | {d['n']} | {d['median_px']:+.3f} | {d['sigma_robust_px']:.3f} | {d['sigma_per_measurement_px']:.3f} | "
              f"{100 * d['gross_share']:.1f} % | " + " / ".join(f"{v['median_px']:+.3f}" for v in d["by_disparity"].values())
              + " |")


def print_speed(sp: dict) -> None:
    keys = ("kitti_threads1", "kitti_threads2", "kitti_row", "rpy")
    print("\n(each cell: frames/s / frames/s without waiting for images / CPU ms per frame of the process)\n")
    print("| round | load avg | KITTI, 1 reader thread | KITTI, 2 reader threads | KITTI, 2 threads, "
          "sparse_search=row | fr1/rpy (tum_fr1) | 2 threads / 1 thread | row / orb (2 threads) | "
          "KITTI 2 threads / fr1-rpy |")
    print("|---|---|---|---|---|---|---|---|---|")
    for k, r in enumerate(sp["rounds"]):
        a, b, w, c = (r[key] for key in keys)
        cells = [f"{d['fps']:.1f} / {d['processing_fps']:.1f} / {d['cpu_ms_per_frame']:.0f}" for d in (a, b, w, c)]
        print(f"| {k} | {r['load_average']:.1f} | {' | '.join(cells)} | {b['fps'] / a['fps']:.2f} | "
              f"{w['fps'] / b['fps']:.2f} | {b['fps'] / c['fps']:.2f} |")
    med = {key: float(np.median([r[key]["fps"] for r in sp["rounds"]])) for key in keys}
    r0 = sp["rounds"][0]
    print(f"\nmedians (frames/s): " + ", ".join(f"{key} {v:.1f}" for key, v in med.items())
          + f"; ATE orb {r0['kitti_threads2']['ate']:.4f} m, row {r0['kitti_row']['ate']:.4f} m")
    print("\nCPU ms per frame, medians over the rounds: main thread (tracking, pose graph, evaluation) / other "
          "threads (frame readers): " + ", ".join(
              f"{key} {np.median([r[key]['main_thread_cpu_ms_per_frame'] for r in sp['rounds']]):.0f} / "
              f"{np.median([r[key]['cpu_ms_per_frame'] - r[key]['main_thread_cpu_ms_per_frame'] for r in sp['rounds']]):.0f}"
              for key in keys))
    b = sp["reader_breakdown_ms"]
    print("\nreader CPU per KITTI pair (ms, medians): " + ", ".join(f"{k} {v:.1f}" for k, v in b.items()
                                                             if k != "opencv_threads"))


def print_kitti(kitti: dict) -> None:
    print("\n| KITTI 06 0-50 | ATE (m) | t_err (%) | r_err (deg/m) | end drift (%) | lost | frames/s | "
          "frames/s / fr1-rpy frames/s |")
    print("|---|---|---|---|---|---|---|---|")
    ref = kitti["rgbd_fr1_rpy"]["fps"]
    for m in ("sparse", "sgbm"):
        d = kitti[m]
        print(f"| {m} | {d['ate']:.4f} | {d['t_err_pct']:.3f} | {d['r_err_deg_per_m']:.4f} | {d['end_drift_pct']:.3f} | "
              f"{d['lost']} | {d['fps']:.1f} | {d['fps'] / ref:.2f} |")
    d = kitti["rgbd_fr1_rpy"]
    print(f"| (RGB-D fr1/rpy 200, tum_fr1) | {d['ate']:.4f} | | | | {d['lost']} | {d['fps']:.1f} | 1.00 |")


def print_orb(orb: dict) -> None:
    print("\n| sequence (distance) | rgbdslam ATE (m), lost | ATE / distance | ORB-SLAM3 stereo ATE (m), lost, per round | "
          "ATE ratio rgbdslam / ORB-SLAM3 | CPU ms per pair rgbdslam / ORB-SLAM3 | CPU ratio ORB-SLAM3 / rgbdslam | "
          "wall ms per frame rgbdslam / ORB-SLAM3 track_stereo (medians) |")
    print("|---|---|---|---|---|---|---|---|")
    for name, row in orb.items():
        a, o = row["rgbdslam"], row["orb"]
        ate = a[0]["ate"]
        orb_ate = float(np.median([x["ate"] for x in o]))
        ours_cpu = float(np.median([x["cpu_ms_per_frame"] for x in a]))
        orb_cpu = float(np.median([1e3 * (x["cpu_s"] - row["orb_startup_cpu_s"]) / max(1, x["frames"] - 2) for x in o]))
        wall = float(np.median([1e3 / x["fps"] for x in a]))
        print(f"| {name} ({row['distance_m']:.1f} m) | {ate:.4f}, {a[0]['lost']} | {100 * ate / row['distance_m']:.2f} % | "
              + " / ".join(f"{x['ate']:.4f}, {x['lost']}" for x in o)
              + f" | {ate / orb_ate:.2f} | {ours_cpu:.0f} / {orb_cpu:.0f} | {orb_cpu / ours_cpu:.2f} | "
              f"{wall:.0f} / {np.median([x['track_ms'] for x in o]):.0f} |")


def print_synthetic(synth: list[dict]) -> None:
    methods = [m for m in METHODS if m in synth[0]]
    print("\n| sequence | RGB-D ATE (m) | " + " | ".join(f"stereo {m} ATE (m) (lost) | ratio" for m in methods) + " |")
    print("|---|---|" + "---|---|" * len(methods))
    for s in synth:
        print(f"| {s['motion']} seed {s['seed']} | {s['rgbd']:.4f} | " + " | ".join(
            f"{s[m]:.4f} ({s[f'{m}_lost']}) | {s[f'{m}_ratio']:.2f}" for m in methods) + " |")
    for m in methods:
        ratios = [s[f"{m}_ratio"] for s in synth]
        print(f"\n{m}: median ratio {np.median(ratios):.2f}, worst {max(ratios):.2f}")


if __name__ == "__main__":
    main()
