"""The run driver: a sequence through the SLAM chain into a run folder.

``run_sequence`` reads as its steps: check the settings, open the sequence, prepare the run
folder, track every frame (:class:`rgbdslam.slam.SLAM`, one frame at a time), then either fail
with one clear error or post-process (pose-graph optimisation, outputs, evaluation, map). The
per-frame chain is in ``slam.py``, the run folder in ``runfolder/``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rgbdslam.config import Config, save_config
from rgbdslam.datasets import Sequence, open_sequence
from rgbdslam.errors import InputError, RgbdslamError, TrackingLost, was_interrupted
from rgbdslam.io.atomic import atomic_write_text, make_dirs
from rgbdslam.stereo.depth import frame_warning
from rgbdslam.io.trajectory import Trajectory, as_written
from rgbdslam.runfolder.folder import (RunRecord, folder_lock, make_way_for_run, print_summary, run_summary,
                                      write_outputs, write_trajectories)
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
    first_frame_s: float | None = None  # from the start of the process to the first frame tracked


def run_sequence(sequence: str | Path | Sequence, out_dir: str | Path, cfg: Config,
                 progress: bool = True, map_dir: str | Path | None = None, localize: bool = False,
                 announce: str | None = None) -> dict[str, Any]:
    """Run SLAM over a sequence and write the run folder (with its map, ``map.npz``); returns the run summary.

    ``announce``: a line printed with the camera once the run has started (the command line's
    choice of preset), so that an error before that stays the only line.

    ``map_dir``: a finished run's folder whose map the camera relocalises in and then extends, or
    only localises in with ``localize`` (:mod:`rgbdslam.session`); checked before anything is written.

    Ctrl-C stops the run after the current frame: everything tracked so far is written
    (``run.json`` says ``interrupted``) and KeyboardInterrupt is raised again. Ctrl-C at any
    other moment after the folder was prepared (start-up, evaluation, map) and any error there (a
    full disk) leave run.json saying ``interrupted`` or ``failed`` with the stage
    (:class:`rgbdslam.runfolder.folder.RunRecord`). The folder is locked while the run writes into it
    (:func:`rgbdslam.runfolder.folder.folder_lock`): a second run into it is one error line.
    """
    check_settings(cfg)
    seq = sequence if isinstance(sequence, Sequence) else open_sequence(sequence, cfg)
    session = None
    if map_dir is not None:
        from rgbdslam.session.sessions import open_map

        session = open_map(map_dir, seq.camera, Path(out_dir), localize)
    elif localize:
        raise InputError("--localize needs --map RUN_DIR (the run whose map to localise in)")
    out_dir = make_dirs(Path(out_dir))
    with folder_lock(out_dir, "run"):
        record = RunRecord(out_dir, str(Path(seq.root).resolve()))
        try:
            return _run(seq, out_dir, cfg, progress, record, session, announce)
        except KeyboardInterrupt:
            record.close("interrupted")
            raise
        except TrackingLost:
            raise  # run.json already says failed
        except (RgbdslamError, OSError) as e:
            record.close("failed", str(e) if isinstance(e, RgbdslamError) else
                         f"{e.filename or ''}: {e.strerror or e}".lstrip(": "))
            raise
        except BaseException as e:  # a library's error; after Ctrl-C (an import cut short) an interruption
            if isinstance(e, Exception) and was_interrupted():
                record.close("interrupted")
            else:
                record.close("failed", f"{type(e).__name__}: {e}")
            raise


def _run(seq: Sequence, out_dir: Path, cfg: Config, progress: bool, record: RunRecord, session,
         announce: str | None = None) -> dict[str, Any]:
    """The run's steps, in the locked folder; ``record`` keeps run.json and the stage; ``session``
    the saved map this run localises in or extends (None: a new map)."""
    from rgbdslam.ui import console

    prepare_run_folder(out_dir, cfg, console, record)
    if announce:
        console.print(announce, highlight=False)
    announce_camera(seq, console)  # after the folder: a path that cannot be written stays one error line
    gt = seq.groundtruth()
    observer = make_observer(cfg, seq.camera, gt)
    if not seq.streaming and len(seq) == 0:  # a live stream's length is known when it ends
        raise InputError(f"sequence {seq.root} has no frames; check rgb.txt/depth.txt (or 'matched')")
    # with --map the map is fused after the run (every session of a joined map, in the map's frame)
    mapper = start_live_map(cfg, seq, out_dir) if session is None else None
    plotter = None
    try:
        try:
            slam = SLAM(cfg, seq.camera, observer, keyframe_dir=out_dir / "keyframes", mapper=mapper)
            if session is not None:
                session.attach(slam)
            plotter = start_plot_worker(cfg, gt)
            record.stage = "tracking"
            run = track_all(seq, slam, cfg, out_dir, progress, console)
            record.stage = "writing the trajectory"
            if not slam.state.records or (len(slam.state.records) == 1 and run.frames > 1 and not run.interrupted):
                fail(seq, slam, run, out_dir, record)  # raises
        except BaseException:
            if mapper is not None:
                mapper.abort()
            raise
        return _finish_run(seq, out_dir, cfg, progress, record, session, slam, run, gt, plotter, console)
    finally:
        if plotter is not None:
            plotter.close()


def _finish_run(seq: Sequence, out_dir: Path, cfg: Config, progress: bool, record: RunRecord, session, slam: SLAM,
                run: Tracking, gt: Trajectory | None, plotter, console) -> dict[str, Any]:
    """After the last frame: the final pose graph, the outputs, evaluation, plots and map."""
    record.stage = "pose graph"
    t_end = time.perf_counter()  # the last frame is tracked: what follows is what the user waits for on top
    c_end = time.process_time()
    final = as_written(slam.finish())  # the poses trajectory.tum holds: the outputs, live map and evaluation use them
    after = {"pose_graph": time.perf_counter() - t_end}
    summary = run_summary(seq, slam, run.frames, run.wall, run.load_time, run.interrupted)
    summary["first_frame_s"] = run.first_frame_s
    if run.interrupted:
        summary["stopped_during"] = "tracking"
    record.stage = "saving the map"
    final = save_map_of_run(out_dir, slam, seq, cfg, session, summary, final, console)
    record.stage = "writing the trajectory"
    write_outputs(out_dir, slam, summary, final)
    record.write(summary)
    after["outputs"] = time.perf_counter() - t_end - after["pose_graph"]
    summary["after_tracking_s"] = after
    post_process(summary, slam, final, gt, out_dir, cfg, run.interrupted, progress, console, record,
                 groundtruth_name(seq), plotter)
    after["total"] = time.perf_counter() - t_end
    after["cpu"] = time.process_time() - c_end  # CPU seconds of this process (its helpers' are in map.timings)
    summary["after_tracking_s"] = {k: round(v, 3) for k, v in after.items()}
    record.stage = "end"
    failure = None if run.interrupted else mostly_lost(seq, summary)
    if failure is not None:
        summary.update(status="failed", error=failure)
    record.write(summary, final=True)  # only now: "finished" (or "interrupted" from the tracking loop)
    print_summary(summary, out_dir, console)
    if run.interrupted:
        raise KeyboardInterrupt
    if failure is not None:
        raise TrackingLost(failure)
    return summary


def mostly_lost(seq: Sequence, summary: dict[str, Any]) -> str | None:
    """One line when tracking failed for most frames (more lost than tracked): the settings do not
    fit the sequence, and its trajectory and ATE mean nothing. The outputs stay for a look."""
    lost, tracked = summary["lost"], summary["tracked"]
    if lost <= tracked:
        return None
    if seq.rig is not None:  # stereo: depth from the pair, no depth scale
        fix = "a wrong preset (--config kitti for a car-mounted rig) or stereo calibration"
    else:
        fix = ("a wrong preset (--config, e.g. tum_fr1 for TUM freiburg1), camera (--camera FILE) or depth scale "
               "(--set dataset.depth_scale=UNITS_PER_METRE)")
    return (f"{lost} of {lost + tracked} frames of {seq.name} could not be tracked, so its trajectory "
            f"and ATE mean nothing; likely {fix}; `rgbdslam info SEQUENCE` shows what was used")


def announce_camera(seq: Sequence, console) -> None:
    """Say which camera the run uses and where it came from (and how the reader converts the
    ground truth, when it does); warn when the camera is only a guess."""
    if seq.groundtruth_convention:
        console.print(f"ground truth: {seq.groundtruth_convention}", highlight=False)
    setup = seq.camera_setup
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
        from rgbdslam.config import validate_section

        validate_section("mapping", cfg.mapping)


def start_plot_worker(cfg: Config, gt: Trajectory | None):
    """The process that draws the evaluation plots after the last frame, started now so that it has
    imported matplotlib by then (:mod:`rgbdslam.evaluation.plot_worker`); None without plots to draw."""
    if not (cfg.output.plots and gt is not None and len(gt) > 1):
        return None
    from rgbdslam.evaluation.plot_worker import PlotWorker

    return PlotWorker(cfg.mapping.live_nice)


def start_live_map(cfg: Config, seq: Sequence, out_dir: Path):
    """The map fused while tracking (:mod:`rgbdslam.mapping.live`) when the map is made of the
    keyframes and ``mapping.live``; None otherwise (the map is fused after the run)."""
    m = cfg.mapping
    if not (m.enabled and m.live and m.keyframes_only) or seq.streaming:
        return None  # a stream's frames cannot be read again for re-integration
    if seq.rig is not None and cfg.stereo.map_depth not in ("same", cfg.stereo.depth):
        return None  # stereo: the map wants other depth than tracking (stereo.map_depth): fused after the run
    from rgbdslam.mapping.live import LiveMap

    return LiveMap(m, seq.camera, str(seq.root), cfg, str(out_dir / "keyframes"))


def prepare_run_folder(out_dir: Path, cfg: Config, console, record: RunRecord) -> Path:
    """Move a finished earlier run in ``out_dir`` to ``previous/``, save the config used and a
    first run.json ("running")."""
    if make_way_for_run(out_dir):
        console.print(f"note: the earlier run in {out_dir} was moved to {out_dir / 'previous'}")
    record.start()
    save_config(cfg, out_dir / "config.yaml", outputs=False)  # a re-run from it must not overwrite this run's outputs
    record.write(record.summary)
    return out_dir


def save_map_of_run(out_dir: Path, slam: SLAM, seq: Sequence, cfg: Config, session, summary: dict[str, Any],
                    final: Trajectory, console) -> Trajectory:
    """map.npz of the run (a failure to write it is a warning: the trajectories still stand);
    with ``--map``, run.json's session entry and, when localising, the localised frames only."""
    from rgbdslam.session.sessions import save_run_map

    if session is not None:
        final = session.finish(slam, summary, final)
        ss = summary["session"]
        if ss["relocalized"]:
            gaps = sum(b - a + 1 for a, b in ss["not_localized"])
            console.print(f"session {ss['session']}: relocalised in the map at frame {ss['first_localized_frame']}, "
                          f"{len(summary['map_loops'])} loops into it; {gaps} frames not localised"
                          + (" (left out of trajectory.tum)" if session.localize and gaps else ""))
        else:
            console.print(f"[yellow]warning:[/] the camera never relocalised in the map {session.path}: " + (
                "no frame is localised, trajectory.tum is empty (odometry.tum has the session in its own coordinates)"
                if session.localize else "this session is a separate segment of the saved map (its own coordinates)"))
    try:
        save_run_map(out_dir, slam, seq, cfg, session, summary)
    except (OSError, RgbdslamError) as e:
        console.print(f"[yellow]warning:[/] no map file: {e}")
        summary["map_file"] = None
    return final


