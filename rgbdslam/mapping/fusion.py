"""Map fusion: a coloured point cloud and a TSDF mesh from posed RGB-D frames.

Frames are streamed: one frame is in memory at a time. For every chosen frame the depth
(the DIF-filtered keyframe depth when the run saved it, else the raw depth) is

* integrated into an Open3D TSDF volume (the tensor ``VoxelBlockGrid``), from which a
  triangle mesh is extracted by marching cubes;
* back-projected (every ``cloud_pixel_stride``-th pixel) into a coloured cloud that is
  reduced to one averaged point per voxel and merged into the map cloud
  (:class:`VoxelCloud`), so memory stays bounded by the map's size and not by the number
  of frames.

At the end the cloud gets statistical outlier removal and both are written as PLY
atomically. Poses are camera-to-world (TUM convention); Open3D's ``integrate`` wants
the world-to-camera extrinsic, i.e. the inverse.
"""

from __future__ import annotations

import contextlib
import resource
import time
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np

from rgbdslam.config import load_config, validate_section
from rgbdslam.datasets import open_sequence
from rgbdslam.datasets.base import Sequence, as_rgb
from rgbdslam.errors import InputError
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import inv, rotation_angle
from rgbdslam.io.atomic import interrupts_deferred
from rgbdslam.io.trajectory import Trajectory
from rgbdslam.mapping.config import MappingConfig
from rgbdslam.mapping.staging import MAP_FILES, FuseResult, remove_stale_stages, staged
from rgbdslam.runfolder.depth import DEPTH_SCALE, keyframe_depth_path, read_keyframe_depth
from rgbdslam.io.manifest import RUN, Manifest
from rgbdslam.runfolder.read import check_run_frames, read_run

with interrupts_deferred():  # Ctrl-C during Open3D's start-up leaves its C++ state half made (exit 1
    import open3d as o3d  # and a page of memory statistics at exit): the interrupt waits for the import

MAP_DIR = "map"  # a run folder's map, beside its trajectory
STAMP_TOLERANCE = 1e-3  # seconds: a trajectory line belongs to a frame when the stamps agree this well


# ----------------------------------------------------------------------------- helpers


def rss_mb() -> float:
    """Current resident set size in MB (Linux /proc; 0 elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * resource.getpagesize() / 2**20
    except OSError:  # pragma: no cover - non-Linux
        return 0.0


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def match_frames(frame_stamps: np.ndarray, traj: Trajectory, tol: float = STAMP_TOLERANCE) -> np.ndarray:
    """For each frame stamp the row of ``traj`` with the same stamp (within ``tol``), else -1."""
    frame_stamps = np.asarray(frame_stamps, dtype=np.float64)
    if len(traj) == 0:
        return np.full(len(frame_stamps), -1)
    order = np.argsort(traj.timestamps)
    ts = traj.timestamps[order]
    j = np.clip(np.searchsorted(ts, frame_stamps), 1, max(len(ts) - 1, 1))
    j0 = np.clip(j - 1, 0, len(ts) - 1)
    j1 = np.clip(j, 0, len(ts) - 1)
    best = np.where(np.abs(ts[j0] - frame_stamps) <= np.abs(ts[j1] - frame_stamps), j0, j1)
    ok = np.abs(ts[best] - frame_stamps) <= tol
    return np.where(ok, order[best], -1)


def select_by_motion(poses: np.ndarray, min_translation: float, min_rotation_deg: float) -> list[int]:
    """Indices (into ``poses``) of the first pose and every pose that moved at least
    ``min_translation`` metres or ``min_rotation_deg`` degrees since the last chosen one."""
    if len(poses) == 0:
        return []
    chosen = [0]
    last = poses[0]
    min_rot = np.deg2rad(min_rotation_deg)
    for k in range(1, len(poses)):
        rel = inv(last) @ poses[k]
        if np.linalg.norm(rel[:3, 3]) >= min_translation or rotation_angle(rel[:3, :3]) >= min_rot:
            chosen.append(k)
            last = poses[k]
    return chosen


class Undistorter:
    """Remaps colour (bilinear) and depth (nearest: never blends depths across edges) to the ideal pinhole."""

    def __init__(self, camera: Camera, enabled: bool):
        self.maps = None
        if enabled and camera.has_distortion:
            self.maps = cv2.initUndistortRectifyMap(
                camera.K, np.array(camera.dist), None, camera.K, (camera.width, camera.height), cv2.CV_32FC1
            )

    def __call__(self, rgb: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.maps is None or rgb.shape[:2] != self.maps[0].shape:
            return rgb, depth
        m1, m2 = self.maps
        return (
            cv2.remap(rgb, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT),
            cv2.remap(depth, m1, m2, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT),
        )


def backproject_image(depth: np.ndarray, camera: Camera, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (M,3) of the valid (depth > 0) pixels and their flat pixel indices."""
    h, w = depth.shape
    v, u = np.mgrid[0:h:stride, 0:w:stride]
    z = depth[::stride, ::stride]
    ok = z > 0
    z = z[ok]
    pts = np.stack([(u[ok] - camera.cx) * z / camera.fx, (v[ok] - camera.cy) * z / camera.fy, z], axis=1)
    return pts.astype(np.float32), (v[ok] * w + u[ok])


def voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """One int64 per voxel of side ``voxel`` (21 bits per axis: +-10 km at 1 cm)."""
    q = np.floor(np.asarray(points, dtype=np.float64) / voxel).astype(np.int64) + (1 << 20)
    q = np.clip(q, 0, (1 << 21) - 1)
    return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]


def _reduce(keys: np.ndarray, sums: np.ndarray, counts: np.ndarray):
    """Sum ``sums`` (M, C) and ``counts`` (M,) over equal keys."""
    uniq, inverse = np.unique(keys, return_inverse=True)
    out = np.empty((len(uniq), sums.shape[1]), np.float64)
    for c in range(sums.shape[1]):
        out[:, c] = np.bincount(inverse, weights=sums[:, c], minlength=len(uniq))
    return uniq, out, np.bincount(inverse, weights=counts, minlength=len(uniq))


class VoxelCloud:
    """Coloured cloud on a voxel grid: per voxel the sum of positions and colours and the
    number of points, so merging clouds averages exactly. New points are reduced per frame
    and merged into the map whenever the pending part has grown as large as the map (the
    merge work stays proportional to the map's size; memory to ~2x the map)."""

    def __init__(self, voxel: float):
        self.voxel = voxel
        self.keys = np.zeros(0, np.int64)
        self.sums = np.zeros((0, 6), np.float64)
        self.counts = np.zeros(0, np.float64)
        self.pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.pending_n = 0

    def add(self, points: np.ndarray, colors: np.ndarray) -> None:
        if len(points) == 0:
            return
        sums = np.hstack([np.asarray(points, np.float64), np.asarray(colors, np.float64)])
        part = _reduce(voxel_keys(points, self.voxel), sums, np.ones(len(points)))
        self.pending.append(part)
        self.pending_n += len(part[0])
        if self.pending_n >= max(len(self.keys), 200_000):
            self.merge()

    def merge(self) -> None:
        if not self.pending:
            return
        parts = [(self.keys, self.sums, self.counts)] + self.pending
        self.pending, self.pending_n = [], 0
        self.keys, self.sums, self.counts = _reduce(*(np.concatenate(x) for x in zip(*parts)))

    def __len__(self) -> int:
        self.merge()
        return len(self.keys)

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean position (N, 3) float64 and mean colour (N, 3) uint8 of every occupied voxel."""
        self.merge()
        mean = self.sums / self.counts[:, None]
        return mean[:, :3], np.clip(mean[:, 3:] + 0.5, 0, 255).astype(np.uint8)


class Tsdf:
    """Open3D tensor VoxelBlockGrid (CPU). The legacy ScalableTSDFVolume of the Open3D 0.20
    wheel returned empty meshes for every input tried here, so it is not offered."""

    def __init__(self, cfg: MappingConfig, camera: Camera):
        import open3d as o3d
        import open3d.core as o3c

        self.cfg = cfg
        self.o3c = o3c
        self.vol = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"),
            attr_dtypes=(o3c.float32, o3c.uint16, o3c.uint16),  # 12 bytes per voxel
            attr_channels=((1), (1), (3)),
            voxel_size=cfg.tsdf_voxel,
            block_resolution=8,
            block_count=cfg.tsdf_initial_blocks,  # the hash map grows when needed
            device=o3c.Device("CPU:0"),
        )
        self.intr = o3c.Tensor(camera.K, o3c.float64)

    def integrate(self, rgb: np.ndarray, depth: np.ndarray, pose_c2w: np.ndarray) -> None:
        import open3d as o3d

        o3c = self.o3c
        # in the keyframe depth images' own steps (lossless for them); the uint16/uint8 kernel is the lean one
        units = np.round(depth * DEPTH_SCALE).astype(np.uint16)
        d = o3d.t.geometry.Image(o3c.Tensor(units))
        c = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(rgb, dtype=np.uint8)))
        ext = o3c.Tensor(inv(pose_c2w), o3c.float64)  # Open3D wants world -> camera
        blocks = self.vol.compute_unique_block_coordinates(d, self.intr, ext, DEPTH_SCALE, self.cfg.depth_max)
        self.vol.integrate(blocks, d, c, self.intr, ext, DEPTH_SCALE, self.cfg.depth_max,
                           self.cfg.sdf_trunc / self.cfg.tsdf_voxel)

    def mesh(self, min_frames: int):
        import open3d as o3d

        # the weight counts the frames that saw a voxel; Open3D keeps voxels with weight > threshold
        mesh = self.vol.extract_triangle_mesh(weight_threshold=min_frames - 0.5).to_legacy()
        if mesh.has_vertex_colors():
            mesh.vertex_colors = o3d.utility.Vector3dVector(np.clip(np.asarray(mesh.vertex_colors), 0.0, 1.0))
        return canonical_mesh(mesh)


KEY_BITS = 21  # bits per axis of the packed keys of canonical_order and of the triangles (3 x 21 < 63)


def canonical_order(rows: np.ndarray) -> np.ndarray:
    """The order (indices) that sorts ``rows`` (N, 3 + C: x, y, z, then e.g. colour)
    lexicographically by (qx, qy, qz, x, y, z, the other columns), where q is the position
    quantised to ``2**KEY_BITS - 1`` steps over the rows' extent: identical rows end up next to
    each other and the order depends on the rows only, not on where they stood.

    One stable argsort of the packed (qx, qy, qz) key, then a lexsort over every column of the few
    rows that share a key with another (marching cubes puts the vertices of every edge around a
    voxel whose TSDF is exactly 0 on that voxel: 28 of 269k on fr1/rpy)."""
    rows = np.asarray(rows, dtype=np.float64)
    if len(rows) == 0:
        return np.zeros(0, np.int64)
    lo = rows[:, :3].min(axis=0)
    extent = float((rows[:, :3].max(axis=0) - lo).max())
    steps = (1 << KEY_BITS) - 1
    q = np.zeros((len(rows), 3), np.int64) if extent == 0 else np.minimum(
        np.floor((rows[:, :3] - lo) * (steps / extent)).astype(np.int64), steps - 1)
    key = (q[:, 0] << (2 * KEY_BITS)) | (q[:, 1] << KEY_BITS) | q[:, 2]
    order = np.argsort(key, kind="stable")
    k = key[order]
    same = np.zeros(len(k), bool)  # rows whose key another row shares (vertices on one voxel corner)
    same[1:] = k[1:] == k[:-1]
    same[:-1] |= same[1:].copy()
    if same.any():  # order each run of equal keys by all the rows' values (runs stay where they are)
        at = np.flatnonzero(same)
        run = np.cumsum(np.r_[True, k[at[1:]] != k[at[:-1]]])
        order[at] = order[at][np.lexsort((*rows[order[at]].T[::-1], run))]
    return order


def canonical_mesh(mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
    """The same mesh with its vertices in a fixed order (:func:`canonical_order`: by quantised
    position, then x, y, z and colour; copies of one vertex welded) and its triangles (each
    rotated to start at its smallest vertex index, keeping its orientation) sorted: the TSDF's
    hash map is walked by several threads, so marching cubes emits the same vertices in a
    different order on every run, and mesh.ply would differ byte for byte."""
    import open3d as o3d

    v = np.asarray(mesh.vertices)
    if len(v) == 0:
        return mesh
    c = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else np.zeros((len(v), 0))
    # marching cubes may emit a vertex shared by neighbouring blocks once per block, and which copy
    # a triangle names varies: weld them (identical rows are next to each other once sorted)
    rows = np.concatenate([v, c], axis=1)
    order = canonical_order(rows)
    rows = rows[order]
    first_copy = np.ones(len(rows), bool)
    first_copy[1:] = np.any(rows[1:] != rows[:-1], axis=1)
    rank = np.empty(len(rows), np.int64)
    rank[order] = np.cumsum(first_copy) - 1
    uniq = rows[first_copy]
    tri = rank[np.asarray(mesh.triangles, dtype=np.int64)]
    first = np.argmin(tri, axis=1)  # cyclic rotation: same triangle, same winding
    tri = np.take_along_axis(tri, (first[:, None] + np.arange(3)) % 3, axis=1)
    if len(uniq) < (1 << KEY_BITS):  # triangles sorted by (first, second, third) index: one packed key
        tri = tri[np.argsort((tri[:, 0] << (2 * KEY_BITS)) | (tri[:, 1] << KEY_BITS) | tri[:, 2], kind="stable")]
    else:
        tri = tri[np.lexsort(tri.T[::-1])]
    # int32 and contiguous: Open3D converts other layouts element by element (40x slower)
    out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.ascontiguousarray(uniq[:, :3])),
                                    o3d.utility.Vector3iVector(tri.astype(np.int32)))
    if c.shape[1]:
        out.vertex_colors = o3d.utility.Vector3dVector(np.ascontiguousarray(uniq[:, 3:]))
    return out


def _write_ply(path: Path, geom, mesh: bool) -> None:
    """An Open3D cloud or mesh as binary PLY (rgbdslam.io.ply: one error naming the file when the
    disk is full, where Open3D's writer prints a line per element and reports success)."""
    from rgbdslam.io.ply import write_ply

    pts = np.asarray(geom.vertices if mesh else geom.points)
    colors = np.asarray(geom.vertex_colors if mesh else geom.colors) if (
        geom.has_vertex_colors() if mesh else geom.has_colors()) else None
    normals = np.asarray(geom.vertex_normals if mesh else geom.normals) if (
        geom.has_vertex_normals() if mesh else geom.has_normals()) else None
    write_ply(path, pts, colors, normals, np.asarray(geom.triangles) if mesh else None)


# ----------------------------------------------------------------------------- settings


def validate_mapping(cfg: MappingConfig) -> None:
    """Check the mapping settings before anything is read or written, by the config's own rules
    (a MappingConfig made in Python has not been through ``load_config``)."""
    validate_section("mapping", cfg)


# ----------------------------------------------------------------------------- fusion


def fuse(
    sequence: Sequence,
    trajectory: Trajectory,
    frame_indices,
    cfg: MappingConfig,
    out_dir: str | Path,
    depth_dir: str | Path | None = None,
    progress: bool = True,
) -> FuseResult:
    """Fuse the frames ``frame_indices`` (positions in ``sequence``) posed by ``trajectory``
    (camera-to-world, matched to frames by time stamp) into ``out_dir``/cloud.ply and mesh.ply
    (and the 2-D map when ``cfg.map2d``). ``depth_dir`` holds depth_<index:06d>.png files used
    instead of the raw depth where present. Frames without a pose are skipped.

    The settings are checked first (:func:`validate_mapping`). All files are written into a
    temporary folder inside ``out_dir`` and moved into place only when every one of them is
    complete (:func:`_commit`): a failure or Ctrl-C part-way leaves the earlier map as it was."""
    from rgbdslam.ui import console, frame_progress

    t_start = time.perf_counter()
    rss0 = rss_mb()
    validate_mapping(cfg)
    out_dir = Path(out_dir)
    depth_dir = Path(depth_dir) if depth_dir is not None else None
    stamps = np.asarray(sequence.timestamps)
    idx = [int(i) for i in frame_indices]
    bad = [i for i in idx if not 0 <= i < len(stamps)]
    if bad:
        raise InputError(f"frame {bad[0]} to fuse is not in {sequence.root} (frames 0..{len(stamps) - 1}); "
                         f"give frame indices of this sequence")
    rows = match_frames(stamps[idx], trajectory) if idx else np.zeros(0, int)
    todo = [(i, r) for i, r in zip(idx, rows) if r >= 0]
    if not todo:
        raise InputError(
            f"no frame of {sequence.root} to fuse has a pose in the trajectory; check that the trajectory's "
            f"time stamps are the sequence's colour stamps"
        )
    res = staged(out_dir, lambda stage: _fuse_into(stage, sequence, trajectory, todo, cfg, depth_dir, progress,
                                                   console, frame_progress))
    res.seconds = time.perf_counter() - t_start
    res.peak_rss_mb = peak_rss_mb()
    res.rss_growth_mb = max(peak_rss_mb() - rss0, 0.0)
    return res


def prepare_frame(rgb: np.ndarray, depth: np.ndarray, undistort, cfg: MappingConfig) -> tuple[np.ndarray, np.ndarray]:
    """Colour and depth as fused: undistorted (a grey camera's image as grey colour), depth outside
    [depth_min, depth_max] set to 0."""
    rgb, depth = undistort(as_rgb(rgb), depth.astype(np.float32, copy=False))
    depth = np.where((depth >= cfg.depth_min) & (depth <= cfg.depth_max), depth, 0).astype(np.float32)
    return rgb, depth


def integrate_frame(tsdf, acc: VoxelCloud | None, rgb: np.ndarray, depth: np.ndarray, pose: np.ndarray, camera: Camera,
                    cfg: MappingConfig, timings: dict[str, float] | None = None) -> None:
    """One prepared frame into the TSDF and the voxel cloud (either may be None), at camera-to-world ``pose``."""
    t1 = time.perf_counter()
    if tsdf is not None and depth.any():  # Open3D aborts on a frame that touches no block
        tsdf.integrate(rgb, depth, pose)
    t2 = time.perf_counter()
    if acc is not None:
        pts, flat = backproject_image(depth, camera, cfg.cloud_pixel_stride)
        pts_w = pts @ pose[:3, :3].T.astype(np.float32) + pose[:3, 3].astype(np.float32)
        acc.add(pts_w, rgb.reshape(-1, 3)[flat])
    if timings is not None:
        timings["tsdf"] = timings.get("tsdf", 0.0) + t2 - t1
        timings["cloud"] = timings.get("cloud", 0.0) + time.perf_counter() - t2


def _fuse_into(stage: Path, sequence: Sequence, trajectory: Trajectory, todo: list[tuple[int, int]],
               cfg: MappingConfig, depth_dir: Path | None, progress: bool, console, frame_progress) -> FuseResult:
    """The work of :func:`fuse`, writing into the (temporary) folder ``stage``."""
    camera = sequence.camera
    undistort = Undistorter(camera, cfg.undistort)
    tsdf = Tsdf(cfg, camera) if cfg.mesh else None
    acc = VoxelCloud(cfg.voxel_size)
    timings = {"load": 0.0, "tsdf": 0.0, "cloud": 0.0}
    fused: list[int] = []
    n_depth = 0  # pixels with a depth inside [depth_min, depth_max]
    with frame_progress(len(todo), "fusing map", enabled=progress) as advance:
        for i, r in todo:
            t0 = time.perf_counter()
            frame = sequence.load(i)
            depth = frame.depth
            if depth_dir is not None and keyframe_depth_path(depth_dir, i).is_file():
                depth = read_keyframe_depth(keyframe_depth_path(depth_dir, i))
            rgb, depth = prepare_frame(frame.rgb, depth, undistort, cfg)
            n_depth += int(np.count_nonzero(depth))
            timings["load"] += time.perf_counter() - t0
            integrate_frame(tsdf, acc, rgb, depth, trajectory.poses[r], camera, cfg, timings)
            fused.append(i)
            advance()
    return write_map(stage, acc, tsdf, fused, n_depth, cfg, trajectory, sequence, timings, console,
                     depth_dir is not None)


def write_map(stage: Path, acc: VoxelCloud, tsdf, fused: list[int], n_depth: int, cfg: MappingConfig,
              trajectory: Trajectory, sequence: Sequence, timings: dict[str, float], console,
              filtered_depth: bool) -> FuseResult:
    """The fused cloud (outliers removed) and mesh as PLY, and the 2-D map, into ``stage``."""
    check_depth(n_depth, fused, cfg, filtered_depth)
    t0 = time.perf_counter()
    points, colors = cloud_points(acc, cfg)
    del acc
    cloud_path, points, colors = write_cloud(stage, points, colors, cfg)
    timings["cloud"] = timings.get("cloud", 0.0) + time.perf_counter() - t0
    mesh_path, n_vert, n_tri = None, 0, 0
    if tsdf is not None:
        t0 = time.perf_counter()
        mesh_path, n_vert, n_tri = write_mesh(stage, tsdf, len(fused), cfg, console)
        del tsdf
        timings["mesh"] = time.perf_counter() - t0
    points = points.astype(np.float32)
    map2d_path, grid = write_2d(stage, points, trajectory, cfg, _accelerometer_of(sequence), timings)
    return FuseResult(
        out_dir=stage,
        cloud_path=cloud_path,
        mesh_path=mesh_path,
        map2d_path=map2d_path,
        frames=fused,
        n_points=len(points),
        n_vertices=n_vert,
        n_triangles=n_tri,
        seconds=0.0,
        peak_rss_mb=0.0,
        rss_growth_mb=0.0,
        timings=timings,
        cloud_points=points,
        cloud_colors=colors,
        map2d=grid,
    )


# the parts of write_map, apart: the map fused while tracking writes the mesh in its own process
# while the run writes the cloud and the 2-D map (rgbdslam.mapping.live)


def check_depth(n_depth: int, fused: list[int], cfg: MappingConfig, filtered_depth: bool) -> None:
    """An InputError when no fused pixel had a depth in [depth_min, depth_max]."""
    if n_depth == 0:
        used = " (the run's filtered keyframe depth where present)" if filtered_depth else ""
        raise InputError(
            f"the map would be empty: no depth of the {len(fused)} frame{'s' if len(fused) != 1 else ''} to fuse{used} lies between "
            f"mapping.depth_min={cfg.depth_min:g} and mapping.depth_max={cfg.depth_max:g} m; widen that range "
            f"(defaults 0.3 and 3.0)"
        )


def cloud_points(acc: VoxelCloud, cfg: MappingConfig) -> tuple[np.ndarray, np.ndarray]:
    """The voxel cloud's points and colours; an InputError when it is empty."""
    points, colors = acc.result()
    if len(points) == 0:
        raise InputError(
            f"the map would be empty: no pixel sampled every mapping.cloud_pixel_stride={cfg.cloud_pixel_stride} "
            f"pixels has a depth in range; lower mapping.cloud_pixel_stride (default 2)"
        )
    return points, colors


def outlier_keep(points: np.ndarray, cfg: MappingConfig) -> np.ndarray | None:
    """The indices (int64, ascending) of the points the cloud's outlier removal keeps
    (``cfg.outlier_method``: :func:`statistical_keep` or :func:`voxel_keep`); None when it is off or
    the cloud is too small. An InputError when it would keep none."""
    if cfg.outlier_method == "voxel":
        if cfg.outlier_min_neighbors <= 0 or len(points) == 0:
            return None
        keep = voxel_keep(points, cfg.voxel_size, cfg.outlier_min_neighbors, cfg.outlier_radius)
        if len(keep) == 0:
            raise InputError(
                f"voxel outlier removal left no point of the {len(points)} in the cloud (none has "
                f"mapping.outlier_min_neighbors={cfg.outlier_min_neighbors} occupied voxels among its "
                f"neighbours); lower it or set mapping.outlier_min_neighbors=0"
            )
        return keep
    return statistical_keep(points, cfg)


def statistical_keep(points: np.ndarray, cfg: MappingConfig) -> np.ndarray | None:
    """Open3D's statistical outlier removal: the indices (int64) of the points whose mean distance
    to the ``outlier_neighbors`` nearest points is at most ``outlier_std`` standard deviations
    above the cloud's mean; None when it is off or the cloud is too small. An InputError when it
    would keep none."""
    import open3d as o3d

    if not (cfg.outlier_neighbors > 0 and len(points) > cfg.outlier_neighbors):
        return None
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    _, keep = cloud.remove_statistical_outlier(cfg.outlier_neighbors, cfg.outlier_std)
    keep = np.asarray(keep, dtype=np.int64)
    if len(keep) == 0:
        raise InputError(
            f"statistical outlier removal left no point of the {len(points)} in the cloud; raise "
            f"mapping.outlier_std (now {cfg.outlier_std:g}) or set mapping.outlier_neighbors=0"
        )
    return keep


VOXEL_DENSE_CELLS = 4 * 2**20  # voxel_neighbours' occupancy buffer (1 byte a cell) holds at most this many cells


def voxel_neighbours(points: np.ndarray, voxel: float, radius: int = 1,
                     max_cells: int = VOXEL_DENSE_CELLS) -> np.ndarray:
    """For every point, the number of occupied voxels (of side ``voxel``, the grid of
    :func:`voxel_keys`) among the (2 radius + 1)^3 - 1 around its own voxel (its own not counted,
    however many points share it); uint16. The points go through a dense uint8 occupancy buffer of
    at most ``max_cells`` cells in slabs along x (one gather per neighbour offset, the buffer
    reused: its pages are touched once); when one x plane of the points' y-z box does not fit, a
    search in the sorted voxel keys gives the same counts, slower."""
    n = len(points)
    counts = np.zeros(n, np.uint16)
    if n == 0:
        return counts
    # the voxel coordinates of voxel_keys (21 bits per axis, clipped the same way)
    q = np.clip(np.floor(np.asarray(points, dtype=np.float64) / voxel).astype(np.int64) + (1 << 20),
                0, (1 << 21) - 1)
    r = int(radius)
    offsets = [(dx, dy, dz) for dx in range(-r, r + 1) for dy in range(-r, r + 1) for dz in range(-r, r + 1)
               if (dx, dy, dz) != (0, 0, 0)]
    lo = q.min(axis=0) - r
    nz = int(q[:, 2].max()) + r + 1 - int(lo[2])
    sy = (int(q[:, 1].max()) + r + 1 - int(lo[1])) * nz  # cells of one x plane
    slab = max_cells // sy - 2 * r  # x planes whose points one buffer fill counts
    if slab < 1:
        return _voxel_neighbours_sorted(q, offsets, counts)
    x = q[:, 0]
    order = None if np.all(x[1:] >= x[:-1]) else np.argsort(x, kind="stable")
    xs = x if order is None else x[order]
    # within a buffer starting at x plane x0 - r, the cell of (x, y, z) is (x - x0 + r) sy + (y - lo_y) nz + (z - lo_z)
    yz = (q[:, 1] - lo[1]) * nz + (q[:, 2] - lo[2])
    if order is not None:
        yz = yz[order]
    grid = np.zeros((slab + 2 * r) * sy, np.uint8)
    far = r * sy + r * nz + r
    shifts = [dx * sy + dy * nz + dz + far for dx, dy, dz in offsets]
    out = np.zeros(n, np.uint16)
    i = 0
    while i < n:
        x0 = int(xs[i])
        a, b, c = np.searchsorted(xs, [x0 - r, x0 + slab, x0 + slab + r])  # filled [a, c), counted [i, b)
        cell = (xs[a:c] - (x0 - r)) * sy + yz[a:c]
        grid[cell] = 1
        base = cell[i - a:b - a] - far
        part = out[i:b]
        for shift in shifts:
            part += np.take(grid[shift:], base)
        grid[cell] = 0
        i = b
    if order is None:
        return out
    counts[order] = out
    return counts


def _voxel_neighbours_sorted(q: np.ndarray, offsets, counts: np.ndarray) -> np.ndarray:
    """:func:`voxel_neighbours` by binary search in the sorted voxel keys (any box)."""
    keys = np.unique((q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2])
    top = (1 << 21) - 1
    for dx, dy, dz in offsets:
        nb = q + np.array([dx, dy, dz], np.int64)
        inside = ((nb >= 0) & (nb <= top)).all(axis=1)
        nk = (nb[:, 0] << 42) | (nb[:, 1] << 21) | nb[:, 2]
        at = np.minimum(np.searchsorted(keys, nk), len(keys) - 1)
        counts += (inside & (keys[at] == nk)).astype(np.uint16)
    return counts


def voxel_keep(points: np.ndarray, voxel: float, min_neighbors: int, radius: int = 1,
               max_cells: int = VOXEL_DENSE_CELLS) -> np.ndarray:
    """The indices (int64, ascending) of the points with at least ``min_neighbors`` occupied
    voxels around their own (:func:`voxel_neighbours`): isolated speckles and thin streaks of
    flying pixels go, points of a surface (8 or more neighbours in a plane at radius 1) stay."""
    return np.flatnonzero(voxel_neighbours(points, voxel, radius, max_cells) >= min_neighbors).astype(np.int64)


def write_cloud(stage: Path, points: np.ndarray, colors: np.ndarray, cfg: MappingConfig
                ) -> tuple[Path, np.ndarray, np.ndarray]:
    """Statistical outlier removal (:func:`outlier_keep`), then ``stage``/cloud.ply; the points and
    colours kept."""
    keep = outlier_keep(points, cfg)
    if keep is not None:
        points, colors = points[keep], colors[keep]
    from rgbdslam.io.ply import write_cloud_ply

    cloud_path = stage / "cloud.ply"
    write_cloud_ply(cloud_path, points, colors)
    return cloud_path, points, colors


def write_mesh(stage: Path, tsdf, n_fused: int, cfg: MappingConfig, console) -> tuple[Path | None, int, int]:
    """Marching cubes of the TSDF into ``stage``/mesh.ply; (path or None when empty, vertices, triangles)."""
    min_frames = max(1, min(cfg.mesh_min_frames, n_fused))  # a single keyframe still gives a mesh
    mesh = tsdf.mesh(min_frames)
    n_vert, n_tri = len(mesh.vertices), len(mesh.triangles)
    if not n_tri:  # _commit removes an older run's mesh.ply: never leave it behind
        console.print(
            f"[yellow]warning:[/] the TSDF mesh is empty (no voxel was seen by {min_frames} frames); "
            f"mesh.ply not written; lower mapping.mesh_min_frames"
        )
        return None, n_vert, n_tri
    mesh.compute_vertex_normals()
    mesh_path = stage / "mesh.ply"
    _write_ply(mesh_path, mesh, mesh=True)
    return mesh_path, n_vert, n_tri


def write_2d(stage: Path, points: np.ndarray, trajectory: Trajectory, cfg: MappingConfig,
             accelerometer: Path | None, timings: dict[str, float]):
    """The 2-D map of the (outlier-free) cloud into ``stage`` when ``cfg.map2d``; (path, Map2D) or Nones.
    The points become float32 (what the Rerun log and the export take)."""
    if not (cfg.map2d and len(points)):
        return None, None
    from rgbdslam.mapping.map2d import build_map2d, write_map2d

    t0 = time.perf_counter()
    grid = build_map2d(points.astype(np.float32), trajectory, cfg, accelerometer=accelerometer)
    path = write_map2d(grid, stage, trajectory)
    timings["map2d"] = time.perf_counter() - t0
    return path, grid


def _accelerometer_of(sequence: Sequence) -> Path | None:
    p = Path(getattr(sequence, "root", "")) / "accelerometer.txt"
    return p if p.is_file() else None


def fuse_run(run_dir: str | Path, cfg: MappingConfig | None = None, progress: bool = True) -> FuseResult:
    """Fuse the map of a finished run folder into ``run_dir``/map (see :func:`fuse`).

    Frames: run.json's keyframes when ``keyframes_only`` (chosen by motion when the run has
    none), else every tracked frame; frames of tracking segments that no loop linked to the
    map (run.json ``segments``, after a tracking loss) are left out. The sequence is re-opened
    with the run's dataset config. The settings and run.json are checked before anything is
    written; a keyframe outside the sequence is an error (run.json is not of this sequence)."""
    run_dir = Path(run_dir)
    info, run_cfg, traj = read_run(run_dir)
    cfg = cfg or run_cfg.mapping
    validate_mapping(cfg)
    if len((info.get("map_file") or {}).get("session_trajectories") or []) > 1:  # a map joined over sessions
        from rgbdslam.session.fusion import joined_source

        seq, traj, frames, per_session = joined_source(run_dir, cfg.keyframes_only, run_cfg)
        with map_of(run_dir):
            res = fuse(seq, traj, frames, cfg, run_dir / "map", None, progress)  # raw depth: keyframes/ is per run
        res.sessions = per_session
        return res
    seq = open_sequence(info["sequence"], run_cfg, purpose="map")
    check_run_frames(run_dir, info, len(seq))
    rows = match_frames(np.asarray(seq.timestamps), traj)
    tracked = np.flatnonzero(rows >= 0)
    if cfg.keyframes_only and info.get("keyframes"):
        frames = [int(i) for i in info["keyframes"]]
    elif cfg.keyframes_only:
        pick = select_by_motion(traj.poses[rows[tracked]], cfg.select_translation, cfg.select_rotation_deg)
        frames = [int(tracked[k]) for k in pick]
    else:
        frames = [int(i) for i in tracked]
    off = [g for g in info.get("segments") or [] if not g.get("map", True)]
    if off:  # never relocalised after a tracking loss: unknown offset, would be a ghost copy
        frames = [i for i in frames if not any(g["first"] <= i <= g["last"] for g in off)]
        if not frames:
            raise InputError(f"{run_dir / 'run.json'}: no frame of the run is in a tracking segment that "
                             f"belongs to the map; re-run with loop closure on (loop.enabled=true)")
    depth_dir = run_dir / "keyframes"
    with map_of(run_dir):
        return fuse(seq, traj, frames, cfg, run_dir / "map", depth_dir if depth_dir.is_dir() else None, progress)


@contextlib.contextmanager
def map_of(run_dir: Path) -> Iterator[None]:
    """The map folder of a run folder, for a block that writes the map: first nothing in the way of
    its files that the run folder's manifest does not list as a run's (an InputError naming it;
    a user's other files in map/ stay as they are), then the files made listed there."""
    m = Manifest(run_dir)
    remove_stale_stages(run_dir / MAP_DIR)  # a killed fusion's temporary folders (ours by their name)
    fix = f"move it away (a map is written only over the files rgbdslam made in {run_dir / MAP_DIR})"
    m.check_way([MAP_DIR], [RUN], fix, below=False)
    m.check_way(map_paths(), [RUN], fix)
    m.unlink_links([MAP_DIR, *map_paths()])
    yield
    m = Manifest(run_dir)  # as the block left it (a run records its own files meanwhile)
    m.record([MAP_DIR], RUN, below=False)
    m.record(map_paths(), RUN)


def map_paths() -> list[str]:
    """The files a fusion writes, relative to the run folder."""
    return [f"{MAP_DIR}/{name}" for name in MAP_FILES]


def fuse_command(run_dir: str | Path, overrides: list[str] | tuple[str, ...] = (), progress: bool = True,
                 render: Callable[[Path, Path], list[Path]] | None = None) -> FuseResult:
    """``rgbdslam fuse``: the run's config with ``mapping.key=value`` overrides, fuse, print a
    summary; ``render(run_dir, map_dir)``: also write images of the map while the folder is held
    and print the paths it returns (the CLI's ``--render`` passes :func:`rgbdslam.viz.render.render_run`)."""
    from rgbdslam.ui import console

    from rgbdslam.runfolder.folder import folder_lock

    from rgbdslam.errors import ConfigError

    for item in overrides:  # the run's other settings are fixed by its trajectory: only the map's may change
        key = item.split("=", 1)[0].strip()
        if "=" in item and not key.startswith("mapping."):
            raise ConfigError(f"fuse --set changes map settings only (mapping.KEY=VALUE); '{key}' is not one; "
                              f"re-run `rgbdslam run` to change it")
    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.yaml"
    cfg = load_config(cfg_path if cfg_path.is_file() else None, overrides)
    if not run_dir.is_dir():
        read_run(run_dir)  # the one-line error of a folder that is no run folder
    with folder_lock(run_dir, "fusion"):  # never while a run (or another fusion) writes there
        res = fuse_run(run_dir, cfg.mapping, progress=progress)
        console.print(
            f"fused {len(res.frames)} frames in {res.seconds:.1f} s (peak memory {res.peak_rss_mb:.0f} MB): "
            f"{res.n_points} cloud points, {res.n_triangles} mesh triangles -> {res.out_dir}",
            soft_wrap=True,
        )
        if render is not None:
            with map_of(run_dir):
                for p in render(run_dir, res.out_dir):
                    console.print(f"rendered {p}", soft_wrap=True, highlight=False)
    return res
