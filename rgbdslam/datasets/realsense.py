"""A live RealSense camera as a sequence (``rgbdslam live``; optional extra ``[realsense]``).

The SDK (``pyrealsense2``) streams colour (rgb8) and depth (z16); every frameset is aligned to
the colour camera with the SDK's own ``rs.align`` and handed to the same pipeline as a recorded
sequence, the camera being the colour stream's intrinsics. Every frame is also written, as it
arrives, into a TUM-layout folder (``rgb/``, ``depth/``, ``rgb.txt``, ``depth.txt`` and a
``camera.yaml`` with the intrinsics and the depth scale), so any live session can be run again
and evaluated like a recorded one. ``playback=FILE`` takes the frames from a recording (``.bag``
or ``.db3``) through the SDK's own playback instead of a device: the same code path, used by the
tests (there is no camera on the build machines).

The sequence is a stream: its length is not known in advance (``streaming = True``); it ends when
the device stops sending, the recording ends, ``max_frames`` is reached, or :meth:`stop` is
called (``rgbdslam live`` calls it on the first Ctrl-C, so the run then finishes normally: loop
closure, map and all outputs are written).
"""

from __future__ import annotations

import threading
from concurrent.futures import Future
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np
import yaml

from rgbdslam.datasets.base import Frame, Sequence
from rgbdslam.datasets.camera_file import CameraSetup
from rgbdslam.errors import InputError
from rgbdslam.io import validate
from rgbdslam.geometry.camera import Camera
from rgbdslam.io.atomic import atomic_path, atomic_write_text

WAIT_MS = 5000  # a device that sends nothing for this long has stopped


def import_realsense():
    try:
        import pyrealsense2 as rs
    except ImportError:
        raise InputError("live mode needs the RealSense SDK's Python package: pip install 'rgbdslam[realsense]' "
                         "(pyrealsense2)") from None
    return rs


class TumRecorder:
    """Writes frames into a TUM-layout folder as they arrive (each image atomically; the lists
    are appended and flushed line by line, so an interrupted session leaves a readable folder)."""

    def __init__(self, root: Path, camera: Camera, depth_scale: float):
        self.root = Path(root)
        if (self.root / "rgb.txt").exists():
            raise InputError(f"{self.root} already holds a recording (rgb.txt); choose another --record folder")
        (self.root / "rgb").mkdir(parents=True, exist_ok=True)
        (self.root / "depth").mkdir(parents=True, exist_ok=True)
        cam = {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
               "size": [camera.width, camera.height], "distortion": list(camera.dist), "depth_scale": depth_scale}
        atomic_write_text(self.root / "camera.yaml",
                          "# written by rgbdslam live: the colour camera; depth is aligned to it\n"
                          + yaml.safe_dump(cam, sort_keys=False, default_flow_style=None))
        header = "# written by rgbdslam live\n# timestamp filename\n"
        self._rgb = open(self.root / "rgb.txt", "w", encoding="utf-8")
        self._depth = open(self.root / "depth.txt", "w", encoding="utf-8")
        for f in (self._rgb, self._depth):
            f.write(header)
            f.flush()
        self.count = 0

    def write(self, t_rgb: float, rgb: np.ndarray, t_depth: float, depth_raw: np.ndarray) -> None:
        for kind, t, img, lst in (("rgb", t_rgb, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), self._rgb),
                                  ("depth", t_depth, depth_raw, self._depth)):
            name = f"{kind}/{t:.6f}.png"
            with atomic_path(self.root / name) as tmp:
                if not cv2.imwrite(str(tmp), img):
                    raise OSError(f"cannot write {self.root / name}")
            lst.write(f"{t:.6f} {name}\n")
            lst.flush()
        self.count += 1

    def close(self) -> None:
        self._rgb.close()
        self._depth.close()