def track_all(seq: Sequence, slam: SLAM, cfg: Config, out_dir: Path, progress: bool, console) -> Tracking:
    """Every frame through ``slam.track``; unreadable frames are skipped with a warning, the
    trajectories are flushed every ``FLUSH_EVERY`` frames, Ctrl-C stops after the current frame."""
    from rgbdslam.frontend.features import with_detections
    from rgbdslam.frontend.odometry import detection_features
    from rgbdslam.ui import frame_progress

    st = slam.state
    interrupted = False
    load_time = 0.0
    first_frame_s = None
    t_start = time.perf_counter()
    # the reader thread also finds the key points (colour only), overlapping the tracking of the last frame
    fc = detection_features(cfg.features, cfg.landmarks.n_features if cfg.landmarks.enabled and not seq.own_key_points else 0)
    frames = seq.prefetched(cfg.dataset.prefetch, then=lambda f: with_detections(f, fc),
                            workers=cfg.dataset.reader_threads)
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
                if not st.records and not st.lost and (warning := frame_warning(frame)):
                    console.print(f"[yellow]warning:[/] {warning}")  # once, on the first readable frame
                slam.track(frame)
                if first_frame_s is None:
                    first_frame_s = seconds_since_process_start()
                advance(f"{len(st.loops)} loops, {len(st.lost)} lost" + (f", {len(st.restarts)} restarts"
                                                                      if st.restarts else ""))
                if (i + 1) % FLUSH_EVERY == 0 and st.records:
                    write_trajectories(out_dir, slam.odometry())
    except KeyboardInterrupt:
        interrupted = True
    finally:
        frames.close()  # stops the reader thread
    return Tracking(len(st.records) + len(st.lost) + len(st.skipped), time.perf_counter() - t_start, load_time,
                    interrupted, first_frame_s)


