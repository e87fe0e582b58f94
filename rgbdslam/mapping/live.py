"""Fusion while tracking: keyframes go into the map in a separate process as they are made.

One TSDF volume and one voxel cloud hold the map, each keyframe integrated at the pose the pose
graph gave it when it was made. Both are sums over frames — the cloud per voxel the sum of
positions, colours and the point count; a TSDF voxel the weighted mean of the frames' signed
distances with the number of frames as weight — so a frame can be taken out again exactly:
when poses change (after a loop closure, a batch optimisation of the graph so far; at the end,
the final optimisation and the tracking segments left out of the map), the keyframes whose points
moved more than a quarter of a voxel (:func:`shift_m`) are *de-integrated* (their images integrated into a scratch volume at the old pose and
subtracted) and integrated at the new pose. When more than half of the keyframes moved, the map
is rebuilt instead (one integration per keyframe instead of two). So the map at the end is the
one fusing the final poses gives, up to the quarter-voxel tolerance and float rounding
(docs/mapping.md, "Fusion while tracking", has the measured difference), and memory is that of
one map, not of one volume per keyframe.

The newest ``mapping.live_lag`` keyframes wait before they go into the map (their poses still move
with every loop closure; at the end they are integrated once, at their final poses).

All the work happens in the map process (:class:`LiveMap`); the tracking thread only enqueues.
While tracking the map process works in a thread niced by ``mapping.live_nice`` — in its main
thread, at the run's priority, whenever it is more than ``mapping.live_backlog`` keyframes behind
(:func:`_while_tracking`) — and after the last frame in its main thread. It takes every queued job before it integrates a
keyframe: pose updates are coalesced (when several are waiting, only the newest is applied) and
come before the integration of keyframes queued with them. A keyframe's prepared images are cached for re-integration (up to
:data:`CACHE_MB`; beyond, ``load`` reads them again). At the end the cloud is brought to the final
poses first and left for the cloud process (files in the map's temporary folder), then the TSDF and
the mesh (:func:`_finish`). An error in the
process is raised by :meth:`LiveMap.finish`.
"""

from __future__ import annotations

import queue
import time
from typing import Callable

import numpy as np

from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import inv, rotation_angle
from rgbdslam.io.worker import end, exit_now, in_niced_thread, receive, stop
from rgbdslam.mapping.config import MappingConfig

CACHE_MB = 512  # keyframe images kept for re-integration (640x480: ~1.5 MB each); beyond, they are read again
REBUILD_FRACTION = 0.5  # more keyframes than this share moved: rebuild the map instead of de-/re-integrating
SCRATCH_BLOCKS_PER_KEYFRAME = 1500  # TSDF blocks one 640x480 keyframe touches (~1150 on fr1/rpy), preallocated
SCRATCH_MAX_BLOCKS = 16000  # at most (94 MB) for a scratch volume; beyond, its hash map grows
REDO_CHUNK = 32  # keyframes taken out and put in again together (their images held meanwhile)
# the cloud handed to the cloud process, and the indices of the points its outlier removal keeps
CLOUD_POINTS, CLOUD_COLORS, CLOUD_KEEP = ".cloud-points.npy", ".cloud-colors.npy", ".cloud-keep.npy"
SIZE_LOG_EVERY = 100  # keyframes between two entries of the map's size log (run.json map.timings.size_log)


