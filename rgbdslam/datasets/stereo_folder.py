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


from rgbdslam.datasets.registry import reader
from rgbdslam.datasets.stereo_base import StereoSequence, check_baseline, frame_times, image_files
from rgbdslam.datasets.tum import select_frames
from rgbdslam.errors import InputError, cut
from rgbdslam.io import validate
from rgbdslam.io.images import read_image
from rgbdslam.geometry.stereo import StereoRig
from rgbdslam.io.text import optional_file, read_text
from rgbdslam.io.trajectory import read_tum
from rgbdslam.io.yamlfile import load_yaml

CAMERA_FILE = "stereo.yaml"
DEFAULT_FPS = 30.0


def _is_stereo_folder(path: Path) -> bool:
    return (path / "left").is_dir() and (path / "right").is_dir()


def read_stereo_yaml(path: Path) -> dict:
    if not path.is_file():
        raise InputError(f"{path} is missing: a stereo folder needs a camera file with fx, fy, cx, cy and "
                         f"baseline (metres)")
    data = load_yaml(read_text(path, "camera file"), str(path))
    if not isinstance(data, dict):
        raise InputError(f"{path} must be a mapping with fx, fy, cx, cy and baseline")
    known = {"fx", "fy", "cx", "cy", "baseline", "fps", "width", "height"}
    unknown = sorted(set(map(str, data)) - known)
    if unknown:
        shown = ", ".join(cut(k, 30) for k in unknown[:5]) + (f" and {len(unknown) - 5} more" if len(unknown) > 5 else "")
        raise InputError(f"{path}: unknown key(s) {shown}; allowed: {', '.join(sorted(known))}")
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in data]
    if missing:
        raise InputError(f"{path}: missing {', '.join(missing)}; give the rectified left camera's fx, fy, cx, cy")
    if "baseline" not in data:
        raise InputError(f"{path} gives no stereo baseline; add 'baseline: <metres>' (the distance between the "
                         f"two camera centres)")
    where = str(path)
    out = {k: validate.number(v, where, k) for k, v in data.items() if k in ("fx", "fy", "cx", "cy", "baseline")}
    out["fps"] = validate.rate(data.get("fps", DEFAULT_FPS), where)
    for k in ("width", "height"):
        if k in data:
            out[k] = validate.number(data[k], where, k, 1, validate.MAX_IMAGE_SIDE, integer=True)
    return out


@reader("stereo", _is_stereo_folder)
class StereoFolderSequence(StereoSequence):
    def __init__(self, root: str | Path, cfg=None) -> None:
        from rgbdslam.datasets.config import DatasetConfig

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
        ts = frame_times(root / "times.txt", n, c["fps"])
        first, why = read_image(left[0])
        if first is None:
            raise InputError(f"left image {left[0]} cannot be decoded ({why}); replace it with a valid image")
        h, w = first.shape[:2]
        cam = validate.camera(c["fx"], c["fy"], c["cx"], c["cy"], c.get("width", w), c.get("height", h),
                              name="stereo", where=str(root / CAMERA_FILE))
        keep = select_frames(n, cfg, root)
        gt = read_tum(root / "groundtruth.txt") if optional_file(root / "groundtruth.txt", "ground truth") else None
        super().__init__(root, root.resolve().name, StereoRig(cam, baseline), ts[keep], [left[k] for k in keep],
                         [right[k] for k in keep], gt)
