"""Where the map's time goes (issue 22): the steps of the map fused while tracking, per keyframe
and after the last frame, replayed on a finished run folder, in CPU seconds of one thread
(``OMP_NUM_THREADS=1``: Open3D's threads would otherwise be counted while they spin), so the
numbers hold on a loaded machine too. Also what integrating downsampled images would save and
how far that map is from the full-resolution one.

Usage::

    .venv/bin/python scripts/profile_map.py RUN_DIR      # e.g. the default run of bench_scale.py --parts run

Steps (each keyframe of run.json at its final pose, as `rgbdslam fuse` does):

* per keyframe: read the images, prepare them (undistort, depth range), Open3D's block search
  (``compute_unique_block_coordinates``) and ``integrate``, the voxel cloud's ``add``;
* a re-integration after a loop closure, for 10 keyframes: integrating them into scratch volumes,
  subtracting (``merge_tsdf``, ``add_cloud``) and adding them back;
* after the last frame: the cloud's points, its outlier removal and cloud.ply, marching cubes,
  the canonical vertex order, normals and mesh.ply, the 2-D map, ATE/RPE and the three plots
  (the first drawing of a process, with matplotlib's import, and a second one);
* downsampled integration: depth (nearest) and colour (area) at 1/2 and 1/4 of the size with the
  intrinsics scaled, against the full-resolution TSDF: mesh vertices and their nearest-neighbour
  distances both ways; and the cloud with ``cloud_pixel_stride`` 3 and 4 against 2.
"""

from __future__ import annotations

import os

os.environ["OMP_NUM_THREADS"] = "1"  # before NumPy/Open3D start their thread pools

import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


class Clock:
    """CPU seconds per step (``time.process_time``), summed over calls."""

    def __init__(self):
        self.cpu: dict[str, float] = {}
        self.calls: dict[str, int] = {}

    def __call__(self, name: str, fn, *args, **kw):
        c0 = time.process_time()
        out = fn(*args, **kw)
        self.cpu[name] = self.cpu.get(name, 0.0) + time.process_time() - c0
        self.calls[name] = self.calls.get(name, 0) + 1
        return out


def _nn_agreement(a: np.ndarray, b: np.ndarray, voxel: float) -> str:
    from scipy.spatial import cKDTree

    d = np.concatenate([cKDTree(b).query(a)[0], cKDTree(a).query(b)[0]])
    return (f"{len(a)} / {len(b)} | {100 * np.mean(d <= voxel / 4):.1f}% | {100 * np.mean(d <= voxel):.1f}% | "
            f"{1e3 * np.median(d):.2f} / {1e3 * np.percentile(d, 99):.2f}")