def seconds_since_process_start() -> float | None:
    """Wall time since this process started (Linux /proc; None elsewhere): what a user waits
    from pressing Enter, imports included."""
    try:
        with open("/proc/self/stat") as f:
            ticks = int(f.read().rsplit(")", 1)[1].split()[19])  # start time, clock ticks after boot
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return None
    import os

    return uptime - ticks / os.sysconf("SC_CLK_TCK")


def _skip(st, index: int, error: InputError, console) -> None:
    st.skipped.append(index)
    if len(st.skipped) <= MAX_FRAME_WARNINGS:
        console.print(f"[yellow]warning:[/] skipped frame {index}: {error}")
    if len(st.skipped) == MAX_FRAME_WARNINGS:
        console.print("[yellow]warning:[/] further unreadable frames are skipped silently; "
                      "run.json lists them all (skipped_frames)")


def fail(seq: Sequence, slam: SLAM, run: Tracking, out_dir: Path, record: RunRecord) -> None:
    """Nothing, or only the first frame (the origin; no frame after it registered) was tracked:
    run.json says so and no trajectory is left; raises TrackingLost (KeyboardInterrupt if interrupted)."""
    summary = run_summary(seq, slam, run.frames, run.wall, run.load_time, run.interrupted)
    if run.interrupted:
        summary["stopped_during"] = "tracking"
    else:
        summary["status"] = "failed"
        for name in ("trajectory.tum", "odometry.tum", "poses.txt"):  # a 50-frame flush of this run: not a result
            (out_dir / name).unlink(missing_ok=True)
    record.write(summary, final=True)
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
                 cfg: Config, interrupted: bool, progress: bool, console, record: RunRecord,
                 gt_name: str = "ground truth", plotter=None) -> None:
    """Evaluation against the ground truth, the trajectories for the observer, the map; each
    adds to run.json and none of them fails a finished run by bad input (a full disk or Ctrl-C
    does: ``record`` names the stage). With ``plotter`` (a :class:`PlotWorker`) the plots are drawn
    there while the map is finished."""
    observer = slam.observer
    after = summary.setdefault("after_tracking_s", {})  # seconds per step, for the run record
    live = None
    if slam.mapper is not None:
        if cfg.mapping.enabled and not interrupted and slam.state.keyframes:
            import concurrent.futures

            pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="map")
            live = pool.submit(finish_live_map, slam, summary, final, out_dir, cfg)  # overlaps the evaluation
            pool.shutdown(wait=False)
        else:
            slam.mapper.abort()
    t0 = time.perf_counter()
    if gt is not None and len(final) > 1:
        record.stage = "evaluation"
        summary["evaluation"] = evaluate(gt, final, out_dir, cfg, console, gt_name, plotter)
        record.write(summary)
    observer.log_trajectory("estimate", final)
    if gt is not None:
        observer.log_trajectory("groundtruth", gt)
    after["evaluation"] = time.perf_counter() - t0
    if cfg.mapping.enabled and not interrupted:
        t0 = time.perf_counter()
        record.stage = "map"
        if live is not None:
            summary["map"] = _map_summary(live, observer, console)
        else:
            summary["map"] = fuse_map(out_dir, cfg, observer, progress, console)
        record.write(summary)
        after["map"] = time.perf_counter() - t0  # with the live map: the wait for it after the evaluation
    if plotter is not None and plotter.submitted:
        t0 = time.perf_counter()
        record.stage = "evaluation"
        collect_plots(plotter, summary, out_dir, console)
        record.write(summary)
        after["plots"] = time.perf_counter() - t0  # the wait for the plot process after the map
    t0 = time.perf_counter()
    record.stage = "recording"
    observer.close()
    after["recording"] = time.perf_counter() - t0


