"""Microsoft 7-Scenes reader, in the data set's own layout.

A sequence folder (``seq-01``, or a part of one) holds ``frame-NNNNNN.color.jpg`` (or ``.png``),
``frame-NNNNNN.depth.png`` (16-bit millimetres, 65535 = no measurement) and
``frame-NNNNNN.pose.txt`` (4x4 camera-to-world, KinectFusion's tracking) per frame, and often
``camera-intrinsics.txt`` (3x3 K). No time stamps: the Kinect ran at 30 Hz, so frame N is at
N / 30 s.

Colour and depth come from the Kinect's two cameras and are **not registered**; the published
intrinsics (fx = fy = 585, cx 320, cy 240, also in ``camera-intrinsics.txt``) are the depth
camera's. By default the camera shipped with rgbdslam (``rgbdslam/cameras/7scenes.yaml``: colour
fx = fy = 530, the depth camera the folder's ``camera-intrinsics.txt`` or the published one) is
used: every depth image is re-projected into the colour camera
(:class:`rgbdslam.geometry.depth_registration.DepthRegistration`); on redkitchen 0-299 the ATE is
0.0192 m with it and 0.0303 m with the depth camera's intrinsics used for colour
(docs/formats.md "7-Scenes"). ``--camera FILE`` wins over it.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np

from rgbdslam.datasets.registry import reader
from rgbdslam.datasets.camera_file import CameraSetup, read_shipped_camera, resolve_camera
from rgbdslam.datasets.tum import RgbdFileSequence, data_lines, pick_depth_scale, select_frames
from rgbdslam.errors import InputError
from rgbdslam.geometry.camera import Camera
from rgbdslam.io import validate
from rgbdslam.io.text import optional_file, require_file
from rgbdslam.io.trajectory import Trajectory

RATE_HZ = 30.0
DEPTH_SCALE = 1000.0  # millimetres
INVALID = 65535
INTRINSICS = "camera-intrinsics.txt"
SHIPPED_CAMERA = "rgbdslam/cameras/7scenes.yaml"
_COLOR = re.compile(r"^frame-(\d+)\.color\.(png|jpg)$")


def _color_frames(root: Path) -> list[tuple[int, Path]]:
    found = []
    for p in root.iterdir():
        m = _COLOR.match(p.name)
        if m:
            found.append((int(m.group(1)), p))
    return sorted(found)


def _is_7scenes(path: Path) -> bool:
    return any(path.glob("frame-*.color.*")) and any(path.glob("frame-*.depth.png"))


def read_intrinsics(path: Path) -> Camera:
    rows = [f for _, f in data_lines(require_file(path, "7-Scenes intrinsics"))]
    try:
        K = np.array(rows, dtype=np.float64)
        ok = K.shape == (3, 3)
    except ValueError:
        ok = False
    if not ok:
        raise InputError(f"{path}: expected a 3x3 camera matrix (three rows 'fx 0 cx', '0 fy cy', '0 0 1')")
    return validate.camera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], 640, 480, name="7scenes", where=str(path))


def read_pose(path: Path) -> np.ndarray:
    rows = [f for _, f in data_lines(require_file(path, "7-Scenes pose"))]
    try:
        T = np.array(rows, dtype=np.float64)
        ok = T.shape == (4, 4)
    except ValueError:
        ok = False
    if not ok:
        raise InputError(f"{path}: expected a 4x4 camera-to-world matrix (4 rows of 4 numbers)")
    if not np.isfinite(T).all():  # 7-Scenes marks a pose KinectFusion lost with inf: no pose, not an error
        return T
    return validate.poses(T, str(path))[0]


def shipped_setup(root: Path) -> CameraSetup:
    """The 7-Scenes camera shipped with rgbdslam, its depth camera the folder's
    ``camera-intrinsics.txt`` where there is one (the published intrinsics otherwise)."""
    setup = read_shipped_camera("7scenes", f"the 7-Scenes camera shipped with rgbdslam ({SHIPPED_CAMERA})")
    setup = dataclasses.replace(setup, camera=dataclasses.replace(setup.camera, name="7scenes"))
    if optional_file(root / INTRINSICS, "7-Scenes intrinsics") is None:  # a folder there is refused
        return setup
    depth = read_intrinsics(root / INTRINSICS)
    if (depth.fx, depth.fy, depth.cx, depth.cy) == (setup.depth_camera.fx, setup.depth_camera.fy,
                                                    setup.depth_camera.cx, setup.depth_camera.cy):
        return setup
    return dataclasses.replace(setup, depth_camera=depth, source=f"{setup.source}, depth camera from {INTRINSICS}")


@reader("7scenes", _is_7scenes)
class SevenScenesSequence(RgbdFileSequence):
    """A 7-Scenes sequence folder; see the module docstring."""

    def __init__(self, root: str | Path, cfg=None) -> None:
        from rgbdslam.datasets.config import DatasetConfig

        cfg = cfg or DatasetConfig()
        root = Path(root)
        frames = _color_frames(root)
        if not frames:
            raise InputError(f"{root} has no frame-NNNNNN.color.jpg images (7-Scenes layout)")
        keep = select_frames(len(frames), cfg, root)
        numbers = [frames[k][0] for k in keep]
        setup = resolve_camera(cfg, root, shipped_setup(root))
        super().__init__(
            root=root,
            name=root.resolve().name,
            camera=setup,
            timestamps=np.array(numbers, dtype=np.float64) / RATE_HZ,
            rgb_files=[frames[k][1] for k in keep],
            depth_files=[root / f"frame-{n:06d}.depth.png" for n in numbers],
            depth_scale=pick_depth_scale(cfg, setup, DEPTH_SCALE),
            depth_correction=cfg.depth_correction,
            invalid_depth=INVALID,
        )
        self.frame_numbers = numbers

    def groundtruth(self) -> Trajectory | None:
        """Every frame's pose.txt (all frames of the folder, not only the selected ones). The
        poses are the depth camera's (KinectFusion tracked depth); when depth is re-projected
        into the colour camera the run estimates the colour camera's poses, so the ground truth
        is moved to it too: T_world_colour = T_world_depth @ inv(depth_to_color)."""
        stamps, poses = [], []
        for n, _ in _color_frames(self.root):
            p = self.root / f"frame-{n:06d}.pose.txt"
            if optional_file(p, "7-Scenes pose") is not None:
                T = read_pose(p)
                if np.isfinite(T).all() and abs(T[3, 3] - 1) < 1e-6:  # 7-Scenes marks lost poses with inf
                    stamps.append(n / RATE_HZ)
                    poses.append(T)
        if not stamps:
            return None
        poses = np.array(poses).reshape(-1, 4, 4)
        T = self.camera_setup.depth_to_color
        if T is not None:
            poses = poses @ np.linalg.inv(T)
        return Trajectory(np.array(stamps), poses)
