"""A plain stereo folder: ``left/`` and ``right/`` (images paired by sorted name), a camera file
``stereo.yaml`` with the rectified intrinsics and the baseline, optional ``times.txt`` (one
time stamp per frame, seconds; else ``fps`` from the camera file, default 30) and optional
``groundtruth.txt`` (TUM format, left camera, matched to the frames by time stamp).

``stereo.yaml``::

    fx: 718.9          # pixels, of the rectified left camera
    fy: 718.9
    cx: 607.2
    cy: 185.2
    baseline: 0.537    # metres, right camera centre along the left camera's x axis
    fps: 10            # optional
"""

from __future__ import annotations

from pathlib import Path

import cv2
import yaml

from rgbdslam.datasets.registry import reader
from rgbdslam.datasets.stereo_base import StereoSequence, check_baseline, frame_times, image_files
from rgbdslam.datasets.tum import select_frames
from rgbdslam.errors import InputError
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.stereo import StereoRig
from rgbdslam.io.text import read_text
from rgbdslam.io.trajectory import read_tum

CAMERA_FILE = "stereo.yaml"


def _is_stereo_folder(path: Path) -> bool:
    return (path / "left").is_dir() and (path / "right").is_dir()


def read_stereo_yaml(path: Path) -> dict:
    if not path.is_file():
        raise InputError(f"{path} is missing: a stereo folder needs a camera file with fx, fy, cx, cy and "
                         f"baseline (metres)")
    try:
        data = yaml.safe_load(read_text(path, "camera file"))
    except yaml.YAMLError:
        raise InputError(f"{path} is not valid YAML; fix its syntax") from None
    if not isinstance(data, dict):
        raise InputError(f"{path} must be a mapping with fx, fy, cx, cy and baseline")
    known = {"fx", "fy", "cx", "cy", "baseline", "fps", "width", "height"}
    unknown = set(map(str, data)) - known
    if unknown:
        raise InputError(f"{path}: unknown key(s) {', '.join(sorted(unknown))}; allowed: {', '.join(sorted(known))}")
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in data]
    if missing:
        raise InputError(f"{path}: missing {', '.join(missing)}; give the rectified left camera's fx, fy, cx, cy")
    if "baseline" not in data:
        raise InputError(f"{path} gives no stereo baseline; add 'baseline: <metres>' (the distance between the "
                         f"two camera centres)")
    try:
        out = {k: float(v) for k, v in data.items()}
    except (TypeError, ValueError):
        raise InputError(f"{path}: every value must be a number") from None
    return out


@reader("stereo", _is_stereo_folder)
class StereoFolderSequence(StereoSequence):
    def __init__(self, root: str | Path, cfg=None) -> None:
        from rgbdslam.config import DatasetConfig

        cfg = cfg or DatasetConfig()
        root = Path(root)
        c = read_stereo_yaml(root / CAMERA_FILE)
        baseline = check_baseline(c["baseline"], root / CAMERA_FILE)
        left, right = image_files(root / "left"), image_files(root / "right")
        if len(left) != len(right):
            raise InputError(f"{root} has {len(left)} left and {len(right)} right images; a stereo sequence needs "
                             f"one right image per left image")
        if not left:
            raise InputError(f"{root / 'left'} holds no images")
        n = len(left)
        ts = frame_times(root / "times.txt", n, c.get("fps", 30.0))
        first = cv2.imread(str(left[0]), cv2.IMREAD_UNCHANGED)
        if first is None:
            raise InputError(f"left image {left[0]} cannot be decoded; replace it with a valid image")
        h, w = first.shape[:2]
        cam = Camera(c["fx"], c["fy"], c["cx"], c["cy"], int(c.get("width", w)), int(c.get("height", h)),
                     (0.0,) * 5, "stereo")
        keep = select_frames(n, cfg, root)
        gt = read_tum(root / "groundtruth.txt") if (root / "groundtruth.txt").is_file() else None
        super().__init__(root, root.resolve().name, StereoRig(cam, baseline), ts[keep], [left[k] for k in keep],
                         [right[k] for k in keep], gt)