def groundtruth_name(seq: Sequence) -> str:
    """The ground-truth file's path, as `rgbdslam evaluate --json` names it."""
    path = seq.groundtruth_path()
    return str(path) if path is not None else "ground truth"


def evaluate(gt: Trajectory, est: Trajectory, out_dir: Path, cfg: Config, console,
             gt_name: str = "ground truth", plotter=None) -> dict[str, Any]:
    """ATE/RPE into evaluation.json; the plots drawn here, or sent to ``plotter`` (then
    :func:`collect_plots` adds them to evaluation.json when they are written)."""
    from rgbdslam.evaluation.report import evaluate_trajectories

    plot_dir = out_dir / "plots" if cfg.output.plots else None
    try:  # the files named as `rgbdslam evaluate GT RUN_DIR/trajectory.tum --json` names them
        rep = evaluate_trajectories(gt, est, json_path=out_dir / "evaluation.json",
                                    plot_dir=plot_dir if plotter is None else None,
                                    gt_name=gt_name, est_name=str(out_dir / "trajectory.tum"))
    except RgbdslamError as e:  # evaluation is a bonus: it never stops a finished run
        console.print(f"[yellow]warning:[/] no evaluation: {e}")
        return {}
    if plotter is not None and plot_dir is not None:
        plotter.submit(rep, plot_dir)
    return rep.to_dict() if hasattr(rep, "to_dict") else {}


