"""What every stereo reader shares: a rectified pair per frame turned into a depth frame.

A reader (``kitti``, ``euroc``, ``stereo`` folder) lists the left and right image files, the
time stamps, the rectified :class:`~rgbdslam.geometry.stereo.StereoRig` and, for unrectified
recordings, the rectification maps; :class:`StereoSequence` reads a pair, rectifies it,
computes depth with the configured method (``stereo.depth``: sparse or SGBM,
:mod:`rgbdslam.stereo.depth`) and returns a normal :class:`Frame` (grey or colour left image
as ``rgb``, depth in metres) that also carries the right image and the depth noise model
(``Frame.depth_noise``). Every later stage runs unchanged.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from rgbdslam.datasets.base import Frame, Sequence
from rgbdslam.errors import InputError
from rgbdslam.geometry.stereo import StereoRig
from rgbdslam.io.images import read_image as decode_image
from rgbdslam.io.kitti import read_kitti_times
from rgbdslam.io.text import optional_file
from rgbdslam.io.trajectory import Trajectory


def read_image(path: Path, what: str) -> np.ndarray:
    """An 8-bit grey (H, W) or colour (H, W, 3, RGB order) image; InputError naming the file."""
    if not path.is_file():
        raise InputError(f"{what} image {path} is missing; restore it or remove it from the sequence")
    img, why = decode_image(path)  # a damaged file: our line only, no libpng/libjpeg noise above it
    if img is None:
        raise InputError(f"{what} image {path} cannot be decoded ({why}); replace it with a valid PNG/JPEG")
    if img.dtype != np.uint8:
        raise InputError(f"{what} image {path} is {img.dtype}, expected 8-bit; convert it to 8-bit grey or colour")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3:
        if img.shape[2] not in (3, 4):
            raise InputError(f"{what} image {path} has {img.shape[2]} channels; expected grey or colour")
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return img


def check_pair_lists(left: list[Path], right: list[Path], where: Path) -> None:
    if len(left) != len(right):
        raise InputError(f"{where} has {len(left)} left and {len(right)} right images; a stereo sequence needs one "
                         f"right image per left image")
    if not left:
        raise InputError(f"{where} has no stereo images; check the image folders")


IMAGE_EXT = (".png", ".jpg", ".jpeg", ".pgm", ".bmp")


def image_files(folder: Path) -> list[Path]:
    """The images of one camera's folder, in name order."""
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXT)


def frame_times(times_file: Path, n: int, hz: float) -> np.ndarray:
    """Time stamps of ``n`` pairs: ``times_file`` (KITTI's times.txt, one per line) when it exists,
    else a constant rate ``hz``."""
    if optional_file(times_file, "time stamp file") is None:
        return np.arange(n) / hz
    ts = read_kitti_times(times_file)
    if len(ts) != n:
        raise InputError(f"{times_file} has {len(ts)} time stamps for {n} frames; they must match")
    return ts


MAX_BASELINE = 1e3  # metres


def check_baseline(baseline: float, source: Path) -> float:
    if not np.isfinite(baseline) or baseline <= 0:
        raise InputError(f"{source} gives no stereo baseline (got {baseline:g} m); the calibration must give the "
                         f"right camera's offset (e.g. KITTI P1 with -fx*B in its 4th column, or 'baseline:')")
    if baseline > MAX_BASELINE:
        raise InputError(f"{source} gives a stereo baseline of {baseline:g} m, more than {MAX_BASELINE:g} m; "
                         f"the baseline is in metres")
    return float(baseline)


