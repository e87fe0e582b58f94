"""Anchored landmarks (issue 17, revisit): the observing pose's drift in the Kalman filter, and
landmark-to-keyframe edges that let the pose graph pull a revisit back to the old landmarks."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from rgbdslam.config import LandmarksConfig
from rgbdslam.frontend.features import descriptor_words
from rgbdslam.geometry.se3 import inv
from rgbdslam.landmarks.kalman import kalman_update, with_pose_drift
from rgbdslam.landmarks.stage import LandmarkTracker
from tests.landmarks.scenes import CAM, seen
from tests.landmarks.scenes import pose as _pose
from tests.landmarks.scenes import scene as _scene


def test_pose_drift_adds_sigma2_times_age_by_hand():
    R = np.stack([np.eye(3) * 1e-6, np.diag([1e-6, 2e-6, 3e-6])])
    out = with_pose_drift(R, np.array([100, -5]), 1e-4)  # 1e-8 per frame; a negative age counts as 0
    assert np.allclose(out[0], np.eye(3) * 2e-6) and np.allclose(out[1], R[1])
    assert with_pose_drift(R, np.array([100, 100]), 0.0) is R


def test_a_late_observation_moves_the_landmark_by_the_drift_weighted_gain():
    # P = 1e-6, R = 1e-6 + (1e-4)^2 * 100 = 2e-6: K = 1/3, so x = 0 + (3 mm - 0) / 3 = 1 mm
    # (without the drift term K = 1/2: the landmark would follow the drifted pose half way)
    R = with_pose_drift(np.eye(3)[None] * 1e-6, np.array([100]), 1e-4)
    x, P = kalman_update(np.zeros((1, 3)), np.eye(3)[None] * 1e-6, np.full((1, 3), 0.003), R, 0.0)
    assert np.allclose(x, 0.001) and np.allclose(P, np.eye(3) * (2e-6 / 3))


def _frame(P, X, desc):
    """Frame features of the points of ``X`` a camera at ``P`` sees (exact pixels and depths)."""
    _, uv, z = seen(P, X)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480) & (z > 0.3)
    Xc = (X @ inv(P)[:3, :3].T + inv(P)[:3, 3])[inside]
    return SimpleNamespace(pts=Xc, uv=uv[inside], uv_raw=uv[inside], valid=np.ones(inside.sum(), bool),
                           desc=desc[inside], words=descriptor_words(desc[inside]), octave=np.zeros(0))


def test_anchor_edge_is_the_pose_against_the_old_keyframes_landmarks():
    """Landmarks made by keyframe 0 (pose A) and keyframe 40, seen again by keyframe 120 from ``truth``
    after 1.5 cm of drift: the edge 0 -> 120 is A⁻¹ · truth (the old landmarks' coordinates), with a
    full-rank information; keyframe 40's landmarks are too young (anchor_age 100) for an edge, and a
    keyframe the pose graph does not hold gets none."""
    rng = np.random.default_rng(3)
    X = _scene(500, 4)
    desc = rng.integers(0, 256, size=(len(X), 32), dtype=np.uint8)
    A = _pose([0.0, 0.01, 0.0], [0.0, 0.0, 0.0])
    truth = _pose([0.01, -0.02, 0.0], [0.05, 0.02, 0.0])
    drifted = truth @ _pose([0.0, 0.002, 0.0], [0.015, 0.0, 0.0])
    cfg = LandmarksConfig(enabled=True, mode="seed", anchor_edges=True, anchor_age=100, anchor_min_landmarks=20,
                          min_seen=1, stale_after=0)  # only old landmarks in view: none left out as stale
    tr = LandmarkTracker(cfg, CAM)
    cov = np.tile(np.eye(3) * 1e-6, (len(X), 1, 1))
    half = len(X) // 2
    tr.map.add(X[:half], cov[:half], desc[:half], 0, 0)
    tr.map.end_step(0)
    tr.map.add(X[half:], cov[half:], desc[half:], 40, 40)
    tr.kf_pose[0], tr.kf_pose[40] = A, _pose([0, 0, 0], [0.02, 0, 0])
    tr.map.end_step(40)
    feats = _frame(truth, X, desc)
    P = tr.track(120, feats, drifted)
    assert np.linalg.norm(P[:3, 3] - truth[:3, 3]) < 1e-4  # seed mode: the map pose
    edges = tr.anchor_edges(120, feats, P, {0: A, 40: tr.kf_pose[40]})
    assert [(e.i, e.j) for e in edges] == [(0, 120)]
    e = edges[0]
    assert np.allclose(e.T_ij, inv(A) @ truth, atol=1e-4) and e.n_inliers >= 100
    assert np.all(np.linalg.eigvalsh(e.information) > 0)
    assert tr.anchor_edges(120, feats, P, {40: tr.kf_pose[40]}) == []  # keyframe 0 not in the graph
    tr.cfg.anchor_edges = False
    assert tr.anchor_edges(120, feats, P, {0: A}) == []
    assert tr.summary()["anchor_edges"] == 1


@pytest.mark.data
def test_anchor_edges_reach_the_pose_graph_on_real_frames(desk9, tmp_path):
    """fr1/desk, 9 frames: with a short anchor age the keyframes get landmark edges to the first
    keyframes through the whole pipeline, and the trajectory stays accurate."""
    from rgbdslam.config import load_config
    from rgbdslam.pipeline import run_sequence

    cfg = load_config(None, ["mapping.enabled=false", "output.plots=false", "landmarks.enabled=true",
                             "landmarks.anchor_edges=true", "landmarks.anchor_age=3", "keyframes.max_gap=2"])
    s = run_sequence(desk9, tmp_path / "run", cfg, progress=False)
    assert s["tracked"] == 9 and s["landmarks"]["anchor_edges"] >= 1
    assert s["evaluation"]["ate"]["rmse"] < 0.03


def test_old_landmark_wins_its_feature_over_a_younger_copy_with_the_bonus():
    """Two landmarks project onto the same feature: an old one (made at frame 0) 8 bits from its
    descriptor, a young copy (frame 90) 2 bits. Plain matching takes the copy; with a 10-bit bonus
    for landmarks made before frame 50 the old one wins; the bonus does not open the max_hamming gate."""
    from rgbdslam.landmarks.map import LandmarkMap
    from rgbdslam.landmarks.tracking import match_to_map

    P = _pose([0, 0, 0], [0, 0, 0])
    X = np.array([[0.1, 0.05, 2.0], [0.1, 0.05, 2.0005]])
    d = np.zeros((1, 32), np.uint8)
    old, young = d.copy(), d.copy()
    old[0, 0], young[0, 0] = 0xFF, 0x03  # 8 and 2 bits from the feature's descriptor
    lmap = LandmarkMap(store="single", min_seen=1)
    lmap.add(X[:1], np.eye(3)[None] * 1e-6, old, 0, 0)
    lmap.add(X[1:], np.eye(3)[None] * 1e-6, young, 90, 90)
    lmap.end_step(90)
    feats = _frame(P, X[:1], d)
    plain = match_to_map(lmap, feats, P, CAM, 10.0, 50, 5.0)
    bonus = match_to_map(lmap, feats, P, CAM, 10.0, 50, 5.0, old_before=50, old_bonus=10)
    assert plain.lm.tolist() == [1] and bonus.lm.tolist() == [0]
    gated = match_to_map(lmap, feats, P, CAM, 10.0, 5, 5.0, old_before=50, old_bonus=10)
    assert gated.lm.tolist() == [1]  # the old one is 8 bits away: beyond max_hamming 5 despite the bonus


def test_consistency_scale_is_the_median_disagreement_over_its_chi2_median():
    """H_reg = H_map = 2 I: the disagreement's covariance is I, so its Mahalanobis² is |η|², and the
    map's share of it is r = tr(C⁻¹ Σ_map) / 6 = 1/2. With |η|² = 4 · 5.348 (k = 4) the map's
    covariance must grow by s with 1 - r + s r = k: s = 1 + 3 / 0.5 = 7 (then Σ_reg + 7 Σ_map = 4 I,
    four times the assumed sum), once 5 frames are in (1 before); a disagreement within the
    informations (|η|² = 1) never raises the map's weight (factor 1)."""
    import gtsam

    from rgbdslam.landmarks.stage import CHI2_MEDIAN_6DOF

    eta = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 0.0])
    eta *= np.sqrt(4 * CHI2_MEDIAN_6DOF / (eta @ eta))
    A = _pose([0.1, 0, 0], [1.0, 2.0, 0.5])
    B = A @ gtsam.Pose3.Expmap(eta).matrix()
    tr = LandmarkTracker(LandmarksConfig(enabled=True, consistency_window=7), CAM)
    ks = [tr._consistency(A, 2 * np.eye(6), B, 2 * np.eye(6)) for _ in range(6)]
    assert ks[:4] == [1.0] * 4 and np.allclose(ks[4:], 7.0)
    assert np.allclose(tr.stats.consistency, 4.0)
    small = A @ gtsam.Pose3.Expmap(np.array([0, 0, 0, 1.0, 0, 0])).matrix()
    tr2 = LandmarkTracker(LandmarksConfig(enabled=True, consistency_window=7), CAM)
    assert [tr2._consistency(A, 2 * np.eye(6), small, 2 * np.eye(6)) for _ in range(6)] == [1.0] * 6
    assert np.isclose(tr2.stats.consistency[-1], 1.0 / CHI2_MEDIAN_6DOF)
    for _ in range(6):  # the window keeps the last 7: after 7 large ones the median is the large one
        tr2._consistency(A, 2 * np.eye(6), B, 2 * np.eye(6))
    assert len(tr2._chi2) == 7 and np.isclose(tr2.stats.consistency[-1], 4.0)