class RealSenseSequence(Sequence):
    """Frames from a RealSense device (or the SDK's playback of a recording); see the module docstring."""

    streaming = True

    def __init__(self, record_dir: str | Path | None = None, playback: str | Path | None = None,
                 width: int = 640, height: int = 480, fps: int = 30, max_frames: int | None = None,
                 serial: str | None = None) -> None:
        rs = import_realsense()
        self._rs = rs
        self.name = Path(playback).stem if playback else "live"
        self.root = Path(record_dir) if record_dir else Path(playback or ".")
        self.max_frames = max_frames
        self._stop = threading.Event()
        self._stamps: list[float] = []
        pipe, cfg = rs.pipeline(), rs.config()
        if playback is not None:
            if not Path(playback).is_file():
                raise InputError(f"recording {playback} does not exist; give a RealSense .bag or .db3 file")
            cfg.enable_device_from_file(str(playback), repeat_playback=False)
        else:
            if serial:
                cfg.enable_device(serial)
            cfg.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
            cfg.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
        try:
            profile = pipe.start(cfg)
        except RuntimeError as e:
            what = f"cannot play back {playback}" if playback else "no RealSense camera could be started"
            raise InputError(f"{what} ({e}); check the connection (USB 3) or the file") from None
        self._pipe = pipe
        if playback is not None:
            profile.get_device().as_playback().set_real_time(False)  # every frame, as fast as we take them
        try:
            color = profile.get_stream(rs.stream.color).as_video_stream_profile()
            depth_sensor = profile.get_device().first_depth_sensor()
        except RuntimeError as e:
            pipe.stop()
            raise InputError(f"the {'recording' if playback else 'camera'} has no colour and depth streams ({e})") from None
        intr = color.get_intrinsics()
        dist = tuple(float(c) for c in intr.coeffs)
        if intr.model not in (rs.distortion.none, rs.distortion.brown_conrady) and any(dist):
            dist = (0.0,) * 5  # the SDK's rectified colour stream: its "inverse" models are close to none
        self.camera = validate.camera(float(intr.fx), float(intr.fy), float(intr.ppx), float(intr.ppy),
                                      int(intr.width), int(intr.height), dist if len(dist) in (4, 5, 8) else (0.0,) * 5,
                                      "realsense", where=f"the {'recording ' + str(playback) if playback else 'camera'}"
                                                         f"'s colour intrinsics")
        units = float(depth_sensor.get_depth_scale())  # metres per z16 unit
        self.depth_scale = 1.0 / units  # raw units per metre, as a camera file says it
        source = f"the {'recording ' + str(playback) if playback else 'RealSense device'}'s colour stream"
        self.camera_setup = CameraSetup(self.camera, source, self.depth_scale)
        self._align = rs.align(rs.stream.color)
        self.recorder = TumRecorder(Path(record_dir), self.camera, self.depth_scale) if record_dir else None

    @property
    def timestamps(self) -> np.ndarray:
        return np.asarray(self._stamps, dtype=np.float64)

    def __len__(self) -> int:
        return len(self._stamps)

    def stop(self) -> None:
        """End the stream after the frame being read (thread-safe; Ctrl-C in ``rgbdslam live``)."""
        self._stop.set()

    def load(self, i: int) -> Frame:
        raise InputError("a live camera cannot go back to an earlier frame; use the recorded folder")

    def _frames(self) -> Iterator[Frame]:
        rs = self._rs
        i = 0
        try:
            while not self._stop.is_set() and (self.max_frames is None or i < self.max_frames):
                ok, frames = self._pipe.try_wait_for_frames(WAIT_MS)
                if not ok:
                    break  # the recording ended or the device stopped sending
                frames = self._align.process(frames)
                d, c = frames.get_depth_frame(), frames.get_color_frame()
                if not d or not c:
                    continue
                raw = np.asanyarray(d.get_data()).copy()
                rgb = np.asanyarray(c.get_data()).copy()
                if rgb.shape[:2] != (self.camera.height, self.camera.width) or raw.shape != rgb.shape[:2]:
                    raise InputError(f"frame {i}: colour {rgb.shape[1]}x{rgb.shape[0]}, depth {raw.shape[1]}x"
                                     f"{raw.shape[0]} do not match the camera's {self.camera.width}x{self.camera.height}")
                t_c, t_d = c.get_timestamp() / 1000.0, d.get_timestamp() / 1000.0
                if self.recorder is not None:
                    self.recorder.write(t_c, rgb, t_d, raw)
                # metres exactly as the folder reader computes them from the recorded PNG and camera.yaml
                depth = raw.astype(np.float32) * np.float32(1.0 / self.depth_scale)
                self._stamps.append(t_c)
                yield Frame(i, t_c, rgb, depth, self.camera, f"live#{i}")
                i += 1
        finally:
            self.close()

    def close(self) -> None:
        if self._pipe is not None:
            try:
                self._pipe.stop()
            except RuntimeError:
                pass
            self._pipe = None
        if self.recorder is not None:
            self.recorder.close()

    def prefetched(self, ahead: int = 4, then: Callable[[Frame], Frame] | None = None, workers: int = 1
                   ) -> Iterator[tuple[int, Future]]:
        """``(i, future)`` per frame as it arrives (read in the caller's thread: the device
        buffers ahead by itself)."""
        try:
            for frame in self._frames():
                fut: Future = Future()
                fut.set_result(then(frame) if then is not None else frame)
                yield frame.index, fut
        finally:
            self.close()
