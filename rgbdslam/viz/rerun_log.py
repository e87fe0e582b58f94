"""Rerun recordings of a SLAM run: live while tracking (:class:`RerunLogger`) or rebuilt from a
finished run folder (:func:`record_run`), and opening them (:func:`view`).

Entity layout (time lines ``frame`` = sequence position, ``time`` = the frame's time stamp):

- ``world/camera``                  Transform3D, camera-to-world of the current frame
- ``world/camera/image``            Pinhole (RDF camera axes), the frustum
- ``world/camera/image/rgb|depth``  colour and depth, downsampled to ``output.rerun_image_width``
- ``world/camera/image/keypoints``  ORB key points (green: with depth, red: without)
- ``world/camera/image/matches``    inlier matches as segments previous -> current position
- ``world/trajectory/live``         the estimated trajectory so far (grows frame by frame)
- ``world/trajectory/<name>``       whole trajectories (``estimate``, ``odometry``, ``groundtruth``)
- ``world/loops``                   loop edges as segments between the two camera centres
- ``world/map``                     the fused coloured cloud
- ``world/landmarks``               the landmark map (``landmarks.enabled``), coloured by age
- ``world/camera/image/map_matches`` this frame's key points matched to the landmark map
- ``timings/<stage>``               per-stage time in ms (Scalars); ``stats/*`` matches, inliers, lost

The ground truth is drawn in the estimate's world frame: it is moved by the rigid transform that
puts its pose at the first tracked frame onto the estimated pose (a first-frame alignment, for
looking; the evaluation's ATE uses its own alignment).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import weakref
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING

import cv2
import numpy as np

from rgbdslam.errors import InputError, RgbdslamError
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import inv
from rgbdslam.io.atomic import atomic_path, commit, make_dirs, write_target
from rgbdslam.io.trajectory import Trajectory

if TYPE_CHECKING:
    from rgbdslam.config import Config

APPLICATION_ID = "rgbdslam"
RECORDING_ID = "rgbdslam-run"  # fixed, so re-recording a run replaces it in an open viewer
LIVE_STRIP_MAX = 500  # the live trajectory is re-logged every frame up to this length, then sparser


def has_display() -> bool:
    """Whether a GUI window can be opened (X11/Wayland on Linux; assumed elsewhere)."""
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def rerun_executable() -> str | None:
    """The ``rerun`` viewer shipped with rerun-sdk (next to this Python), else on PATH."""
    cand = Path(sys.executable).parent / "rerun"
    return str(cand) if cand.is_file() else shutil.which("rerun")


# trajectories of the sessions of a joined map (world/trajectory/session_<s>)
SESSION_COLORS = ((0, 200, 255), (255, 80, 80), (120, 220, 90), (200, 120, 255), (255, 200, 60))

class RerunLogger:
    """Observer the pipeline calls per frame; writes to a viewer (``spawn``) and/or an .rrd file."""

    def __init__(self, cfg: Config, camera: Camera, groundtruth: Trajectory | None, spawn: bool,
                 save_path: str | Path | None, recording_id: str = RECORDING_ID):
        import rerun as rr

        self.rr = rr
        self.cfg = cfg
        self.camera = camera
        self.groundtruth = groundtruth
        self.gt_align: np.ndarray | None = None
        self.positions: list[np.ndarray] = []
        self.loops: list[list[np.ndarray]] = []
        self.n_frames = 0
        if not spawn and save_path is None:
            raise RgbdslamError("the Rerun logger needs a viewer (--rerun) or a file (--rerun-save FILE.rrd)")
        if spawn and not has_display():
            if save_path is None:
                raise RgbdslamError(
                    "cannot open a Rerun viewer: this machine has no display; record with --rerun-save FILE.rrd "
                    "and open it later with `rgbdslam view FILE.rrd`"
                )
            print("warning: no display for a Rerun viewer; recording to the --rerun-save file only", file=sys.stderr)
            spawn = False
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
        self.save_path = Path(save_path) if save_path is not None else None
        # The recording goes to a temporary file beside ``save_path``; close() renames it over
        # ``save_path``, so a run that fails (or abort()) never replaces an earlier good recording.
        self.tmp_path: Path | None = None
        self._cleanup = None
        self._closed = False
        if self.save_path is not None:
            if self.save_path.is_dir():
                raise InputError(f"--rerun-save {self.save_path} is a folder; give a file name such as "
                                 f"{self.save_path / 'run.rrd'}")
            target, atomic = write_target(self.save_path)  # a link's target; a device is written into at close()
            if atomic:
                make_dirs(target.parent)
            fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent if atomic else None)
            os.close(fd)
            self.tmp_path = Path(tmp)
            # removes the temporary file if the logger is dropped (or the process exits) unclosed
            self._cleanup = weakref.finalize(self, _remove_file, self.tmp_path)
        try:
            if spawn:
                try:
                    self.rec.spawn(connect=False)  # start the viewer; the sinks below stream to it (and the file)
                    sinks = [rr.GrpcSink()] + ([rr.FileSink(str(self.tmp_path))] if self.tmp_path else [])
                    self.rec.set_sinks(*sinks)
                except Exception as e:  # noqa: BLE001 - any failure to start a GUI is the same to the user
                    raise RgbdslamError(
                        f"cannot start the Rerun viewer ({e.__class__.__name__}); use --rerun-save FILE.rrd instead"
                    ) from None
            else:
                self.rec.save(str(self.tmp_path))
        except BaseException:
            if self._cleanup is not None:
                self._cleanup()
            raise
        width = max(16, int(cfg.output.rerun_image_width))
        self.scale = min(1.0, width / camera.width)
        self.img_size = (int(round(camera.width * self.scale)), int(round(camera.height * self.scale)))
        s = self.scale
        self.rec.log(
            "world/camera/image",
            rr.Pinhole(
                image_from_camera=np.array([[camera.fx * s, 0, camera.cx * s], [0, camera.fy * s, camera.cy * s],
                                            [0, 0, 1]]),
                resolution=list(self.img_size),
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=0.2,
            ),
            static=True,
        )
        if groundtruth is not None and len(groundtruth):
            self._log_strip("world/trajectory/groundtruth", groundtruth.positions, (255, 170, 0), static=True)

    # ------------------------------------------------------------------ helpers

    def _set_time(self, index: int, timestamp: float) -> None:
        self.rec.set_time("frame", sequence=int(index))
        self.rec.set_time("time", timestamp=float(timestamp))

    def _log_strip(self, path: str, pts: np.ndarray, color, static: bool = False, radius: float = 0.004) -> None:
        self.rec.log(path, self.rr.LineStrips3D([np.asarray(pts, np.float32)], colors=[color], radii=[radius]),
                     static=static)

    def _align_groundtruth(self, timestamp: float, pose: np.ndarray) -> None:
        gt = self.groundtruth
        if gt is None or len(gt) == 0 or self.gt_align is not None:
            return
        k = int(np.argmin(np.abs(gt.timestamps - timestamp)))
        if abs(gt.timestamps[k] - timestamp) > 0.05:
            return
        self.gt_align = pose @ inv(gt.poses[k])
        P = gt.positions @ self.gt_align[:3, :3].T + self.gt_align[:3, 3]
        self._log_strip("world/trajectory/groundtruth", P, (255, 170, 0), static=True)

    # ------------------------------------------------------------------ observer API

    def log_frame(self, frame, result) -> None:
        """One tracked (or lost) frame: images, key points, pose, frustum, live trajectory, timings."""
        rr = self.rr
        index = getattr(result, "index", getattr(frame, "index", self.n_frames))
        timestamp = getattr(result, "timestamp", getattr(frame, "timestamp", 0.0))
        self._set_time(index, timestamp)
        self.n_frames += 1
        pose = getattr(result, "pose", None)
        lost = bool(getattr(result, "lost", pose is None))
        if pose is not None and not lost:
            pose = np.asarray(pose, dtype=np.float64)
            if not self.positions and np.allclose(pose, np.eye(4), atol=1e-6):
                # the world is the first camera's frame: tell the viewer its axes (x right, y down, z forward)
                self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
            self._align_groundtruth(timestamp, pose)
            self.rec.log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
            self.positions.append(pose[:3, 3].copy())
            n = len(self.positions)
            if n < LIVE_STRIP_MAX or n % max(1, n // LIVE_STRIP_MAX) == 0:
                self._log_strip("world/trajectory/live", np.array(self.positions), (40, 120, 255))
        every = max(1, int(self.cfg.output.rerun_log_every))
        if frame is not None and (self.n_frames - 1) % every == 0:
            self._log_images(frame)
            feats = getattr(result, "features", None)
            if feats is not None:
                self._log_keypoints(feats)
        self.rec.log("stats/lost", rr.Scalars(float(lost)))
        if getattr(result, "reset", False):
            self.rec.log("log", rr.TextLog(f"frame {index}: tracking restarted after a loss; relocalising "
                                           "against the map", level="WARN"))
        for key in ("n_matches", "n_inliers"):
            v = getattr(result, key, None)
            if v is not None:
                self.rec.log(f"stats/{key}", rr.Scalars(float(v)))
        for stage, sec in (getattr(result, "timings", None) or {}).items():
            self.rec.log(f"timings/{stage}", rr.Scalars(1e3 * float(sec)))

    def _log_images(self, frame) -> None:
        rr = self.rr
        rgb = np.asarray(frame.rgb)
        depth = np.asarray(frame.depth, dtype=np.float32)
        if self.scale < 1.0:
            rgb = cv2.resize(rgb, self.img_size, interpolation=cv2.INTER_AREA)
            depth = cv2.resize(depth, self.img_size, interpolation=cv2.INTER_NEAREST)
        self.rec.log("world/camera/image/rgb", rr.Image(rgb, color_model="RGB" if rgb.ndim == 3 else "L").compress(jpeg_quality=85))
        mm = np.clip(np.round(depth * 1000.0), 0, 65535).astype(np.uint16)
        self.rec.log("world/camera/image/depth", rr.DepthImage(mm, meter=1000.0))

    def log_filtered_depth(self, index: int, timestamp: float, depth: np.ndarray) -> None:
        """DIF's output for frame ``index``, next to the measured depth. Called before
        ``log_frame`` of the same frame, it logs the frames whose images ``log_frame`` will log."""
        if self.n_frames % max(1, int(self.cfg.output.rerun_log_every)) != 0:
            return
        depth = np.asarray(depth, dtype=np.float32)
        if self.scale < 1.0:
            depth = cv2.resize(depth, self.img_size, interpolation=cv2.INTER_NEAREST)
        mm = np.clip(np.round(depth * 1000.0), 0, 65535).astype(np.uint16)
        self._set_time(index, timestamp)
        self.rec.log("world/camera/image/depth_filtered", self.rr.DepthImage(mm, meter=1000.0))

    def log_gate(self, index: int, timestamp: float, measure: float, threshold: float, sharp: bool) -> None:
        """The loop-closure sharpness gate: the frame's measure, the threshold it had to exceed, the verdict."""
        self._set_time(index, timestamp)
        self.rec.log("loop/sharpness", self.rr.Scalars(float(measure)))
        if np.isfinite(threshold):
            self.rec.log("loop/threshold", self.rr.Scalars(float(threshold)))
        self.rec.log("loop/sharp", self.rr.Scalars(float(sharp)))

    def _log_keypoints(self, feats) -> None:
        uv = getattr(feats, "uv_raw", None)
        if uv is None or len(uv) == 0:  # distorted pixels match the logged (raw) image; else the ideal ones
            uv = getattr(feats, "uv", None)
        if uv is None or len(uv) == 0:
            return
        uv = np.asarray(uv, dtype=np.float32) * self.scale
        valid = np.asarray(getattr(feats, "valid", np.ones(len(uv), bool)), dtype=bool)
        colors = np.where(valid[:, None], [[0, 220, 0]], [[230, 40, 40]]).astype(np.uint8)
        self.rec.log("world/camera/image/keypoints", self.rr.Points2D(uv, colors=colors, radii=1.5))

    def log_inlier_matches(self, index: int, uv_ref: np.ndarray, uv_cur: np.ndarray) -> None:
        """Inlier matches of frame ``index`` as segments from the reference to the current pixel."""
        seg = np.stack([np.asarray(uv_ref, np.float32), np.asarray(uv_cur, np.float32)], 1) * self.scale
        self.rec.set_time("frame", sequence=int(index))
        self.rec.log("world/camera/image/matches", self.rr.LineStrips2D(seg, colors=[(255, 220, 0)], radii=0.5))

    def log_landmarks(self, index: int, pos: np.ndarray, age: np.ndarray, uv_matched: np.ndarray | None) -> None:
        """The landmark map (coloured by age in frames: young red -> old (>= 300) blue) and this frame's
        pixels matched to the map."""
        self.rec.set_time("frame", sequence=int(index))
        if len(pos):
            a = np.clip(np.asarray(age, np.float64) / 300.0, 0.0, 1.0)[:, None]
            colors = ((1 - a) * np.array([230, 50, 40]) + a * np.array([40, 90, 230])).astype(np.uint8)
            self.rec.log("world/landmarks", self.rr.Points3D(np.asarray(pos, np.float32), colors=colors, radii=0.006))
        if uv_matched is not None and len(uv_matched):
            self.rec.log("world/camera/image/map_matches",
                         self.rr.Points2D(np.asarray(uv_matched, np.float32) * self.scale, colors=[(40, 90, 230)],
                                          radii=2.0))

    def log_loop(self, i: int, j: int, pose_i: np.ndarray, pose_j: np.ndarray) -> None:
        """A loop edge between frames i and j (drawn between their camera centres; all loops so far)."""
        self.loops.append([np.asarray(pose_i)[:3, 3], np.asarray(pose_j)[:3, 3]])
        self.rec.log("world/loops", self.rr.LineStrips3D(np.array(self.loops, np.float32), colors=[(255, 0, 200)],
                                                         radii=[0.006]))
        self.rec.log("log", self.rr.TextLog(f"loop closure {i} <-> {j}", level="INFO"))

    def log_trajectory(self, name: str, traj: Trajectory) -> None:
        """A whole trajectory (static). ``groundtruth`` gets the first-frame alignment (module docstring)."""
        if traj is None or len(traj) == 0:
            return
        P = traj.positions
        if name == "groundtruth" and self.gt_align is not None:
            P = P @ self.gt_align[:3, :3].T + self.gt_align[:3, 3]
        color = {"groundtruth": (255, 170, 0), "odometry": (150, 150, 150)}.get(name, (0, 200, 255))
        if name.startswith("session_") and name[8:].isdigit():  # the sessions of a joined map, one colour each
            color = SESSION_COLORS[int(name[8:]) % len(SESSION_COLORS)]
        self._log_strip(f"world/trajectory/{name}", P, color, static=True)

    def log_map(self, points: np.ndarray, colors: np.ndarray) -> None:
        """The fused cloud (N, 3) with colours (N, 3) uint8."""
        if points is None or len(points) == 0:
            return
        self.rec.log("world/map", self.rr.Points3D(np.asarray(points, np.float32),
                                                   colors=np.asarray(colors, np.uint8), radii=0.004), static=True)

    def close(self) -> None:
        """Finish the recording: the complete file replaces ``save_path`` (only now)."""
        if self._closed:
            return
        self._closed = True
        self.rec.flush()
        self.rec.disconnect()
        if self.tmp_path is not None:
            commit(self.tmp_path, self.save_path)
            self._cleanup.detach()

    def abort(self) -> None:
        """Stop recording after a failure: the temporary file is removed, ``save_path`` is untouched."""
        if self._closed:
            return
        self._closed = True
        try:
            self.rec.disconnect()
        finally:
            if self._cleanup is not None:
                self._cleanup()


