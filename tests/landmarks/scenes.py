"""Hand-built scenes shared by the landmark tests: a pinhole camera, poses from a rotation vector,
random points in front of the camera, and what a camera at a pose sees of them."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from rgbdslam.frontend.features import descriptor_words
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import inv

CAM = Camera(525.0, 525.0, 319.5, 239.5, 640, 480)


def pose(rotvec, t) -> np.ndarray:
    P = np.eye(4)
    P[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    P[:3, 3] = t
    return P


def scene(n: int = 300, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(1.0, 4.0, n)])


def seen(P: np.ndarray, X: np.ndarray):
    """Camera-frame points, pixels and depths of world points ``X`` from camera-to-world pose ``P``."""
    Tcw = inv(P)
    Pc = X @ Tcw[:3, :3].T + Tcw[:3, 3]
    return Pc, CAM.project(Pc), Pc[:, 2]


def frame_features(P, X, desc):
    """Frame features of the points of ``X`` a camera at ``P`` sees (exact pixels and depths)."""
    _, uv, z = seen(P, X)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480) & (z > 0.3)
    Xc = (X @ inv(P)[:3, :3].T + inv(P)[:3, 3])[inside]
    return SimpleNamespace(pts=Xc, uv=uv[inside], uv_raw=uv[inside], valid=np.ones(inside.sum(), bool),
                           desc=desc[inside], words=descriptor_words(desc[inside]), octave=np.zeros(0))


def drifted_revisit():
    """A frame seeing 600 landmarks of which one half is to be stored 1.5 cm / 0.3° off (another visit's
    drift): (points X, descriptors, the frame's true pose, the rigid shift of that half, the frame's features)."""
    rng = np.random.default_rng(5)
    X = scene(600, 7)
    desc = rng.integers(0, 256, size=(len(X), 32), dtype=np.uint8)
    truth = pose([0.0, 0.01, 0.0], [0.02, 0.0, 0.0])
    shift = pose([0.0, 0.0, np.radians(0.3)], [0.015, 0.0, 0.0])
    return X, desc, truth, shift, frame_features(truth, X, desc)
