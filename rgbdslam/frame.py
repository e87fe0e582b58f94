"""The frame record every stage passes on: one RGB-D frame (or a stereo pair read as one).

It sits below the readers (:mod:`rgbdslam.datasets`), the front end and the stereo depth, which all
use it; the readers also compute with the front end (a stereo reader detects key points and
computes depth in its own thread), so the record cannot live with them."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rgbdslam.geometry.camera import Camera


@dataclass
class Frame:
    """One RGB-D frame as every stage sees it (a stereo pair arrives as one too: the left image
    and the depth computed from the pair, see datasets/stereo_base.py)."""

    index: int  # position in the sequence (after stride/first_frame)
    timestamp: float  # seconds (the colour image's time stamp)
    rgb: np.ndarray  # (H, W, 3) uint8, RGB order, or (H, W) uint8 for a grey camera (see as_rgb)
    depth: np.ndarray  # (H, W) float32 metres, 0 = no measurement
    camera: Camera
    name: str = ""  # e.g. the colour file's relative path, for messages
    # seconds from the colour image's time to the depth image's (TUM freiburg1: 0-14 ms; 0 = taken
    # together); features.depth_delay compensates the camera's motion over it
    depth_delay: float = 0.0
    # key points found ahead of time (frontend.features.detect, run in the reader thread), or None
    detections: Any = field(default=None, repr=False, compare=False)
    # stereo sources only: the rectified right image, and the depth noise model of the depth
    # (geometry.stereo.DepthNoise: depth_noise.sigma(z) in metres, depth_noise.covariance(points));
    # None for RGB-D cameras
    right: np.ndarray | None = field(default=None, repr=False, compare=False)
    depth_noise: Any = field(default=None, repr=False, compare=False)


def as_rgb(image: np.ndarray) -> np.ndarray:
    """A (H, W, 3) view of a colour image, or the grey image repeated in three channels."""
    image = np.asarray(image)
    return image if image.ndim == 3 else np.repeat(image[:, :, None], 3, axis=2)


def depth_warning(frame: Frame) -> str | None:
    """A sentence when the frame's metric depth does not look like an RGB-D camera's (wrong
    ``dataset.depth_scale`` or an empty depth stream), else None. RGB-D cameras measure about
    0.3-8 m, so a median of the valid pixels above 8 m or below 0.25 m is suspect. A heuristic:
    it catches a scale off by 5 (TUM's 5000 per metre read as millimetres, or back) in most
    indoor scenes, not every wrong scale."""
    d = np.asarray(frame.depth)
    valid = d[d > 0]
    where = f"the depth of frame {frame.index}" + (f" ({frame.name})" if frame.name else "")
    if valid.size < 0.01 * d.size:
        return (f"{where} is almost empty ({valid.size} of {d.size} pixels); check the depth images "
                f"and depth.txt pairing (tracking needs depth)")
    med = float(np.median(valid))
    if med > 8.0:
        return (f"{where} has a median of {med:.1f} m, more than an RGB-D camera sees; if the images store "
                f"millimetres set --set dataset.depth_scale=1000 (TUM uses 5000 per metre)")
    if med < 0.25:
        return (f"{where} has a median of {med * 100:.1f} cm, less than an RGB-D camera sees; check "
                f"dataset.depth_scale (raw units per metre: TUM 5000, PUT/Kinect mm 1000)")
    return None
