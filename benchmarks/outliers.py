"""The cloud's two outlier filters (mapping.outlier_method statistical / voxel) on the real cloud
of finished runs: CPU time (median of repeats, in one sitting), which points each keeps, how far
the points each removes lie from the run's TSDF mesh (speckles and flying pixels lie off the
surface), and the 2-D maps of the two kept clouds.

    python -m benchmarks.outliers RUN_DIR... [--repeat 5] [--min 2,3,4,5,6]

RUN_DIR is a finished `rgbdslam run` folder; it is fused again (`fusion.fuse_run`, its map/ is
rewritten, with the run's own configuration and outlier removal off) to get the cloud before outlier
removal and the mesh.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import time
from pathlib import Path

import numpy as np

from rgbdslam.mapping import fusion
from rgbdslam.runfolder.read import read_run


def cloud_before_outliers(run: Path) -> np.ndarray:
    """The run's fused cloud before outlier removal (what the filters get): the run fused again
    with its own configuration, outlier removal off (its map/ is rewritten so)."""
    import open3d as o3d

    _, run_cfg, _ = read_run(run)
    cfg = dataclasses.replace(run_cfg.mapping, outlier_method="statistical", outlier_neighbors=0)
    res = fusion.fuse_run(run, cfg, progress=False)
    return np.asarray(o3d.io.read_point_cloud(str(res.cloud_path)).points, dtype=np.float64)


def cpu(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        c0 = time.process_time()
        fn()
        times.append(time.process_time() - c0)
    return statistics.median(times)


def map2d_diff(points, keep_a, keep_b, run: Path, cfg) -> str:
    """The 2-D maps of two kept clouds: the floor's tilt and height apart and the cells that differ
    (looked up at the first map's cell centres)."""
    from rgbdslam.mapping.map2d import build_map2d

    info, _, traj = read_run(run)
    acc = Path(info["sequence"]) / "accelerometer.txt"
    maps = [build_map2d(points[k].astype(np.float32), traj, cfg, accelerometer=acc if acc.is_file() else None)
            for k in (keep_a, keep_b)]
    a, b = maps
    tilt = np.degrees(np.arccos(np.clip(a.world_to_map[2, :3] @ b.world_to_map[2, :3], -1, 1)))
    h, w = a.image.shape
    rr, cc = np.mgrid[0:h, 0:w]
    flat = np.c_[(a.origin[0] + (cc.ravel() + 0.5) * a.resolution),
                 (a.origin[1] + (h - 1 - rr.ravel() + 0.5) * a.resolution), np.zeros(h * w)]
    inv = np.linalg.inv(a.world_to_map)
    r2, c2 = b.cells(flat @ inv[:3, :3].T + inv[:3, 3])
    ok = (r2 >= 0) & (r2 < b.image.shape[0]) & (c2 >= 0) & (c2 < b.image.shape[1])
    va = a.image.ravel()
    vb = np.full(va.shape, 205, np.uint8)
    vb[ok] = b.image[r2[ok], c2[ok]]
    counts = ", ".join(f"{name} {(va == v).sum()} / {(vb == v).sum()}" for v, name in ((0, "occupied"), (254, "free")))
    return (f"floor {a.floor_source} / {b.floor_source}, {tilt:.2f} deg and "
            f"{abs(a.world_to_map[2, 3] - b.world_to_map[2, 3]) * 1000:.1f} mm apart; cells equal "
            f"{100 * (va == vb).mean():.1f} %; {counts}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--min", default="2,3,4,5,6", help="voxel filter thresholds (outlier_min_neighbors) to compare")
    a = ap.parse_args(argv)
    import open3d as o3d

    print(f"load {os.getloadavg()[0]:.1f} (1 min); CPU s are medians of {a.repeat}")
    for run in a.runs:
        points = cloud_before_outliers(run)
        _, run_cfg, _ = read_run(run)
        cfg = run_cfg.mapping
        n = len(points)
        t_stat = cpu(lambda: fusion.statistical_keep(points, cfg), a.repeat)
        t_vox = cpu(lambda: fusion.voxel_neighbours(points, cfg.voxel_size, cfg.outlier_radius), a.repeat)
        stat = np.zeros(n, bool)
        stat[fusion.statistical_keep(points, cfg)] = True
        counts = fusion.voxel_neighbours(points, cfg.voxel_size, cfg.outlier_radius)
        mesh = o3d.io.read_triangle_mesh(str(run / "map" / "mesh.ply"))
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        d = scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()
        far, near = d > 0.02, d <= 0.005
        print(f"\n### {run} ({n} points; {100 * far.mean():.1f} % more than 2 cm from the mesh, "
              f"{100 * near.mean():.1f} % within 5 mm)\n")
        print(f"CPU s: statistical {t_stat:.3f}, voxel (radius {cfg.outlier_radius}) {t_vox:.3f}\n")
        print("| filter | removes % | both keep % | both remove % | only this removes % | only the other removes % "
              "| of the far points removed % | its removals far % / near % | far points left in the kept cloud % |")
        print("|---|---|---|---|---|---|---|---|---|")

        def row(name, keep, other):
            out = ~keep
            print(f"| {name} | {100 * out.mean():.2f} | {100 * (keep & other).mean():.2f} | "
                  f"{100 * (out & ~other).mean():.2f} | {100 * (out & other).mean():.2f} | "
                  f"{100 * (keep & ~other).mean():.2f} | {100 * (out & far).sum() / far.sum():.1f} | "
                  f"{100 * (out & far).sum() / max(1, out.sum()):.1f} / {100 * (out & near).sum() / max(1, out.sum()):.1f} | "
                  f"{100 * (keep & far).sum() / keep.sum():.2f} |")

        row("statistical", stat, stat)
        for m in (int(v) for v in a.min.split(",")):
            row(f"voxel, min {m}", counts >= m, stat)
        vox = counts >= cfg.outlier_min_neighbors
        print(f"\n2-D maps (statistical / voxel min {cfg.outlier_min_neighbors}): "
              + map2d_diff(points, np.flatnonzero(stat), np.flatnonzero(vox), run, cfg))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
