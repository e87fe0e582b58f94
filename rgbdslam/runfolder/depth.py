"""The keyframe depth images of a run folder (``keyframes/depth_<frame:06d>.png``): the run's
filtered depth of each keyframe as a 16-bit PNG in steps of ``1 / DEPTH_SCALE`` metres (0 = no
depth). The run writes them (:func:`write_keyframe_depth`), map fusion, the live map and the
exports read them back (:func:`read_keyframe_depth`); :func:`quantise` is the depth as the PNG
holds it, for a consumer that takes the depth before it reaches the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rgbdslam.errors import InputError
from rgbdslam.io.atomic import atomic_path, make_dirs
from rgbdslam.io.images import read_image

DEPTH_SCALE = 5000.0  # PNG units per metre (the TUM RGB-D convention: 0.2 mm steps, up to 13.1 m)


def keyframe_depth_path(folder: str | Path, index: int) -> Path:
    """The depth image of frame ``index`` in the keyframe folder ``folder``."""
    return Path(folder) / f"depth_{int(index):06d}.png"


def encode(depth: np.ndarray) -> np.ndarray:
    """Metres (float) -> the PNG's uint16 units (rounded, clipped to 0..65535)."""
    return np.clip(np.round(depth * DEPTH_SCALE), 0, 65535).astype(np.uint16)


def decode(units: np.ndarray) -> np.ndarray:
    """The PNG's units -> metres (float32)."""
    return units.astype(np.float32) / DEPTH_SCALE


def quantise(depth: np.ndarray) -> np.ndarray:
    """``depth`` as written to and read back from a keyframe depth PNG."""
    return decode(encode(depth))


def write_keyframe_depth(path: str | Path, depth: np.ndarray) -> None:
    """Write ``depth`` (metres) as a keyframe depth PNG, atomically."""
    import cv2

    path = Path(path)
    make_dirs(path.parent)
    with atomic_path(path) as tmp:  # the temporary name keeps the .png suffix cv2 needs
        cv2.imwrite(str(tmp), encode(depth))


def read_keyframe_depth(path: str | Path) -> np.ndarray:
    """A keyframe depth PNG in metres (float32); an InputError names a file that is not one."""
    d, _ = read_image(path)
    if d is None or d.ndim != 2:
        raise InputError(f"depth image {path} is unreadable or not a 16-bit single-channel PNG; delete it or re-run")
    return decode(d)