def _remove_file(path: Path) -> None:
    try:
        path.unlink(missing_ok=True)
    except OSError:  # pragma: no cover - best effort at shutdown
        pass


# ----------------------------------------------------------------------------- finished runs


def record_run(run_dir: str | Path, out_rrd: str | Path, progress: bool = True) -> Path:
    """Build a recording of a finished run folder: trajectories (final, odometry, ground truth),
    loop edges, the fused map cloud, the landmark map (when map.npz has one), and the keyframes'
    images and poses."""
    import open3d as o3d

    from rgbdslam.datasets import open_sequence
    from rgbdslam.io.trajectory import read_tum
    from rgbdslam.mapping.fusion import match_frames
    from rgbdslam.runfolder.read import check_run_frames, read_run
    from rgbdslam.ui import console, frame_progress

    run_dir, out_rrd = Path(run_dir), Path(out_rrd)
    info, cfg, traj = read_run(run_dir)
    seq = None
    try:
        seq = open_sequence(info["sequence"], cfg)
    except InputError as e:
        console.print(f"[yellow]warning:[/] no images in the recording: {e}")
    if seq is not None:
        check_run_frames(run_dir, info, len(seq))
    camera = seq.camera if seq is not None else Camera(525.0, 525.0, 319.5, 239.5)
    gt = seq.groundtruth() if seq is not None else None
    # written to a temporary file beside out_rrd, which it replaces only when complete (close());
    # on any failure abort() removes it and an earlier out_rrd is left as it was
    log = RerunLogger(cfg, camera, gt, spawn=False, save_path=out_rrd)
    try:
        if seq is not None:
            keyframes = list(info.get("keyframes") or [])
            rows = match_frames(np.asarray(seq.timestamps), traj)
            if not keyframes:
                keyframes = [int(i) for i in np.flatnonzero(rows >= 0)]
            with frame_progress(len(keyframes), "recording keyframes", enabled=progress) as advance:
                for i in keyframes:
                    if rows[i] < 0:  # a keyframe without a pose in trajectory.tum
                        continue
                    frame = seq.load(i)
                    log.log_frame(frame, SimpleNamespace(index=i, timestamp=frame.timestamp,
                                                         pose=traj.poses[rows[i]], lost=False))
                    advance()
        log.log_trajectory("estimate", traj)
        if (run_dir / "odometry.tum").is_file():
            log.log_trajectory("odometry", read_tum(run_dir / "odometry.tum"))
        if gt is not None:
            log.log_trajectory("groundtruth", gt)
        for name in (info.get("map_file") or {}).get("session_trajectories") or []:  # a map joined over sessions
            if (run_dir / name).is_file():
                log.log_trajectory(Path(name).stem, read_tum(run_dir / name))
        stamps = {round(float(t), 6): k for k, t in enumerate(traj.timestamps)}
        for i, j in info.get("loops") or []:
            if seq is not None and 0 <= i < len(seq) and 0 <= j < len(seq):
                ki = stamps.get(round(float(seq.timestamps[i]), 6))
                kj = stamps.get(round(float(seq.timestamps[j]), 6))
                if ki is not None and kj is not None:
                    log.log_loop(int(i), int(j), traj.poses[ki], traj.poses[kj])
        cloud = run_dir / "map" / "cloud.ply"
        if cloud.is_file():
            pc = o3d.io.read_point_cloud(str(cloud))
            log.log_map(np.asarray(pc.points), (np.asarray(pc.colors) * 255 + 0.5).astype(np.uint8))
        _log_saved_landmarks(log, run_dir, len(seq) - 1 if seq is not None else int(info.get("frames", 1)) - 1)
    except BaseException:
        log.abort()
        raise
    log.close()
    return out_rrd


