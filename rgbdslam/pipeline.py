"""The SLAM orchestrator: one frame's way through the stages, and a whole run.

``SLAM`` composes the stage objects chosen by the config::

    Frame ─▶ frontend.track   (ORB features, matching, ISVD/ISLAM registration → pose or lost)
          ─▶ depth_filter     (DIF, needs the pose; filtered depth goes back to the front end)
          ─▶ loop.observe     (sharpness gate) ─▶ loop.detect (sharp frames only)
          ─▶ keyframes        (motion policy; loops force a keyframe)
          ─▶ graph            (GTSAM pose graph over keyframes, initial values from MASAT)

``run_sequence`` drives ``SLAM`` over a sequence and writes the run folder (see
``docs/formats.md``): trajectories, the config used, ``run.json``, evaluation and map.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rgbdslam import __version__
from rgbdslam.config import Config, save_config
from rgbdslam.datasets import Frame, Sequence, open_sequence
from rgbdslam.datasets.base import depth_warning
from rgbdslam.errors import InputError, RgbdslamError, TrackingLost
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import inv
from rgbdslam.io.atomic import atomic_path, atomic_write_text
from rgbdslam.io.trajectory import Trajectory, write_tum

FLUSH_EVERY = 50  # frames between intermediate trajectory writes
MAX_FRAME_WARNINGS = 5  # per-frame warnings printed before the rest are only counted
# what a run writes into its folder; a new run into the same folder first moves these to previous/
RUN_ARTEFACTS = ("trajectory.tum", "odometry.tum", "posegraph.g2o", "config.yaml", "run.json", "evaluation.json",
                 "plots", "map", "keyframes", "recording.rrd")


def _finished_run(run_json: Path) -> bool:
    """True when ``run_json`` records a run that ran to its end (``status`` "finished"; older
    run.json files without a status count as finished unless they say ``interrupted``)."""
    try:
        info = json.loads(run_json.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    if not isinstance(info, dict):
        return False
    return info.get("status", "interrupted" if info.get("interrupted") else "finished") == "finished"


def keep_previous_run(out_dir: Path) -> bool:
    """Move a finished earlier run's files in ``out_dir`` to ``out_dir/previous`` (replacing an
    older ``previous``), so that a new run that fails or is interrupted part-way never overwrites
    a finished one. A failed or interrupted run in ``out_dir`` is not moved: the new run replaces
    it, and ``previous/`` keeps the last finished one. True when a run was moved."""
    import shutil

    if not _finished_run(out_dir / "run.json"):
        return False
    prev = out_dir / "previous"
    if prev.exists():
        if not (prev.is_dir() and (prev / "run.json").is_file()):  # not ours: never delete it
            raise InputError(f"{prev} exists and is not an earlier run of rgbdslam; move it away or choose "
                             f"another --out (a new run keeps the last one there)")
        shutil.rmtree(prev)
    prev.mkdir()
    for name in RUN_ARTEFACTS:
        if (out_dir / name).exists():
            (out_dir / name).replace(prev / name)
    return True


@dataclass
class FrameRecord:
    """What the orchestrator keeps of a tracked frame (small: no images)."""

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
    """Composes the stages built from a typed config and tracks one frame at a time."""

    def __init__(self, cfg: Config, camera: Camera, observer: Any | None = None,
                 keyframe_dir: Path | None = None):
        from rgbdslam.frontend.keyframes import KeyframePolicy
        from rgbdslam.frontend.odometry import build_frontend
        from rgbdslam.frontend.pairwise import build_pair_registration

        self.cfg = cfg
        self.camera = camera
        self.observer = observer
        self.keyframe_dir = keyframe_dir
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
            from rgbdslam.backend.slam_graph import PoseGraph

            self.graph = PoseGraph(cfg.backend)
        self.state = SlamState()
        self._last_kf: FrameRecord | None = None
        self._info_since_kf: list[np.ndarray] = []
        self.optimised: dict[int, np.ndarray] | None = None  # keyframe poses after finish()

    # ------------------------------------------------------------------ one frame
    def track(self, frame: Frame):
        st = self.state
        result = self.frontend.track(frame)
        for k, v in (getattr(result, "timings", None) or {}).items():
            st.add_time(k, v)
        if result.lost or result.pose is None:
            st.lost.append(frame.index)
            if self.observer is not None:
                self.observer.log_frame(frame, result)
            return result
        pose = result.pose
        if getattr(result, "information", None) is not None:
            self._info_since_kf.append(result.information)

        restart = bool(getattr(result, "reset", False))
        if self.landmarks is not None and not restart:  # the map places the frame (registration predicts)
            t0 = time.perf_counter()
            info = getattr(result, "information", None)
            if info is not None and getattr(result, "n_fused", 0) > 1:  # the references share this frame's noise:
                info = info / result.n_fused  # their summed information counts it n_fused times
            mpose = self.landmarks.track(frame.index, result.features, pose, info)
            if mpose is not pose:
                pose = mpose
                result.pose = pose
                self.frontend.correct_last(pose)
            st.add_time("landmarks", time.perf_counter() - t0)
        depth = frame.depth
        if self.depth_filter is not None:
            if restart:  # the last depth maps' poses are unrelated to this one's: nothing to warp
                self.depth_filter.reset()
            t0 = time.perf_counter()
            depth = self.depth_filter(frame.depth, pose)
            self.frontend.set_depth(frame.index, depth)
            st.add_time("depth_filter", time.perf_counter() - t0)
            if self.observer is not None:
                self.observer.log_filtered_depth(frame.index, frame.timestamp, depth)

        if restart:  # the front end restarted after a loss: a new segment, to be relocalised
            st.restarts.append(frame.index)
            if self.loop is not None:
                self.loop.new_segment()
        loops = []
        if self.loop is not None:
            t0 = time.perf_counter()
            sharp = self.loop.observe(result.features)
            st.sharp += int(sharp)
            if self.observer is not None:
                self.observer.log_gate(frame.index, frame.timestamp, *self.loop.gate.last, sharp)
            # relocalising: every frame searches the older segments; due: none searched for query_gap frames
            if sharp or self.loop.relocalizing or self.loop.due(frame.index):
                loops = self.loop.detect(result.features, pose)
            st.add_time("loop_closure", time.perf_counter() - t0)

        is_kf = self.keyframe_policy.is_keyframe(frame.index, pose)
        if (loops or restart) and not is_kf:  # a loop edge / a segment's first pose needs a graph node
            self.keyframe_policy.force(frame.index, pose)
            is_kf = True
        if is_kf and self.landmarks is not None:
            t0 = time.perf_counter()
            refined = self.landmarks.add_keyframe(frame.index, result.features, pose)
            if refined is not None:  # local BA moved this keyframe: tracking continues from there
                pose = refined
                result.pose = pose
                self.frontend.correct_last(pose)
            st.add_time("local_ba" if self.landmarks.ba is not None else "landmarks", time.perf_counter() - t0)
        if self.landmarks is not None:
            self.landmarks.end_frame(frame.index)
            if self.observer is not None and hasattr(self.observer, "log_landmarks") and \
                    frame.index % max(1, self.cfg.output.rerun_log_every) == 0:
                self.landmarks.log(self.observer, frame.index, result.features, is_kf)
        if is_kf:
            self._add_keyframe(frame, result, pose, depth)
        rec = FrameRecord(frame.index, frame.timestamp, pose.copy(), frame.index if is_kf else self._last_kf.index)
        st.records.append(rec)
        if is_kf:
            self._last_kf = rec
        if loops and self.graph is not None:
            t0 = time.perf_counter()
            for e in loops:
                self.graph.add_loop(e)
                st.loops.append((int(e.i), int(e.j)))
                if self.observer is not None:
                    self.observer.log_loop(e.i, e.j, self._pose_of(e.i), pose)
            st.add_time("pose_graph", time.perf_counter() - t0)
        if self.observer is not None:
            self.observer.log_frame(frame, result)
            if getattr(result, "matches", None) is not None:
                m = result.matches
                self.observer.log_inlier_matches(frame.index, m[:, :2], m[:, 2:])
        return result

    def _pose_of(self, index: int) -> np.ndarray | None:
        for r in reversed(self.state.records):
            if r.index == index:
                return r.pose
        return None

    def _add_keyframe(self, frame: Frame, result, pose: np.ndarray, depth: np.ndarray) -> None:
        st = self.state
        st.keyframes.append(frame.index)
        if self.graph is not None:
            self.graph.add_node(frame.index, pose)
            if self._last_kf is not None:
                T_ij = inv(self._last_kf.pose) @ pose
                self.graph.add_odometry(self._last_kf.index, frame.index, T_ij, self._keyframe_information())
        self._info_since_kf = []
        if self.loop is not None:
            self.loop.add_keyframe(result.features, pose)
        if self.keyframe_dir is not None and self.depth_filter is not None:
            _write_depth_png(self.keyframe_dir / f"depth_{frame.index:06d}.png", depth)

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
        self.optimised = optimised
        if self.landmarks is not None:  # landmarks move with the keyframe that anchors them
            self.landmarks.finish(optimised)
        self.state.add_time("pose_graph", time.perf_counter() - t0)
        kf_pose = {r.index: r.pose for r in self.state.records if r.index == r.keyframe}
        poses = []
        for r in self.state.records:
            if r.keyframe in optimised:
                poses.append(optimised[r.keyframe] @ inv(kf_pose[r.keyframe]) @ r.pose)
            else:
                poses.append(r.pose)
        return Trajectory(odo.timestamps, np.array(poses).reshape(-1, 4, 4))


def _write_depth_png(path: Path, depth: np.ndarray, scale: float = 5000.0) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    d = np.clip(np.round(depth * scale), 0, 65535).astype(np.uint16)
    with atomic_path(path) as tmp:  # the temporary name keeps the .png suffix cv2 needs
        cv2.imwrite(str(tmp), d)


# ----------------------------------------------------------------------------- a whole run


def _make_observer(cfg: Config, camera: Camera, gt: Trajectory | None):
    if not (cfg.output.rerun or cfg.output.rerun_save):
        return None
    from rgbdslam.viz.rerun_log import RerunLogger

    return RerunLogger(cfg, camera, gt, spawn=cfg.output.rerun, save_path=cfg.output.rerun_save)


def tracking_segments(tracked: list[int], restarts: list[int], loops: list[tuple[int, int]]) -> list[dict[str, Any]]:
    """The run's tracking segments and which of them share one map.

    A segment runs from the first tracked frame (or a restart after a tracking loss) to the
    frame before the next restart. Loops between two segments relate their coordinates; the
    segments connected by loops to the one with the most tracked frames form the map
    (``"map": true``). A segment outside it was never relocalised: its poses are right only up
    to an unknown offset, so fusing it would put a ghost copy of its scene into the map.
    Returns ``[{"first", "last", "frames", "map"}]`` in time order (empty without tracked frames).
    """
    tracked = sorted(int(i) for i in tracked)
    if not tracked:
        return []
    starts = sorted({tracked[0], *(int(r) for r in restarts if r > tracked[0])})
    seg_of = lambda i: int(np.searchsorted(starts, i, side="right")) - 1  # noqa: E731
    parent = list(range(len(starts)))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for i, j in loops:
        a, b = root(seg_of(i)), root(seg_of(j))
        if a != b:
            parent[max(a, b)] = min(a, b)
    counts = np.bincount([seg_of(i) for i in tracked], minlength=len(starts))
    size: dict[int, int] = {}
    for k, c in enumerate(counts):
        size[root(k)] = size.get(root(k), 0) + int(c)
    main = max(size, key=lambda r: (size[r], -r))  # most frames; ties: the earliest
    out = []
    for k, first in enumerate(starts):
        members = [i for i in tracked if seg_of(i) == k]
        out.append({"first": first, "last": members[-1] if members else first, "frames": len(members),
                    "map": root(k) == main})
    return out


def _summary(seq: Sequence, slam: SLAM, n_frames: int, wall: float, load_time: float,
             interrupted: bool) -> dict[str, Any]:
    st = slam.state
    tracked = len(st.records)
    proc = max(wall - load_time, 1e-9)
    per_stage = {k: {"median_ms": 1e3 * float(np.median(v)), "total_s": float(np.sum(v))}
                 for k, v in st.timings.items() if v}
    return {
        "version": __version__,
        "sequence": str(Path(seq.root).resolve()),
        "dataset_kind": type(seq).__name__,
        "camera": seq.camera.name,
        "frames": n_frames,
        "tracked": tracked,
        "lost": len(st.lost),
        "skipped": len(st.skipped),
        "lost_frames": st.lost,
        "skipped_frames": st.skipped,
        "restarts": st.restarts,
        "relocalized": int(slam.loop.stats["n_relocalized"]) if slam.loop is not None else 0,
        "segments": tracking_segments([r.index for r in st.records], st.restarts, st.loops),
        # the loop closer's counters: searches, candidates, verifications, accepted and rejected loops
        "loop_closure": {k: (round(v, 3) if isinstance(v, float) else v) for k, v in slam.loop.stats.items()
                         if k not in ("isam2_failed", "batch_failed")} if slam.loop is not None else {},
        "keyframes": st.keyframes,
        "timestamps_keyframes": [r.timestamp for r in st.records if r.index == r.keyframe],
        "loops": [list(x) for x in st.loops],
        "sharp_frames": st.sharp,
        "wall_time_s": wall,
        "load_time_s": load_time,
        "fps": n_frames / wall if wall > 0 else math.nan,
        "processing_fps": n_frames / proc,
        "timings": per_stage,
        "landmarks": slam.landmarks.summary() if slam.landmarks is not None else {},
        "interrupted": interrupted,
        "status": "interrupted" if interrupted else "finished",  # "failed" when nothing could be tracked
    }


def _write_outputs(out_dir: Path, slam: SLAM, summary: dict, final: Trajectory | None) -> None:
    odo = slam.odometry()
    write_tum(odo, out_dir / "odometry.tum")
    write_tum(final if final is not None else odo, out_dir / "trajectory.tum")
    if slam.graph is not None and slam.graph.order:
        from rgbdslam.backend.graph_io import write_g2o

        write_g2o(out_dir / "posegraph.g2o", slam.graph.as_graph(slam.optimised))
    if slam.landmarks is not None and slam.landmarks.map.size:  # the thesis' 2-D map: landmarks from above
        slam.landmarks.top_view(out_dir / "map" / "landmarks_topview.png")
    atomic_write_text(out_dir / "run.json", json.dumps(summary, indent=2))


def run_sequence(sequence: str | Path | Sequence, out_dir: str | Path, cfg: Config,
                 progress: bool = True) -> dict[str, Any]:
    """Run SLAM over a sequence and write the run folder; returns the run summary.

    Ctrl-C stops the run after the current frame: everything tracked so far is written
    (``run.json`` says ``interrupted``) and KeyboardInterrupt is raised again.
    """
    from rgbdslam.ui import console, frame_progress

    if cfg.mapping.enabled:  # a mapping setting fusion would refuse: say so before the run, not after it
        from rgbdslam.mapping.fusion import validate_mapping

        validate_mapping(cfg.mapping)
    seq = sequence if isinstance(sequence, Sequence) else open_sequence(sequence, cfg.dataset)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if keep_previous_run(out_dir):
        console.print(f"note: the earlier run in {out_dir} was moved to {out_dir / 'previous'}")
    save_config(cfg, out_dir / "config.yaml")
    gt = seq.groundtruth()
    observer = _make_observer(cfg, seq.camera, gt)
    slam = SLAM(cfg, seq.camera, observer, keyframe_dir=out_dir / "keyframes")

    n = len(seq)
    if n == 0:
        raise InputError(f"sequence {seq.root} has no frames; check rgb.txt/depth.txt (or 'matched')")
    interrupted = False
    load_time = 0.0
    t_start = time.perf_counter()
    from rgbdslam.frontend.features import with_detections

    # the reader thread also finds the key points (colour only), overlapping the tracking of the last frame
    frames = seq.prefetched(cfg.dataset.prefetch, then=lambda f: with_detections(f, cfg.features))
    try:
        with frame_progress(n, f"SLAM {seq.name}", enabled=progress) as advance:
            for i, pending in frames:
                t0 = time.perf_counter()
                try:
                    frame = pending.result()  # time waited for the reader thread counts as loading
                except InputError as e:
                    slam.state.skipped.append(i)
                    if len(slam.state.skipped) <= MAX_FRAME_WARNINGS:
                        console.print(f"[yellow]warning:[/] skipped frame {i}: {e}")
                    if len(slam.state.skipped) == MAX_FRAME_WARNINGS:
                        console.print("[yellow]warning:[/] further unreadable frames are skipped silently; "
                                      "run.json lists them all (skipped_frames)")
                    advance()
                    continue
                load_time += time.perf_counter() - t0
                if not slam.state.records and not slam.state.lost and (warning := depth_warning(frame)):
                    console.print(f"[yellow]warning:[/] {warning}")  # once, on the first readable frame
                slam.track(frame)
                st = slam.state
                advance(f"{len(st.loops)} loops, {len(st.lost)} lost" + (f", {len(st.restarts)} restarts"
                                                                      if st.restarts else ""))
                if (i + 1) % FLUSH_EVERY == 0 and slam.state.records:
                    write_tum(slam.odometry(), out_dir / "odometry.tum")
                    write_tum(slam.odometry(), out_dir / "trajectory.tum")
    except KeyboardInterrupt:
        interrupted = True
    finally:
        frames.close()  # stops the reader thread
    wall = time.perf_counter() - t_start
    n_done = len(slam.state.records) + len(slam.state.lost) + len(slam.state.skipped)

    if not slam.state.records or (len(slam.state.records) == 1 and n_done > 1 and not interrupted):
        # nothing, or only the first frame (the origin; no frame after it registered): no trajectory
        summary = _summary(seq, slam, n_done, wall, load_time, interrupted)
        if not interrupted:
            summary["status"] = "failed"
            for name in ("trajectory.tum", "odometry.tum"):  # a 50-frame flush of this run: not a result
                (out_dir / name).unlink(missing_ok=True)
        atomic_write_text(out_dir / "run.json", json.dumps(summary, indent=2))
        if observer is not None:  # nothing worth recording: an earlier .rrd at that path stays
            observer.abort()
        if interrupted:
            raise KeyboardInterrupt
        what = "no frame" if not slam.state.records else f"no frame after the first ({slam.state.records[0].index})"
        raise TrackingLost(
            f"{what} of {seq.root} could be tracked; check that depth images are valid and the camera "
            f"preset matches (--config), e.g. tum_fr1 for freiburg1"
        )
    final = slam.finish()
    summary = _summary(seq, slam, n_done, wall, load_time, interrupted)
    _write_outputs(out_dir, slam, summary, final)

    if gt is not None and len(final) > 1:
        summary["evaluation"] = _evaluate(gt, final, out_dir, cfg, console)
        atomic_write_text(out_dir / "run.json", json.dumps(summary, indent=2))
    if observer is not None:
        observer.log_trajectory("estimate", final)
        if gt is not None:
            observer.log_trajectory("groundtruth", gt)
    if cfg.mapping.enabled and not interrupted:
        from rgbdslam.mapping.fusion import fuse_run

        try:
            fused = fuse_run(out_dir, cfg.mapping, progress=progress)
        except RgbdslamError as e:  # like evaluation, the map never stops a finished run
            console.print(f"[yellow]warning:[/] no map: {e}")
            summary["map"] = {}
        else:
            summary["map"] = fused.summary()
            if observer is not None and getattr(fused, "cloud_points", None) is not None:
                observer.log_map(fused.cloud_points, fused.cloud_colors)
        atomic_write_text(out_dir / "run.json", json.dumps(summary, indent=2))
    if observer is not None:
        observer.close()
    _print_summary(summary, out_dir, console)
    if interrupted:
        raise KeyboardInterrupt
    return summary


def _evaluate(gt: Trajectory, est: Trajectory, out_dir: Path, cfg: Config, console) -> dict[str, Any]:
    from rgbdslam.evaluation.report import evaluate_trajectories

    plot_dir = out_dir / "plots" if cfg.output.plots else None
    try:
        rep = evaluate_trajectories(gt, est, json_path=out_dir / "evaluation.json", plot_dir=plot_dir)
    except RgbdslamError as e:  # evaluation is a bonus: it never stops a finished run
        console.print(f"[yellow]warning:[/] no evaluation: {e}")
        return {}
    return rep.to_dict() if hasattr(rep, "to_dict") else {}


def _print_summary(s: dict[str, Any], out_dir: Path, console) -> None:
    msg = (f"{s['frames']} frames, {s['tracked']} tracked, {s['lost']} lost"
           + (f", {s['skipped']} unreadable" if s["skipped"] else "")
           + f", {len(s['keyframes'])} keyframes, {len(s['loops'])} loops; "
           f"{s['fps']:.1f} frames/s ({s['processing_fps']:.1f} without waiting for images)")
    console.print(msg)
    if s.get("restarts"):
        n, r = len(s["restarts"]), s.get("relocalized", 0)
        frames = ", ".join(str(i) for i in s["restarts"])
        console.print(f"[yellow]tracking restarted {n}× after a loss (frame {frames}); "
                      + (f"{r} of {n} new segment(s) relocalised against the map[/]" if r else
                         "not relocalised: those segments' poses are only known up to an offset[/]"))
        off = [g for g in s.get("segments", []) if not g["map"]]
        if off:
            spans = ", ".join(f"{g['first']}–{g['last']}" for g in off)
            console.print(f"[yellow]frames {spans} ({sum(g['frames'] for g in off)} tracked) are not linked to the "
                          f"map by any loop: trajectory.tum keeps them (up to an unknown offset), the map leaves "
                          f"them out[/]")
    ev = s.get("evaluation") or {}
    ate = (ev.get("ate") or {}).get("rmse")
    if ate is not None:
        console.print(f"ATE RMSE {ate:.4f} m over {ev['ate'].get('n_pairs', '?')} poses")
    console.print(f"outputs in {out_dir}")


def run_demo(out_dir: str | Path, frames: int, cfg: Config) -> dict[str, Any]:
    """Generate the embedded synthetic sequence (once) and run SLAM on it."""
    from rgbdslam.datasets.synthetic import generate_sequence
    from rgbdslam.ui import console

    if frames < 2:
        raise InputError(f"--frames must be at least 2 for a trajectory (got {frames})")
    out_dir = Path(out_dir)
    seq_dir = out_dir / "sequence"
    marker = seq_dir / "demo.json"
    want = {"frames": frames, "motion": "loop", "noise": True, "seed": 0}
    if not marker.exists() or json.loads(marker.read_text()) != want:
        console.print(f"generating a synthetic sequence of {frames} frames in {seq_dir}")
        generate_sequence(seq_dir, frames=frames, motion="loop", noise=True, seed=0)
        atomic_write_text(marker, json.dumps(want))
    run = out_dir / "run"
    summary = run_sequence(seq_dir, run, cfg)
    if (run / "trajectory.tum").exists() and summary.get("evaluation"):
        from rgbdslam.evaluation.report import compare_and_print

        # what loop closure and the pose graph added to the front end, against the exact ground truth
        compare_and_print(seq_dir / "groundtruth.txt", [run / "odometry.tum", run / "trajectory.tum"],
                          plots=False, console=console)
    console.print(f"next: [bold]rgbdslam view {run}[/] (Rerun), the map in {run / 'map'}, "
                  f"the plots in {run / 'plots'}; `rgbdslam run SEQUENCE` for your own data")
    return summary