def shift_m(a: np.ndarray, b: np.ndarray, depth_max: float, box: np.ndarray | None = None) -> float:
    """How far a keyframe's points move from pose ``a`` to ``b`` at most, in metres.

    With ``box`` (2x3: the lowest and highest x, y, z of its points in its camera frame) it is exact
    for that box: a point p moves by |(R - I) p + t| (R, t: the relative pose ``a``^-1 ``b``), a convex
    function of p, so its largest value over the box is at one of the box's 8 corners. Without a box:
    the translation plus the rotation angle times ``depth_max`` (a point straight ahead at depth_max)."""
    rel = inv(a) @ b
    if box is None:
        return float(np.linalg.norm(rel[:3, 3]) + rotation_angle(rel[:3, :3]) * depth_max)
    corners = np.array([[box[i, 0], box[j, 1], box[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    step = corners @ (rel[:3, :3] - np.eye(3)).T + rel[:3, 3]
    return float(np.sqrt((step * step).sum(axis=1)).max())


def points_box(depth: np.ndarray, camera: Camera) -> np.ndarray | None:
    """The lowest and highest camera-frame x, y, z (2x3) of the points of a prepared depth image
    (depth > 0); None when it has none.

    Per image column (row) only the nearest and the farthest depth matter: x = (u - cx) z / fx is
    monotonic in z for a fixed column u, so its extremes over the column are at those two depths
    (the same products as over every pixel, so the same numbers; 1.3 instead of 5.9 ms of CPU on
    a 640x480 keyframe)."""
    ok = depth > 0
    cols, rows = ok.any(axis=0), ok.any(axis=1)
    if not cols.any():
        return None
    near, far = np.where(ok, depth, np.inf), np.where(ok, depth, -np.inf)
    u, v = np.flatnonzero(cols), np.flatnonzero(rows)
    zc = np.concatenate([near.min(axis=0)[cols], far.max(axis=0)[cols]]).astype(np.float64)
    zr = np.concatenate([near.min(axis=1)[rows], far.max(axis=1)[rows]]).astype(np.float64)
    x = (np.concatenate([u, u]) - camera.cx) * zc / camera.fx
    y = (np.concatenate([v, v]) - camera.cy) * zr / camera.fy
    return np.array([[x.min(), y.min(), zc.min()], [x.max(), y.max(), zc.max()]])


class MapState:
    """The map as keyframes are added and moved (see the module doc); synchronous — it runs in
    the map process (:class:`LiveMap`) or wherever it is called.

    ``load(index) -> (rgb, depth)`` gives a keyframe's images again: the colour of the sequence
    and the depth the map uses (the run's filtered keyframe depth)."""

    def __init__(self, cfg: MappingConfig, camera: Camera, load: Callable[[int], tuple[np.ndarray, np.ndarray]],
                 cache_mb: float = CACHE_MB):
        from rgbdslam.mapping.fusion import Undistorter

        self.cfg = cfg
        self.camera = camera
        self.load = load
        self.undistort = Undistorter(camera, cfg.undistort)
        # live_tolerance voxels (a quarter by default): how far a keyframe's points may be from where
        # its final pose puts them (translation + rotation angle x depth_max)
        self.tol_m = min(cfg.voxel_size, cfg.tsdf_voxel) * cfg.live_tolerance
        self.tsdf = None
        self.cloud = None
        self.used: dict[int, np.ndarray] = {}  # keyframe -> pose it is in the map at
        self.lag = cfg.live_lag
        self.waiting: dict[int, np.ndarray] = {}  # the newest keyframes, not in the map yet -> their latest pose
        # keyframes' prepared images for re-integration, up to cache_mb (then read again with load)
        self.cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.cache_bytes = 0
        self.cache_limit = int(cache_mb * 2**20)
        self.n_depth: dict[int, int] = {}
        self.box: dict[int, np.ndarray | None] = {}  # keyframe -> its points' camera-frame box (shift_m)
        self.stats = {"integrated": 0, "deintegrated": 0, "reintegrated": 0, "rebuilds": 0, "refreshes": 0,
                      "pose_updates_skipped": 0, "reloaded": 0, "final_moved": 0, "final_shift_median_mm": 0.0,
                      "final_shift_max_mm": 0.0, "final_s": 0.0, "busy_s": 0.0,
                      "busy_cpu_s": 0.0, "catch_ups": 0, "catch_up_s": 0.0, "catch_up_cpu_s": 0.0}

    def sizes(self) -> dict:
        """What the map holds (docs/benchmarks.md "Memory"): TSDF blocks in use and allocated (8^3
        voxels of 12 bytes; Open3D's hash map doubles its capacity when full), cloud voxels (64 bytes
        each while summing), cached keyframe images."""
        out = {"cache_mb": self.cache_bytes / 2**20, "cached_keyframes": len(self.cache)}
        if self.cloud is not None:
            out["cloud_voxels"] = len(self.cloud)
        if self.tsdf is not None:
            hm = self.tsdf.vol.hashmap()
            out.update(tsdf_blocks=int(hm.size()), tsdf_capacity_blocks=int(hm.capacity()),
                       tsdf_mb=hm.capacity() * 512 * 12 / 2**20)
        return out

    def shift_mm(self, poses: dict[int, np.ndarray]) -> np.ndarray:
        """How far each keyframe in the map would move to ``poses`` (the most any of its points moves,
        :func:`shift_m`), in mm."""
        return 1e3 * np.array([self._shift(i, poses[i]) for i in self.used if i in poses])

    def _shift(self, index: int, pose: np.ndarray) -> float:
        return shift_m(self.used[index], pose, max(self.cfg.depth_max, 1e-3), self.box.get(index))

    def result(self):
        """``(tsdf or None, VoxelCloud, fused keyframes, depth pixel count)``."""
        fused = sorted(self.used)
        return self.tsdf, self.cloud, fused, sum(self.n_depth[i] for i in fused)

    def _volume(self, tsdf: bool = True, cloud: bool = True, blocks: int = 0):
        """A new, empty TSDF (None without a mesh or when not ``tsdf``; ``blocks`` preallocated, at
        least ``mapping.tsdf_initial_blocks``) and voxel cloud (None when not ``cloud``)."""
        import dataclasses

        from rgbdslam.mapping.fusion import VoxelCloud, Tsdf

        cfg = self.cfg if blocks <= self.cfg.tsdf_initial_blocks else dataclasses.replace(self.cfg, tsdf_initial_blocks=blocks)
        return ((Tsdf(cfg, self.camera) if self.cfg.mesh and tsdf else None),
                VoxelCloud(self.cfg.voxel_size) if cloud else None)

    def _prepared(self, index: int, rgb=None, depth=None) -> tuple[np.ndarray, np.ndarray]:
        """A keyframe's colour and depth as fused (:func:`prepare_frame`): from the cache, else
        prepared from ``rgb``/``depth`` or from ``load`` (and cached while the cache has room)."""
        from rgbdslam.mapping.fusion import prepare_frame
        from rgbdslam.runfolder.depth import DEPTH_SCALE

        hit = self.cache.get(index)
        if hit is not None:
            return hit[0], _unpack_depth(hit[1])
        if rgb is None:
            rgb, depth = self.load(index)
            self.stats["reloaded"] += 1
        rgb, depth = prepare_frame(rgb, depth, self.undistort, self.cfg)
        self.n_depth[index] = int(np.count_nonzero(depth))
        if index not in self.box:
            self.box[index] = points_box(depth, self.camera)
        keep = _pack_depth(depth, DEPTH_SCALE)
        size = rgb.nbytes + keep.nbytes
        if self.cache_bytes + size <= self.cache_limit:
            self.cache[index] = (rgb, keep)
            self.cache_bytes += size
        return rgb, depth

    def _uncache(self, index: int) -> None:
        hit = self.cache.pop(index, None)
        if hit is not None:
            self.cache_bytes -= hit[0].nbytes + hit[1].nbytes

    def _integrate(self, tsdf, cloud, pose, prepared: tuple[np.ndarray, np.ndarray]) -> None:
        from rgbdslam.mapping.fusion import integrate_frame

        integrate_frame(tsdf, cloud, *prepared, pose, self.camera, self.cfg)

    def add(self, index: int, rgb, depth, pose, settle: bool = True) -> None:
        """A new keyframe at ``pose``. It waits (``mapping.live_lag`` keyframes, :attr:`waiting`)
        before it goes into the map: the newest keyframes' poses move with every loop closure, and
        a keyframe integrated once at a settled pose costs one integration where one moved later
        costs three (de-integration, re-integration and the merges). Without ``settle`` it only
        waits: the map process integrates (:meth:`settle`) when no pose update is queued."""
        prepared = self._prepared(index, rgb, depth)
        self.waiting[index] = pose
        while settle and self.unsettled():
            self.settle(prepared if min(self.waiting) == index else None)

    def unsettled(self) -> bool:
        """True when more keyframes wait than ``mapping.live_lag``."""
        return self.backlog() > 0

    def backlog(self) -> int:
        """How many keyframes wait beyond ``mapping.live_lag``: the ones the map is behind by."""
        return max(0, len(self.waiting) - self.lag)

    def settle(self, prepared=None) -> None:
        """The oldest waiting keyframe into the map, at its newest pose (``prepared``: its images)."""
        first = min(self.waiting)
        self._put({first: self.waiting.pop(first)}, ("cloud", "tsdf"), prepared)

    def _put(self, poses: dict[int, np.ndarray], parts: tuple[str, ...], prepared=None) -> None:
        """Integrate the keyframes ``poses`` (not in the map yet) at those poses into the ``parts``
        of the map ("cloud", "tsdf"); with ``prepared``: the images of the only keyframe."""
        if "cloud" in parts and self.cloud is None:  # the first keyframe
            self.tsdf, self.cloud = self._volume()
        tsdf = self.tsdf if "tsdf" in parts else None
        cloud = self.cloud if "cloud" in parts else None
        if tsdf is None and cloud is None:  # the TSDF part without a mesh: the cloud part did it all
            return
        for i, pose in poses.items():
            self._integrate(tsdf, cloud, pose, prepared if prepared is not None else self._prepared(i))
            if "tsdf" not in parts and self.tsdf is not None:
                continue  # the TSDF part follows (the end: the cloud goes first)
            self.used[i] = pose
            self.stats["integrated"] += 1
            if self.stats["integrated"] % SIZE_LOG_EVERY == 0:  # how the map grows (docs/benchmarks.md "Memory")
                from rgbdslam.mapping.fusion import rss_mb

                self.stats.setdefault("size_log", []).append(
                    {"keyframes": self.stats["integrated"], "rss_mb": round(rss_mb(), 1),
                     **{k: round(v, 1) if isinstance(v, float) else v for k, v in self.sizes().items()}})

    def refresh(self, poses: dict[int, np.ndarray], keep: set[int] | None = None, between=None,
                flush: bool = False) -> int:
        """Bring the map to ``poses`` (keyframes without one stay where they are; only the keyframes
        in ``keep``, if given); returns how many keyframes in the map moved or left. The waiting
        keyframes take their new poses (they are not in the map yet: nothing to redo); with
        ``flush`` (the end) they are integrated at them.

        ``between(fused)``, if given, is called when the cloud is at the poses and before the TSDF
        is (``fused``: the keyframes the map then holds): at the end of a run the cloud goes to the
        run, which removes its outliers and makes the 2-D map while the TSDF is redone here."""
        for i in list(self.waiting):
            if keep is not None and i not in keep:
                del self.waiting[i]
                self.box.pop(i, None)
                self._uncache(i)
            elif i in poses:
                self.waiting[i] = poses[i]
        want = {i: poses.get(i, p) for i, p in self.used.items() if keep is None or i in keep}
        drop = [i for i in self.used if i not in want]
        move = [i for i in want if self._shift(i, want[i]) > self.tol_m]
        put = dict(sorted(self.waiting.items())) if flush else {}
        n = len(drop) + len(move)
        rebuild = n > REBUILD_FRACTION * len(self.used)
        if n:
            self.stats["refreshes"] += 1
            self.stats["rebuilds"] += rebuild
            self.stats["deintegrated"] += 0 if rebuild else n
            self.stats["reintegrated"] += len(want) if rebuild else len(move)
        for parts in ((("cloud", "tsdf"),) if between is None else (("cloud",), None, ("tsdf",))):
            if parts is None:
                between(sorted(set(want) | set(put)))
                continue
            if n:
                self._redo(parts, want, drop + move, rebuild)
            if put:
                self._put(put, parts)
        for i in drop:
            del self.used[i]
            self.box.pop(i, None)
            self._uncache(i)
        self.used.update(want if rebuild else {i: want[i] for i in move})  # a rebuild put every keyframe at its pose
        if flush:
            self.stats["final_waiting"] = len(put)
            self.waiting.clear()
        return n

    def _redo(self, parts: tuple[str, ...], want: dict[int, np.ndarray], redo: list[int], rebuild: bool) -> None:
        """The ``parts`` of the map ("cloud", "tsdf") made again from the keyframes ``want`` at
        their poses (``rebuild``), or with the keyframes ``redo`` taken out at the pose they are in
        the map at (integrated into a scratch volume that is subtracted) and integrated again at
        their ``want`` pose (those that have one) straight into the map: Open3D's running weighted
        mean is what adding a one-frame volume gives."""
        tsdf = "tsdf" in parts and self.tsdf is not None
        cloud = "cloud" in parts
        if not (tsdf or cloud):  # no mesh
            return
        if rebuild:
            t, c = self._volume(tsdf, cloud)
            for i, pose in want.items():
                self._integrate(t, c, pose, self._prepared(i))
            self.tsdf = t if tsdf else self.tsdf
            self.cloud = c if cloud else self.cloud
            return
        for k in range(0, len(redo), REDO_CHUNK):  # the images of a chunk are held (read once when not cached)
            chunk = {i: self._prepared(i) for i in redo[k:k + REDO_CHUNK]}
            # the scratch volume sized for the keyframes it takes (a growing hash map costs ~70 % more per frame)
            old_t, old_c = self._volume(tsdf, cloud, blocks=min(SCRATCH_BLOCKS_PER_KEYFRAME * len(chunk),
                                                                SCRATCH_MAX_BLOCKS))
            for i, prepared in chunk.items():
                self._integrate(old_t, old_c, self.used[i], prepared)
            if tsdf:
                merge_tsdf(self.tsdf.vol, old_t.vol, sign=-1)
            if cloud:
                add_cloud(self.cloud, old_c, sign=-1)
            del old_t, old_c
            for i, prepared in chunk.items():
                if i in want:
                    self._integrate(self.tsdf if tsdf else None, self.cloud if cloud else None, want[i], prepared)


def _pack_depth(depth: np.ndarray, scale: float) -> np.ndarray:
    """Depth in 1/``scale`` m steps, as the TUM reader (steps x float32(1/scale)) or a keyframe PNG
    (steps / scale) makes it, as uint16 steps (2 bytes a pixel instead of 4) with the way back in
    its ``dtype`` metadata; other depth as it is. Lossless either way (:func:`_unpack_depth`)."""
    units = np.round(depth.astype(np.float64) * scale)
    if units.min(initial=0) < 0 or units.max(initial=0) > 65535:
        return depth
    steps = units.astype(np.uint16)
    for how in ("mul", "div"):
        packed = steps.view(np.dtype(np.uint16, metadata={"scale": scale, "how": how}))
        if np.array_equal(_unpack_depth(packed), depth):
            return packed
    return depth


def _unpack_depth(packed: np.ndarray) -> np.ndarray:
    if packed.dtype != np.uint16:
        return packed
    scale, how = packed.dtype.metadata["scale"], packed.dtype.metadata["how"]
    steps = packed.astype(np.float32)
    return steps * np.float32(1.0 / scale) if how == "mul" else steps / scale


class _SequenceImages:
    """``load(index)`` for the map process: the sequence re-opened there, the filtered keyframe
    depth from ``depth_dir`` where the run wrote it."""

    def __init__(self, root: str, dataset_cfg, depth_dir: str | None):
        self.root, self.dataset_cfg, self.depth_dir = root, dataset_cfg, depth_dir
        self._seq = None

    def __call__(self, i: int):
        from rgbdslam.datasets import open_sequence
        from rgbdslam.runfolder.depth import keyframe_depth_path, read_keyframe_depth

        if self._seq is None:
            # the whole config: a stereo sequence then computes its map depth (stereo.map_depth, e.g. SGBM)
            self._seq = open_sequence(self.root, self.dataset_cfg, purpose="map")
        frame = self._seq.load(i)
        png = keyframe_depth_path(self.depth_dir, i) if self.depth_dir else None
        return frame.rgb, (read_keyframe_depth(png) if png is not None and png.is_file() else frame.depth)


def limit_threads(n: int) -> None:
    """At most ``n`` threads (0: as many as there are cores) for Open3D's (oneTBB) and OpenCV's
    parallel loops in this process. While tracking the map process keeps to one: it is niced, and
    a second thread that waits for the core tracking uses stalls the first at every join."""
    import cv2
    import open3d as o3d

    if hasattr(o3d.utility, "set_max_threads"):
        o3d.utility.set_max_threads(n)
    cv2.setNumThreads(n if n else -1)


def _process(cfg: MappingConfig, camera: Camera, load, jobs, results, applied=None) -> None:
    """The map process's body: :func:`_serve`, then exit without the interpreter's teardown (freeing
    Open3D's and NumPy's modules takes longer than the map's last step; the run waits for it)."""
    _serve(cfg, camera, load, jobs, results, applied)
    exit_now(results)


def _serve(cfg: MappingConfig, camera: Camera, load, jobs, results, applied=None) -> None:
    """The map process: keyframes and pose updates from ``jobs`` (:func:`_while_tracking`: in a
    thread niced by ``mapping.live_nice`` while it keeps up); at ``finish`` the map is brought to the
    final poses, written, and its :class:`FuseResult` put on ``results`` — in the main thread,
    at the run's priority and with every core (the user waits for it now)."""
    import signal

    from rgbdslam.io.worker import follow_parent

    follow_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the driver's to handle: it stops us
    try:
        # Open3D's and OpenCV's imports (~1 s of CPU) once the first keyframe is here, i.e. after the run
        # has tracked its first frame: at start they competed with the run's own start-up (on a busy
        # machine its first frame came 2-4 s later); niced, a busy machine starved them past the run
        first = jobs.get()
        if first is None:
            return
        state = _start(cfg, camera, load)
        finish = _while_tracking(state, cfg, jobs, applied, first)
        if finish is not None:
            limit_threads(0)  # tracking is over: the redo, the TSDF and the mesh may use every core
            results.put(("ok", _finish(state, results, *finish[1:])))
    except BaseException as e:  # noqa: BLE001 - the driver reports it (OSError as itself: a full disk names its file)
        from rgbdslam.errors import RgbdslamError

        results.put(("error", e if isinstance(e, (RgbdslamError, OSError)) else RuntimeError(f"{type(e).__name__}: {e}")))


def _start(cfg: MappingConfig, camera: Camera, load) -> MapState:
    """The map process's state, Open3D imported, one core for the map while tracking."""
    state = MapState(cfg, camera, load)
    limit_threads(1)
    return state


BEHIND, CAUGHT_UP = "behind", "caught up"  # what _track returns when its ``stop`` says so


def _queued(jobs) -> int:
    """How many jobs wait in ``jobs`` (0 where a queue cannot tell)."""
    try:
        return jobs.qsize()
    except NotImplementedError:  # pragma: no cover - macOS
        return 0


def _while_tracking(state: MapState, cfg: MappingConfig, jobs, applied=None, first=None):
    """The map process while tracking: :func:`_track` in a thread niced by ``mapping.live_nice``
    (tracking first) while the map keeps up; when more than ``mapping.live_backlog`` keyframes wait
    beyond ``mapping.live_lag`` (the niced thread gets too little CPU: a busy machine), in this
    thread, at the run's priority, until none does, then niced again. So what is left for after
    the last frame stays bounded (``live_lag`` + ``live_backlog`` keyframes and the redo of the
    last pose update) whatever the machine's load; on a machine with a free core the niced thread
    keeps up and tracking keeps its speed. The jobs still queued count as keyframes behind too (a
    niced thread that takes 50 queued keyframes first spends its little CPU on preparing them).
    ``first``: a job already taken from ``jobs``. Returns the ``finish`` job or None (stopped)."""
    bound = cfg.live_backlog
    taken = [first] if first is not None else []  # jobs taken from ``jobs`` and not done yet (oldest first)
    while True:
        out = in_niced_thread(cfg.live_nice, lambda: _track(
            state, jobs, applied, taken,
            stop=(lambda: BEHIND if _behind(state, jobs, taken) > bound else None) if cfg.live_nice else None))
        if out != BEHIND:
            return out
        state.stats["catch_ups"] += 1
        t0, c0 = time.perf_counter(), time.process_time()
        out = _track(state, jobs, applied, taken, stop=lambda: CAUGHT_UP if not _behind(state, jobs, taken) else None)
        state.stats["catch_up_s"] += time.perf_counter() - t0
        state.stats["catch_up_cpu_s"] += time.process_time() - c0
        if out != CAUGHT_UP:
            return out


def _behind(state: MapState, jobs, taken: list) -> int:
    """Keyframes the map is behind by: waiting beyond ``mapping.live_lag``, taken and not added yet,
    or still queued (every job counted as one)."""
    return state.backlog() + sum(j is not None and j[0] == "add" for j in taken) + _queued(jobs)


def _track(state: MapState, jobs, applied=None, taken: list | None = None,
           stop: Callable[[], str | None] | None = None):
    """The map while tracking: keyframes and pose updates from ``jobs`` until ``finish`` (returned)
    or None (returns None). Every job queued is taken before a keyframe is integrated: a pose update
    is applied first and the keyframes waiting go in at their newest poses. ``taken`` (oldest first)
    holds the jobs taken from ``jobs`` and not done yet; they come before the queue's.

    ``stop()`` ends it early with what it returns (:data:`BEHIND`, :data:`CAUGHT_UP`). It is asked
    before every step: before a job is taken, after every keyframe added (each is prepared:
    undistorted, its box found) and before a pose update is applied — so a niced thread that
    took many queued jobs at once hands them back (in ``taken``, in order) as soon as the map is
    behind, instead of working through all of them at its low priority first."""
    taken = [] if taken is None else taken

    def take(block: bool):
        if taken:
            return taken.pop(0)
        return jobs.get() if block else jobs.get_nowait()

    while True:
        if stop is not None and (why := stop()) is not None:
            return why
        try:  # a keyframe to integrate: only when no job waits
            job = take(block=not state.unsettled())
        except queue.Empty:
            job = ("settle",)
        if job is None:
            return None
        t0, c0 = time.perf_counter(), time.process_time()
        batch = [job]
        while job[0] not in ("finish", "settle"):  # everything queued: the keyframes, the newest poses
            try:
                job = take(block=False)
            except queue.Empty:
                break
            if job is None:
                return None
            batch.append(job)
        why = None
        for k, j in enumerate(batch):
            if j[0] != "add":
                continue
            state.add(*j[1:], settle=False)
            if stop is None:
                continue
            rest = batch[k + 1:]
            taken[:0] = rest  # counted as behind while stop() is asked; the other thread's if it stops
            if (why := stop()) is not None:
                batch = batch[:k + 1]
                break
            del taken[:len(rest)]
        finish = batch[-1] if batch[-1][0] == "finish" else None
        poses = [j for j in batch if j[0] == "poses"]
        if why is None and poses and finish is None and stop is not None:
            why = stop()
        if why is not None:  # the pose update is the other thread's (before the jobs handed back)
            taken[:0] = poses
            poses = []
        n_poses = len(poses)
        if why is None and job[0] == "settle":
            state.settle()
        elif n_poses:
            state.stats["pose_updates_skipped"] += n_poses - (finish is None)
            if finish is None:
                state.refresh(poses[-1][1])
        state.stats["busy_s"] += time.perf_counter() - t0
        state.stats["busy_cpu_s"] += time.process_time() - c0  # all its threads (Open3D's too)
        if n_poses and applied is not None:
            with applied.get_lock():
                applied.value += n_poses
        if finish is not None:
            return finish
        if why is not None:
            return why


def _finish(state: MapState, results, poses, keep, stage: str, filtered_depth: bool) -> dict:
    """The end, in the map process: the map brought to the final poses, the cloud first: its points
    are saved into the run's temporary map folder ``stage`` (:data:`CLOUD_POINTS`, :data:`CLOUD_COLORS`)
    and ``("cloud", fused keyframes)`` put on ``results`` (the cloud process removes the outliers and
    makes the 2-D map, the run writes cloud.ply) while this process brings the TSDF to the poses and
    extracts and writes mesh.ply into ``stage``."""
    from pathlib import Path

    from rgbdslam.errors import InputError
    from rgbdslam.mapping.fusion import check_depth, cloud_points, peak_rss_mb, write_mesh
    from rgbdslam.ui import console

    t0, c0 = time.perf_counter(), time.process_time()
    state.stats["at_map_finish"] = time.time()
    shift = state.shift_mm(poses)
    state.stats["final_shift_mm"] = {int(i): round(float(s), 2) for i, s in zip((i for i in state.used if i in poses), shift)
                                     if s > 1e3 * state.tol_m}
    if len(shift):
        state.stats["final_shift_median_mm"] = float(np.median(shift))
        state.stats["final_shift_max_mm"] = float(shift.max())
    # how far the waiting keyframes' newest poses were from their final ones
    state.stats["final_waiting_shift_mm"] = {
        int(i): round(1e3 * shift_m(p, poses[i], max(state.cfg.depth_max, 1e-3), state.box.get(i)), 2)
        for i, p in state.waiting.items() if i in poses}

    def send_cloud(fused: list[int]) -> None:
        if not fused:
            raise InputError("no keyframe of the run is in a tracking segment that belongs to the map; "
                             "re-run with loop closure on (loop.enabled=true)")
        check_depth(sum(state.n_depth[i] for i in fused), fused, state.cfg, filtered_depth)
        t1 = time.perf_counter()
        state.stats["final_cloud_s"] = t1 - t0
        state.stats["cloud_voxels"] = len(state.cloud)
        points, colors = cloud_points(state.cloud, state.cfg)
        state.cloud = None
        # through a file in the map's temporary folder, not the queue: a queue pipes its ~10 MB
        # in 64 KB pieces to the run and again to the cloud process (0.4 + 0.8 s at load 12)
        _save_handover(stage, CLOUD_POINTS, points)
        _save_handover(stage, CLOUD_COLORS, colors)
        results.put(("cloud", fused))
        state.stats["cloud_points"] = time.perf_counter() - t1
        state.stats["at_cloud_sent"] = time.time()

    state.stats["final_moved"] = state.refresh(poses, keep, between=send_cloud, flush=True)
    state.stats["final_s"] = time.perf_counter() - t0 - state.stats["cloud_points"]
    state.stats["at_tsdf_done"] = time.time()
    tsdf, _, fused, _ = state.result()
    state.stats.update(state.sizes())
    state.cache.clear()  # the images are not needed any more
    out = {"mesh_path": None, "n_vertices": 0, "n_triangles": 0}
    if tsdf is not None:
        t0 = time.perf_counter()
        path, out["n_vertices"], out["n_triangles"] = write_mesh(Path(stage), tsdf, len(fused), state.cfg, console)
        out["mesh_path"] = str(path) if path is not None else None
        state.stats["mesh"] = time.perf_counter() - t0
        state.stats["at_mesh_done"] = time.time()
    state.stats["final_cpu_s"] = time.process_time() - c0  # CPU of every thread of the map process after the last frame
    out["timings"] = {k: round(v, 3) if isinstance(v, float) else v for k, v in state.stats.items()}
    out["peak_rss_mb"] = peak_rss_mb()
    return out


BLAS_THREADS = "OPENBLAS_NUM_THREADS"  # read by NumPy's OpenBLAS when a process imports NumPy


def one_blas_thread() -> None:
    """The processes this one starts from now on (the map, cloud and plot processes) run NumPy's
    OpenBLAS on one thread, unless the user set ``OPENBLAS_NUM_THREADS``; this process's NumPy is
    loaded already and keeps its threads. Their matrix products are tall and thin (N x 3 points
    times a 3 x 3 rotation): split over OpenBLAS's threads, whose workers spin while they wait, the
    2-D map's (380k x 3) @ (3 x 3) took 145 ms of CPU instead of 5 ms beside a busy core, at the
    end where both cores are busy; and the workers, started by the map process's main thread, ran
    at the run's priority beside tracking where the map's thread is niced. :class:`LiveMap` calls
    it in the run's main thread before tracking starts (the environment is not changed while the
    run's other threads may read it)."""
    import os

    os.environ.setdefault(BLAS_THREADS, "1")


class LiveMap:
    """The map process, seen from the run: keyframes and pose updates are sent to it as they are
    made (:meth:`add`, :meth:`update_poses`), :meth:`finish` waits for the written map.

    It is a process, not a thread: integrating a keyframe is long C++ calls (Open3D, NumPy) that
    would hold the interpreter lock and stall tracking; another process runs beside it on its own
    core. It is started with ``spawn`` (a fresh interpreter) and imports Open3D while the first
    frames are tracked."""

    def __init__(self, cfg: MappingConfig, camera: Camera, root: str, dataset_cfg, depth_dir: str | None):
        from rgbdslam.io.worker import spawn_context, start

        one_blas_thread()
        ctx = spawn_context()
        self.cfg = cfg
        self._jobs = ctx.Queue()
        self._results = ctx.Queue()
        self._applied = ctx.Value("q", 0)  # pose updates the map process has applied
        self._sent = 0
        self._proc = ctx.Process(target=_process, name="rgbdslam-map", daemon=True,
                                 args=(cfg, camera, _SequenceImages(root, dataset_cfg, depth_dir), self._jobs,
                                       self._results, self._applied))
        start(self._proc)
        self._cloud = None  # the cloud process: started with the first keyframe (after the first frame)

    def add(self, index: int, rgb: np.ndarray, depth: np.ndarray, pose: np.ndarray) -> None:
        """A new keyframe (its depth as the map will use it) at its current world pose."""
        self._jobs.put(("add", int(index), rgb, depth, np.array(pose, dtype=np.float64)))
        if self._cloud is None:
            # the cloud's end (outlier removal, cloud.ply, the 2-D map) in a third process that imports
            # Open3D niced while tracking: in the run process that import (~1 s of CPU) came after the
            # last frame, on the end's longest chain; started now, not beside the run's own start-up
            from rgbdslam.io.worker import Helper

            self._cloud = Helper("cloud process", "rgbdslam.mapping.live:_warm_cloud", self.cfg.live_nice)

    def update_poses(self, poses: dict[int, np.ndarray]) -> None:
        """The keyframes' current poses (after a loop closure): moved keyframes are re-integrated."""
        self._sent += 1
        self._jobs.put(("poses", {int(k): np.array(v) for k, v in poses.items()}))

    def ready(self) -> bool:
        """True when the map process has applied every pose update sent so far."""
        return self._applied.value >= self._sent

    def finish(self, poses: dict[int, np.ndarray], keep: set[int] | None, out_dir, trajectory, root: str,
               filtered_depth: bool, want_points: bool = True):
        """Bring the map to the final ``poses`` (only the keyframes in ``keep``), write it into
        ``out_dir`` (atomically, as ``rgbdslam fuse`` does) and return the :class:`FuseResult`.

        The work is shared: the map process sends the cloud's points and then writes the mesh, this
        process (meanwhile) removes the cloud's outliers, writes it and makes the 2-D map, into one
        temporary folder moved into place at the end."""
        from pathlib import Path

        from rgbdslam.mapping.staging import FuseResult, staged

        def work(stage: Path):
            at = {"at_finish_sent": time.time()}
            self._jobs.put(("finish", {int(k): np.array(v) for k, v in poses.items()}, keep, str(stage),
                            filtered_depth))
            try:
                fused = self._receive("cloud")
                at["at_cloud_received"] = time.time()
                acc = Path(root) / "accelerometer.txt"
                args = (stage, self.cfg, trajectory, acc if acc.is_file() else None, want_points)
                in_run = self._cloud is None or not self._cloud.ready()
                if not in_run:
                    # the cloud process removes the outliers, then makes the 2-D map; meanwhile this
                    # process writes cloud.ply (NumPy only) from the indices of the points it kept
                    self._cloud.submit("rgbdslam.mapping.live:_cloud_outliers", stage, self.cfg)
                    self._cloud.submit("rgbdslam.mapping.live:_cloud_2d", *args)
                    n_points, timings = self._cloud.result()
                    at["at_outliers_received"] = time.time()
                    cloud_path = _write_kept_cloud(stage)
                    at["at_cloud_ply_written"] = time.time()
                    (points, colors), map2d_path, grid, more = self._cloud.result()
                    timings.update(more)
                else:  # its niced imports are not done (a short run, a busy machine): here, as before
                    self._close_cloud(wait=0.0)  # it reads its queue only after them: do not wait for it
                    cloud_path, n_points, points, colors, map2d_path, grid, timings = _cloud_end(*args)
                timings["cloud_in_run"] = in_run
                at["at_cloud_done"] = time.time()
                mesh = self._receive("ok")
                at["at_mesh_received"] = time.time()
            except BaseException:
                self._stop()  # they may still be writing into the folder that is about to be removed
                raise
            self._close_cloud()
            self._proc.join(timeout=30)
            # the map process has ended: a job still in the pipe (a keyframe sent while an interrupted run
            # was winding down) has no reader, and the interpreter's exit must not wait to flush it
            self._jobs.cancel_join_thread()
            at["at_map_joined"] = time.time()
            timings.update(mesh["timings"])
            timings.update(at)
            t_end = at["at_finish_sent"]  # the end's timeline: seconds since the finish job was sent
            timings["end_timeline"] = {k[3:]: round(timings.pop(k) - t_end, 3) for k in list(timings)
                                       if k.startswith("at_")}
            return FuseResult(out_dir=stage, cloud_path=Path(cloud_path),
                              mesh_path=Path(mesh["mesh_path"]) if mesh["mesh_path"] else None,
                              map2d_path=map2d_path, frames=fused, n_points=n_points,
                              n_vertices=mesh["n_vertices"], n_triangles=mesh["n_triangles"], seconds=0.0,
                              peak_rss_mb=mesh["peak_rss_mb"], rss_growth_mb=0.0, timings=timings,
                              cloud_points=points, cloud_colors=colors, map2d=grid)

        return staged(Path(out_dir), work)

    def _receive(self, want: str):
        """The map process's next result, ``want`` (its error raised here)."""
        from rgbdslam.errors import RgbdslamError

        status, value = receive(self._results, self._proc, "map process")
        if status == "error":
            raise value
        if status != want:
            raise RgbdslamError(f"the map process sent {status!r} where {want!r} was due")
        return value

    def _stop(self) -> None:
        if self._proc.is_alive():
            stop(self._proc)
        self._jobs.cancel_join_thread()
        self._close_cloud(wait=0.0)

    def _close_cloud(self, wait: float = 5.0) -> None:
        """End the cloud process: it is asked to end and, after ``wait`` s, terminated (at once where
        it may be busy: an error, a Ctrl-C, its imports not done)."""
        if self._cloud is not None:
            self._cloud.close(wait)

    def abort(self) -> None:
        """Stop the map process (and the cloud process) without a map (a failed or interrupted run)."""
        end(self._proc, self._jobs)
        self._close_cloud(wait=0.0)


def _warm_cloud() -> None:
    """The cloud process's imports, while tracking (:class:`rgbdslam.io.worker.Helper`)."""
    import rgbdslam.mapping.fusion  # noqa: F401 - Open3D
    import rgbdslam.mapping.map2d  # noqa: F401


def _load_cloud(stage) -> tuple[np.ndarray, np.ndarray]:
    """The cloud the map process left in ``stage`` (:data:`CLOUD_POINTS`, :data:`CLOUD_COLORS`)."""
    from pathlib import Path

    return np.load(Path(stage) / CLOUD_POINTS), np.load(Path(stage) / CLOUD_COLORS)


def _save_handover(stage, name: str, arr: np.ndarray) -> None:
    """``arr`` as ``stage``/``name`` (.npy) for the other process. A write that fails (a full disk)
    is an OSError naming the map file it was for, ``stage``/cloud.ply (which the map's staging turns
    into the map folder's cloud.ply): NumPy's own writer says only "problem writing element N"."""
    import io
    from pathlib import Path

    buf = io.BytesIO()
    np.save(buf, arr)
    try:
        (Path(stage) / name).write_bytes(buf.getbuffer())
    except OSError as e:
        raise OSError(e.errno, e.strerror, str(Path(stage) / "cloud.ply")) from None


_KEPT: dict = {}  # the cloud process's outlier-free cloud, from its first job to its second


def _cloud_outliers(stage, cfg: MappingConfig):
    """The cloud process's first job at the end: the outliers of the cloud in ``stage`` removed, the
    kept points' indices saved beside it (:data:`CLOUD_KEEP`, None: all); ``(points kept, timings)``."""
    from pathlib import Path

    from rgbdslam.mapping.fusion import outlier_keep

    t0, c0 = time.perf_counter(), time.process_time()
    timings: dict = {"at_cloud_start": time.time()}
    points, colors = _load_cloud(stage)
    keep = outlier_keep(points, cfg)
    _save_handover(stage, CLOUD_KEEP, keep if keep is not None else np.arange(len(points)))
    _KEPT.update(points=points if keep is None else points[keep], colors=colors if keep is None else colors[keep])
    timings["cloud"] = time.perf_counter() - t0  # outlier removal (cloud.ply is written by the run meanwhile)
    timings["cloud_cpu_s"] = time.process_time() - c0
    timings["at_outliers_done"] = time.time()
    return len(_KEPT["points"]), timings


def _write_kept_cloud(stage):
    """In the run, while the cloud process makes the 2-D map: ``stage``/cloud.ply of the points its
    outlier removal kept; the cloud's files in ``stage`` removed."""
    from pathlib import Path

    from rgbdslam.io.ply import write_cloud_ply  # not from fusion: that imports Open3D

    points, colors = _load_cloud(stage)
    keep = np.load(Path(stage) / CLOUD_KEEP)
    path = Path(stage) / "cloud.ply"
    write_cloud_ply(path, points[keep], colors[keep])
    for name in (CLOUD_POINTS, CLOUD_COLORS, CLOUD_KEEP):
        (Path(stage) / name).unlink()
    return path


def _cloud_2d(stage, cfg: MappingConfig, trajectory, accelerometer, want_points: bool = True):
    """The cloud process's second job: the 2-D map of its outlier-free cloud (:func:`_cloud_outliers`);
    ``(points (float32) and colours or Nones without want_points, 2-D map path, Map2D, timings)``."""
    from rgbdslam.mapping.fusion import write_2d

    points, colors = _KEPT.pop("points").astype(np.float32), _KEPT.pop("colors")
    timings: dict = {}
    c0 = time.process_time()
    map2d_path, grid = write_2d(stage, points, trajectory, cfg, accelerometer, timings)
    timings["map2d_cpu_s"] = time.process_time() - c0
    timings["at_map2d_done"] = time.time()
    return (points, colors) if want_points else (None, None), map2d_path, grid, timings


def _cloud_end(stage, cfg: MappingConfig, trajectory, accelerometer, want_points: bool = True):
    """The cloud's part of the end in one process (the run's, when the cloud process's imports are
    not done): outlier removal, ``stage``/cloud.ply, the 2-D map; ``(cloud path, points kept, their
    points (float32) and colours or Nones without ``want_points``, 2-D map path, Map2D, timings)``."""
    try:
        n_points, timings = _cloud_outliers(stage, cfg)
        cloud_path = _write_kept_cloud(stage)
        (points, colors), map2d_path, grid, more = _cloud_2d(stage, cfg, trajectory, accelerometer, want_points)
    finally:
        _KEPT.clear()  # the kept cloud (~10 MB) is not held after an error
    return cloud_path, n_points, points, colors, map2d_path, grid, {**timings, **more}


def add_cloud(dst, src, sign: int) -> None:
    """Add (``sign`` +1) or take out (-1) the voxel cloud ``src`` from ``dst``; voxels left
    without points disappear."""
    src.merge()
    dst.merge()
    dst.pending.append((src.keys, sign * src.sums, sign * src.counts))
    dst.merge()
    keep = dst.counts > 0.5
    if not keep.all():
        dst.keys, dst.sums, dst.counts = dst.keys[keep], dst.sums[keep], dst.counts[keep]


def merge_tsdf(dst, src, sign: int = 1) -> None:
    """Add (``sign`` +1) or take out (-1) the Open3D VoxelBlockGrid ``src`` to/from ``dst`` (same
    voxel size and attributes): per voxel the weight-averaged TSDF value and colour, the weights
    added or subtracted — what integrating (or never having integrated) ``src``'s frames gives."""
    import open3d.core as o3c

    hs = src.hashmap()
    idx = hs.active_buf_indices().to(o3c.int64)
    if idx.shape[0] == 0:
        return
    keys = hs.key_tensor()[idx]
    idx = idx.numpy()
    s_t = src.attribute("tsdf").numpy()[idx]
    s_w = src.attribute("weight").numpy()[idx].astype(np.float32) * sign
    s_c = src.attribute("color").numpy()[idx].astype(np.float32)
    hd = dst.hashmap()
    _, existed = hd.find(keys)
    existed = existed.numpy().astype(bool)
    hd.activate(keys)  # new blocks; may grow the table, so the attribute views are taken after it
    buf, _ = hd.find(keys)
    buf = buf.to(o3c.int64).numpy()
    T, W, C = dst.attribute("tsdf").numpy(), dst.attribute("weight").numpy(), dst.attribute("color").numpy()
    new = ~existed  # blocks activated now: their memory is not cleared
    d_w = W[buf].astype(np.float32)
    d_w[new] = 0
    d_t = T[buf]
    d_t[new] = 0
    d_c = C[buf].astype(np.float32)
    d_c[new] = 0
    tw = d_w + s_w
    ok = tw > 0.5
    safe = np.where(ok, tw, 1)
    T[buf] = np.where(ok, (d_t * d_w + s_t * s_w) / safe, 0)
    C[buf] = np.where(ok, np.clip(np.round((d_c * d_w + s_c * s_w) / safe), 0, 65535), 0).astype(np.uint16)
    W[buf] = np.where(ok, np.clip(np.round(tw), 0, 65535), 0).astype(np.uint16)
