"""The run driver: a sequence through the SLAM chain into a run folder.

``run_sequence`` reads as its steps: check the settings, open the sequence, prepare the run
folder, track every frame (:class:`rgbdslam.slam.SLAM`, one frame at a time), then either fail
with one clear error or post-process (pose-graph optimisation, outputs, evaluation, map). The
per-frame chain is in ``slam.py``, the run folder's files in ``run_folder.py``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rgbdslam.config import Config, save_config
from rgbdslam.datasets import Sequence, open_sequence
from rgbdslam.datasets.base import depth_warning
from rgbdslam.errors import InputError, RgbdslamError, TrackingLost
from rgbdslam.io.atomic import atomic_write_text
from rgbdslam.io.trajectory import Trajectory
from rgbdslam.run_folder import (keep_previous_run, print_summary, run_summary, write_outputs, write_summary,
                                 write_trajectories)
from rgbdslam.slam import SLAM
from rgbdslam.viz.observer import make_observer

FLUSH_EVERY = 50  # frames between intermediate trajectory writes
MAX_FRAME_WARNINGS = 5  # per-frame warnings printed before the rest are only counted


@dataclass
class Tracking:
    """How tracking the whole sequence went."""

    frames: int  # frames handled: tracked, lost or unreadable
    wall: float  # seconds
    load_time: float  # seconds spent waiting for frames
    interrupted: bool  # Ctrl-C


def run_sequence(sequence: str | Path | Sequence, out_dir: str | Path, cfg: Config,
                 progress: bool = True) -> dict[str, Any]:
    """Run SLAM over a sequence and write the run folder; returns the run summary.

    Ctrl-C stops the run after the current frame: everything tracked so far is written
    (``run.json`` says ``interrupted``) and KeyboardInterrupt is raised again.
    """
    from rgbdslam.ui import console

    check_settings(cfg)
    seq = sequence if isinstance(sequence, Sequence) else open_sequence(sequence, cfg.dataset)
    out_dir = prepare_run_folder(Path(out_dir), cfg, console)
    announce_camera(seq, console)  # after the folder: a path that cannot be written stays one error line
    gt = seq.groundtruth()
    observer = make_observer(cfg, seq.camera, gt)
    slam = SLAM(cfg, seq.camera, observer, keyframe_dir=out_dir / "keyframes")
    if not seq.streaming and len(seq) == 0:  # a live stream's length is known when it ends
        raise InputError(f"sequence {seq.root} has no frames; check rgb.txt/depth.txt (or 'matched')")
    run = track_all(seq, slam, cfg, out_dir, progress, console)
    if not slam.state.records or (len(slam.state.records) == 1 and run.frames > 1 and not run.interrupted):
        fail(seq, slam, run, out_dir)  # raises
    final = slam.finish()
    summary = run_summary(seq, slam, run.frames, run.wall, run.load_time, run.interrupted)
    write_outputs(out_dir, slam, summary, final)
    post_process(summary, slam, final, gt, out_dir, cfg, run.interrupted, progress, console)
    print_summary(summary, out_dir, console)
    if run.interrupted:
        raise KeyboardInterrupt
    return summary


def announce_camera(seq: Sequence, console) -> None:
    """Say which camera the run uses and where it came from; warn when it is only a guess."""
    setup = getattr(seq, "camera_setup", None)
    if setup is None:
        console.print(f"camera {seq.camera.name or 'custom'}: fx {seq.camera.fx:g} fy {seq.camera.fy:g} "
                      f"cx {seq.camera.cx:g} cy {seq.camera.cy:g}", highlight=False)
        return
    console.print(setup.describe(), highlight=False)
    if (warning := setup.fallback_warning()) is not None:
        console.print(f"[yellow]warning:[/] {warning}", highlight=False)


def check_settings(cfg: Config) -> None:
    """Settings a later stage would refuse: say so before the run, not after it."""
    if cfg.mapping.enabled:
        from rgbdslam.mapping.fusion import validate_mapping

        validate_mapping(cfg.mapping)


def prepare_run_folder(out_dir: Path, cfg: Config, console) -> Path:
    """Create ``out_dir``, move a finished earlier run to ``previous/``, save the config used."""
    out_dir.mkdir(parents=True, exist_ok=True)
    if keep_previous_run(out_dir):
        console.print(f"note: the earlier run in {out_dir} was moved to {out_dir / 'previous'}")
    save_config(cfg, out_dir / "config.yaml")
    return out_dir


def track_all(seq: Sequence, slam: SLAM, cfg: Config, out_dir: Path, progress: bool, console) -> Tracking:
    """Every frame through ``slam.track``; unreadable frames are skipped with a warning, the
    trajectories are flushed every ``FLUSH_EVERY`` frames, Ctrl-C stops after the current frame."""
    from rgbdslam.frontend.features import with_detections
    from rgbdslam.ui import frame_progress

    st = slam.state
    interrupted = False
    load_time = 0.0
    t_start = time.perf_counter()
    # the reader thread also finds the key points (colour only), overlapping the tracking of the last frame
    frames = seq.prefetched(cfg.dataset.prefetch, then=lambda f: with_detections(f, cfg.features))
    try:
        with frame_progress(None if seq.streaming else len(seq), f"SLAM {seq.name}", enabled=progress) as advance:
            for i, pending in frames:
                t0 = time.perf_counter()
                try:
                    frame = pending.result()  # time waited for the reader thread counts as loading
                except InputError as e:
                    _skip(st, i, e, console)
                    advance()
                    continue
                load_time += time.perf_counter() - t0
                if not st.records and not st.lost and (warning := depth_warning(frame)):
                    console.print(f"[yellow]warning:[/] {warning}")  # once, on the first readable frame
                slam.track(frame)
                advance(f"{len(st.loops)} loops, {len(st.lost)} lost" + (f", {len(st.restarts)} restarts"
                                                                      if st.restarts else ""))
                if (i + 1) % FLUSH_EVERY == 0 and st.records:
                    write_trajectories(out_dir, slam.odometry())
    except KeyboardInterrupt:
        interrupted = True
    finally:
        frames.close()  # stops the reader thread
    return Tracking(len(st.records) + len(st.lost) + len(st.skipped), time.perf_counter() - t_start, load_time,
                    interrupted)


def _skip(st, index: int, error: InputError, console) -> None:
    st.skipped.append(index)
    if len(st.skipped) <= MAX_FRAME_WARNINGS:
        console.print(f"[yellow]warning:[/] skipped frame {index}: {error}")
    if len(st.skipped) == MAX_FRAME_WARNINGS:
        console.print("[yellow]warning:[/] further unreadable frames are skipped silently; "
                      "run.json lists them all (skipped_frames)")


def fail(seq: Sequence, slam: SLAM, run: Tracking, out_dir: Path) -> None:
    """Nothing, or only the first frame (the origin; no frame after it registered) was tracked:
    run.json says so and no trajectory is left; raises TrackingLost (KeyboardInterrupt if interrupted)."""
    summary = run_summary(seq, slam, run.frames, run.wall, run.load_time, run.interrupted)
    if not run.interrupted:
        summary["status"] = "failed"
        for name in ("trajectory.tum", "odometry.tum"):  # a 50-frame flush of this run: not a result
            (out_dir / name).unlink(missing_ok=True)
    write_summary(out_dir, summary)
    slam.observer.abort()  # nothing worth recording: an earlier .rrd at that path stays
    if run.interrupted:
        raise KeyboardInterrupt
    records = slam.state.records
    what = "no frame" if not records else f"no frame after the first ({records[0].index})"
    raise TrackingLost(
        f"{what} of {seq.root} could be tracked; check that depth images are valid and the camera "
        f"preset matches (--config), e.g. tum_fr1 for freiburg1"
    )


def post_process(summary: dict[str, Any], slam: SLAM, final: Trajectory, gt: Trajectory | None, out_dir: Path,
                 cfg: Config, interrupted: bool, progress: bool, console) -> None:
    """Evaluation against the ground truth, the trajectories for the observer, the map; each
    adds to run.json and none of them fails a finished run."""
    observer = slam.observer
    if gt is not None and len(final) > 1:
        summary["evaluation"] = evaluate(gt, final, out_dir, cfg, console)
        write_summary(out_dir, summary)
    observer.log_trajectory("estimate", final)
    if gt is not None:
        observer.log_trajectory("groundtruth", gt)
    if cfg.mapping.enabled and not interrupted:
        summary["map"] = fuse_map(out_dir, cfg, observer, progress, console)
        write_summary(out_dir, summary)
    observer.close()


def evaluate(gt: Trajectory, est: Trajectory, out_dir: Path, cfg: Config, console) -> dict[str, Any]:
    from rgbdslam.evaluation.report import evaluate_trajectories

    plot_dir = out_dir / "plots" if cfg.output.plots else None
    try:
        rep = evaluate_trajectories(gt, est, json_path=out_dir / "evaluation.json", plot_dir=plot_dir)
    except RgbdslamError as e:  # evaluation is a bonus: it never stops a finished run
        console.print(f"[yellow]warning:[/] no evaluation: {e}")
        return {}
    return rep.to_dict() if hasattr(rep, "to_dict") else {}


def fuse_map(out_dir: Path, cfg: Config, observer, progress: bool, console) -> dict[str, Any]:
    from rgbdslam.mapping.fusion import fuse_run

    try:
        fused = fuse_run(out_dir, cfg.mapping, progress=progress)
    except RgbdslamError as e:  # like evaluation, the map never stops a finished run
        console.print(f"[yellow]warning:[/] no map: {e}")
        return {}
    if getattr(fused, "cloud_points", None) is not None:
        observer.log_map(fused.cloud_points, fused.cloud_colors)
    return fused.summary()


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
