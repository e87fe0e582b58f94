"""Own data: what 7-Scenes' unregistered depth costs, and bag / RealSense runs against folder runs.

1. 7-Scenes redkitchen frames 0-299 (``$RGBDSLAM_DATA/7scenes/frames_0000_0299``): ATE RMSE
   against the KinectFusion poses, depth as recorded (the published intrinsics for colour too)
   and re-projected into the colour camera with several camera files (colour focal length and
   depth-to-colour offset; rgbdslam/cameras/7scenes.yaml is one of them).
2. fr1/rpy head200 (``$RGBDSLAM_DATA/tum``): the TUM folder, then the same frames written into a
   ROS 1 bag, a ROS 2 mcap bag (rosbags' writers), a RealSense SDK recording (pyrealsense2's
   recorder) and the SDK's playback of that recording through ``rgbdslam live``: ATE of each and
   the largest pose difference to the folder run.

    python -m benchmarks.owndata --work /tmp/bench_owndata
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from benchmarks.common import DATA, ROOT
from rgbdslam.config import load_config
from rgbdslam.io.trajectory import read_tum
from rgbdslam.pipeline import run_sequence


def _cfg(*extra):
    return load_config(None, ["mapping.enabled=false", "output.plots=false", *extra])


def _run(seq, out, *extra) -> dict:
    t0 = time.perf_counter()
    s = run_sequence(seq, out, _cfg(*extra), progress=False)
    s["_wall"] = time.perf_counter() - t0
    return s


def seven_scenes(data: Path, work: Path) -> list[str]:
    seq = data / "7scenes" / "frames_0000_0299"
    base = yaml.safe_load((ROOT / "rgbdslam" / "cameras" / "7scenes.yaml").read_text())
    variants = [("as recorded: depth intrinsics (585) for colour, no re-projection", None)]
    for f, tx in ((530.0, 0.0), (530.0, -0.02), (530.0, 0.02), (525.0, -0.025), (585.0, -0.02)):
        cam = dict(base, fx=f, fy=f, depth_to_color=[tx, 0.0, 0.0])
        path = work / f"7s_f{f:g}_t{tx:+g}.yaml"
        path.write_text(yaml.safe_dump(cam))
        note = " (rgbdslam/cameras/7scenes.yaml)" if (f, tx) == (base["fx"], base["depth_to_color"][0]) else ""
        variants.append((f"colour focal {f:g}, depth re-projected, depth-to-colour x {tx * 100:+.1f} cm{note}", path))
    rows = ["| depth / camera | ATE RMSE (m) | tracked | frames/s |", "|---|---|---|---|"]
    for label, cam in variants:
        extra = [f"dataset.camera_file={cam}"] if cam else []
        s = _run(seq, work / ("7s_" + (cam.stem if cam else "raw")), *extra)
        ate = s.get("evaluation", {}).get("ate", {}).get("rmse", float("nan"))
        rows.append(f"| {label} | {ate:.4f} | {s['tracked']}/{s['frames']} | {s['fps']:.1f} |")
        print(rows[-1], flush=True)
    return rows


def parity(data: Path, work: Path) -> list[str]:
    from rgbdslam.datasets.testing import write_bag, write_realsense_recording

    src = data / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
    runs = [("TUM folder", src, [])]
    runs.append(("ROS 1 bag (rgb8, 16UC1 raw units)", write_bag(src, work / "rpy.bag", "ros1"),
                 ["dataset.depth_scale=5000"]))
    runs.append(("ROS 2 mcap bag (PNG CompressedImage, compressedDepth)",
                 write_bag(src, work / "rpy_mcap", "mcap", color="png", depth="compressedDepth"),
                 ["dataset.depth_scale=5000"]))
    rec = write_realsense_recording(src, work / "rpy_sdk.db3")
    runs.append(("RealSense SDK recording (.db3, pyrealsense2 recorder)", rec, []))
    rows = ["| input | ATE RMSE (m) | max pose difference to the folder run | frames/s |", "|---|---|---|---|"]
    ref = None
    gt = read_tum(src / "groundtruth.txt")
    from rgbdslam.evaluation.report import evaluate_trajectories

    def row(label, out, s):
        nonlocal ref
        est = read_tum(out / "trajectory.tum")
        ate = evaluate_trajectories(gt, est).ate.rmse
        if ref is None:
            ref = est
        diff = float(np.abs(est.poses - ref.poses).max()) if len(est) == len(ref) else float("nan")
        rows.append(f"| {label} | {ate:.4f} | {diff:.2g} | {s['fps']:.1f} |")
        print(rows[-1], flush=True)

    for label, seq, extra in runs:
        out = work / ("run_" + Path(seq).stem)
        row(label, out, _run(seq, out, *extra))
    from rgbdslam.datasets.realsense import RealSenseSequence

    out = work / "run_live"
    live = RealSenseSequence(work / "live_recording", playback=rec)
    row("rgbdslam live --playback of that recording (SDK playback + rs.align)", out, _run(live, out))
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(DATA))
    ap.add_argument("--work", required=True, help="an empty folder for the bags and runs")
    a = ap.parse_args()
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
          f"{time.strftime('%Y-%m-%d')}")
    rows = seven_scenes(Path(a.data), work)
    print("\n".join(rows))
    rows = parity(Path(a.data), work)
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