def _log_saved_landmarks(log: RerunLogger, run_dir: Path, last: int) -> None:
    """The landmark map saved in RUN_DIR/map.npz (runs with ``landmarks.enabled``; positions after the
    pose graph) as ``world/landmarks`` at frame ``last``, coloured by age as in the live recording;
    landmarks of earlier sessions of a joined map count as old."""
    from rgbdslam.session.mapfile import MapFileError, load_map, map_path

    if not map_path(run_dir).is_file():
        return
    try:
        lm = load_map(map_path(run_dir)).landmarks
    except MapFileError as e:
        from rgbdslam.ui import console

        console.print(f"[yellow]warning:[/] no landmarks in the recording: {e}")
        return
    if lm is None or not len(lm["lm_pos"]):
        return
    current = lm["lm_session"] == lm["lm_session"].max()
    age = np.where(current, np.maximum(last - lm["lm_first"], 0), 300)
    log.log_landmarks(last, lm["lm_pos"], age, None)


MAX_SERVE_S = 3.2e7  # seconds (a year); --serve-for takes a finite time above 0


def view(path: str | Path, save: str | Path | None = None, progress: bool = True, web: bool = False,
         bind: str = "127.0.0.1", web_port: int = 9090, grpc_port: int = 9876,
         serve_for: float | None = None) -> Path:
    """Open an .rrd file or a run folder in the Rerun viewer and return the .rrd's path.

    A run folder is recorded first (to ``save``, else RUN_DIR/recording.rrd unless that exists).
    Without a display the viewer is not started: one line says so and names the file.
    ``web``: serve Rerun's web viewer instead (:func:`serve_web`), for a machine without a display."""
    from rgbdslam.io.validate import number
    from rgbdslam.ui import console

    if serve_for is not None:  # nan compared false with every time out: it served for ever
        number(serve_for, "--serve-for", "the time to serve", 0.0, MAX_SERVE_S, lo_open=True)
    path = Path(path)
    if path.is_dir():
        rrd = Path(save) if save is not None else path / "recording.rrd"
        if rrd.is_dir():
            raise InputError(f"--save {rrd} is a folder; give a file name such as {rrd / 'recording.rrd'}")
        if save is not None or not rrd.exists():
            record_run(path, rrd, progress=progress)
            if save is None:  # the run folder's own recording: listed as the run's (docs/outputs.md)
                from rgbdslam.io.manifest import RUN, Manifest

                Manifest(path).record(["recording.rrd"], RUN)
    elif path.is_file():
        if path.suffix not in (".rrd", ".rbl"):
            raise InputError(f"{path} is not a Rerun recording (.rrd) or a run folder; give one of them")
        rrd = path
        if save is not None and Path(save).resolve() != path.resolve():
            if Path(save).is_dir():
                raise InputError(f"--save {save} is a folder; give a file name such as {Path(save) / path.name}")
            with atomic_path(save) as tmp:  # a failed copy leaves an earlier SAVE as it was
                shutil.copyfile(path, tmp)
            rrd = Path(save)
    else:
        raise InputError(f"{path} does not exist; give an .rrd file or the --out folder of `rgbdslam run`")
    exe = rerun_executable()
    if web:
        server = rerun_binary() or exe
        if server is None:
            raise RgbdslamError("the `rerun` program of rerun-sdk was not found; reinstall rerun-sdk")
        serve_web(server, rrd, bind, web_port, grpc_port, serve_for)
        return rrd
    if not has_display():
        console.print(f"no display here, so no viewer was opened; the recording is {rrd.resolve()} "
                      f"(open it with `rerun {rrd.resolve()}` on a machine with a display)", soft_wrap=True)
        return rrd
    if exe is None:
        raise RgbdslamError(f"the `rerun` viewer was not found; install rerun-sdk, then run `rerun {rrd}`")
    subprocess.Popen([exe, str(rrd)], start_new_session=True)
    return rrd


