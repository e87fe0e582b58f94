"""Scale and speed: the whole command against its tracking, start-up, the map fused
while tracking against fusing the final poses, a sweep on the local pool and on Ray, and the
memory of a long run. One command gives the whole table.

Usage::

    python -m benchmarks.scale [--work DIR] [--parts run,sweep,memory]
                                            [--long-frames 5000] [--repeat 3] [--write-docs]

* run: ``rgbdslam run`` on TUM fr1/rpy head200 (preset tum_fr1), as a user starts it (a new
  process, wall time from start to exit), with the map fused while tracking (default), fused after
  the run (``mapping.live=false``) and without a map. Reported: the whole-command rate (frames /
  wall) over the tracking rate the same run writes to run.json (``fps``), the time from the
  process start to the first tracked frame (run.json ``first_frame_s``), and ``rgbdslam --help``.
  The live map is compared with ``rgbdslam fuse`` of the same run folder (the final poses fused
  from scratch): cloud points and nearest-neighbour distances, mesh vertices.
* sweep: 12 cells — 3 sequences (fr1/desk 9 frames and two 40-frame synthetic sequences) x
  ``loop.enabled`` x ``depth_filter.enabled`` — with ``rgbdslam sweep``: in one process, on the
  local process pool (2 workers), on a new local Ray cluster (2 CPUs; the wall time includes
  starting it) and on a running 2-CPU cluster (``ray start --head --block`` on a private port,
  ``--address``; stopped afterwards), ``--repeat`` times interleaved (medians).
  The tables must be identical apart from the timing columns.
* memory: ``rgbdslam run`` (map fused while tracking) on a long synthetic ``loop`` sequence
  (320x240); the resident memory of the run process and of its map process, sampled every 0.5 s,
  at every 1000 frames (frames tracked read from odometry.tum, flushed every 50 frames).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import shlex
import shutil
import statistics
import subprocess
import sys
import time
from datetime import date
from pathlib import Path

from benchmarks.common import DATA

from benchmarks.common import publish_markdown as publish, reference_timing

RPY = DATA / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
DESK = DATA / "tum" / "rgbd_dataset_freiburg1_desk_9frames"
BIN = Path(sys.executable).parent / "rgbdslam"
TIMING = ("tracking_fps", "cell_fps", "cell_s")


def sh(args, **kw) -> float:
    """Run a command; its wall time (s). Fails loudly."""
    t0 = time.perf_counter()
    subprocess.run([str(a) for a in args], check=True, stdout=subprocess.DEVNULL, **kw)
    return time.perf_counter() - t0


# ------------------------------------------------------------------------------------------ run


def _cloud(path: Path):
    import numpy as np
    import open3d as o3d

    return np.asarray(o3d.io.read_point_cloud(str(path)).points)


def _compare_maps(live_dir: Path, work: Path) -> dict:
    """The live map of a run against `rgbdslam fuse` of a copy of its folder: nearest-neighbour
    distances both ways (live -> fused and fused -> live), percentiles and the share within the
    default tolerance (2.5 mm)."""
    import numpy as np
    import open3d as o3d
    from scipy.spatial import cKDTree

    ref = work / f"refused_{live_dir.name}"
    shutil.rmtree(ref, ignore_errors=True)
    shutil.copytree(live_dir, ref, ignore=shutil.ignore_patterns("map", "previous"))
    sh([BIN, "fuse", ref, "-q"])
    out = {}
    for what, a, b in (
            ("cloud", _cloud(live_dir / "map" / "cloud.ply"), _cloud(ref / "map" / "cloud.ply")),
            ("mesh", np.asarray(o3d.io.read_triangle_mesh(str(live_dir / "map" / "mesh.ply")).vertices),
             np.asarray(o3d.io.read_triangle_mesh(str(ref / "map" / "mesh.ply")).vertices))):
        d = np.concatenate([cKDTree(b).query(a)[0], cKDTree(a).query(b)[0]]) * 1e3
        out[what] = {"live": len(a), "fused": len(b), "same": float(np.mean(d < 1e-3)),
                     "within": float(np.mean(d <= 2.5)), "p50": float(np.median(d)),
                     "p99": float(np.percentile(d, 99)), "max": float(d.max())}
    return out


RUN_VARIANTS = {  # --variants: key -> (row name, extra arguments of `rgbdslam run`)
    "default": ("map fused while tracking (default)", []),
    "nice0": ("map fused while tracking, map process at tracking's priority (mapping.live_nice=0)",
              ["--set", "mapping.live_nice=0"]),
    "nobacklog": ("map fused while tracking, never at tracking's priority (mapping.live_backlog=10000: before 2026-12-02 06:00)",
                  ["--set", "mapping.live_backlog=10000"]),
    "voxel": ("map fused while tracking, voxel outlier removal of the cloud (mapping.outlier_method=voxel)",
              ["--set", "mapping.outlier_method=voxel"]),
    "lag0": ("map fused while tracking, every keyframe into the map at once (mapping.live_lag=0)",
             ["--set", "mapping.live_lag=0"]),
    "tol1": ("map fused while tracking, mapping.live_tolerance=1 (1 voxel)", ["--set", "mapping.live_tolerance=1"]),
    "after": ("map fused after the run (mapping.live=false)", ["--set", "mapping.live=false"]),
    "nomap": ("no map (--no-map)", ["--no-map"]),
}


def part_run(work: Path, keys: list[str]) -> list[str]:
    rows = []
    help_s = statistics.median(sh([BIN, "--help"]) for _ in range(3))
    variants = [RUN_VARIANTS[k] for k in keys]
    runs = {}
    after_rows = []
    ratios = []
    for k, (name, extra) in enumerate(variants):
        out = work / f"rpy_{k}"
        shutil.rmtree(out, ignore_errors=True)
        load = os.getloadavg()[0]
        wall = sh([BIN, "run", RPY, "-c", "tum_fr1", "--out", out, "-q", *extra])
        info = json.loads((out / "run.json").read_text())
        runs[name] = out
        whole = info["frames"] / wall
        m = info.get("map") or {}
        t = m.get("timings") or {}
        moved = (f"{t['final_moved']} of {m['frames_fused']} ({t['final_shift_median_mm']:.1f} / "
                 f"{t['final_shift_max_mm']:.1f} mm)" if "final_moved" in t else "-")
        ratios.append((name, whole / info["fps"], wall))
        rows.append(f"| {name} | {load:.1f} | {wall:.1f} | {whole:.1f} | {info['fps']:.1f} | {whole / info['fps']:.2f} | "
                    f"{info.get('first_frame_s') or float('nan'):.2f} | {m.get('seconds', float('nan')):.1f} | {moved} |")
        a = info.get("after_tracking_s") or {}
        rest = wall - (info.get("first_frame_s") or 0) - info["wall_time_s"] - a.get("total", 0)
        after_rows.append(f"| {name} | {info['wall_time_s']:.1f} | " + " | ".join(
            f"{a.get(k, float('nan')):.2f}" for k in ("pose_graph", "outputs", "evaluation", "map", "plots", "recording",
                                                      "total"))
            + f" | {rest:.2f} | {t.get('final_s', float('nan')):.2f} | {t.get('cloud', float('nan')):.2f} | "
              f"{t.get('mesh', float('nan')):.2f} | {t.get('map2d', float('nan')):.2f} | {t.get('final_waiting', '-')} | "
              f"{a.get('cpu', float('nan')):.2f} | {t.get('final_cpu_s', float('nan')):.2f} |")
    cmps = [(RUN_VARIANTS[k][0], _compare_maps(runs[RUN_VARIANTS[k][0]], work)) for k in dict.fromkeys(keys)
            if k in ("default", "nice0", "lag0", "tol1", "nobacklog", "voxel")]
    live_lines = []
    for name, out in runs.items():  # what the map process did, in the runs with a live map
        info = json.loads((out / "run.json").read_text())
        t = (info.get("map") or {}).get("timings") or {}
        if "integrated" in t:
            live_lines.append(
                f"* {name}: {t.get('integrated', 0) - t.get('final_waiting', 0)} keyframes integrated while tracking "
                f"({t.get('final_waiting', 0)} at the end), {t.get('refreshes')} pose "
                f"updates applied ({t.get('pose_updates_skipped')} coalesced), {t.get('deintegrated')} keyframes "
                f"de-integrated, {t.get('reintegrated')} re-integrated, {t.get('rebuilds')} rebuilds; busy "
                f"{t.get('busy_s', 0):.1f} s ({t.get('busy_cpu_s', float('nan')):.1f} s of CPU) during "
                f"{info['wall_time_s']:.1f} s of tracking, of which {t.get('catch_up_s', 0):.1f} s "
                f"({t.get('catch_up_cpu_s', 0):.1f} s of CPU) at tracking's priority in {t.get('catch_ups', 0)} "
                f"catch-ups (mapping.live_backlog) while tracking; "
                f"the cloud process's CPU after the last frame: outlier removal {t.get('cloud_cpu_s', float('nan')):.2f} s, "
                f"2-D map {t.get('map2d_cpu_s', float('nan')):.2f} s; "
                f"keyframes moved more than the tolerance at the end (mm): "
                f"{t.get('final_shift_mm', '-')}; the end's timeline (s after the run sent the final poses): "
                f"{t.get('end_timeline', '-')}.")
    lines = [
        *[f"**Whole-command rate / tracking rate: {r:.2f}** (target >= 0.8; wall {w:.1f} s) - {name}"
          for name, r, w in ratios],
        "",
        f"`rgbdslam --help`: {help_s:.2f} s (median of 3).",
        "",
        "| run | load before | wall s | whole-command frames/s | tracking frames/s (run.json) | ratio | first tracked frame s "
        "| map after tracking s | keyframes redone at the end (shift median / max) |",
        "|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        "After the last frame (run.json `after_tracking_s`; the map's own steps from its timings), seconds:",
        "",
        "| run | tracking | final pose graph | outputs | evaluation (+ plots when drawn in the run) | waiting for the map "
        "| waiting for the plot process | Rerun | total "
        "| wall − first frame − tracking − total (the exit, less the first frame's own tracking time) | map: bring to final poses "
        "| map: cloud (outliers, cloud.ply) | map: mesh | map: 2-D map | keyframes still waiting at the end (integrated once) "
        "| CPU s of the run process after the last frame | CPU s of the map process after the last frame |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        *after_rows,
        "",
        "Map process:",
        "",
        *live_lines,
        "",
        "Live map against `rgbdslam fuse` of the same run folder (the final poses fused from scratch); "
        "nearest-neighbour distances both ways (live to fused and fused to live):",
        "",
        "| run | map | points / vertices live / fused | same (< 1 µm) | within 2.5 mm | median / p99 / max mm |",
        "|---|---|---|---|---|---|",
        *[f"| {name} | {what} | {c[what]['live']} / {c[what]['fused']} | {100 * c[what]['same']:.1f}% | "
          f"{100 * c[what]['within']:.2f}% | {c[what]['p50']:.2f} / {c[what]['p99']:.2f} / {c[what]['max']:.1f} |"
          for name, c in cmps for what in ("cloud", "mesh")],
    ]
    return lines


# ---------------------------------------------------------------------------------------- sweep


def _synth(work: Path, name: str, motion: str, seed: int, frames: int, size=(320, 240)) -> Path:
    from rgbdslam.datasets.synthetic import generate_sequence

    d = work / name
    if not (d / "groundtruth.txt").is_file():
        generate_sequence(d, frames=frames, motion=motion, width=size[0], height=size[1], noise=True, seed=seed)
    return d


def _table(path: Path):
    return [{k: v for k, v in r.items() if k not in TIMING} for r in csv.DictReader(open(path))]


class _RayHead:
    """A Ray cluster started like a user would (``ray start --head --block``) on a private port and
    temporary folder (so no other ``ray.init()`` on this machine finds it), stopped by ending
    that command (``--block``: its processes go with it; never ``ray stop``, which ends every Ray
    on the machine)."""

    def __init__(self, work: Path, cpus: int = 2, port: int = 6391):
        ray = Path(sys.executable).parent / "ray"
        self.tmp = Path("/tmp") / f"rgbdslam_bench_ray_{os.getpid()}"  # short: Ray's socket paths must fit
        self.address = f"127.0.0.1:{port}"
        self.log = open(work / "ray_head.log", "w")
        self.proc = subprocess.Popen([str(ray), "start", "--head", "--block", "--port", str(port), "--num-cpus",
                                      str(cpus), "--include-dashboard", "false", "--disable-usage-stats",
                                      "--temp-dir", str(self.tmp)], stdout=self.log, stderr=subprocess.STDOUT)
        t0 = time.perf_counter()
        while "Ray runtime started" not in (work / "ray_head.log").read_text():
            if self.proc.poll() is not None or time.perf_counter() - t0 > 300:
                raise SystemExit(f"ray start failed; see {work / 'ray_head.log'}")
            time.sleep(0.5)
        self.start_s = time.perf_counter() - t0

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=120)
        self.log.close()
        shutil.rmtree(self.tmp, ignore_errors=True)


def part_sweep(work: Path, repeat: int = 1) -> list[str]:
    seqs = [DESK, _synth(work, "synth_loop", "loop", 1, 40), _synth(work, "synth_xyz", "xyz", 2, 40)]
    grid = ["--grid", "loop.enabled=true,false", "--grid", "depth_filter.enabled=true,false"]
    base = [BIN, "sweep", *seqs, *grid, "-q"]
    head = _RayHead(work)
    try:
        variants = [("one process (--engine local --workers 1)", []),
                    ("local process pool (--engine local --workers 2)", ["--workers", "2"]),
                    ("Ray, new local cluster (--engine ray --workers 2; includes starting it)",
                     ["--engine", "ray", "--workers", "2"]),
                    (f"Ray, running 2-CPU cluster (--engine ray --address; `ray start --head` took "
                     f"{head.start_s:.0f} s before)", ["--engine", "ray", "--address", head.address])]
        walls: dict[str, list[float]] = {name: [] for name, _ in variants}
        tables = {}
        for r in range(repeat):  # interleaved: the machine's load changes alike for every variant
            for k, (name, extra) in enumerate(variants):
                out = work / f"sweep_{k}"
                shutil.rmtree(out, ignore_errors=True)
                load = os.getloadavg()[0]
                wall = sh([*base, "--out", out, *extra])
                walls[name].append(wall)
                with open(work / "sweep_walls.txt", "a") as f:  # as it goes
                    f.write(f"{r}\t{name}\t{wall:.1f}\tload {load:.1f}\n")
                tables[name] = _table(out / "results.csv")
    finally:
        head.stop()
    med = {name: statistics.median(w) for name, w in walls.items()}
    ref = med[variants[1][0]]
    one = tables[variants[0][0]]
    lines = [f"Median of {repeat} interleaved repetitions (each row's walls in brackets).", "",
             "| engine | cells | wall s (median) | / local pool | table identical to one process |",
             "|---|---|---|---|---|"]
    for name, _ in variants:
        lines.append(f"| {name} | {len(tables[name])} | {med[name]:.1f} ({', '.join(f'{w:.0f}' for w in walls[name])})"
                     f" | {med[name] / ref:.2f} | {'yes' if tables[name] == one else 'NO'} |")
    ok = [r for r in one if r["status"] == "ok"]
    lines += ["", f"{len(ok)} of {len(one)} cells ok; ATE of the cells (m): "
              + ", ".join(f"{Path(r['sequence']).name[:12]}/{r['loop.enabled']}/{r['depth_filter.enabled']}="
                          f"{float(r['ate_rmse']):.4f}" for r in ok)]
    return lines


# --------------------------------------------------------------------------------------- memory


def _rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def _children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def part_memory(work: Path, frames: int) -> list[str]:
    seq = _synth(work, f"synth_long_{frames}", "loop", 0, frames)
    out = work / "long_run"
    shutil.rmtree(out, ignore_errors=True)
    proc = subprocess.Popen([str(BIN), "run", str(seq), "--out", str(out), "-q"], stdout=subprocess.DEVNULL)
    samples = []  # (frames tracked, main MB, map process MB)
    t0 = time.perf_counter()
    log = open(work / "long_samples.csv", "w")  # as it goes: a long run stopped part-way still tells
    log.write("seconds,frames,run_mb,map_mb\n")
    while proc.poll() is None:
        try:
            n = sum(1 for _ in open(out / "odometry.tum")) - 1
        except OSError:
            n = 0
        kids = _children(proc.pid)
        samples.append((n, _rss_mb(proc.pid), sum(_rss_mb(c) for c in kids)))
        log.write(f"{time.perf_counter() - t0:.1f},{n},{samples[-1][1]:.0f},{samples[-1][2]:.0f}\n")
        log.flush()
        time.sleep(0.5)
    wall = time.perf_counter() - t0
    if proc.returncode:
        raise SystemExit(f"long run failed ({proc.returncode})")
    info = json.loads((out / "run.json").read_text())
    lines = ["| frames tracked | run process MB | map process MB | total MB |", "|---|---|---|---|"]
    for mark in range(1000, frames + 1, 1000):
        at = [s for s in samples if s[0] >= mark - 50]
        if at:
            n, a, b = at[0]
            lines.append(f"| {mark} | {a:.0f} | {b:.0f} | {a + b:.0f} |")
    sizes = ((info.get("map") or {}).get("timings") or {}).get("size_log") or []
    if sizes:  # what the map process holds, every 100 keyframes (rgbdslam.mapping.live.MapState.sizes)
        lines += ["", "| keyframes in the map | map process MB | TSDF blocks used / allocated | TSDF MB (allocated) "
                  "| cloud voxels | cached keyframe images MB |", "|---|---|---|---|---|---|"]
        lines += [f"| {e['keyframes']} | {e['rss_mb']:.0f} | {e.get('tsdf_blocks', 0)} / {e.get('tsdf_capacity_blocks', 0)} "
                  f"| {e.get('tsdf_mb', 0):.0f} | {e.get('cloud_voxels', 0)} | {e['cache_mb']:.0f} |" for e in sizes]
    peak = max(samples, key=lambda s: s[1] + s[2]) if samples else (0, 0, 0)
    lines += ["", f"{frames} frames in {wall:.0f} s (tracking {info['fps']:.1f} frames/s), "
              f"{len(info['keyframes'])} keyframes, {len(info['loops'])} loops, ATE "
              f"{((info.get('evaluation') or {}).get('ate') or {}).get('rmse', float('nan')):.4f} m; peak "
              f"{peak[1] + peak[2]:.0f} MB at {peak[0]} frames; map {info.get('map', {}).get('cloud_points')} points."]
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_scale"))
    ap.add_argument("--parts", default="run,sweep,memory")
    ap.add_argument("--long-frames", type=int, default=5000)
    ap.add_argument("--repeat", type=int, default=3, help="interleaved repetitions of the sweep variants")
    ap.add_argument("--variants", default=",".join(RUN_VARIANTS),
                    help=f"runs of the 'run' part, in this order (of {', '.join(RUN_VARIANTS)})")
    ap.add_argument("--write-docs", action="store_true")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    parts = a.parts.split(",")
    cmd = "python -m benchmarks.scale " + " ".join(shlex.quote(x) for x in sys.argv[1:])
    out = ["## Scale", "", f"Command: `{cmd}`  ",
           f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
           f"{date.today().isoformat()}; shared with other jobs, so compare ratios within this run.  ",
           f"Speed of the machine: {reference_timing()}; load average at the start {os.getloadavg()[0]:.1f} "
           f"(1 min).", ""]
    if "run" in parts:
        out += ["### Whole command, start-up, live map (TUM fr1/rpy head200)", "", *part_run(a.work, a.variants.split(",")), ""]
    if "sweep" in parts:
        out += ["### Sweep: 12 cells over 3 sequences", "", *part_sweep(a.work, a.repeat), ""]
    if "memory" in parts:
        out += [f"### Memory of a {a.long_frames}-frame run (map fused while tracking)", "",
                *part_memory(a.work, a.long_frames), ""]
    return publish("\n".join(out), a.write_docs)


if __name__ == "__main__":
    raise SystemExit(main())
