"""--localize against a saved landmark map: the frame's pose against the map's landmarks is an edge from a
map keyframe (``MapTracker.landmark_edge``)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from rgbdslam.config import LandmarksConfig
from rgbdslam.geometry.se3 import inv
from rgbdslam.landmarks.map import LandmarkMap
from rgbdslam.loop.config import LoopConfig
from rgbdslam.session.tracking import MapTracker
from tests.landmarks.scenes import CAM, drifted_revisit
from tests.landmarks.scenes import pose as _pose


def _tracker(X, desc):
    lmap = LandmarkMap()
    lmap.add(X, np.tile(np.eye(3) * 1e-6, (len(X), 1, 1)), desc, 0, 0)
    lmap.end_step(0)
    kf = SimpleNamespace(pose=_pose([0.0, 0.05, 0.0], [-0.2, 0.0, 0.0]), index=2**40, segment=0)
    loop = SimpleNamespace(searchable=None, keyframes=[kf])  # the map's keyframes, as the loop closer holds them
    return MapTracker(loop, LoopConfig(), lmap, LandmarksConfig(), CAM), kf


def test_the_frame_pose_against_the_saved_landmarks_is_an_edge_from_the_map_keyframe():
    """The saved landmarks are exact; the prediction is 1 cm / 0.3° off: the edge puts the frame at its
    true map pose (T_ij = kf⁻¹ · truth) with the reprojection refine's information."""
    X, desc, truth, _, feats = drifted_revisit()
    feats.index = 7
    tr, kf = _tracker(X, desc)
    pred = truth @ _pose([0.0, 0.0, np.radians(0.3)], [0.01, 0.0, 0.0])
    e = tr.landmark_edge(kf, feats, pred, 0.0, 0.0)
    assert e is not None and e.i == kf.index and e.n_inliers >= 300
    assert np.allclose(e.T_ij, inv(kf.pose) @ truth, atol=1e-5)
    assert e.information.shape == (6, 6) and np.all(np.linalg.eigvalsh(e.information) > 0)


def test_a_landmark_pose_far_from_the_prediction_is_no_edge():
    """Further from the prediction than the relocalisation gate (10 cm) plus the drift allowance: none."""
    X, desc, truth, _, feats = drifted_revisit()
    feats.index = 7
    tr, kf = _tracker(X, desc)
    far_pred = truth @ _pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.15])  # 15 cm along the optical axis: projections barely move, matches hold
    assert tr.landmark_edge(kf, feats, far_pred, 0.0, 0.0) is None
    assert tr.landmark_edge(kf, feats, far_pred, 0.1, 0.0) is not None  # with 10 cm of drift allowed
