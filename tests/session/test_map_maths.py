"""Hand-worked maths of saved maps, exact to rounding: the map file's landmark section when a
session moves the loaded map's keyframes (rgbdslam.session.sessions._landmarks), and a
localised frame's map edge re-expressed to the last keyframe (rgbdslam.slam)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from rgbdslam.geometry.camera import CAMERAS
from rgbdslam.session.mapfile import MapData
from rgbdslam.session.sessions import MAP_ID_BASE, _landmarks


def _pose(R=np.eye(3), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def test_old_landmarks_follow_their_moved_keyframes_exactly():
    # three map keyframes: k0 at the origin, k1 at x = 1, k2 at y = 2 (all looking along +z)
    kf_pose = np.array([_pose(), _pose(t=(1, 0, 0)), _pose(t=(0, 2, 0))])
    cov1 = np.array([[1.0, 0.5, 0.0], [0.5, 4.0, 0.0], [0.0, 0.0, 9.0]]) * 1e-4
    lm = {
        "lm_pos": np.array([[2.0, 0, 0], [1, 0, 3], [0.5, 0.5, 0.5], [0, 3, 1], [7, 7, 7]]),
        "lm_cov": np.array([cov1, cov1, cov1, cov1, cov1]),
        "lm_desc": np.arange(5 * 32, dtype=np.uint8).reshape(5, 32),
        "lm_session": np.zeros(5, np.int32), "lm_first": np.arange(5), "lm_last": np.arange(5) + 10,
        "lm_seen": np.full(5, 3),
        "lm_anchor": np.array([1, 1, 0, 2, -1], np.int64),
    }
    old_lm = {n: a.copy() for n, a in lm.items()}
    old = MapData({"kf_frame": np.array([0, 5, 9]), "kf_pose": kf_pose}, CAMERAS["fr1"], landmarks=lm)
    # the pose graph turned k1 by +90° about z in place (centre kept), kept k0; k2 is not in the result
    Rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    opt = {MAP_ID_BASE + 0: _pose(), MAP_ID_BASE + 1: _pose(Rz, (1, 0, 0))}
    # the new map's keyframe order: k1 first, then k2, then k0 (this session adds none)
    pos = {MAP_ID_BASE + 1: 0, MAP_ID_BASE + 2: 1, MAP_ID_BASE + 0: 2}

    out = _landmarks(SimpleNamespace(), pos, 1, old, opt)

    # k1's landmarks: offset (1, 0, 0) from k1's centre turns to (0, 1, 0); (0, 0, 3) is on the axis
    expected_pos = np.array([[1.0, 1, 0], [1, 0, 3], [0.5, 0.5, 0.5], [0, 3, 1], [7, 7, 7]])
    np.testing.assert_allclose(out["lm_pos"], expected_pos, atol=1e-12)
    # R cov Rᵀ with R = Rz(90°): x and y swap, the x-y covariance changes sign
    cov1_turned = np.array([[4.0, -0.5, 0.0], [-0.5, 1.0, 0.0], [0.0, 0.0, 9.0]]) * 1e-4
    np.testing.assert_allclose(out["lm_cov"][:2], [cov1_turned, cov1_turned], atol=1e-15)
    np.testing.assert_array_equal(out["lm_cov"][2:], old_lm["lm_cov"][2:])  # k0 kept, k2 not optimised, anchor -1
    # re-anchored to the new map's keyframe positions; -1 stays -1
    np.testing.assert_array_equal(out["lm_anchor"], [0, 0, 2, 1, -1])
    for n in ("lm_desc", "lm_session", "lm_first", "lm_last", "lm_seen"):
        np.testing.assert_array_equal(out[n], old_lm[n])
    for n, a in old_lm.items():  # the loaded map is left as it was
        np.testing.assert_array_equal(lm[n], a)


def test_a_keyframe_left_out_of_the_new_map_unanchors_its_landmarks():
    lm = {"lm_pos": np.array([[0.0, 0, 1], [0, 0, 2]]), "lm_cov": np.tile(np.eye(3) * 1e-4, (2, 1, 1)),
          "lm_anchor": np.array([0, 1], np.int64)}
    old = MapData({"kf_frame": np.array([0, 5]), "kf_pose": np.array([_pose(), _pose()])}, CAMERAS["fr1"],
                  landmarks=lm)
    out = _landmarks(SimpleNamespace(), {MAP_ID_BASE + 1: 3}, 1, old, {})
    np.testing.assert_array_equal(out["lm_anchor"], [-1, 3])
    np.testing.assert_array_equal(out["lm_pos"], lm["lm_pos"])


def test_a_map_edge_of_a_non_keyframe_goes_to_the_last_keyframe():
    """slam.SLAM._to_last_keyframe, hand-worked: the map puts frame j 1 m further along x than the
    odometry does; re-expressed to keyframe k the edge says the same of k; covariances add."""
    from rgbdslam.config import load_config
    from rgbdslam.loop.detector import LoopEdge
    from rgbdslam.slam import SLAM, FrameRecord

    slam = SLAM(load_config(None, []), CAMERAS["fr1"])
    Rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    P_k, P_j = _pose(t=(1, 0, 0)), _pose(Rz, (1, 1, 0))  # odometry poses of keyframe k (frame 3) and frame j (7)
    slam._last_kf = FrameRecord(3, 0.0, P_k, 3)
    slam._info_since_kf = [np.eye(6) * 1e6, np.eye(6) * 2.5e5]  # covariances 1e-6 and 4e-6
    e = LoopEdge(MAP_ID_BASE + 4, 7, _pose(Rz, (2, 1, 0)), np.eye(6) * 1e4, 50, 0.01)  # map keyframe 4 at the origin
    out = slam._to_last_keyframe(e, P_j)
    assert (out.i, out.j, out.n_inliers) == (MAP_ID_BASE + 4, 3, 50)
    np.testing.assert_allclose(out.T_ij, _pose(t=(2, 0, 0)), atol=1e-12)  # k, 1 m further along x
    np.testing.assert_allclose(out.information, np.eye(6) / (1e-4 + 1e-6 + 4e-6), rtol=1e-12)
    assert e.j == 7 and e.T_ij[0, 3] == 2  # the tracker's edge is left as it was
