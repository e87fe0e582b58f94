"""POZNAN/PUT Kinect sequence reader (Kraft et al. 2016) and a TUM -> PUT converter.

Layout: a ``matched`` file with one ``rgb_ts depth_ts`` pair per line (frame k is the
k-th data line, 0-based), images ``rgb_%05d.png`` and ``depth_%05d.png`` (16-bit,
millimetres) in the folder (or in ``rgb/`` and ``depth/`` below it), an optional
``initialPosition`` (``x y z qx qy qz qw``, the pose of frame 0) and an optional ground
truth in TUM format (``dataset.groundtruth``, else ``groundtruth.txt``, else the only
``*.tum`` file). Camera: Kinect v1 (``CAMERAS['kinect1']``) unless ``dataset.camera`` or a
``camera.yaml`` says otherwise.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np

from rgbdslam.io.text import optional_file, read_text
from rgbdslam.datasets.registry import reader
from rgbdslam.datasets.camera_file import CAMERA_FILE, CameraSetup, resolve_camera
from rgbdslam.datasets.tum import RgbdFileSequence, TumSequence, data_lines, pick_depth_scale, select_frames
from rgbdslam.errors import InputError
from rgbdslam.geometry.camera import CAMERAS
from rgbdslam.geometry.se3 import pose_from_tum, pose_to_tum
from rgbdslam.io.atomic import atomic_write_text, make_dirs
from rgbdslam.io.images import read_image
from rgbdslam.io.trajectory import Trajectory, read_tum
from rgbdslam.io.numbers import MAX_COORD, check_magnitude, check_stamps, unit_quaternions

PUT_DEPTH_SCALE = 1000.0
MATCHED = "matched"
INITIAL = "initialPosition"


def read_matched(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The ``matched`` file: colour and depth time stamps (N,) of frames 0..N-1."""
    rows = []
    for lineno, parts in data_lines(path):
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            vals = []
        if len(vals) != 2 or not np.isfinite(vals).all():
            raise InputError(f"{path}:{lineno}: expected 'rgb_timestamp depth_timestamp'; got {' '.join(parts)[:60]!r}")
        check_stamps([vals], path, [lineno])
        rows.append(vals)
    if not rows:
        raise InputError(f"{path} lists no frames; it needs one 'rgb_timestamp depth_timestamp' line per frame")
    a = np.array(rows, dtype=np.float64)
    return a[:, 0], a[:, 1]


def read_initial_position(path: Path) -> np.ndarray:
    """``initialPosition``: 'x y z qx qy qz qw' -> 4x4 camera-to-world pose."""
    try:
        vals = [float(x) for x in read_text(path, "initialPosition file").replace(",", " ").split()]
    except ValueError:
        vals = []
    if len(vals) != 7 or not np.isfinite(vals).all():
        raise InputError(f"{path} must hold 7 numbers 'x y z qx qy qz qw' (a unit quaternion); fix or delete it")
    check_magnitude([vals[:3]], MAX_COORD, path, [1], "position", "positions must be metres")
    return pose_from_tum(np.array(vals[:3]), unit_quaternions([vals[3:]], path, [1])[0])[0]


def _is_put(path: Path) -> bool:
    return (path / MATCHED).is_file()


