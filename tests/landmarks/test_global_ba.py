"""Global bundle adjustment (rgbdslam.landmarks.global_ba): exact problems with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from rgbdslam.config import LandmarksConfig
from rgbdslam.geometry.se3 import inv
from rgbdslam.landmarks.global_ba import global_bundle_adjustment
from rgbdslam.landmarks.map import LandmarkMap
from rgbdslam.landmarks.stage import _KeyframeObs
from tests.landmarks.test_landmarks import CAM, _observe, _pose, _scene

CFG = LandmarksConfig(global_ba_iterations=50, ba_min_observations=30, global_ba_odometry=False)


def _problem(X, truth, seen_by, rng, pose_noise=0.02, point_noise=0.02):
    """A map of ``X`` (positions perturbed), keyframes at ``truth`` seeing the points ``seen_by[k]``
    with exact pixels and depth, initial poses perturbed (keyframe 0 exact: the gauge)."""
    lmap = LandmarkMap(store="single")
    ids = lmap.add(X + rng.normal(scale=point_noise, size=X.shape), np.tile(np.eye(3) * 1e-4, (len(X), 1, 1)),
                   np.zeros((len(X), 32), np.uint8), 0, 0)
    kfs, guess = [], {}
    for k, P in enumerate(truth):
        sel = seen_by[k]
        uv, z = _observe(P, X[sel])
        kfs.append(_KeyframeObs(k, ids[sel], uv, z))
        guess[k] = P if k == 0 else P @ _pose(rng.normal(scale=pose_noise, size=3), rng.normal(scale=pose_noise, size=3))
    return lmap, ids, kfs, guess


def test_global_ba_recovers_known_poses_and_points_from_noisy_guesses():
    """Exact observations, every keyframe off by ~2 cm / ~1 deg, points off by 2 cm: the BA returns
    the true poses and points (keyframe 0 fixed); its error drops to ~0."""
    rng = np.random.default_rng(1)
    X = _scene(300, 2)
    truth = [_pose([0.0, 0.05 * k, 0.0], [0.1 * k, 0.02 * k, 0.0]) for k in range(4)]
    lmap, ids, kfs, guess = _problem(X, truth, [np.arange(len(X))] * 4, rng)
    before = [np.linalg.norm(guess[k][:3, 3] - truth[k][:3, 3]) for k in (1, 2, 3)]
    res = global_bundle_adjustment(CFG, CAM, lmap, kfs, guess)
    assert res is not None and sorted(res.poses) == [0, 1, 2, 3] and res.landmarks == 300
    assert np.allclose(res.poses[0], truth[0])  # the gauge
    for k in (1, 2, 3):
        assert np.linalg.norm(res.poses[k][:3, 3] - truth[k][:3, 3]) < 1e-5 < min(before)
        assert np.allclose(res.poses[k][:3, :3], truth[k][:3, :3], atol=1e-6)
    assert np.abs(lmap.pos[ids] - X).max() < 1e-4
    assert res.error[1] < 1e-6 * res.error[0]


def test_global_ba_keeps_a_loop_correction_where_no_landmark_is_shared():
    """Keyframes 0-1 see one half of the points, 2-3 the other: nothing ties 2-3 to 0-1 but the
    loop edge 0 -> 3 (exact). With it the BA brings 2 and 3 to the truth; without it they stay
    where the guess put them (the landmarks alone cannot move them)."""
    rng = np.random.default_rng(2)
    X = _scene(400, 3)
    truth = [_pose([0.0, 0.03 * k, 0.0], [0.08 * k, 0.0, 0.01 * k]) for k in range(4)]
    A, B = np.arange(200), np.arange(200, 400)
    seen_by = [A, A, B, B]
    loop = [(0, 3, inv(truth[0]) @ truth[3], np.eye(6) * 1e6)]
    lmap, _, kfs, guess = _problem(X, truth, seen_by, rng, point_noise=0.0)
    shift = _pose([0, 0, 0], [0.05, -0.03, 0.02])
    for k in (2, 3):  # the second half drifted by 6 cm, consistently with its own landmarks
        guess[k] = shift @ truth[k]
    lmap.pos[B] = X[B] @ shift[:3, :3].T + shift[:3, 3]
    res = global_bundle_adjustment(CFG, CAM, lmap, kfs, guess, loops=loop)
    for k in (1, 2, 3):
        assert np.linalg.norm(res.poses[k][:3, 3] - truth[k][:3, 3]) < 1e-4
    assert np.abs(lmap.pos[B] - X[B]).max() < 1e-3
    lmap2, _, _, _ = _problem(X, truth, seen_by, np.random.default_rng(2), point_noise=0.0)
    lmap2.pos[B] = X[B] @ shift[:3, :3].T + shift[:3, 3]
    free = global_bundle_adjustment(CFG, CAM, lmap2, kfs, guess)
    for k in (2, 3):
        assert np.linalg.norm(free.poses[k][:3, 3] - truth[k][:3, 3]) > 0.05


def test_global_ba_ties_a_weakly_observed_keyframe_with_its_odometry():
    """A keyframe seeing fewer than ba_min_observations landmarks gets its odometry edges. Its 12
    observations were made from 3 cm beside its true pose; the (exact, stiff) odometry edge holds
    it at the truth; without the edge the observations alone take it 3 cm away."""
    rng = np.random.default_rng(3)
    X = _scene(300, 4)
    truth = [_pose([0.0, 0.04 * k, 0.0], [0.05 * k, 0.0, 0.0]) for k in range(3)]
    seen_by = [np.arange(300), np.arange(300), np.arange(12)]
    lmap, ids, kfs, guess = _problem(X, truth, seen_by, rng, pose_noise=0.01, point_noise=0.0)
    off = truth[2] @ _pose([0, 0, 0], [0.03, 0, 0])
    uv, z = _observe(off, X[:12])
    kfs[2] = _KeyframeObs(2, ids[:12], uv, z)
    odo = [(0, 1, inv(truth[0]) @ truth[1], np.eye(6) * 1e8), (1, 2, inv(truth[1]) @ truth[2], np.eye(6) * 1e8)]
    pos0 = lmap.pos.copy()
    res = global_bundle_adjustment(CFG, CAM, lmap, kfs, guess, odometry=odo)
    assert res.between == 1  # only the weak keyframe's edge: 0 -> 1 is left to the landmarks
    assert np.linalg.norm(res.poses[2][:3, 3] - truth[2][:3, 3]) < 2e-3
    lmap.pos[:] = pos0
    every = global_bundle_adjustment(LandmarksConfig(global_ba_iterations=50, global_ba_odometry=True), CAM, lmap, kfs,
                                     guess, odometry=odo)
    assert every.between == 2  # global_ba_odometry: every edge
    lmap.pos[:] = pos0
    free = global_bundle_adjustment(CFG, CAM, lmap, kfs, guess)
    assert np.linalg.norm(free.poses[2][:3, 3] - off[:3, 3]) < 2e-3


@pytest.mark.data
def test_global_ba_runs_at_the_end_of_a_real_run(desk9):
    """fr1/desk, 9 frames, landmarks + global BA through SLAM: it runs after the pose graph over
    every keyframe, the final trajectory's keyframes are its poses, the frames between keep their
    pose relative to their keyframe, the landmark anchors follow, and the accuracy stays."""
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.evaluation.ate import ate
    from rgbdslam.slam import SLAM

    cfg = load_config(None, ["landmarks.enabled=true", "landmarks.global_ba=true", "landmarks.global_ba_frames=true",
                             "keyframes.max_gap=3", "landmarks.ba_min_observations=10"])
    seq = open_sequence(desk9, cfg.dataset)
    slam = SLAM(cfg, seq.camera)
    for i in range(len(seq)):
        slam.track(seq[i])
    recs = {r.index: (r.pose.copy(), r.keyframe) for r in slam.state.records}
    traj = slam.finish()
    g = slam.landmarks.global_ba_stats
    assert g["ran"] and g["keyframes"] == len(slam.state.keyframes) >= 3 and g["between"] >= 2
    assert g["observations"] > 2000 and g["error_after"] < g["error_before"]
    assert any(len(k.frames) for k in slam.landmarks.all_keyframes)  # the frames between keyframes joined
    for n, (P, kf) in enumerate(recs.values()):
        assert np.allclose(traj.poses[n], slam.optimised[kf] @ inv(recs[kf][0]) @ P, atol=1e-9)
    for k in slam.state.keyframes:
        assert np.allclose(slam.landmarks.kf_pose[k], slam.optimised[k])
    assert ate(seq.groundtruth(), traj).rmse < 0.03
