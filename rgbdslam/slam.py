"""The SLAM per-frame chain: one frame's way through the stages (docs/architecture.md, docs/slam.md).

``SLAM`` composes the stage objects, each built from its own config section; :meth:`SLAM.track`
takes a frame through them in this order::

    Frame ─▶ frontend.track   (ORB features, registration against the reference frames → pose or lost)
          ─▶ stages.on_tracked (refinement stages, e.g. the landmark map: the pose checked against it)
          ─▶ depth_filter     (DIF, needs the pose; the filtered depth goes back to the front end)
          ─▶ loop.observe     (sharpness gate) ─▶ loop.detect (sharp or due frames only)
          ─▶ map_tracker      (--localize: registration against the nearest keyframes of the fixed map)
          ─▶ stages.on_loops  (the loop edges re-measured or dropped)
          ─▶ keyframes        (motion policy; loops and restarts force a keyframe)
          ─▶ stages.on_frame  (the end of the frame's step; keyframes: new landmarks)
          ─▶ graph            (GTSAM pose graph over keyframes, initial values from MASAT)

A refinement stage implements :class:`Stage`; a stage changes poses only by returning
``{frame index: new pose}``, which :meth:`SLAM._apply` writes into the front end's references, the
frame records and the pose graph together. The run driver (:mod:`rgbdslam.pipeline`) feeds the
frames and writes the run folder.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol

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


class Stage(Protocol):
    """A per-frame refinement step between the front end and the back end (the landmark map is one:
    :class:`rgbdslam.landmarks.stage.LandmarkTracker`). Corrections are ``{frame index: new pose}``:
    the current frame's, or keyframes' that are already records (empty: nothing moves)."""

    name: str  # its timing key in run.json

    def on_tracked(self, frame: Frame, result: TrackResult, pose: np.ndarray) -> dict[int, np.ndarray]:
        """After the front end placed the frame at ``pose`` (``result.reset``: tracking restarted)."""

    def on_loops(self, frame: Frame, result: TrackResult, loops: list) -> list:
        """The loop closer's edges to the frame (map-tracking edges are not among them); returns those to add."""

    def on_frame(self, frame: Frame, result: TrackResult, pose: np.ndarray, keyframe: bool) -> dict[int, np.ndarray]:
        """The frame's final step, once the keyframe decision is made."""

    def on_finish(self, optimised: dict[int, np.ndarray]) -> None:
        """After the final pose-graph optimisation (keyframe poses)."""


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

            observer = None if isinstance(self.observer, NullObserver) else self.observer
            self.landmarks = LandmarkTracker(cfg.landmarks, camera, observer, cfg.output.rerun_log_every)
        # the refinement stages between the front end and the back end, in chain order (protocol: Stage)
        self.stages: list[Stage] = [s for s in (self.landmarks,) if s is not None]
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
        """One frame through the chain; every pose change goes through :meth:`_apply`."""
        result = self.frontend.track(frame)  # ORB features, registration against the reference frames
        for k, v in result.timings.items():
            self.state.add_time(k, v)
        if result.lost or result.pose is None:
            return self._lost(frame, result)
        pose, restart = result.pose, bool(result.reset)
        if result.information is not None:
            self._info_since_kf.append(result.information)
        for s in self.stages:  # e.g. the landmark map: the pose checked against it
            pose = self._apply(frame, result, pose, self._timed(s.name, s.on_tracked, frame, result, pose))
        depth = self._filter_depth(frame, pose, restart)  # DIF: filtered depth for the map and the references
        if restart:  # a new segment, to be relocalised
            self._restart(frame)
        loops, map_edges = self._detect_loops(frame, result, pose)
        for s in self.stages:
            loops = self._timed(s.name, s.on_loops, frame, result, loops)
        is_kf, loops = self._keyframe(frame, pose, restart, loops, map_edges)
        for s in self.stages:  # the frame's last step in each stage (keyframe: new landmarks)
            pose = self._apply(frame, result, pose, self._timed(s.name, s.on_frame, frame, result, pose, is_kf))
        self._record(frame, result, pose, depth, is_kf)  # frame record; a keyframe: graph, loop closer, live map
        self._add_loops(loops)  # into the pose graph (iSAM2 updates); the live map follows
        if self._map_stale:
            self._feed_map()
        self._log(frame, result)
        return result

    def _apply(self, frame: Frame, result: TrackResult, pose: np.ndarray, moved: dict[int, np.ndarray]) -> np.ndarray:
        """The one place poses change after the front end: ``moved`` = {frame index: new pose} from a
        stage. This frame's new pose replaces ``pose`` (and ``result.pose``) and the front end continues
        from it (its newest reference and constant velocity); the other entries are keyframes, written
        back by :meth:`_move_keyframes` (their frames, the front end's references, the pose graph).
        Returns the frame's pose."""
        if not moved:
            return pose
        moved = dict(moved)
        if frame.index in moved:
            pose = moved.pop(frame.index)
            result.pose = pose
            self.frontend.correct_last(pose)
        if moved:
            self._move_keyframes(moved)
        return pose

    def _timed(self, name: str, step, *args):
        t0 = time.perf_counter()
        out = step(*args)
        self.state.add_time(name, time.perf_counter() - t0)
        return out

    def _lost(self, frame: Frame, result: TrackResult) -> TrackResult:
        self.state.lost.append(frame.index)
        self.observer.log_frame(frame, result)
        return result

    def _restart(self, frame: Frame) -> None:
        self.state.restarts.append(frame.index)
        if self.loop is not None:
            self.loop.new_segment()

    def _keyframe(self, frame: Frame, pose: np.ndarray, restart: bool, loops: list, map_edges: list) -> tuple[bool, list]:
        """Whether the frame is a keyframe — by motion, or forced (a loop edge or a segment's first pose
        needs a graph node; map-tracking edges force one only every ``loop.map_track_keyframe_every``-th
        anchored frame, else they are re-expressed to the last keyframe) — and the edges to add."""
        is_kf = self.keyframe_policy.is_keyframe(frame.index, pose)
        to_last = False
        if map_edges and not (is_kf or loops or restart or self._last_kf is None):
            every = self.cfg.loop.map_track_keyframe_every
            self._anchored_since_kf += 1
            to_last = every <= 0 or self._anchored_since_kf < every
        if to_last:
            return is_kf, [self._to_last_keyframe(e, pose) for e in map_edges]
        loops = loops + map_edges
        if (loops or restart) and not is_kf:
            self.keyframe_policy.force(frame.index, pose)
            is_kf = True
        return is_kf, loops

    def _record(self, frame: Frame, result: TrackResult, pose: np.ndarray, depth: np.ndarray, is_kf: bool) -> None:
        if is_kf:
            self._add_keyframe(frame, result, pose, depth)
        rec = FrameRecord(frame.index, frame.timestamp, pose.copy(), frame.index if is_kf else self._last_kf.index)
        self.state.records.append(rec)
        if is_kf:
            self._last_kf = rec

    def _log(self, frame: Frame, result: TrackResult) -> None:
        self.observer.log_frame(frame, result)
        if result.matches is not None:
            self.observer.log_inlier_matches(frame.index, result.matches[:, :2], result.matches[:, 2:])

    def _move_keyframes(self, refined: dict[int, np.ndarray]) -> None:
        """Write refined keyframe poses back: each keyframe's frames follow it rigidly (their pose
        relative to it kept), so do the front end's reference frames; the pose graph's odometry edges
        are re-measured between the refined keyframes."""
        old = {r.index: r.pose for r in self.state.records if r.index in refined and r.keyframe == r.index}
        corr = {k: refined[k] @ inv(P) for k, P in old.items()}
        if not corr:
            return
        moved = {}
        for r in self.state.records:
            C = corr.get(r.keyframe)
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
        odo = self.odometry()
        if self.graph is None or not self.state.keyframes:
            return odo
        t0 = time.perf_counter()
        optimised = self.graph.optimize()
        for s in self.stages:  # e.g. the landmarks move with the keyframe that anchors them
            s.on_finish(optimised)
        self.state.add_time("pose_graph", time.perf_counter() - t0)
        self.optimised = optimised
        kf_pose = {r.index: r.pose for r in self.state.records if r.index == r.keyframe}
        poses = []
        for r in self.state.records:
            if r.keyframe in optimised:
                poses.append(optimised[r.keyframe] @ inv(kf_pose[r.keyframe]) @ r.pose)
            else:
                poses.append(r.pose)
        return Trajectory(odo.timestamps, np.array(poses).reshape(-1, 4, 4))
