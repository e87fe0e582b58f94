"""The SLAM per-frame chain: one frame's way through the stages (docs/architecture.md).

``SLAM`` composes the stage objects, each built from its own config section::

    Frame ─▶ frontend.track   (ORB features, registration against the reference frames → pose or lost)
          ─▶ landmarks        (landmarks.enabled: the pose checked against the landmark map, the map updated)
          ─▶ depth_filter     (DIF, needs the pose; the filtered depth goes back to the front end)
          ─▶ loop.observe     (sharpness gate) ─▶ loop.detect (sharp or due frames only)
          ─▶ map_tracker      (--localize: registration against the nearest keyframes of the fixed map)
          ─▶ keyframes        (motion policy; loops and restarts force a keyframe)
          ─▶ graph            (GTSAM pose graph over keyframes, initial values from MASAT)

The run driver (:mod:`rgbdslam.pipeline`) feeds the frames and writes the run folder.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rgbdslam.config import Config
from rgbdslam.datasets import Frame
from rgbdslam.frontend.keyframes import KeyframePolicy
from rgbdslam.frontend.odometry import TrackResult, build_frontend
from rgbdslam.frontend.pairwise import build_pair_registration
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import inv
from rgbdslam.io.trajectory import Trajectory
from rgbdslam.runfolder.depth import keyframe_depth_path, quantise, write_keyframe_depth
from rgbdslam.viz.observer import NullObserver


MAP_BATCH_SHARE = 10.0  # a batch optimisation for the live map at most every 10x its own duration


@dataclass
class FrameRecord:
    """What the chain keeps of a tracked frame (small: no images)."""

    index: int
    timestamp: float
    pose: np.ndarray  # front-end (odometry) pose, camera-to-world
    keyframe: int  # frame index of the keyframe this frame hangs from


@dataclass
class SlamState:
    records: list[FrameRecord] = field(default_factory=list)
    keyframes: list[int] = field(default_factory=list)
    loops: list[tuple[int, int]] = field(default_factory=list)
    lost: list[int] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)
    restarts: list[int] = field(default_factory=list)  # frames where tracking restarted after a loss
    timings: dict[str, list[float]] = field(default_factory=dict)
    sharp: int = 0

    def add_time(self, stage: str, seconds: float) -> None:
        self.timings.setdefault(stage, []).append(seconds)


class SLAM:
    """The stages built from a typed config; :meth:`track` takes one frame through them."""

    def __init__(self, cfg: Config, camera: Camera, observer=None, keyframe_dir: Path | None = None,
                 mapper=None):
        self.cfg = cfg
        self.observer = observer if observer is not None else NullObserver()
        self.keyframe_dir = keyframe_dir
        self.mapper = mapper  # rgbdslam.mapping.live.LiveMap: keyframes fused while tracking
        register = build_pair_registration(cfg)  # matching + the registration strategy, shared with loop closure
        self.frontend = build_frontend(cfg, camera, register)
        self.keyframe_policy = KeyframePolicy(cfg.keyframes)
        self.depth_filter = None
        if cfg.depth_filter.enabled:
            from rgbdslam.frontend.depth_filter import DepthFilter

            self.depth_filter = DepthFilter(cfg.depth_filter, camera)
        self.loop = None
        if cfg.loop.enabled:
            from rgbdslam.loop.detector import build_loop_closer

            self.loop = build_loop_closer(cfg, register)
        self.landmarks = None
        if cfg.landmarks.enabled:
            from rgbdslam.landmarks.stage import LandmarkTracker

            self.landmarks = LandmarkTracker(cfg.landmarks, camera)
        self.graph = None
        if cfg.backend.enabled or cfg.loop.enabled:
            from rgbdslam.backend.slam_graph import KeyframeGraph

            self.graph = KeyframeGraph(cfg.backend)
        self.state = SlamState()
        self._last_kf: FrameRecord | None = None
        self._info_since_kf: list[np.ndarray] = []
        self._anchored_since_kf = 0  # frames with map-tracking edges since the last keyframe
        self.optimised: dict[int, np.ndarray] | None = None  # keyframe poses after finish()
        self.map_poses: dict[int, np.ndarray] = {}  # keyframes of a loaded map (rgbdslam.session), by id
        # the live map gets batch-optimised keyframe poses (see _feed_map): the correction of the
        # front-end poses by the last batch it was sent, whether new loops await one, when one may run
        self._map_fix: np.ndarray | None = None
        self._map_stale = False
        self._map_next_batch = 0.0
        self.map_tracker = None  # rgbdslam.session.tracking.MapTracker when localising in a fixed map

    # ------------------------------------------------------------------ one frame
    def track(self, frame: Frame) -> TrackResult:
        st = self.state
        # 1. front end: the frame's pose from its registrations against the reference frames
        result = self.frontend.track(frame)
        for k, v in result.timings.items():
            st.add_time(k, v)
        if result.lost or result.pose is None:
            st.lost.append(frame.index)
            self.observer.log_frame(frame, result)
            return result
        pose, restart = result.pose, bool(result.reset)
        if result.information is not None:
            self._info_since_kf.append(result.information)
        # 1b. the landmark map: the pose checked against it (fused with the registration's), the map updated
        if self.landmarks is not None and not restart:
            pose = self._track_map(frame, result, pose)
        # 2. DIF: filtered depth for the map and the front end's references
        depth = self._filter_depth(frame, pose, restart)
        # 3. a restart after a tracking loss begins a new segment, to be relocalised
        if restart:
            st.restarts.append(frame.index)
            if self.loop is not None:
                self.loop.new_segment()
        # 4. loop closure on sharp (or due) frames
        loops, map_edges = self._detect_loops(frame, result, pose)
        if loops and self.landmarks is not None and self.cfg.landmarks.loop_refine and not restart:
            loops = [self.landmarks.refine_loop(frame.index, _map_feats(result), e) for e in loops]  # vs the map
        if loops and self.landmarks is not None and self.cfg.landmarks.map_loop_landmarks > 0:
            loops = [e for e in loops if not self.landmarks.holds(frame.index, e.i)]  # the map closed them
        # 5. keyframe: by motion, or forced (a loop edge / a segment's first pose needs a graph node);
        # map-tracking edges force one only every loop.map_track_keyframe_every-th anchored frame
        is_kf = self.keyframe_policy.is_keyframe(frame.index, pose)
        to_last = False  # this frame's map edges re-expressed to the last keyframe (no new graph node)
        if map_edges and not (is_kf or loops or restart or self._last_kf is None):
            every = self.cfg.loop.map_track_keyframe_every
            self._anchored_since_kf += 1
            to_last = every <= 0 or self._anchored_since_kf < every
        if to_last:
            loops = [self._to_last_keyframe(e, pose) for e in map_edges]
        else:
            loops = loops + map_edges
            if (loops or restart) and not is_kf:
                self.keyframe_policy.force(frame.index, pose)
                is_kf = True
        if self.landmarks is not None:
            pose = self._update_map(frame, result, pose, is_kf)
        if is_kf:
            self._add_keyframe(frame, result, pose, depth)
            if self.landmarks is not None and self.graph is not None:  # old landmarks -> their keyframes
                for e in self.landmarks.anchor_edges(frame.index, _map_feats(result), pose, self.graph.guess):
                    self.graph.add_loop(e)
        rec = FrameRecord(frame.index, frame.timestamp, pose.copy(), frame.index if is_kf else self._last_kf.index)
        st.records.append(rec)
        if is_kf:
            self._last_kf = rec
        # 6. loop edges into the pose graph (iSAM2 updates); the live map follows
        self._add_loops(loops)
        if loops and is_kf and self.landmarks is not None and self.cfg.landmarks.loop_correct and \
                self.graph is not None and self.map_tracker is None:
            t0 = time.perf_counter()  # the map moves into the loop-corrected frame (docs/slam.md)
            self.landmarks.correct(frame.index, self.graph.batch_estimate())
            st.add_time("landmarks", time.perf_counter() - t0)
        if self._map_stale:
            self._feed_map()
        self.observer.log_frame(frame, result)
        if result.matches is not None:
            self.observer.log_inlier_matches(frame.index, result.matches[:, :2], result.matches[:, 2:])
        return result

    def _track_map(self, frame: Frame, result: TrackResult, pose: np.ndarray) -> np.ndarray:
        t0 = time.perf_counter()
        info = result.information
        if info is not None and result.n_fused > 1:  # the references share this frame's noise:
            info = info / result.n_fused  # their summed information counts it n_fused times
        mpose = self.landmarks.track(frame.index, _map_feats(result), pose, info)
        if self.cfg.landmarks.graph_information and self.landmarks.step_information is not None and \
                self._info_since_kf and result.information is not None:
            self._info_since_kf[-1] = self.landmarks.step_information  # the odometry edge: what the pose is
        if mpose is not pose:
            pose = mpose
            result.pose = pose
            self.frontend.correct_last(pose)
        self.state.add_time("landmarks", time.perf_counter() - t0)
        return pose

    def _update_map(self, frame: Frame, result: TrackResult, pose: np.ndarray, is_kf: bool) -> np.ndarray:
        """New landmarks and local BA on a keyframe; the end of the map's step; Rerun."""
        if is_kf:
            t0 = time.perf_counter()
            refined = self.landmarks.add_keyframe(frame.index, _map_feats(result), pose)
            current = None
            if frame.index in refined:  # local BA moved this keyframe: tracking continues from there
                current = (frame.index, refined[frame.index] @ inv(pose))
                pose = refined.pop(frame.index)
                result.pose = pose
                self.frontend.correct_last(pose)
            if refined:  # the window's older keyframes, their frames, references and graph edges
                self._move_keyframes(refined, pose, current)
            self.state.add_time("local_ba" if self.landmarks.ba is not None else "landmarks", time.perf_counter() - t0)
        else:
            refined = self.landmarks.handover(frame.index, pose)  # landmarks.ba_handover: the BA due now
            if refined:
                t0 = time.perf_counter()
                pose = refined.pop(frame.index, pose)
                result.pose = pose
                self.frontend.correct_last(pose)
                self._move_keyframes(refined, pose)
                self.state.add_time("local_ba", time.perf_counter() - t0)
            self.landmarks.record_frame(frame.index, _map_feats(result), pose)
        self.landmarks.end_frame(frame.index)
        if not isinstance(self.observer, NullObserver) and frame.index % max(1, self.cfg.output.rerun_log_every) == 0:
            self.landmarks.log(self.observer, frame.index, _map_feats(result), is_kf)
        return pose

    def _move_keyframes(self, refined: dict[int, np.ndarray], pose: np.ndarray | None = None,
                        current: tuple[int, np.ndarray] | None = None) -> None:
        """Write local-BA keyframe poses back: each keyframe's frames follow it rigidly (their pose
        relative to it kept), so do the front end's reference frames; the pose graph's odometry edges
        are re-measured between the refined keyframes (the current keyframe, not yet a node, gets its
        edge from ``pose``). ``current``: (this keyframe, its correction), which the frames since the
        last keyframe approach with ``landmarks.ba_frames: interpolate``."""
        old = {r.index: r.pose for r in self.state.records if r.index in refined and r.keyframe == r.index}
        corr = {k: refined[k] @ inv(P) for k, P in old.items()}
        if not corr:
            return
        moved = {}
        follow = _interpolated if self.cfg.landmarks.ba_frames == "interpolate" else _rigid
        for r, C in zip(self.state.records, follow(self.state.records, corr, current)):
            if C is not None:
                r.pose = C @ r.pose
                moved[r.index] = r.pose
        self.frontend.move_references(moved)
        if self.graph is not None:
            self.graph.refine_poses({k: refined[k] for k in corr})

    def _filter_depth(self, frame: Frame, pose: np.ndarray, restart: bool) -> np.ndarray:
        if self.depth_filter is None:
            return frame.depth
        if restart:  # the last depth maps' poses are unrelated to this one's: nothing to warp
            self.depth_filter.reset()
        t0 = time.perf_counter()
        depth = self.depth_filter(frame.depth, pose)
        self.frontend.set_depth(frame.index, depth)
        self.state.add_time("depth_filter", time.perf_counter() - t0)
        self.observer.log_filtered_depth(frame.index, frame.timestamp, depth)
        return depth

    def _detect_loops(self, frame: Frame, result: TrackResult, pose: np.ndarray) -> tuple[list, list]:
        """The loop closer's edges, and (localising) the map tracker's."""
        if self.loop is None:
            return [], []
        t0 = time.perf_counter()
        sharp = self.loop.observe(result.features)
        self.state.sharp += int(sharp)
        self.observer.log_gate(frame.index, frame.timestamp, *self.loop.gate.last, sharp)
        loops = []
        # relocalising: every frame searches the older segments; due: none searched for query_gap frames
        if sharp or self.loop.relocalizing or self.loop.due(frame.index):
            loops = self.loop.detect(result.features, pose)
        self.state.add_time("loop_closure", time.perf_counter() - t0)
        map_edges = []
        if self.map_tracker is not None:  # localising: the frame registered against the nearest map keyframes
            t0 = time.perf_counter()
            map_edges = self.map_tracker.track(result.features, pose, loops)
            self.state.add_time("map_tracking", time.perf_counter() - t0)
        return loops, map_edges

    def _to_last_keyframe(self, e, pose: np.ndarray):
        """Map edge ``e`` (map keyframe i -> this frame) re-expressed as i -> the last keyframe k:
        T_ik = T_ij · (odometry k -> j)⁻¹; covariance = the edge's + the odometry's since k (first
        order, as :meth:`_keyframe_information`)."""
        k = self._last_kf
        T_kj = inv(k.pose) @ pose
        cov = np.linalg.inv(e.information) + sum((np.linalg.inv(I) for I in self._info_since_kf), np.zeros((6, 6)))
        return replace(e, j=k.index, T_ij=e.T_ij @ inv(T_kj), information=np.linalg.inv(cov))

    def _add_loops(self, loops: list) -> None:
        if not loops or self.graph is None:
            return
        t0 = time.perf_counter()
        if self.landmarks is not None and self.cfg.landmarks.graph_information:
            # a loop edge is one registration: its information calibrated as the fusion calibrates the
            # registration's (landmarks.fuse_scale), so it weighs against the odometry edges' as measured
            loops = [replace(e, information=e.information * self.cfg.landmarks.fuse_scale) for e in loops]
        for e in loops:
            self.graph.add_loop(e)
            self.state.loops.append((int(e.i), int(e.j)))
            self.observer.log_loop(e.i, e.j, self._pose_of(e.i), self._pose_of(e.j))
        self._map_stale = self.mapper is not None  # the loop moves the keyframes: the map follows (_feed_map)
        self.state.add_time("pose_graph", time.perf_counter() - t0)

    def _feed_map(self) -> None:
        """Send the live map the keyframe poses a batch optimisation of the graph gives now — the
        final optimisation's poses once no loop comes any more, which iSAM2's estimate is not
        (:meth:`KeyframeGraph.batch_estimate`) — when the map has applied the last ones (one update
        in flight at a time) and at most a tenth of the time goes into them."""
        now = time.perf_counter()
        if now < self._map_next_batch or not self.mapper.ready():
            return
        poses = self.graph.batch_estimate()
        last = self.graph.order[-1]
        self._map_fix = poses[last] @ inv(self.graph.guess[last])  # new keyframes follow the last one
        self.mapper.update_poses(poses)
        self._map_stale = False
        took = time.perf_counter() - now
        self._map_next_batch = now + MAP_BATCH_SHARE * took
        self.state.add_time("pose_graph", took)

    def _pose_of(self, index: int) -> np.ndarray | None:
        for r in reversed(self.state.records):
            if r.index == index:
                return r.pose
        return self.map_poses.get(index)

    def _add_keyframe(self, frame: Frame, result: TrackResult, pose: np.ndarray, depth: np.ndarray) -> None:
        self.state.keyframes.append(frame.index)
        if self.graph is not None:
            self.graph.add_node(frame.index, pose)
            if self._last_kf is not None:
                T_ij = inv(self._last_kf.pose) @ pose
                self.graph.add_odometry(self._last_kf.index, frame.index, T_ij, self._keyframe_information())
        self._info_since_kf = []
        self._anchored_since_kf = 0
        if self.loop is not None:
            self.loop.add_keyframe(result.features, pose)
        if self.keyframe_dir is not None and self.depth_filter is not None:
            write_keyframe_depth(keyframe_depth_path(self.keyframe_dir, frame.index), depth)
        if self.mapper is not None:  # at the pose graph's current estimate, with the depth the PNG holds
            map_depth = quantise(depth) if self.depth_filter is not None else frame.depth
            fix = self._map_fix if self._map_fix is not None else (
                self.graph.correction() if self.graph is not None else np.eye(4))
            self.mapper.add(frame.index, frame.rgb, map_depth, fix @ pose)

    def _keyframe_information(self) -> np.ndarray:
        """Information of the chained relative pose between two keyframes.

        Covariances of the chained frame-to-frame registrations add up (to first order,
        ignoring the rotation of the frames), so the information is the inverse of the sum
        of the per-frame covariances.
        """
        infos = self._info_since_kf or [np.eye(6) * 1e4]
        cov = sum(np.linalg.inv(I) for I in infos)
        return np.linalg.inv(cov)

    # ---------------------------------------------------------------- trajectories
    def odometry(self) -> Trajectory:
        recs = self.state.records
        return Trajectory(np.array([r.timestamp for r in recs]), np.array([r.pose for r in recs]).reshape(-1, 4, 4))

    def finish(self) -> Trajectory:
        """Optimise the pose graph (if any) and return every tracked frame's final pose.

        Non-keyframes follow their keyframe: final = optimised(kf) · odo(kf)⁻¹ · odo(frame).
        """
        if self.landmarks is not None:  # the local BA still in flight (landmarks.ba_worker) is written back
            refined = self.landmarks.flush()
            if refined:
                self._move_keyframes(refined)
            self.landmarks.close()
        odo = self.odometry()
        if self.graph is None or not self.state.keyframes:
            return odo
        t0 = time.perf_counter()
        optimised = self.graph.optimize()
        if self.landmarks is not None:  # landmarks move with the keyframe that anchors them
            self.landmarks.finish(optimised)
        self.state.add_time("pose_graph", time.perf_counter() - t0)
        if self.landmarks is not None and self.cfg.landmarks.global_ba and not self.map_poses:
            t0 = time.perf_counter()  # one bundle adjustment over every keyframe, the loops kept
            loops = [(int(e.i), int(e.j), e.T_ij, e.information) for e in self.graph.loops]
            optimised = self.landmarks.global_ba(optimised, loops, self.graph.odometry)
            self.state.add_time("global_ba", time.perf_counter() - t0)
        self.optimised = optimised
        kf_pose = {r.index: r.pose for r in self.state.records if r.index == r.keyframe}
        poses = []
        for r in self.state.records:
            if r.keyframe in optimised:
                poses.append(optimised[r.keyframe] @ inv(kf_pose[r.keyframe]) @ r.pose)
            else:
                poses.append(r.pose)
        return Trajectory(odo.timestamps, np.array(poses).reshape(-1, 4, 4))


