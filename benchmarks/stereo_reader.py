"""CPU time per step of preparing a stereo pair (the reader thread), two source trees A/B interleaved.

Usage::

    python -m benchmarks.stereo_reader [--trees OLD NEW] [--reps 3] [--sequence DIR] [--config kitti]
        [--work DIR] [--json FILE]

``--trees`` are two checkouts of rgbdslam (e.g. ``git worktree add /tmp/old main``; default: this one
twice). For each of ``--reps`` rounds, each tree in turn runs this file in a child process with
``PYTHONPATH=TREE``, so the child imports that tree's ``rgbdslam`` and times that tree's code on the same
pairs (KITTI 06 0-50 by default, the ``kitti`` preset):

* the reader's steps in one thread, CPU time (``time.process_time``: every thread of the child, OpenCV's
  included) per pair, median over the pairs: reading both images (``rectified_pair``), left key points
  (``features.detect``: ORB, grid bucketing, the FAST detection count), right ORB (``orb_features`` with
  the right image's budget, as ``stereo/depth.py`` calls it), row matching (``match_rows``), the sub-pixel
  refinement (``refine_disparity``), the whole stereo step (``sparse_matches``) and the whole
  ``Sequence.load`` (read + key points + depth + frame);
* the whole command on the sequence (``pipeline.run_sequence``, mapping off): CPU time of the process per
  pair (reader threads and tracking), and the trajectory file, compared byte for byte between the trees.

The machine may be shared: only CPU times (not wall-clock rates) are compared, and the rounds are
interleaved (A B A B ...) so that both trees see the same load. Prints a Markdown table (medians over the
rounds) and writes the rounds to ``--json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve()
DATA = Path(os.environ.get("RGBDSLAM_DATA", HERE.parent.parent.parent / "shared" / "data"))
KITTI = DATA / "kitti" / "odometry_06_head51"
STEPS = [("read", "read both images (decode)"), ("left", "left key points (ORB, grid, detection count)"),
         ("right_orb", "right ORB (2x budget, no grid)"), ("match", "row matching (descriptors)"),
         ("refine", "sub-pixel refinement (zero-mean SAD)"), ("stereo", "stereo step in all (`sparse_matches`)"),
         ("load", "**`Sequence.load` in all**"), ("run", "whole `rgbdslam run` (mapping off), CPU of the process")]


def measure(sequence: Path, config: str, out: Path) -> dict:
    """This tree's CPU ms per pair for each step (medians over the pairs), and one whole run."""
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.frontend.features import detect, orb_features
    from rgbdslam.pipeline import run_sequence
    from rgbdslam.stereo.depth import match_rows, refine_disparity, sparse_matches

    cfg = load_config(config, ["mapping.enabled=false", "output.plots=false"])
    seq = open_sequence(sequence, cfg)
    seq.configure(cfg)
    fc, sc = cfg.features, cfg.stereo
    fc_right = dataclasses.replace(fc, n_features=sc.right_features * fc.n_features, grid_rows=1, grid_cols=1)
    # the right image's ORB as this tree's stereo/depth.py calls it (newer trees skip responses and levels)
    right_kw = {"attributes": False} if "attributes" in inspect.signature(orb_features).parameters else {}
    steps: dict[str, list[float]] = {k: [] for k, _ in STEPS if k != "run"}

    def timed(key, f, *a, **kw):
        t = time.process_time()
        r = f(*a, **kw)
        steps[key].append(time.process_time() - t)
        return r

    seq.load(0)  # caches (ORB objects), imports
    for i in range(len(seq)):
        left, right = timed("read", seq.rectified_pair, i)
        det = timed("left", detect, left, fc)
        uv_r, desc_r = timed("right_orb", orb_features, right, fc_right, **right_kw)[:2]
        il, ir = timed("match", match_rows, det.uv_raw, det.desc, uv_r, desc_r, sc)
        u0, v0 = np.rint(det.uv_raw[il, 0]), np.rint(det.uv_raw[il, 1])
        timed("refine", refine_disparity, left, right, u0, v0, uv_r[ir, 0] + (u0 - det.uv_raw[il, 0]),
              sc.patch_radius, sc.search_radius, sc.subpixel)
        timed("stereo", sparse_matches, left, right, seq.rig, det.uv_raw, det.desc, sc, fc)
        timed("load", seq.load, i)
    res = {k: 1e3 * float(np.median(v)) for k, v in steps.items()}
    t = time.process_time()
    summary = run_sequence(seq, out, cfg, progress=False)
    res["run"] = 1e3 * (time.process_time() - t) / max(1, summary["frames"])
    res["ate"] = ((summary.get("evaluation") or {}).get("ate") or {}).get("rmse")
    res["trajectory"] = str(out / "trajectory.tum")
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trees", nargs=2, metavar=("OLD", "NEW"), default=[str(HERE.parent.parent)] * 2,
                    help="two rgbdslam checkouts, A/B (default: this one twice)")
    ap.add_argument("--reps", type=int, default=3, help="interleaved rounds (each runs both trees)")
    ap.add_argument("--sequence", type=Path, default=KITTI)
    ap.add_argument("--config", default="kitti")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rgbdslam_stereo_reader"))
    ap.add_argument("--json", type=Path, help="write the rounds here")
    ap.add_argument("--one", type=Path, help=argparse.SUPPRESS)  # child: measure this tree, write JSON here
    args = ap.parse_args()
    if args.one is not None:
        res = measure(args.sequence, args.config, args.one.with_suffix(""))
        args.one.write_text(json.dumps(res))
        return
    rounds = []
    for k in range(args.reps):
        row = {}
        for name, tree in zip(("old", "new"), args.trees):
            out = args.work / f"{name}_{k}.json"
            out.parent.mkdir(parents=True, exist_ok=True)
            env = dict(os.environ, PYTHONPATH=str(Path(tree).resolve()))
            subprocess.run([sys.executable, str(HERE), "--one", str(out), "--sequence", str(args.sequence),
                            "--config", args.config], env=env, check=True, stdout=subprocess.DEVNULL)
            row[name] = json.loads(out.read_text())
        row["identical"] = Path(row["old"]["trajectory"]).read_bytes() == Path(row["new"]["trajectory"]).read_bytes()
        rounds.append(row)
        print(f"round {k}: load {row['old']['load']:.1f} / {row['new']['load']:.1f} ms, trajectories "
              f"{'identical' if row['identical'] else 'DIFFER'}", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"trees": args.trees, "rounds": rounds}, indent=1))
    print(f"\n{args.sequence.name}, `--config {args.config}`, {args.reps} interleaved rounds; CPU ms per pair "
          f"(medians over the pairs, then over the rounds)\n")
    print("| step | before | after | after / before |")
    print("|---|---|---|---|")
    for key, label in STEPS:
        a = float(np.median([r["old"][key] for r in rounds]))
        b = float(np.median([r["new"][key] for r in rounds]))
        print(f"| {label} | {a:.2f} | {b:.2f} | {b / a:.2f} |")
    ates = {f"{r['old']['ate']:.4f} / {r['new']['ate']:.4f}" for r in rounds}
    print(f"\nATE (m) before / after: {', '.join(sorted(ates))}; trajectory files byte-identical in "
          f"{sum(r['identical'] for r in rounds)} of {len(rounds)} rounds")


if __name__ == "__main__":
    main()
