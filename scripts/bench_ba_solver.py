"""The local BA's two solvers on the problems of a real run: GTSAM's graph against the NumPy Schur complement.

Usage::

    .venv/bin/python scripts/bench_ba_solver.py [--sequence DIR] [--set KEY=VALUE] ... [--repeat 3] [--json FILE]

Runs ``rgbdslam.pipeline.run_sequence`` on the sequence (default TUM fr1/rpy head200) with
``landmarks.enabled=true landmarks.local_ba=true landmarks.ba_solver=gtsam`` (plus ``--set``; map
fusion and plots off) and records every local BA problem (``BAProblem``) the run made; then solves
each one with ``ba_solver=gtsam`` and ``ba_solver=schur``, alternating, ``--repeat`` times, and
prints the CPU time (``time.process_time``: less sensitive to a shared machine's load than wall
time) per problem of each (median over problems of the best of the repeats, and the sum), their
ratio, the largest difference of a refined keyframe pose (matrix entries) and landmark position
(metres), the largest relative difference of the final graph error, and the problem sizes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def record_problems(sequence: Path, out: Path, sets: list[str]):
    """(problems, camera) of one run: every local BA problem, in order."""
    import rgbdslam.landmarks.local_ba as lb
    from rgbdslam.config import load_config
    from rgbdslam.pipeline import run_sequence

    problems, cams = [], []
    solve = lb.solve_problem

    def recording(cfg, factors, p):
        problems.append((cfg, p))
        cams.append(factors.camera)
        return solve(cfg, factors, p)

    lb.solve_problem = recording
    try:
        cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", "landmarks.enabled=true",
                                 "landmarks.local_ba=true", "landmarks.ba_solver=gtsam", *sets])
        run_sequence(sequence, out, cfg, progress=False)
    finally:
        lb.solve_problem = solve
    return problems, (cams[0] if cams else None)


def compare(problems, camera, repeat: int) -> dict:
    from rgbdslam.landmarks.local_ba import StereoFactors, solve_problem

    cpu = {"gtsam": [], "schur": []}
    d_pose, d_lm, d_err = 0.0, 0.0, 0.0
    sizes = []
    for cfg, p in problems:
        best, res = {}, {}
        for _ in range(repeat):
            for solver in ("gtsam", "schur"):
                c = dataclasses.replace(cfg, ba_solver=solver)
                f = StereoFactors(c, camera)
                t = time.process_time()
                res[solver] = solve_problem(c, f, p)
                best[solver] = min(best.get(solver, np.inf), time.process_time() - t)
        for s in cpu:
            cpu[s].append(best[s])
        g, s = res["gtsam"], res["schur"]
        sizes.append((len(p.window - p.fixed), len(p.fixed), len(p.use), sum(len(o[1]) for o in p.obs)))
        if g is None or s is None:
            continue
        for k in g.poses:
            d_pose = max(d_pose, float(np.abs(g.poses[k] - s.poses[k]).max()))
        d_lm = max(d_lm, float(np.abs(g.after - s.after).max()))
        d_err = max(d_err, abs(g.error[1] - s.error[1]) / max(g.error[1], 1e-300))
    sz = np.array(sizes)
    return {"problems": len(problems),
            "gtsam_ms_median": 1e3 * float(np.median(cpu["gtsam"])), "schur_ms_median": 1e3 * float(np.median(cpu["schur"])),
            "gtsam_s_total": float(np.sum(cpu["gtsam"])), "schur_s_total": float(np.sum(cpu["schur"])),
            "ratio_total": float(np.sum(cpu["gtsam"]) / max(np.sum(cpu["schur"]), 1e-12)),
            "max_pose_diff": d_pose, "max_landmark_diff_m": d_lm, "max_rel_error_diff": d_err,
            "free_keyframes_median": float(np.median(sz[:, 0])), "held_keyframes_median": float(np.median(sz[:, 1])),
            "landmarks_median": float(np.median(sz[:, 2])), "observations_median": float(np.median(sz[:, 3]))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequence", type=Path, default=Path(os.environ.get("RGBDSLAM_DATA", ROOT.parent / "shared" / "data"))
                    / "tum" / "rgbd_dataset_freiburg1_rpy_head200")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench_ba_solver_") as tmp:
        problems, camera = record_problems(a.sequence, Path(tmp) / "run", a.set)
    if not problems:
        raise SystemExit("error: the run made no local BA problem")
    r = compare(problems, camera, a.repeat)
    machine = (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
               f"{time.strftime('%Y-%m-%d %H:%M')} UTC, shared; load average {'%.2f %.2f %.2f' % load0} at the start, "
               f"{'%.2f %.2f %.2f' % os.getloadavg()} at the end")
    command = "python " + " ".join(shlex.quote(x) for x in [os.path.relpath(sys.argv[0], ROOT), *sys.argv[1:]])
    print(f"Command: `{command}`  \nMachine: {machine}\n")
    print("| problems | free / held keyframes (median) | landmarks / observations (median) | GTSAM CPU ms (median) | "
          "Schur CPU ms (median) | CPU total GTSAM / Schur | max pose diff | max landmark diff (m) | max rel. error diff |")
    print("|---|---|---|---|---|---|---|---|---|")
    print(f"| {r['problems']} | {r['free_keyframes_median']:.0f} / {r['held_keyframes_median']:.0f} | "
          f"{r['landmarks_median']:.0f} / {r['observations_median']:.0f} | {r['gtsam_ms_median']:.1f} | "
          f"{r['schur_ms_median']:.1f} | {r['gtsam_s_total']:.2f} s / {r['schur_s_total']:.2f} s "
          f"({r['ratio_total']:.1f}x) | {r['max_pose_diff']:.1e} | {r['max_landmark_diff_m']:.1e} | "
          f"{r['max_rel_error_diff']:.1e} |")
    if a.json is not None:
        a.json.write_text(json.dumps({"command": command, "machine": machine, **r}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
