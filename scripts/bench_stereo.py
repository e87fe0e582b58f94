"""Stereo input: accuracy and speed of the two depth methods, on real KITTI and on synthetic
stereo with exact ground truth.

Usage::

    .venv/bin/python scripts/bench_stereo.py [--seeds 0,1,2] [--frames 150] [--motions loop,circle]
        [--work DIR] [--json FILE] [--parts depth,kitti,synthetic,speed] [--repeats 3]

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
4. Speed: the whole pipeline on KITTI-sized pairs (1226x370) with each depth method, next to the
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

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

DATA = Path(os.environ.get("RGBDSLAM_DATA", ROOT.parent / "shared" / "data"))
KITTI = DATA / "kitti" / "odometry_06_head51"
RPY = DATA / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
# stereo depth variants of the synthetic comparison
METHODS = {"sparse": ["stereo.depth=sparse"], "row": ["stereo.depth=sparse", "stereo.sparse_search=row"],
           "sgbm": ["stereo.depth=sgbm"]}


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
    steps: dict[str, list[float]] = {k: [] for k in ("read", "left_orb", "stereo_orb", "stereo_row")}
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
    ap.add_argument("--parts", default="depth,kitti,synthetic,speed",
                    help="comma list of the parts to run: depth (accuracy), kitti (+ fr1/rpy), synthetic, speed")
    ap.add_argument("--repeats", type=int, default=3, help="rounds of the speed part")
    ap.add_argument("--methods", default="sparse,row,sgbm", help="stereo depth variants of the synthetic part: "
                    + ", ".join(f"{k} ({' '.join(v)})" for k, v in METHODS.items()))
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
                a = run(rg, None, [], work / f"run_{motion}_{seed}_rgbd")
                row = {"motion": motion, "seed": seed, "rgbd": a["ate"]}
                for method in args.methods.split(","):
                    b = run(st, None, METHODS[method], work / f"run_{motion}_{seed}_{method}")
                    row[method] = b["ate"]
                    row[f"{method}_lost"] = b["lost"]
                    row[f"{method}_ratio"] = b["ate"] / a["ate"] if a["ate"] and b["ate"] is not None else None
                synth.append(row)
                print("synthetic", row, flush=True)
    report["synthetic"] = synth
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
    if r["kitti"]:
        print_kitti(r["kitti"])
    if r["synthetic"]:
        print_synthetic(r["synthetic"])
    if r["speed"]:
        print_speed(r["speed"])


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