@reader("put", _is_put)
class PutSequence(RgbdFileSequence):
    """A PUT Kinect folder; see the module docstring."""

    def __init__(self, root: str | Path, cfg=None) -> None:
        from rgbdslam.datasets.config import DatasetConfig

        cfg = cfg or DatasetConfig()
        root = Path(root)
        if not (root / MATCHED).is_file():
            raise InputError(f"{root} has no '{MATCHED}' file; a PUT sequence lists 'rgb_ts depth_ts' per frame there")
        ts_rgb, ts_d = read_matched(root / MATCHED)
        keep = select_frames(len(ts_rgb), cfg, root)
        img_dir = root
        if not (root / "rgb_00000.png").exists() and (root / "rgb" / "rgb_00000.png").exists():
            img_dir = None
        rgb_files = [(root if img_dir else root / "rgb") / f"rgb_{k:05d}.png" for k in keep]
        depth_files = [(root if img_dir else root / "depth") / f"depth_{k:05d}.png" for k in keep]
        camera = resolve_camera(cfg, root, CameraSetup(CAMERAS["kinect1"], "the PUT data set's Kinect v1"))
        super().__init__(
            root=root,
            name=root.resolve().name,
            camera=camera,
            timestamps=ts_rgb[keep],
            rgb_files=rgb_files,
            depth_files=depth_files,
            depth_scale=pick_depth_scale(cfg, camera, PUT_DEPTH_SCALE),
            depth_correction=cfg.depth_correction,
            depth_timestamps=ts_d[keep],
        )
        self.frame_numbers = keep  # k of rgb_%05d.png for each frame
        self._gt_name = getattr(cfg, "groundtruth", None)
        p = root / INITIAL
        self.initial_pose: np.ndarray | None = read_initial_position(p) if p.is_file() else None

    def groundtruth_path(self) -> Path | None:
        if self._gt_name:
            p = Path(self._gt_name)
            if not p.is_absolute() and (self.root / p).is_file():
                p = self.root / p  # relative to the sequence folder first, then to the working dir
            if not p.is_file():
                raise InputError(f"ground-truth file {p} does not exist; fix dataset.groundtruth or leave it null")
            return p
        if optional_file(self.root / "groundtruth.txt", "ground-truth file") is not None:
            return self.root / "groundtruth.txt"
        tums = sorted(self.root.glob("*.tum"))
        if len(tums) > 1:
            raise InputError(
                f"{self.root} holds several *.tum files ({', '.join(p.name for p in tums)}); "
                "name the ground truth with dataset.groundtruth"
            )
        return tums[0] if tums else None

    def groundtruth(self) -> Trajectory | None:
        p = self.groundtruth_path()
        return read_tum(p) if p is not None else None


def convert_tum_to_put(src: str | Path, dst: str | Path, max_frames: int | None = None) -> Path:
    """Write the TUM sequence ``src`` (its associated frames) into ``dst`` in the PUT layout.

    Colour PNGs are copied byte for byte; depth is rescaled to millimetres (rounded, so
    within 0.5 mm of the source); ``matched`` gets the colour and depth time stamps;
    ``groundtruth.txt`` is the TUM ground truth copied; ``initialPosition`` is the
    ground-truth pose nearest in time to frame 0. The camera is named in ``camera.yaml``
    (the source's), since a TUM camera is not the PUT Kinect.
    """
    from rgbdslam.datasets.config import DatasetConfig

    src, dst = Path(src), Path(dst)
    seq = TumSequence(src, DatasetConfig(max_frames=max_frames))
    if dst.exists() and any(dst.iterdir()):
        raise InputError(f"output folder {dst} is not empty; give a new or empty folder")
    make_dirs(dst)
    lines = []
    for k in range(len(seq)):
        rgb_src, depth_src = seq.rgb_files[k], seq.depth_files[k]
        if rgb_src.suffix.lower() == ".png" and rgb_src.is_file():
            shutil.copyfile(rgb_src, dst / f"rgb_{k:05d}.png")
        else:
            bgr = cv2.cvtColor(seq.load(k).rgb, cv2.COLOR_RGB2BGR)
            cv2.imwrite(str(dst / f"rgb_{k:05d}.png"), bgr)
        raw, _ = read_image(depth_src)
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            raise InputError(f"depth image {depth_src} is not a readable 16-bit single-channel PNG")
        mm = np.round(raw.astype(np.float64) * (PUT_DEPTH_SCALE / seq.depth_scale))
        cv2.imwrite(str(dst / f"depth_{k:05d}.png"), np.clip(mm, 0, 65535).astype(np.uint16))
        lines.append(f"{seq.timestamps[k]:.6f} {seq.depth_timestamps[k]:.6f}")
    atomic_write_text(dst / MATCHED, "\n".join(lines) + "\n")
    c = seq.camera
    atomic_write_text(
        dst / CAMERA_FILE,
        f"camera: {c.name}\nfx: {c.fx}\nfy: {c.fy}\ncx: {c.cx}\ncy: {c.cy}\n"
        f"width: {c.width}\nheight: {c.height}\ndist: [{', '.join(str(d) for d in c.dist)}]\n",
    )
    gt = seq.groundtruth()
    if gt is not None:
        shutil.copyfile(seq.root / "groundtruth.txt", dst / "groundtruth.txt")
        j = int(np.argmin(np.abs(gt.timestamps - seq.timestamps[0])))
        t, q = pose_to_tum(gt.poses[j])
        atomic_write_text(dst / INITIAL, " ".join(f"{v:.9f}" for v in (*t[0], *q[0])) + "\n")
    return dst
