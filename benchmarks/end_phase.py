"""The end of a run: what ``rgbdslam run`` does after the last frame is tracked, step by step, for
several versions of the code, interleaved (A B A B ...) so that a changing load hits them alike
(results: docs/speed.md "The end of a run").

Usage::

    python -m benchmarks.end_phase --commits a033124,HEAD [--repeat 3] [--work DIR] [--sequence SEQ]
    OPENBLAS_NUM_THREADS=1 python -m benchmarks.end_phase --steps RUN_DIR [--repeat 3]

Each commit's ``rgbdslam`` package is exported (``git archive``) into ``WORK/code-<commit>`` and run
with ``PYTHONPATH`` pointing there (its helper processes inherit it), on TUM fr1/rpy head200 with
the preset ``tum_fr1`` and the map fused while tracking. Reported per run, from run.json: the
whole command's wall time, the tracking time (frames / ``fps``), the wall time after the last frame
(``after_tracking_s.total``), the CPU seconds each process spent after the last frame (the run's
``after_tracking_s.cpu``, the map process's ``map.timings.final_cpu_s``, the cloud process's outlier
removal ``cloud_cpu_s`` and 2-D map ``map2d_cpu_s``), the keyframes integrated at the end
(``final_waiting``), and the end's timeline (``map.timings.end_timeline``: seconds
after the final poses were sent). CPU seconds depend less on the machine's load than wall seconds.

``--steps RUN_DIR``: each step of the end alone, in this process, on a finished run's keyframes at
their final poses (CPU and wall seconds, medians of ``--repeat``): a keyframe's TSDF and cloud
integration, the cloud's points, both outlier removals, the floor search and the rest of the 2-D
map, the mesh (marching cubes and canonical order; normals and mesh.ply). Run it with
``OPENBLAS_NUM_THREADS=1``, as the helper processes run.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from benchmarks.common import DATA

RPY = DATA / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
BIN = Path(sys.executable).parent / "rgbdslam"
ROOT = Path(__file__).resolve().parents[1]


def export(commit: str, work: Path) -> Path:
    """The ``rgbdslam`` package of ``commit`` in ``work``/code-<short hash> (exported once)."""
    sha = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", commit], check=True,
                         capture_output=True, text=True).stdout.strip()
    dest = work / f"code-{sha}"
    if not (dest / "rgbdslam").is_dir():
        dest.mkdir(parents=True, exist_ok=True)
        tar = subprocess.run(["git", "-C", str(ROOT), "archive", sha, "rgbdslam"], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dest)], input=tar, check=True)
    return dest


def one_run(code: Path, seq: Path, out: Path) -> dict:
    """A whole ``rgbdslam run`` with ``code``'s package; the end's numbers from its run.json."""
    env = dict(os.environ, PYTHONPATH=str(code))
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    subprocess.run([str(BIN), "run", str(seq), "-c", "tum_fr1", "--out", str(out), "-q"], env=env, check=True,
                   stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    info = json.loads((out / "run.json").read_text())
    t = info["map"]["timings"]
    a = info["after_tracking_s"]
    cpu = {"run": a["cpu"], "map": t["final_cpu_s"], "outliers": t.get("cloud_cpu_s", 0.0),
           "map2d": t.get("map2d_cpu_s", 0.0)}
    return {"load": load, "wall": wall, "tracking": info["frames"] / info["fps"], "after": a["total"],
            "first": info["first_frame_s"], "cpu": cpu, "end_cpu": sum(cpu.values()),
            "waiting": t.get("final_waiting", 0), "timeline": t.get("end_timeline", {})}


def timed(f, *args, repeat: int = 3, **kw):
    """``f(*args, **kw)`` ``repeat`` times: (its last value, median CPU s, median wall s)."""
    cpu, wall = [], []
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        out = f(*args, **kw)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - t0)
    return out, statistics.median(cpu), statistics.median(wall)


def steps(run_dir: Path, repeat: int) -> None:
    """The end's steps one by one on ``run_dir``'s keyframes at their final poses (see the module doc)."""
    import tempfile

    import numpy as np

    from rgbdslam.datasets import open_sequence
    from rgbdslam.mapping.fusion import (VoxelCloud, Tsdf, Undistorter, cloud_points, integrate_frame, match_frames,
                                         prepare_frame, statistical_keep, voxel_keep, write_mesh)
    from rgbdslam.mapping.map2d import build_map2d, find_floor, up_from_cameras, write_map2d
    from rgbdslam.runfolder.depth import keyframe_depth_path, read_keyframe_depth
    from rgbdslam.runfolder.read import read_run
    from rgbdslam.ui import console

    info, run_cfg, traj = read_run(run_dir)
    cfg = run_cfg.mapping
    seq = open_sequence(info["sequence"], run_cfg, purpose="map")
    rows = match_frames(np.asarray(seq.timestamps), traj)
    und = Undistorter(seq.camera, cfg.undistort)
    tsdf, cloud = Tsdf(cfg, seq.camera), VoxelCloud(cfg.voxel_size)
    cost = {"TSDF": [0.0, 0.0], "cloud": [0.0, 0.0]}
    kfs = [int(i) for i in info["keyframes"]]
    for i in kfs:
        frame = seq.load(i)
        png = keyframe_depth_path(run_dir / "keyframes", i)
        rgb, depth = prepare_frame(frame.rgb, read_keyframe_depth(png) if png.is_file() else frame.depth, und, cfg)
        pose = traj.poses[rows[i]]
        for part, args in (("TSDF", (tsdf, None)), ("cloud", (None, cloud))):
            _, c, w = timed(integrate_frame, *args, rgb, depth, pose, seq.camera, cfg, repeat=1)
            cost[part][0] += c
            cost[part][1] += w
    lines = [(f"a keyframe's {part} integration (mean of {len(kfs)})", c / len(kfs), w / len(kfs))
             for part, (c, w) in cost.items()]
    (points, colors), c, w = timed(cloud_points, cloud, cfg, repeat=1)  # once: it merges the pending parts
    lines.append((f"the cloud's points ({len(points)}; the pending parts merged)", c, w))
    keep, c, w = timed(statistical_keep, points, cfg, repeat=repeat)
    lines.append((f"statistical outlier removal ({len(keep)} kept)", c, w))
    kept_v, c, w = timed(voxel_keep, points, cfg.voxel_size, cfg.outlier_min_neighbors, cfg.outlier_radius,
                         repeat=repeat)
    lines.append((f"voxel outlier removal ({len(kept_v)} kept)", c, w))
    kept = points[keep].astype(np.float32)
    acc = Path(info["sequence"]) / "accelerometer.txt"
    _, c, w = timed(find_floor, kept.astype(np.float64), up_from_cameras(traj), cfg, repeat=repeat)
    lines.append(("2-D map: the floor (RANSAC, refit)", c, w))
    grid, c, w = timed(build_map2d, kept, traj, cfg, accelerometer=acc if acc.is_file() else None, repeat=repeat)
    lines.append(("2-D map: all of build_map2d (floor included)", c, w))
    with tempfile.TemporaryDirectory() as tmp:
        _, c, w = timed(write_map2d, grid, tmp, traj, repeat=repeat)
        lines.append(("2-D map: its three files", c, w))
        mesh, c, w = timed(tsdf.mesh, max(1, min(cfg.mesh_min_frames, len(kfs))), repeat=repeat)
        lines.append((f"mesh: marching cubes and canonical order ({len(mesh.triangles)} triangles)", c, w))
        _, c, w = timed(write_mesh, Path(tmp), tsdf, len(kfs), cfg, console, repeat=repeat)
        lines.append(("mesh: all of write_mesh (marching cubes, normals, mesh.ply)", c, w))
    print(f"{run_dir} ({len(kfs)} keyframes), OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', '-')}\n")
    print("| step | CPU s | wall s |")
    print("|---|---|---|")
    for name, c, w in lines:
        print(f"| {name} | {c:.3f} | {w:.3f} |")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--commits", default="main,HEAD", help="comma-separated commits, run in this order each round")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--work", type=Path, default=Path("/tmp/end_phase"))
    ap.add_argument("--sequence", type=Path, default=RPY)
    ap.add_argument("--steps", type=Path, metavar="RUN_DIR", help="time the end's steps on this run folder instead")
    args = ap.parse_args(argv)
    if args.steps is not None:
        steps(args.steps, args.repeat)
        return
    commits = args.commits.split(",")
    codes = {c: export(c, args.work) for c in commits}
    runs: dict[str, list[dict]] = {c: [] for c in commits}
    for r in range(args.repeat):
        for c in commits:
            runs[c].append(one_run(codes[c], args.sequence, args.work / f"run-{codes[c].name}-{r}"))
    print(f"{args.sequence.name}, {os.cpu_count()} cores; seconds; CPU after the last frame per process\n")
    print("| code | round | load | whole | tracking | whole / tracking | after the last frame | CPU: run | map process "
          "| outlier removal | 2-D map | CPU total | keyframes at the end | outliers done | 2-D map done "
          "| mesh done | first frame |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in range(args.repeat):
        for c in commits:
            x = runs[c][r]
            tl = x["timeline"]
            print(f"| {codes[c].name[5:]} | {r + 1} | {x['load']:.1f} | {x['wall']:.1f} | {x['tracking']:.1f} | "
                  f"{x['wall'] / x['tracking']:.2f} | {x['after']:.2f} | {x['cpu']['run']:.2f} | {x['cpu']['map']:.2f} | "
                  f"{x['cpu']['outliers']:.2f} | {x['cpu']['map2d']:.2f} | {x['end_cpu']:.2f} | "
                  f"{x['waiting']} | {tl.get('outliers_done', float('nan')):.2f} | "
                  f"{tl.get('map2d_done', float('nan')):.2f} | {tl.get('mesh_done', float('nan')):.2f} | {x['first']:.2f} |")
    print()
    for c in commits:
        med = lambda f: statistics.median(f(x) for x in runs[c])  # noqa: E731
        print(f"* {codes[c].name[5:]} ({c}): medians of {args.repeat}: after the last frame {med(lambda x: x['after']):.2f} s, "
              f"CPU {med(lambda x: x['end_cpu']):.2f} s (map process {med(lambda x: x['cpu']['map']):.2f}, outlier "
              f"removal {med(lambda x: x['cpu']['outliers']):.2f}, 2-D map {med(lambda x: x['cpu']['map2d']):.2f}, "
              f"run {med(lambda x: x['cpu']['run']):.2f}); whole / tracking {med(lambda x: x['wall'] / x['tracking']):.2f}")


if __name__ == "__main__":
    main()
