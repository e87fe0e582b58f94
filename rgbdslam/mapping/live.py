"""Fusion while tracking: keyframes go into the map in a background thread as they are made.

The map is kept as *submaps* of ``SUBMAP_SIZE`` consecutive keyframes, each with its own TSDF
volume and voxel cloud in world coordinates, integrated at the keyframe's pose when it was made
(the pose graph's current estimate). When the poses change — after a loop closure (iSAM2) and
at the end (the final batch optimisation, tracking segments left out of the map) — only the
submaps with a keyframe whose pose moved more than ``TOL_M`` / ``TOL_DEG`` (or whose set of
keyframes changed) are integrated again, from the keyframe images on disk. At the end the
submaps are merged: the voxel cloud holds sums, so its merge is exact; a TSDF voxel is a
weighted mean of the frames' signed distances, so merging submaps by their weights gives the
volume one would get integrating every keyframe into one volume (up to float rounding). The
map therefore equals fusing the final poses, up to the pose tolerance (docs/mapping.md gives
the measured difference).

All work happens in one worker thread; the tracking thread only enqueues (a keyframe's images
are held until that thread integrated them). An error in the thread is raised by :meth:`finish`.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from rgbdslam.config import MappingConfig
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import inv, rotation_angle

SUBMAP_SIZE = 8  # keyframes per submap
TOL_M = 1e-3  # a keyframe that moved less than this (and TOL_DEG) is not integrated again
TOL_DEG = 0.05


def moved(a: np.ndarray, b: np.ndarray, tol_m: float = TOL_M, tol_deg: float = TOL_DEG) -> bool:
    rel = inv(a) @ b
    return bool(np.linalg.norm(rel[:3, 3]) > tol_m or np.degrees(rotation_angle(rel[:3, :3])) > tol_deg)


@dataclass
class Submap:
    members: list[int] = field(default_factory=list)  # keyframe indices, in order
    used: dict[int, np.ndarray] = field(default_factory=dict)  # pose each member was integrated at
    tsdf: object = None
    cloud: object = None
    n_depth: int = 0


class LiveMap:
    """Keyframes fused while tracking (see the module doc).

    ``load(index) -> (rgb, depth)`` gives a keyframe's images again (for re-integration): the
    colour of the sequence and the depth the map uses (the run's filtered keyframe depth)."""

    def __init__(self, cfg: MappingConfig, camera: Camera, load: Callable[[int], tuple[np.ndarray, np.ndarray]],
                 submap_size: int = SUBMAP_SIZE):
        from rgbdslam.mapping.fusion import _Undistorter

        self.cfg = cfg
        self.camera = camera
        self.load = load
        self.submap_size = submap_size
        self.undistort = _Undistorter(camera, cfg.undistort)
        self.submaps: list[Submap] = []
        self.where: dict[int, int] = {}  # keyframe -> submap
        self.stats = {"integrated": 0, "reintegrated": 0, "submaps_rebuilt": 0, "thread_s": 0.0}
        self._queue: queue.Queue = queue.Queue()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._work, name="live-map", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------ tracking thread
    def add(self, index: int, rgb: np.ndarray, depth: np.ndarray, pose: np.ndarray) -> None:
        """A new keyframe (its depth as the map will use it) at its current world pose."""
        self._queue.put(("add", int(index), rgb, depth, np.array(pose, dtype=np.float64)))

    def update_poses(self, poses: dict[int, np.ndarray]) -> None:
        """The keyframes' current poses (after a loop closure): moved submaps are integrated again."""
        self._queue.put(("poses", {int(k): np.array(v) for k, v in poses.items()}))

    def finish(self, poses: dict[int, np.ndarray], keep: set[int] | None = None):
        """Bring every submap to the final ``poses`` (only the keyframes in ``keep``, if given),
        merge them and return ``(tsdf or None, VoxelCloud, fused keyframes, depth pixel count)``."""
        self._queue.put(("poses", ({int(k): np.array(v) for k, v in poses.items()}, keep)))
        self._queue.put(None)
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._merge(poses, keep)

    def abort(self) -> None:
        """Stop the thread without finishing (a failed or interrupted run)."""
        self._queue.put(None)

    # ------------------------------------------------------------ worker thread
    def _work(self) -> None:
        while True:
            job = self._queue.get()
            if job is None:
                return
            if self._error is not None:
                continue  # drain: finish() reports the first error
            t0 = time.perf_counter()
            try:
                if job[0] == "add":
                    self._add(*job[1:])
                else:
                    poses, keep = job[1] if isinstance(job[1], tuple) else (job[1], None)
                    self._refresh(poses, keep)
            except BaseException as e:  # noqa: BLE001 - handed to finish()
                self._error = e
            self.stats["thread_s"] += time.perf_counter() - t0

    def _new_volume(self):
        from rgbdslam.mapping.fusion import VoxelCloud, _Tsdf

        return (_Tsdf(self.cfg, self.camera) if self.cfg.mesh else None), VoxelCloud(self.cfg.voxel_size)

    def _integrate(self, sub: Submap, index: int, rgb, depth, pose) -> None:
        from rgbdslam.mapping.fusion import integrate_frame, prepare_frame

        rgb, depth = prepare_frame(rgb, depth, self.undistort, self.cfg)
        sub.n_depth += int(np.count_nonzero(depth))
        integrate_frame(sub.tsdf, sub.cloud, rgb, depth, pose, self.camera, self.cfg)
        sub.used[index] = pose

    def _add(self, index: int, rgb, depth, pose) -> None:
        if not self.submaps or len(self.submaps[-1].members) >= self.submap_size:
            self.submaps.append(Submap())
        sub = self.submaps[-1]
        if sub.tsdf is None and sub.cloud is None:
            sub.tsdf, sub.cloud = self._new_volume()
        sub.members.append(index)
        self.where[index] = len(self.submaps) - 1
        self._integrate(sub, index, rgb, depth, pose)
        self.stats["integrated"] += 1

    def _refresh(self, poses: dict[int, np.ndarray], keep: set[int] | None) -> None:
        for sub in self.submaps:
            want = [i for i in sub.members if i in poses and (keep is None or i in keep)]
            stale = set(want) != set(sub.used) or any(moved(sub.used[i], poses[i]) for i in want)
            if not stale:
                continue
            sub.tsdf, sub.cloud = self._new_volume()
            sub.used, sub.n_depth = {}, 0
            for i in want:
                rgb, depth = self.load(i)
                self._integrate(sub, i, rgb, depth, poses[i])
                self.stats["reintegrated"] += 1
            self.stats["submaps_rebuilt"] += 1

    # ------------------------------------------------------------ the end
    def _merge(self, poses, keep):
        from rgbdslam.mapping.fusion import VoxelCloud

        subs = [s for s in self.submaps if s.used]
        cloud = VoxelCloud(self.cfg.voxel_size)
        for s in subs:
            s.cloud._merge()
            cloud.pending.append((s.cloud.keys, s.cloud.sums, s.cloud.counts))
        cloud._merge()
        tsdf = None
        if self.cfg.mesh and subs:
            tsdf = subs[0].tsdf
            for s in subs[1:]:
                merge_tsdf(tsdf.vol, s.tsdf.vol)
        fused = sorted(i for s in subs for i in s.used)
        n_depth = sum(s.n_depth for s in subs)
        self.submaps = []
        return tsdf, cloud, fused, n_depth


def merge_tsdf(dst, src) -> None:
    """Add the Open3D VoxelBlockGrid ``src`` into ``dst`` (same voxel size and attributes):
    per voxel the weight-averaged TSDF value and colour, weights added — what integrating
    ``src``'s frames into ``dst`` would have given."""
    import open3d.core as o3c

    hs = src.hashmap()
    idx = hs.active_buf_indices().to(o3c.int64)
    if idx.shape[0] == 0:
        return
    keys = hs.key_tensor()[idx]
    idx = idx.numpy()
    s_t = src.attribute("tsdf").numpy()[idx]
    s_w = src.attribute("weight").numpy()[idx].astype(np.float32)
    s_c = src.attribute("color").numpy()[idx].astype(np.float32)
    hd = dst.hashmap()
    _, existed = hd.find(keys)
    existed = existed.numpy().astype(bool)
    hd.activate(keys)  # new blocks; may grow the table, so the attribute views are taken after it
    buf, _ = hd.find(keys)
    buf = buf.to(o3c.int64).numpy()
    T, W, C = dst.attribute("tsdf").numpy(), dst.attribute("weight").numpy(), dst.attribute("color").numpy()
    new_blocks = ~existed  # activated now: their memory is not cleared
    d_w = W[buf].astype(np.float32)
    d_w[new_blocks] = 0
    d_t = np.where(new_blocks[:, None, None, None, None], 0, T[buf])
    d_c = np.where(new_blocks[:, None, None, None, None], 0, C[buf]).astype(np.float32)
    tw = d_w + s_w
    safe = np.where(tw > 0, tw, 1)
    T[buf] = np.where(tw > 0, (d_t * d_w + s_t * s_w) / safe, d_t)
    C[buf] = np.clip(np.round(np.where(tw > 0, (d_c * d_w + s_c * s_w) / safe, d_c)), 0, 65535).astype(np.uint16)
    W[buf] = np.clip(tw, 0, 65535).astype(np.uint16)
