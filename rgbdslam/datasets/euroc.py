"""EuRoC MAV / ASL layout (Burri et al. 2016): ``mav0/cam0`` (left), ``mav0/cam1`` (right), each
with ``data/`` images, ``data.csv`` (``#timestamp [ns],filename``) and ``sensor.yaml``
(``intrinsics: [fu, fv, cu, cv]``, radial-tangential ``distortion_coefficients`` — k1 k2 p1 p2, or
with OpenCV's k3 as a fifth value —
``resolution``, ``T_BS``: sensor-to-body 4x4). Ground truth, when present:
``mav0/state_groundtruth_estimate0/data.csv`` (body position and ``q_w q_x q_y q_z`` per
time stamp).

The raw pair is distorted and not rectified: OpenCV's ``stereoRectify`` (``alpha = 0``, zero
disparity at infinity) gives the rectifying rotations and the common pinhole camera,
``initUndistortRectifyMap`` the maps applied to every pair. The baseline is that of the
rectified pair. Poses (and the ground truth) are those of the **rectified left camera**:
``T_W_rect = T_WB @ T_BS(cam0) @ [R1^T]``. Left and right images are paired by identical time
stamps (EuRoC's cameras are triggered together).

Give the folder that holds ``mav0/`` or ``mav0/`` itself.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from rgbdslam.datasets.registry import reader
from rgbdslam.datasets.stereo_base import StereoSequence, check_baseline
from rgbdslam.datasets.tum import select_frames
from rgbdslam.errors import InputError, shorten
from rgbdslam.geometry.camera import Camera
from rgbdslam.io import validate
from rgbdslam.io.numbers import unit_quaternions
from rgbdslam.geometry.se3 import inv, pose_from_tum
from rgbdslam.geometry.stereo import StereoRig
from rgbdslam.io.text import optional_file, read_lines, read_text, require_file
from rgbdslam.io.trajectory import Trajectory
from rgbdslam.io.yamlfile import load_yaml


def _mav(path: Path) -> Path | None:
    for p in (path / "mav0", path):
        if (p / "cam0").is_dir() and (p / "cam1").is_dir():
            return p
    return None


def _is_euroc(path: Path) -> bool:
    return _mav(path) is not None


def read_sensor_yaml(path: Path) -> dict:
    """The fields of a EuRoC camera ``sensor.yaml`` we use: K, distortion, size and T_BS."""
    require_file(path, "EuRoC camera calibration", "every EuRoC camera folder needs its sensor.yaml (intrinsics, "
                 "distortion, T_BS)")
    text = "\n".join(line for line in read_text(path, "camera calibration").splitlines()
                     if not line.startswith("%YAML"))
    data = load_yaml(text, str(path))
    if not isinstance(data, dict):
        raise InputError(f"{path} must be a mapping (EuRoC sensor.yaml)")
    for key in ("intrinsics", "resolution"):
        if key not in data:
            raise InputError(f"{path}: expected intrinsics [fu, fv, cu, cv], resolution [w, h], "
                             f"distortion_coefficients [k1, k2, p1, p2] and T_BS (4x4 data); {key} is missing")
    fu, fv, cu, cv = validate.numbers(data["intrinsics"], str(path), "intrinsics [fu, fv, cu, cv]", (4,))
    w, h = validate.numbers(data["resolution"], str(path), "resolution [w, h]", (2,))
    dist = data.get("distortion_coefficients")
    dist = validate.numbers(dist if dist else [0.0] * 4, str(path), "distortion_coefficients", None)
    if len(dist) not in (4, 5):
        raise InputError(f"{path}: distortion_coefficients has {len(dist)} values; radial-tangential takes 4 "
                         f"(k1, k2, p1, p2) or 5 (OpenCV's k1, k2, p1, p2, k3)")
    cam = validate.camera(fu, fv, cu, cv, w, h, dist, where=str(path))  # before OpenCV sees any of it
    T = data.get("T_BS")
    if T is None:
        raise InputError(f"{path} has no T_BS (the camera's pose on the rig); without it the stereo baseline "
                         f"is unknown")
    T = T.get("data") if isinstance(T, dict) else T
    if isinstance(T, list) and all(isinstance(row, list) for row in T):  # written as 4 rows
        T = [v for row in T for v in row]
    flat = validate.numbers(T, str(path), "T_BS data", (16,))
    T_BS = validate.poses(np.array(flat).reshape(4, 4), str(path), what="T_BS")[0]
    model = data.get("distortion_model", "radial-tangential")
    if model not in ("radial-tangential", "radtan", "none"):
        raise InputError(f"{path}: distortion model {shorten(model)} is not supported; use radial-tangential")
    return {"K": cam.K, "dist": np.array(dist), "size": (cam.width, cam.height), "T_BS": T_BS}


def read_camera_csv(path: Path) -> tuple[np.ndarray, list[str]]:
    """Time stamps (int ns) and file names of a EuRoC ``data.csv``."""
    require_file(path, "EuRoC image list", "a EuRoC camera folder lists its images in data.csv")
    stamps, names, lines = [], [], []
    for lineno, line in enumerate(read_lines(path, "EuRoC image list"), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [p.strip() for p in s.split(",")]
        if len(parts) < 2 or not parts[0].lstrip("+-").isdigit():
            raise InputError(f"{path}:{lineno}: expected 'timestamp_ns,filename'; got {shorten(s)}")
        stamps.append(validate.stamp_ns(parts[0], f"{path}:{lineno}"))
        names.append(parts[1])
        lines.append(lineno)
    t = np.array(stamps, dtype=np.int64)
    validate.stamps(t * 1e-9, str(path), lines)
    return t, names


def read_groundtruth_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Time stamps (s) and body poses T_WB (N, 4, 4) of ``state_groundtruth_estimate0/data.csv``."""
    stamps, rows, lines = [], [], []
    for lineno, line in enumerate(read_lines(path, "EuRoC ground truth"), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        try:
            vals = [float(x) for x in s.split(",")[:8]]
        except ValueError:
            raise InputError(f"{path}:{lineno}: expected 'timestamp, px, py, pz, qw, qx, qy, qz, ...'") from None
        if len(vals) < 8:
            raise InputError(f"{path}:{lineno}: expected at least 8 numbers (timestamp, position, quaternion w x y z)")
        stamps.append(validate.stamp_ns(s.split(",")[0], f"{path}:{lineno}") * 1e-9)
        rows.append(vals[1:8])
        lines.append(lineno)
    if not rows:
        raise InputError(f"{path} holds no poses")
    a = np.array(rows)
    if not np.isfinite(a).all():
        raise InputError(f"{path}:{lines[int(np.flatnonzero(~np.isfinite(a).all(axis=1))[0])]}: a value is not a finite number")
    q = unit_quaternions(a[:, [4, 5, 6, 3]], path, lines, order="qw qx qy qz")
    P = validate.poses(pose_from_tum(a[:, :3], q), str(path), lines)
    return validate.stamps(stamps, str(path), lines), P


@reader("euroc", _is_euroc)
class EurocSequence(StereoSequence):
    def __init__(self, root: str | Path, cfg=None) -> None:
        from rgbdslam.datasets.config import DatasetConfig

        cfg = cfg or DatasetConfig()
        root = Path(root)
        mav = _mav(root)
        if mav is None:
            raise InputError(f"{root} is not a EuRoC sequence: expected mav0/cam0 and mav0/cam1")
        s0, s1 = read_sensor_yaml(mav / "cam0" / "sensor.yaml"), read_sensor_yaml(mav / "cam1" / "sensor.yaml")
        if s0["size"] != s1["size"]:
            raise InputError(f"cam0 is {s0['size'][0]}x{s0['size'][1]} but cam1 is {s1['size'][0]}x{s1['size'][1]} "
                             f"(sensor.yaml); a stereo pair needs two images of one size")
        t0, n0 = read_camera_csv(mav / "cam0" / "data.csv")
        t1, n1 = read_camera_csv(mav / "cam1" / "data.csv")
        common, i0, i1 = np.intersect1d(t0, t1, return_indices=True)
        if len(t0) != len(t1) or len(common) != len(t0):
            raise InputError(f"{mav} has {len(t0)} left (cam0) and {len(t1)} right (cam1) images with "
                             f"{len(common)} common time stamps; a stereo sequence needs one right image per left "
                             f"image at the same time")
        if len(common) == 0:
            raise InputError(f"{mav / 'cam0' / 'data.csv'} lists no images")
        # rectification: cam1's pose in cam0's frame from the two T_BS
        T_10 = inv(s1["T_BS"]) @ s0["T_BS"]  # cam0 points -> cam1 points
        check_baseline(float(np.linalg.norm(T_10[:3, 3])), mav / "cam1" / "sensor.yaml")
        size = s0["size"]
        R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(s0["K"], s0["dist"], s1["K"], s1["dist"], size, T_10[:3, :3],
                                                      T_10[:3, 3].reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
        maps = (cv2.initUndistortRectifyMap(s0["K"], s0["dist"], R1, P1, size, cv2.CV_32FC1),
                cv2.initUndistortRectifyMap(s1["K"], s1["dist"], R2, P2, size, cv2.CV_32FC1))
        baseline = check_baseline(-P2[0, 3] / P2[0, 0], mav / "cam1" / "sensor.yaml")
        cam = Camera(float(P1[0, 0]), float(P1[1, 1]), float(P1[0, 2]), float(P1[1, 2]), size[0], size[1],
                     (0.0,) * 5, "euroc_rectified")
        ts = common * 1e-9
        keep = select_frames(len(common), cfg, mav)
        left = [mav / "cam0" / "data" / n0[i] for i in i0[keep]]
        right = [mav / "cam1" / "data" / n1[i] for i in i1[keep]]
        gt = None
        gt_path = mav / "state_groundtruth_estimate0" / "data.csv"
        if optional_file(gt_path, "EuRoC ground truth") is not None:
            g_ts, T_WB = read_groundtruth_csv(gt_path)
            rect = np.eye(4)
            rect[:3, :3] = R1.T  # rectified-left points -> cam0 points
            gt = Trajectory(g_ts, T_WB @ s0["T_BS"] @ rect)
        self.rectifying_rotation = R1
        super().__init__(mav, mav.parent.name if mav.name == "mav0" else mav.name, StereoRig(cam, baseline),
                         ts[keep], left, right, gt, rectify_maps=maps)