def rerun_binary() -> str | None:
    """The viewer binary itself (``rerun_cli/rerun``): the ``rerun`` script on PATH is a Python
    wrapper that runs it as a child, so stopping the wrapper would leave the server running."""
    try:
        import rerun_cli
    except ImportError:
        return None
    cand = Path(rerun_cli.__file__).parent / ("rerun.exe" if sys.platform.startswith("win") else "rerun")
    return str(cand) if cand.is_file() else None


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    """Linux: the server gets SIGTERM when rgbdslam dies, even by SIGKILL (no orphaned server)."""
    import ctypes
    import signal

    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def _port_open(host: str, port: int) -> bool:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.settimeout(0.5)
        return sock.connect_ex((host, port)) == 0


def serve_web(exe: str, rrd: Path, bind: str = "127.0.0.1", web_port: int = 9090, grpc_port: int = 9876,
              serve_for: float | None = None, startup_timeout: float = 30.0) -> None:
    """Serve ``rrd`` with Rerun's web viewer (``rerun --serve-web``): the viewer page on
    ``web_port`` and the recording over gRPC on ``grpc_port``, both bound to ``bind`` (loopback by
    default: reach it from your own machine through an SSH tunnel). Prints how to open it, then
    serves until Ctrl-C (or ``serve_for`` seconds) and stops the server."""
    import time

    from rgbdslam.ui import console

    for name, port in (("--web-port", web_port), ("--grpc-port", grpc_port)):
        if not 1 <= port <= 65535:
            raise InputError(f"{name} must be a port number between 1 and 65535 (got {port})")
    if web_port == grpc_port:
        raise InputError(f"--web-port and --grpc-port must differ (both {web_port})")
    host = "127.0.0.1" if bind in ("0.0.0.0", "::", "") else bind
    for port in (web_port, grpc_port):
        if _port_open(host, port):
            raise InputError(f"port {port} on {host} is already in use (another viewer?); choose another with "
                             f"--web-port / --grpc-port")
    log = tempfile.TemporaryFile()
    cmd = [exe, "--serve-web", "--bind", bind, "--web-viewer-port", str(web_port), "--port", str(grpc_port),
           str(rrd.resolve())]
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                            preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)
    try:
        t0 = time.monotonic()
        while not (_port_open(host, web_port) and _port_open(host, grpc_port)):
            if proc.poll() is not None or time.monotonic() - t0 > startup_timeout:
                log.seek(0)
                lines = [x for x in log.read().decode("utf-8", "replace").splitlines() if x.strip()]
                why = lines[-1].strip() if lines else f"exit code {proc.returncode}"
                raise RgbdslamError(f"the Rerun web viewer did not start ({why[-200:]})")
            time.sleep(0.2)
        name = "localhost" if host == "127.0.0.1" else host
        url = f"http://{name}:{web_port}/?url=rerun%2Bhttp%3A%2F%2F{name}%3A{grpc_port}%2Fproxy"
        console.print(f"serving {rrd} with Rerun's web viewer: open {url} in a browser", soft_wrap=True)
        if host == "127.0.0.1":
            console.print(f"from another computer: ssh -L {web_port}:localhost:{web_port} -L {grpc_port}:localhost:"
                          f"{grpc_port} THIS_MACHINE, then open the same address there "
                          f"(or --bind 0.0.0.0 to serve on the network)", soft_wrap=True)
        console.print("Ctrl-C stops the server" if serve_for is None else f"serving for {serve_for:g} s",
                      soft_wrap=True)
        try:
            proc.wait(timeout=serve_for)
        except subprocess.TimeoutExpired:
            pass
        else:
            raise RgbdslamError(f"the Rerun web viewer stopped (exit code {proc.returncode})")
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        log.close()