def _rigid(records: list, corr: dict[int, np.ndarray], current=None) -> list:
    """Each record's correction: its keyframe's (None: not moved)."""
    return [corr.get(r.keyframe) for r in records]


def _interpolated(records: list, corr: dict[int, np.ndarray], current: tuple[int, np.ndarray] | None = None) -> list:
    """Each record's correction along the geodesic between its keyframe a's and the next keyframe b's,
    C = C_a · Exp(s · Log(C_a⁻¹ C_b)) with s = (frame − a) / (b − a); a keyframe without a correction
    has the identity; ``current`` = (b, C_b): the keyframe being added (not a record yet), the next
    one of the newest record keyframe; without it, after the newest keyframe its own (rigid). None
    where neither moved."""
    import gtsam

    kfs = [r.index for r in records if r.index == r.keyframe]
    nxt = dict(zip(kfs, kfs[1:]))
    if current is not None and kfs:
        nxt[kfs[-1]] = current[0]
        corr = {**corr, current[0]: current[1]}
    out = []
    for r in records:
        a, b = r.keyframe, nxt.get(r.keyframe)
        if a not in corr and (b is None or b not in corr):
            out.append(None)
            continue
        Ca = corr.get(a, np.eye(4))
        if r.index == a or b is None:
            out.append(Ca)
            continue
        Cb = corr.get(b, np.eye(4))
        s = (r.index - a) / (b - a)
        out.append(Ca @ gtsam.Pose3.Expmap(s * gtsam.Pose3.Logmap(gtsam.Pose3(inv(Ca) @ Cb))).matrix())
    return out


def _map_feats(result: TrackResult):
    """The key points the landmark map works with: every one detected (``landmarks.n_features``) or the frame's."""
    return result.features if result.map_features is None else result.map_features
