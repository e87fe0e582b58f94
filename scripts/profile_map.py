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


def rigid_resample(vol, T: np.ndarray, voxel: float, chunk: int = 1500):
    """Prototype (measured here, not used by the map): the TSDF ``vol`` moved rigidly by ``T`` (what
    a submap whose anchor keyframe moved needs), by trilinear interpolation in NumPy. Every voxel of
    the destination blocks the moved source blocks reach gets the weight-weighted mean of the
    source's TSDF and colour at ``T``^-1 x over the 8 source voxels around it, and their
    interpolated weight. Open3D's voxel of block key k and local (x, y, z) sits at
    (8 k + (x, y, z)) * voxel and is element x + 8 y + 64 z of the block. Returns the destination
    block keys (n, 3) and per voxel (n, 512) TSDF, weight and (n, 512, 3) colour."""
    import itertools

    import open3d.core as o3c

    hm = vol.hashmap()
    idx = hm.active_buf_indices().to(o3c.int64)
    keys = hm.key_tensor()[idx].numpy().astype(np.int64)
    buf = idx.numpy()
    n = len(buf)
    src_t = vol.attribute("tsdf").numpy()[buf].reshape(n, 512)
    src_w = vol.attribute("weight").numpy()[buf].reshape(n, 512).astype(np.float32)
    src_c = vol.attribute("color").numpy()[buf].reshape(n, 512, 3).astype(np.float32)
    lo = keys.min(axis=0) - 1
    lut = np.full(tuple(keys.max(axis=0) - lo + 2), -1, np.int64)
    lut[tuple((keys - lo).T)] = np.arange(n)
    corner = np.array(list(itertools.product((0, 8), repeat=3)))
    moved = ((keys[:, None, :] * 8 + corner) * voxel).reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    bk = np.floor(moved / (8 * voxel)).astype(np.int64).reshape(n, 8, 3)
    bmin, bmax = bk.min(axis=1), bk.max(axis=1)
    cand = np.concatenate([bmin + o for o in itertools.product((0, 1), repeat=3)])
    inside = np.concatenate([np.all(bmin + o <= bmax, axis=1) for o in itertools.product((0, 1), repeat=3)])
    dst = np.unique(cand[inside], axis=0)
    z, y, x = np.meshgrid(np.arange(8), np.arange(8), np.arange(8), indexing="ij")
    local = np.stack([x, y, z], axis=-1).reshape(512, 3)
    R, t = T[:3, :3], T[:3, 3]
    out_t = np.zeros((len(dst), 512), np.float32)
    out_w = np.zeros((len(dst), 512), np.float32)
    out_c = np.zeros((len(dst), 512, 3), np.float32)
    for a in range(0, len(dst), chunk):
        g = (dst[a:a + chunk, None, :] * 8 + local).reshape(-1, 3)
        q = ((g * voxel - t) @ R) / voxel  # source voxel coordinates (continuous)
        i0 = np.floor(q).astype(np.int64)
        f = (q - i0).astype(np.float32)
        sw = np.zeros(len(g), np.float32)
        st = np.zeros(len(g), np.float32)
        sc = np.zeros((len(g), 3), np.float32)
        for d in itertools.product((0, 1), repeat=3):
            gi = i0 + d
            b = (gi >> 3) - lo
            ok = np.all((b >= 0) & (b < lut.shape), axis=1)
            row = np.full(len(g), -1, np.int64)
            row[ok] = lut[tuple(b[ok].T)]
            ok = row >= 0
            li = gi[ok] & 7
            flat = li[:, 0] + 8 * li[:, 1] + 64 * li[:, 2]
            wt = np.prod(np.where(np.array(d, bool), f[ok], 1 - f[ok]), axis=1) * src_w[row[ok], flat]
            sw[ok] += wt
            st[ok] += wt * src_t[row[ok], flat]
            sc[ok] += wt[:, None] * src_c[row[ok], flat]
        safe = np.where(sw > 0, sw, 1)
        out_w[a:a + chunk] = sw.reshape(-1, 512)
        out_t[a:a + chunk] = (st / safe).reshape(-1, 512)
        out_c[a:a + chunk] = (sc / safe[:, None]).reshape(-1, 512, 3)
    return dst, out_t, out_w, out_c


