"""Tracking loss and relocalisation: black out a run of frames and see what SLAM makes of it.

Usage::

    python -m benchmarks.tracking_loss [--data DIR] [--work DIR] [--write-docs]

Two sequences, each in a temporary copy (the data are never modified):

* fr1/rpy head200 (``$RGBDSLAM_DATA/tum``) with colour frames 60-89 (and, by default, 20-49 and
  130-164: ``--gaps``) replaced by black images;
* a synthetic loop (``generate_sequence(motion='loop', noise=True, frames=120, seed=0)``) with
  frames 50-84 black, while the camera moves on and comes back to the start.

Each is run with the default configuration, with ``loop.relocalize_confirm=1`` (the first
geometrically sound match links the segments, without waiting for a second one to agree) and
with ``loop.enabled=false`` (nothing can then relate the segment after the restart to the one
before). Reported: tracked frames, the
restart, the frame of the first loop into an older segment (relocalisation), loops, and the
ATE of all tracked frames and of the frames before / after the gap (one alignment for all).
``--write-docs`` replaces the "## Tracking loss" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import DATA

from rgbdslam.config import load_config


def blackout(src: Path, dst: Path, first: int, stop: int) -> Path:
    """A copy of the TUM folder ``src`` with colour frames [first, stop) (rgb.txt order) black."""
    import cv2

    shutil.copytree(src, dst)
    names = [ln.split()[1] for ln in (dst / "rgb.txt").read_text().splitlines()
             if ln.strip() and not ln.startswith("#")]
    for name in names[first:stop]:
        img = cv2.imread(str(dst / name))
        cv2.imwrite(str(dst / name), np.zeros_like(img))
    return dst


def split_ate(gt_path: Path, est_path: Path, t_first: float, t_stop: float) -> tuple[float, float, float]:
    """ATE RMSE of all poses, of those before ``t_first`` and of those from ``t_stop`` on."""
    from rgbdslam.evaluation.ate import ate
    from rgbdslam.io.trajectory import read_tum

    a = ate(read_tum(gt_path), read_tum(est_path))
    t, e = a.timestamps, a.errors

    def rms(mask):
        return float(np.sqrt(np.mean(e[mask] ** 2))) if mask.any() else float("nan")

    return a.rmse, rms(t < t_first), rms(t >= t_stop)


def run_case(name: str, seq: Path, first: int, stop: int, out: Path) -> list[dict]:
    from rgbdslam.datasets import open_sequence
    from rgbdslam.pipeline import run_sequence

    stamps = open_sequence(seq).timestamps
    rows = []
    for label, sets in (("default", []), ("loop.relocalize_confirm=1", ["loop.relocalize_confirm=1"]),
                        ("loop.enabled=false", ["loop.enabled=false"])):
        cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", *sets])
        s = run_sequence(seq, out / f"{name}_{first}-{stop}_{label.replace('=', '_')}", cfg, progress=False)
        older = [j for i, j in s["loops"] if s["restarts"] and i < s["restarts"][0] <= j]
        all_, before, after = split_ate(seq / "groundtruth.txt", out / f"{name}_{first}-{stop}_{label.replace('=', '_')}" /
                                        "trajectory.tum", stamps[first], stamps[stop])
        rows.append({"sequence": name, "gap": f"{first}–{stop - 1}", "config": label, "frames": s["frames"],
                     "tracked": s["tracked"], "restarts": s["restarts"], "relocalized_at": min(older, default=None),
                     "loops": len(s["loops"]), "ate": all_, "ate_before": before, "ate_after": after})
        r = rows[-1]
        print(f"  {name:24s} {label:20s} restarts {r['restarts']} relocalised at {r['relocalized_at']} "
              f"loops {r['loops']} ATE {r['ate']:.4f} (before {before:.4f}, after {after:.4f})", flush=True)
    return rows


def markdown(rows: list[dict], command: str) -> str:
    L = ["## Tracking loss", "",
         f"Command: `{command}`  ",
         f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
         f"{time.strftime('%Y-%m-%d')}. Colour frames of the gap are black (no features), so the front end "
         "loses them, restarts after `registration.max_lost` frames from the last pose, and the loop closer "
         "relocalises the new segment (docs/slam.md). ATE: one SE(3) alignment of all tracked frames; "
         "'before' / 'after' are the RMSE over the frames before / after the gap.", "",
         "| sequence | black frames | configuration | tracked | restart at | relocalised at | loops | "
         "ATE (m) | before | after |",
         "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        restart = ", ".join(str(i) for i in r["restarts"]) or "-"
        reloc = "-" if r["relocalized_at"] is None else str(r["relocalized_at"])
        L.append(f"| {r['sequence']} | {r['gap']} | {r['config']} | {r['tracked']}/{r['frames']} | {restart} | "
                 f"{reloc} | {r['loops']} | {r['ate']:.4f} | {r['ate_before']:.4f} | {r['ate_after']:.4f} |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(DATA))
    ap.add_argument("--work", default=None, help="folder for the altered copies and the runs (default: temporary)")
    ap.add_argument("--gaps", default="60-90,20-50,130-165",
                    help="fr1/rpy frames to black out, FIRST-STOP (STOP excluded), comma-separated")
    ap.add_argument("--write-docs", action="store_true")
    a = ap.parse_args(argv)
    command = "python -m benchmarks.tracking_loss " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:]))
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="bench_loss_"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    rpy = Path(a.data) / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
    if rpy.is_dir():
        for gap in a.gaps.split(","):
            first, stop = (int(x) for x in gap.split("-"))
            rows += run_case("freiburg1_rpy_head200", blackout(rpy, work / f"rpy_gap_{first}-{stop}", first, stop),
                             first, stop, work)
    else:
        print(f"skipping fr1/rpy: {rpy} not found (set --data or RGBDSLAM_DATA)")
    from rgbdslam.datasets.synthetic import generate_sequence

    generate_sequence(work / "synth", frames=120, motion="loop", noise=True, seed=0)
    rows += run_case("synthetic loop (120)", blackout(work / "synth", work / "synth_gap", 50, 85), 50, 85, work)
    md = markdown(rows, command)
    from benchmarks.common import publish_markdown as publish

    return publish(md, a.write_docs)


if __name__ == "__main__":
    raise SystemExit(main())
