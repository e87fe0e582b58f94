"""CPU time per stage of the per-frame chain, for the default (the landmark map) and the thesis chain
(results: docs/speed.md).

Usage::

    python -m benchmarks.profile_chain [--sequence DIR] [--config NAME|FILE] [--chain default|thesis ...]
        [--max-frames N] [--top N] [--json FILE]

``--config`` as ``rgbdslam run --config`` (a preset name or a YAML file), e.g. ``--config kitti`` for
the stereo chain on KITTI; without it the defaults.

Both threads of ``rgbdslam run`` are measured, here one after the other in one thread per frame:
the reader's work (``Sequence.load``: decoding the images; ``features.with_detections``: the key
points, ORB and the detection count) and the tracking thread's (``SLAM.track``). Times are CPU
times of this thread (``time.thread_time``), not wall-clock rates: on a loaded machine waiting for
a core does not count. The end of the run (``SLAM.finish``: the pose graph) is reported apart, once.

Two passes per chain, same frames, same seeded code:

1. unprofiled: load, key points and track per frame (ms, mean over the frames); the floor they
   are compared with, ORB extraction alone (OpenCV's ORB, 1000 key points, on the same grey
   images), and the ratios chain ÷ ORB: "tracking" = ``SLAM.track`` alone, "chain" = key
   points + tracking (image decoding left out, as ORB-SLAM3's ``TrackRGBD`` leaves it out);
2. under cProfile (timer ``time.thread_time``) for the split of ``SLAM.track`` into its stages:
   the cumulative time of every call the orchestrator (code outside the stage packages:
   ``rgbdslam/slam.py`` today) makes into each stage package (front end, depth filter, landmark
   map, loop closure, pose graph); the rest of ``SLAM.track`` is its own glue. Inside the stages,
   named functions (cumulative over all their callers: the loop closer's registrations also use
   the matchers). cProfile's overhead inflates Python-heavy code, so the profiled total is
   printed next to the unprofiled one; then the most expensive functions by own time.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import platform
import pstats
import time
from pathlib import Path

import cv2
import numpy as np

from rgbdslam.config import load_config
from rgbdslam.datasets import open_sequence
from rgbdslam.frontend.features import with_detections
from rgbdslam.frontend.odometry import detection_features
from rgbdslam.slam import SLAM

DATA = Path(os.environ.get("RGBDSLAM_DATA", Path(__file__).resolve().parent.parent.parent / "shared" / "data"))
SEQUENCE = DATA / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
CHAINS = {"default": [], "thesis": ["landmarks.enabled=false"]}  # the landmark map; the frame-to-frame chain
BASE = ["mapping.enabled=false", "output.plots=false"]

# the stage packages SLAM.track calls into (path inside rgbdslam/ -> label); the first match wins
STAGES = [("frontend/depth_filter.py", "depth filter (DIF)"), ("frontend/", "front end"),
          ("landmarks/", "landmark map"), ("loop/", "loop closure"), ("backend/", "pose graph")]
# functions inside the stages (file inside rgbdslam/, function name, label): cumulative over all callers
INNER = [
    ("frontend/features.py", "extract_features", "front end: undistort + lift to 3-D"),
    ("frontend/features.py", "subset", "front end: strongest subset (landmark chain)"),
    ("frontend/matching.py", "match_pairs", "matching: brute force (Hamming matrix)"),
    ("frontend/matching.py", "guided_match", "matching: guided (3-D neighbours)"),
    ("frontend/matching.py", "prefilter", "matching: RANSAC pre-filter"),
    ("frontend/registration/base.py", "fit", "registration (ISLAM) incl. refit"),
    ("frontend/pose_fusion.py", "fuse_candidates", "fusion of the candidates"),
    ("landmarks/stage.py", "track", "landmark map: tracking (match + pose)"),
    ("landmarks/tracking.py", "match_to_map", "  map: match to the projected landmarks"),
    ("landmarks/tracking.py", "estimate_pose", "  map: pose (RANSAC + refine)"),
    ("landmarks/tracking.py", "gauss_newton", "  map: reprojection refine (GN)"),
    ("landmarks/stage.py", "add_keyframe", "landmark map: keyframe (new landmarks)"),
    ("loop/detector.py", "detect", "loop closure: search + verify"),
]


def _rel(filename: str) -> str | None:
    """The path of ``filename`` inside the rgbdslam package, or None outside it."""
    parts = Path(filename).parts
    if "rgbdslam" not in parts:
        return None
    k = len(parts) - 1 - parts[::-1].index("rgbdslam")
    return "/".join(parts[k + 1:])


def _stage(rel: str | None) -> str | None:
    if rel is None:
        return None
    return next((label for prefix, label in STAGES if rel.startswith(prefix)), None)


def stage_split(stats: pstats.Stats) -> tuple[dict[str, float], dict[str, float], list]:
    """(stage -> s, inner function label -> s, [(own s, calls, function)] by own time) of a profile."""
    stages: dict[str, float] = {}
    inner: dict[str, float] = {}
    for (fn, _line, name), (_cc, nc, tt, ct, callers) in stats.stats.items():
        rel = _rel(fn)
        for f, n, label in INNER:
            if rel == f and name == n:
                inner[label] = inner.get(label, 0.0) + ct
        target = _stage(rel)
        if target is None:
            continue
        for (cfn, _cl, _cname), (_c1, _c2, _ctt, cct) in callers.items():
            crel = _rel(cfn)
            if crel is not None and _stage(crel) is None:  # the orchestrator calling into the stage
                stages[target] = stages.get(target, 0.0) + cct
    own = sorted(((tt, nc, f"{_rel(fn) or Path(fn).name}:{name}") for (fn, _l, name), (_cc, nc, tt, _ct, _c)
                  in stats.stats.items()), reverse=True)
    return stages, inner, own


def orb_floor(gray: np.ndarray, orb) -> float:
    """CPU seconds of one plain ORB extraction (detect + describe)."""
    t0 = time.thread_time()
    orb.detectAndCompute(gray, None)
    return time.thread_time() - t0


def run_chain(seq_dir: Path, sets: list[str], max_frames: int | None, profile: bool, config: str | None = None) -> dict:
    cfg = load_config(config, BASE + sets)
    seq = open_sequence(seq_dir, cfg)
    n = len(seq) if max_frames is None else min(len(seq), max_frames)
    fc = detection_features(cfg.features, cfg.landmarks.n_features if cfg.landmarks.enabled and not seq.own_key_points else 0)
    slam = SLAM(cfg, seq.camera)
    orb = cv2.ORB_create(nfeatures=1000)
    load = detect = track = floor = 0.0
    prof = cProfile.Profile(time.thread_time) if profile else None
    for i in range(n):
        t0 = time.thread_time()
        frame = seq.load(i)
        t1 = time.thread_time()
        frame = with_detections(frame, fc)
        t2 = time.thread_time()
        if prof is not None:
            prof.enable()
        slam.track(frame)
        if prof is not None:
            prof.disable()
        t3 = time.thread_time()
        load, detect, track = load + t1 - t0, detect + t2 - t1, track + t3 - t2
        if not profile:
            gray = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY) if frame.rgb.ndim == 3 else frame.rgb
            floor += orb_floor(gray, orb)
    t0 = time.thread_time()
    slam.finish()
    out = {"frames": n, "tracked": len(slam.state.records), "load_ms": 1e3 * load / n, "detect_ms": 1e3 * detect / n,
           "track_ms": 1e3 * track / n, "finish_s": time.thread_time() - t0}
    if profile:
        stages, inner, own = stage_split(pstats.Stats(prof))
        out["stages_ms"] = {k: 1e3 * v / n for k, v in stages.items()}
        out["inner_ms"] = {k: 1e3 * v / n for k, v in inner.items()}
        out["own"] = [(1e3 * tt / n, nc, name) for tt, nc, name in own]
    else:
        out["orb_ms"] = 1e3 * floor / n
    return out


def report(name: str, plain: dict, prof: dict, top: int) -> list[str]:
    L = [f"### {name} ({plain['frames']} frames, {plain['tracked']} tracked)", "",
         "| stage | thread | CPU ms per frame |", "|---|---|---|",
         f"| read images (decode) | reader | {plain['load_ms']:.2f} |",
         f"| key points (ORB + detection count) | reader | {plain['detect_ms']:.2f} |",
         f"| **SLAM.track** (unprofiled) | tracking | **{plain['track_ms']:.2f}** |",
         f"| SLAM.track under cProfile | tracking | {prof['track_ms']:.2f} |"]
    st = prof["stages_ms"]
    for _p, label in STAGES:
        if label in st:
            L.append(f"| &nbsp;&nbsp;{label} | tracking | {st[label]:.2f} |")
    L.append(f"| &nbsp;&nbsp;SLAM.track's own glue | tracking | {prof['track_ms'] - sum(st.values()):.2f} |")
    for _f, _n, label in INNER:
        if label in prof["inner_ms"]:
            L.append(f"| &nbsp;&nbsp;&nbsp;&nbsp;{label.strip()} | tracking | {prof['inner_ms'][label]:.2f} |")
    chain = plain["detect_ms"] + plain["track_ms"]
    L += [f"| ORB alone (OpenCV, 1000 key points) | — | {plain['orb_ms']:.2f} |", "",
          f"Ratios to ORB alone: tracking {plain['track_ms'] / plain['orb_ms']:.2f}, "
          f"chain (key points + tracking) {chain / plain['orb_ms']:.2f}. "
          f"End of the run (SLAM.finish): {plain['finish_s']:.2f} s CPU.", "",
          f"Most expensive functions by own CPU time (under cProfile, ms per frame), top {top}:", "",
          "| function | calls per frame | own ms per frame |", "|---|---|---|"]
    for ms, nc, fname in prof["own"][:top]:
        L.append(f"| `{fname}` | {nc / plain['frames']:.1f} | {ms:.2f} |")
    return L + [""]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequence", type=Path, default=SEQUENCE)
    ap.add_argument("--config", help="a preset name or YAML file, as rgbdslam run --config (default: the defaults)")
    ap.add_argument("--chain", action="append", choices=sorted(CHAINS), help="default: default and thesis")
    ap.add_argument("--max-frames", type=int)
    ap.add_argument("--top", type=int, default=12)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    if not a.sequence.exists():
        raise SystemExit(f"sequence not found: {a.sequence} (set RGBDSLAM_DATA to the shared data folder)")
    cv2.setNumThreads(1)  # CPU time of one thread measures all of OpenCV's work
    lines = [f"{a.sequence.name}; {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
             f"load {os.getloadavg()[0]:.1f}; CPU time (time.thread_time), not wall time.", ""]
    results = {}
    for name in a.chain or ["default", "thesis"]:
        plain = run_chain(a.sequence, CHAINS[name], a.max_frames, profile=False, config=a.config)
        prof = run_chain(a.sequence, CHAINS[name], a.max_frames, profile=True, config=a.config)
        results[name] = {"plain": plain, "profiled": {k: v for k, v in prof.items() if k != "own"}}
        lines += report(name, plain, prof, a.top)
    print("\n".join(lines))
    if a.json:
        a.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