def _grid_of(m, cam, keys, tsdf, weight, color):
    """An Open3D VoxelBlockGrid holding the given blocks (what :func:`rigid_resample` gives)."""
    import open3d.core as o3c

    from rgbdslam.mapping import fusion as F

    grid = F._Tsdf(type(m)(**{**m.__dict__, "tsdf_initial_blocks": len(keys) + 16}), cam)
    hm = grid.vol.hashmap()
    k = o3c.Tensor(keys.astype(np.int32))
    hm.activate(k)
    buf, _ = hm.find(k)
    buf = buf.to(o3c.int64).numpy()
    grid.vol.attribute("tsdf").numpy()[buf] = tsdf.reshape(-1, 8, 8, 8, 1)
    grid.vol.attribute("weight").numpy()[buf] = np.round(weight).astype(np.uint16).reshape(-1, 8, 8, 8, 1)
    grid.vol.attribute("color").numpy()[buf] = np.clip(np.round(color), 0, 65535).astype(np.uint16).reshape(-1, 8, 8, 8, 3)
    return grid


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

    # the whole TSDF moved rigidly (what moving every submap after a loop costs: at the end of fr1/rpy the
    # last loop moves every part of the map) by resampling, against integrating the keyframes at the moved poses
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.deg2rad(1.0) * np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])).as_matrix()
    T[:3, 3] = [0.02, -0.01, 0.015]
    src_voxels = int(tsdf.vol.hashmap().size()) * 512
    c0 = time.process_time()
    keys, rt, rw, rc = rigid_resample(tsdf.vol, T, m.tsdf_voxel)
    resample_cpu = time.process_time() - c0
    moved = _grid_of(m, cam, keys, rt, rw, rc)
    ref = F._Tsdf(m, cam)
    c0 = time.process_time()
    for i in kfs:
        ref.integrate(*prep[i], T @ pose[i])
    reintegrate_cpu = time.process_time() - c0
    v_moved = moved.vol.extract_triangle_mesh(m.mesh_min_frames - 0.5).vertex.positions.numpy().astype(np.float64)
    v_ref = ref.vol.extract_triangle_mesh(m.mesh_min_frames - 0.5).vertex.positions.numpy().astype(np.float64)
    rigid = [
        "", "The whole TSDF moved rigidly (1 degree, 2.7 cm): by trilinear resampling in NumPy (`rigid_resample`, a "
        "prototype of moving submaps) against integrating every keyframe at the moved pose (the reference):", "",
        "| how | CPU s | ns per source voxel | mesh vertices (this / reference) | within 2.5 mm | within 1 voxel "
        "| median / p99 mm |", "|---|---|---|---|---|---|---|",
        f"| resampled ({len(keys)} destination blocks from {src_voxels // 512}) | {resample_cpu:.2f} | "
        f"{1e9 * resample_cpu / src_voxels:.0f} | " + _nn_agreement(v_moved, v_ref, m.tsdf_voxel) + " |",
        f"| integrated at the moved poses ({len(kfs)} keyframes) | {reintegrate_cpu:.2f} | "
        f"{1e9 * reintegrate_cpu / src_voxels:.0f} | " + _nn_agreement(v_ref, v_ref, m.tsdf_voxel) + " |",
    ]

    n = len(kfs)
    lines = [f"Run folder `{run}`: {n} keyframes; CPU seconds of one thread (`OMP_NUM_THREADS=1`).", "",
             "| step | CPU s | per keyframe ms |", "|---|---|---|"]
    for k, v in clk.cpu.items():
        lines.append(f"| {k} | {v:.3f} | {1e3 * v / n:.1f} |" if k in per_kf else f"| {k} | {v:.3f} | |")
    kf_ms = 1e3 * sum(clk.cpu[k] for k in per_kf) / n
    lines += ["", f"One keyframe into the map: {kf_ms:.0f} ms of CPU; {n} keyframes {kf_ms * n / 1e3:.1f} s.", *rigid, ""]

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