def collect_plots(plotter, summary: dict[str, Any], out_dir: Path, console) -> None:
    """The plots the plot process drew, named in evaluation.json and run.json (a plot that cannot
    be written is a warning: the evaluation's numbers stand)."""
    try:
        plots = plotter.result()
    except RgbdslamError as e:
        console.print(f"[yellow]warning:[/] no plots: {e}")
        return
    ev = summary.get("evaluation")
    if ev:
        ev["plots"] = plots
        atomic_write_text(out_dir / "evaluation.json", json.dumps(ev, indent=2) + "\n")


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


def finish_live_map(slam: SLAM, summary: dict[str, Any], final: Trajectory, out_dir: Path, cfg: Config):
    """The live map brought to the final keyframe poses (keyframes of tracking segments that no
    loop linked to the map left out, as ``rgbdslam fuse`` does) and written to ``out_dir/map``."""
    t0 = time.perf_counter()
    st = slam.state
    poses = {r.index: final.poses[k] for k, r in enumerate(st.records) if r.index == r.keyframe}
    off = [g for g in summary.get("segments") or [] if not g.get("map", True)]
    keep = {i for i in poses if not any(g["first"] <= i <= g["last"] for g in off)}
    res = slam.mapper.finish(poses, keep, out_dir / "map", final, summary["sequence"], slam.depth_filter is not None,
                             want_points=getattr(slam.observer, "logs_map", True))
    res.seconds = time.perf_counter() - t0
    return res


def _map_summary(job, observer, console) -> dict[str, Any]:
    try:
        fused = job.result()
    except RgbdslamError as e:  # like evaluation, the map never stops a finished run
        console.print(f"[yellow]warning:[/] no map: {e}")
        return {}
    except OSError:
        raise  # a full disk or a folder that cannot be written: an error naming the file (run.json: failed)
    except Exception as e:  # noqa: BLE001 - the map process failed unexpectedly: the run's outputs stand
        console.print(f"[yellow]warning:[/] no map: the map process failed ({e}); "
                      f"`rgbdslam fuse RUN_DIR` fuses it again")
        return {}
    if getattr(fused, "cloud_points", None) is not None:
        observer.log_map(fused.cloud_points, fused.cloud_colors)
    out = fused.summary()
    out["live"] = True
    return out


def run_demo(out_dir: str | Path, frames: int, cfg: Config) -> dict[str, Any]:
    """Generate the embedded synthetic sequence (once) and run SLAM on it."""
    from rgbdslam.datasets.synthetic import MAX_FRAMES, generate_sequence
    from rgbdslam.ui import console

    if not 2 <= frames <= MAX_FRAMES:
        raise InputError(f"--frames must be a whole number from 2 (a trajectory) to {MAX_FRAMES} (got {frames})")
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
