"""Depth re-projected into the colour camera: hand-worked cases."""

from __future__ import annotations

import numpy as np

from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.depth_registration import DepthRegistration


def test_depth_registration_hand_worked():
    """A wall 2 m away, depth camera 0.1 m to the right of the colour camera (same intrinsics,
    f = 500): the wall appears f * t / z = 25 pixels further right in colour."""
    cam = Camera(500.0, 500.0, 99.5, 79.5, 200, 160)
    T = np.eye(4)
    T[0, 3] = 0.1
    depth = np.zeros((160, 200), np.float32)
    depth[40:120, 50:150] = 2.0  # a square patch of wall
    out = DepthRegistration(cam, cam, T)(depth)
    assert np.array_equal(out > 0, np.roll(depth > 0, 25, axis=1))
    assert np.all(out[out > 0] == np.float32(2.0))
    # the nearer of two surfaces landing on one pixel wins (z-buffer)
    depth2 = np.zeros((160, 200), np.float32)
    depth2[:, 100] = 4.0  # 4 m: shifts 12.5 -> 12 or 13 pixels
    depth2[:, 113] = 2.0  # 2 m: shifts 25 pixels -> 138; a 4 m point at 100 + 12.5 does not reach it
    out2 = DepthRegistration(cam, cam, T)(depth2)
    assert np.all(out2[:, 138] == np.float32(2.0))
