"""Keyframe policy: a new keyframe when the camera moved or turned enough, or after a gap."""

from __future__ import annotations

import numpy as np

from rgbdslam.frontend.config import KeyframeConfig
from rgbdslam.geometry.se3 import motion_between


class KeyframePolicy:
    """Motion thresholds (translation, rotation) relative to the last keyframe + a maximum gap.

    The first frame is always a keyframe. ``is_keyframe`` updates the state when it says yes;
    ``force`` records a keyframe chosen elsewhere (e.g. a frame that closed a loop).
    """

    def __init__(self, cfg: KeyframeConfig):
        self.cfg = cfg
        self.last_index: int | None = None
        self.last_pose: np.ndarray | None = None

    def is_keyframe(self, index: int, pose: np.ndarray) -> bool:
        c = self.cfg
        if self.last_index is None:
            yes = True
        else:
            dt, dr = motion_between(self.last_pose, np.asarray(pose, dtype=np.float64))
            yes = dt >= c.min_translation or dr >= c.min_rotation_deg or index - self.last_index >= c.max_gap
        if yes:
            self.force(index, pose)
        return yes

    def force(self, index: int, pose: np.ndarray) -> None:
        self.last_index = int(index)
        self.last_pose = np.array(pose, dtype=np.float64)