def main() -> int:
    import cv2
    import open3d as o3d
    import open3d.core as o3c

    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.geometry.se3 import inv
    from rgbdslam.io.trajectory import read_tum
    from rgbdslam.mapping import fusion as F
    from rgbdslam.mapping.live import add_cloud, merge_tsdf
    from rgbdslam.mapping.map2d import build_map2d, write_map2d
    from rgbdslam.ui import console

    run = Path(sys.argv[1])
    info = json.loads((run / "run.json").read_text())
    cfg = load_config(run / "config.yaml")
    m = cfg.mapping
    seq = open_sequence(info["sequence"], cfg, purpose="map")
    traj = read_tum(run / "trajectory.tum")
    rows = F.match_frames(np.asarray(seq.timestamps), traj)
    kfs = [i for i in info["keyframes"] if rows[i] >= 0]
    pose = {i: traj.poses[rows[i]] for i in kfs}
    cam = seq.camera
    clk = Clock()
    und = F._Undistorter(cam, m.undistort)
    depth_dir = run / "keyframes"
    prep = {}
    for i in kfs:
        frame = clk("read the images", seq.load, i)
        png = depth_dir / f"depth_{i:06d}.png"
        depth = F.read_depth_png(png) if png.is_file() else frame.depth
        prep[i] = clk("prepare (undistort, depth range)", F.prepare_frame, frame.rgb, depth, und, m)
    tsdf, cloud = F._Tsdf(m, cam), F.VoxelCloud(m.voxel_size)
    for i in kfs:
        rgb, d = prep[i]
        units = np.round(d * F.DEPTH_PNG_SCALE).astype(np.uint16)
        di, ci = o3d.t.geometry.Image(o3c.Tensor(units)), o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(rgb)))
        ext = o3c.Tensor(inv(pose[i]), o3c.float64)
        blocks = clk("TSDF: block search", tsdf.vol.compute_unique_block_coordinates, di, tsdf.intr, ext,
                     F.DEPTH_PNG_SCALE, m.depth_max)
        clk("TSDF: integrate", tsdf.vol.integrate, blocks, di, ci, tsdf.intr, ext, F.DEPTH_PNG_SCALE, m.depth_max,
            m.sdf_trunc / m.tsdf_voxel)
        clk("cloud: add", F.integrate_frame, None, cloud, rgb, d, pose[i], cam, m)
    per_kf = [k for k in clk.cpu]
    sub = kfs[::max(1, len(kfs) // 10)][:10]
    old_t, old_c = F._Tsdf(m, cam), F.VoxelCloud(m.voxel_size)
    for i in sub:
        clk("loop: scratch integration (10 keyframes)", F.integrate_frame, old_t, old_c, *prep[i], pose[i], cam, m)
    for sign in (-1, 1):
        clk("loop: merge_tsdf out and in (10 keyframes)", merge_tsdf, tsdf.vol, old_t.vol, sign)
        clk("loop: add_cloud out and in (10 keyframes)", add_cloud, cloud, old_c, sign)
    stage = Path(tempfile.mkdtemp(prefix="profile_map_"))
    pts, cols = clk("end: cloud points", F.cloud_points, cloud, m)
    _, pts, cols = clk("end: outlier removal + cloud.ply", F.write_cloud, stage, pts, cols, m)
    mesh_t = clk("end: marching cubes", tsdf.vol.extract_triangle_mesh, m.mesh_min_frames - 0.5)
    legacy = clk("end: to legacy mesh", mesh_t.to_legacy)
    full_vertices = np.asarray(legacy.vertices).copy()
    canon = clk("end: canonical vertex order", F.canonical_mesh, legacy)
    clk("end: normals", canon.compute_vertex_normals)
    clk("end: mesh.ply", F._write_ply, stage / "mesh.ply", canon, True)
    acc = Path(info["sequence"]) / "accelerometer.txt"
    grid = clk("end: 2-D map (build)", build_map2d, pts.astype(np.float32), traj, m,
               accelerometer=acc if acc.is_file() else None)
    clk("end: 2-D map (write)", write_map2d, grid, stage, traj)
    gt_path = Path(info["sequence"]) / "groundtruth.txt"
    if gt_path.is_file():
        from rgbdslam.evaluation.report import evaluate_trajectories, write_plots

        gt = read_tum(gt_path)
        rep = clk("end: ATE + RPE", evaluate_trajectories, gt, traj)
        clk("end: plots, first in the process (matplotlib import, fonts)", write_plots, rep, stage)
        clk("end: plots, again", write_plots, rep, stage)

    n = len(kfs)
    lines = [f"Run folder `{run}`: {n} keyframes; CPU seconds of one thread (`OMP_NUM_THREADS=1`).", "",
             "| step | CPU s | per keyframe ms |", "|---|---|---|"]
    for k, v in clk.cpu.items():
        lines.append(f"| {k} | {v:.3f} | {1e3 * v / n:.1f} |" if k in per_kf else f"| {k} | {v:.3f} | |")
    kf_ms = 1e3 * sum(clk.cpu[k] for k in per_kf) / n
    lines += ["", f"One keyframe into the map: {kf_ms:.0f} ms of CPU; {n} keyframes {kf_ms * n / 1e3:.1f} s.", ""]

    # downsampled integration against full resolution
    lines += ["| TSDF from images at | integrate CPU per keyframe ms | mesh vertices (this / full) | within 2.5 mm "
              "| within 1 voxel | median / p99 mm |", "|---|---|---|---|---|---|"]
    K = cam.K
    for down in (1, 2, 4):
        t = F._Tsdf(m, cam)
        Kd = K.copy()
        Kd[:2] /= down
        Kd[0, 2], Kd[1, 2] = (K[0, 2] + 0.5) / down - 0.5, (K[1, 2] + 0.5) / down - 0.5
        intr = o3c.Tensor(Kd, o3c.float64)
        c0 = time.process_time()
        for i in kfs:
            rgb, d = prep[i]
            if down > 1:
                d = np.ascontiguousarray(d[::down, ::down])  # nearest: a measured depth, never a blend
                rgb = cv2.resize(rgb, (rgb.shape[1] // down, rgb.shape[0] // down), interpolation=cv2.INTER_AREA)
            units = np.round(d * F.DEPTH_PNG_SCALE).astype(np.uint16)
            di = o3d.t.geometry.Image(o3c.Tensor(units))
            ci = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(rgb)))
            ext = o3c.Tensor(inv(pose[i]), o3c.float64)
            blocks = t.vol.compute_unique_block_coordinates(di, intr, ext, F.DEPTH_PNG_SCALE, m.depth_max)
            t.vol.integrate(blocks, di, ci, intr, ext, F.DEPTH_PNG_SCALE, m.depth_max, m.sdf_trunc / m.tsdf_voxel)
        ms = 1e3 * (time.process_time() - c0) / n
        v = t.vol.extract_triangle_mesh(m.mesh_min_frames - 0.5).vertex.positions.numpy().astype(np.float64)
        lines.append(f"| 1/{down} ({cam.width // down}x{cam.height // down}) | {ms:.1f} | "
                     + _nn_agreement(v, full_vertices, m.tsdf_voxel) + " |")
    lines += ["", "| cloud_pixel_stride | cloud add CPU per keyframe ms | points (this / stride 2) | within 2.5 mm "
              "| within 1 voxel | median / p99 mm |", "|---|---|---|---|---|---|"]
    ref = None
    for stride in (2, 3, 4):
        c = F.VoxelCloud(m.voxel_size)
        ms_cfg = type(m)(**{**m.__dict__, "cloud_pixel_stride": stride})
        c0 = time.process_time()
        for i in kfs:
            F.integrate_frame(None, c, *prep[i], pose[i], cam, ms_cfg)
        ms = 1e3 * (time.process_time() - c0) / n
        p, _ = c.result()
        ref = p if ref is None else ref
        lines.append(f"| {stride} | {ms:.1f} | " + _nn_agreement(p, ref, m.voxel_size) + " |")
    print("\n".join(lines))
    console.print(f"(files of the replay in {stage})", highlight=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