class StereoSequence(Sequence):
    """A sequence of rectified stereo pairs, read as depth frames (see the module doc)."""

    parallel_load = True  # load() only reads its own files; ORB/SGBM objects are per thread

    def __init__(self, root: Path, name: str, rig: StereoRig, timestamps: np.ndarray, left: list[Path],
                 right: list[Path], gt: Trajectory | None = None, rectify_maps=None) -> None:
        check_pair_lists(left, right, root)
        self.root = Path(root)
        self.name = name
        self.rig = rig
        self.camera = rig.camera
        self._timestamps = np.asarray(timestamps, dtype=np.float64)
        self.left_files = list(left)
        self.right_files = list(right)
        self._gt = gt
        self._maps = rectify_maps  # (left (m1, m2), right (m1, m2)) or None when already rectified
        from rgbdslam.frontend.config import FeaturesConfig
        from rgbdslam.stereo.config import StereoConfig

        self.use_sections(FeaturesConfig(), StereoConfig())
        self._check_first_pair()

    # ------------------------------------------------------------------ configuration
    def configure(self, cfg, purpose: str = "track") -> None:
        """Take the depth method and its settings from ``cfg`` (a full :class:`rgbdslam.config.Config`):
        ``stereo.depth`` for tracking, ``stereo.map_depth`` when the frames are read for the map."""
        self.use_sections(cfg.features, cfg.stereo, purpose)

    def use_sections(self, features_cfg, stereo_cfg, purpose: str = "track") -> None:
        """:meth:`configure` from the two sections it reads (``features`` and ``stereo``)."""
        self.features_cfg = features_cfg
        self.stereo_cfg = stereo_cfg
        method = stereo_cfg.depth
        if purpose == "map" and stereo_cfg.map_depth != "same":
            method = stereo_cfg.map_depth
        self.method = method
        self.own_key_points = method == "sparse"
        from rgbdslam.stereo.depth import check_row_search, depth_noise

        if method == "sparse" and stereo_cfg.sparse_search == "row":
            check_row_search(stereo_cfg, self.camera.width, self.camera.height)  # before any frame is read

        self.depth_noise = depth_noise(self.rig, self.stereo_cfg, method)

    # ------------------------------------------------------------------ reading
    @property
    def timestamps(self) -> np.ndarray:
        return self._timestamps

    def groundtruth(self) -> Trajectory | None:
        return self._gt

    def _check_first_pair(self) -> None:
        if len(self.left_files) == 0:
            return
        left, right = self.read_pair(0)
        h, w = left.shape[:2]
        if (w, h) != (self.camera.width, self.camera.height):
            raise InputError(f"left image {self.left_files[0]} is {w}x{h} but the calibration says "
                             f"{self.camera.width}x{self.camera.height}; check the calibration file")

    def read_pair(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """The raw (unrectified if the source is) left and right images of frame ``i``."""
        lp, rp = self.left_files[i], self.right_files[i]
        left, right = read_image(lp, "left"), read_image(rp, "right")
        if left.shape != right.shape:
            raise InputError(f"left image {lp} is {left.shape[1]}x{left.shape[0]}"
                             f"{'' if left.ndim == 2 else ' colour'} but right image {rp} is "
                             f"{right.shape[1]}x{right.shape[0]}{'' if right.ndim == 2 else ' colour'}; "
                             f"a stereo pair needs two images of one size and kind")
        return left, right

    def rectified_pair(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``i``'s pair decoded and rectified (:meth:`load` takes the same way, through
        :meth:`frame_from_pair`, not through this method)."""
        return self.rectify(*self.read_pair(i))

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A raw pair (:meth:`read_pair`) rectified (as it is when the source is rectified)."""
        if self._maps is not None:
            (l1, l2), (r1, r2) = self._maps
            left = cv2.remap(left, l1, l2, cv2.INTER_LINEAR)
            right = cv2.remap(right, r1, r2, cv2.INTER_LINEAR)
        return left, right

    def load(self, i: int) -> Frame:
        return self.frame_from_pair(i, *self.read_pair(i))

    def frame_from_pair(self, i: int, left: np.ndarray, right: np.ndarray) -> Frame:
        """Frame ``i`` from its decoded raw pair (:meth:`read_pair`): rectified, key points of both images
        (sparse depth) and depth. :meth:`load` is this after the decoding."""
        from rgbdslam.stereo.depth import detect_pair, sgbm_depth, sparse_depth

        left, right = self.rectify(left, right)
        detections = None
        if self.method == "sparse":
            detections, right_kp = detect_pair(left, right, self.features_cfg, self.stereo_cfg)
            depth = sparse_depth(left, right, self.rig, detections.uv_raw, detections.desc, self.stereo_cfg,
                                 self.features_cfg, right_kp)
        else:
            depth = sgbm_depth(left, right, self.rig, self.stereo_cfg)
        try:
            name = str(self.left_files[i].relative_to(self.root))
        except ValueError:
            name = str(self.left_files[i])
        return Frame(i, float(self._timestamps[i]), left, depth, self.camera, name, detections=detections,
                     right=right, depth_noise=self.depth_noise)
