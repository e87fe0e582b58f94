"""The local BA's keyframe projection search: a keyframe observes every local-map landmark it sees."""

from __future__ import annotations

import numpy as np

from rgbdslam.landmarks.config import LandmarksConfig
from rgbdslam.landmarks.map import LandmarkMap
from tests.landmarks.scenes import CAM, frame_features, pose, scene


def _map(X, desc, cov=1e-6):
    lmap = LandmarkMap(store="single")
    ids = lmap.add(X, np.tile(np.eye(3) * cov, (len(X), 1, 1)), desc, 0, 0)
    lmap.end_step(0)
    return lmap, ids


def test_search_finds_every_visible_local_landmark_and_nothing_else():
    """600 landmarks, the keyframe sees most of them exactly: found = visible ∩ local map − already observed,
    each with its own feature; a landmark behind the camera (it projects onto a feature with its descriptor),
    one outside the local map and one 30 cm off along its ray (same pixel, outside the χ² gate) are not."""
    from rgbdslam.landmarks.local_ba import keyframe_search

    rng = np.random.default_rng(0)
    X = scene(600, 3)
    desc = rng.integers(0, 256, size=(len(X), 32), dtype=np.uint8)
    P = pose([0.02, -0.05, 0.01], [0.1, 0.0, -0.05])
    feats = frame_features(P, X, desc)
    # the features' landmarks: the rows of X a feature was made from (frame_features keeps X's order)
    Pc = (X - P[:3, 3]) @ P[:3, :3]
    uv = CAM.project(Pc)
    vis = np.flatnonzero((uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480) & (Pc[:, 2] > 0.3))
    assert len(vis) == len(feats.pts) > 300
    # landmarks: X, with three visible ones replaced: one mirrored behind the camera (projects onto its
    # feature's pixel), one moved 30 cm along its ray (same pixel, ~10σ of the depth noise at 3.9 m), and one left out of the local map
    Xm = X.copy()
    behind, along, outside = vis[:3]
    Xm[behind] = P[:3, :3] @ (-Pc[behind]) + P[:3, 3]
    Xm[along] = P[:3, :3] @ (Pc[along] * (1 + 0.3 / np.linalg.norm(Pc[along]))) + P[:3, 3]
    lmap, ids = _map(Xm, desc)
    allowed = np.ones(lmap.n, bool)
    allowed[outside] = False
    have = vis[3:53]  # already observed by the keyframe (tracking's inliers): not returned again
    have_feat = np.searchsorted(vis, have)
    cfg = LandmarksConfig()
    f, lm = keyframe_search(cfg, lmap, feats, P, CAM, allowed, have_feat, ids[have])
    want = vis[53:]
    assert sorted(lm.tolist()) == want.tolist()
    assert np.array_equal(vis[f], lm)  # each landmark with the feature made from it
    # without the local map every visible one but the two bad ones (and those held) is found
    f2, lm2 = keyframe_search(cfg, lmap, feats, P, CAM, None, have_feat, ids[have])
    assert sorted(lm2.tolist()) == sorted([outside, *want.tolist()])


def test_keyframe_observes_the_landmarks_it_sees_with_local_ba():
    """Two keyframes of one scene, the second not tracked: with local BA it observes the first one's landmarks
    (the search) and makes new ones only where none projects; without, it sees none of the old ones."""
    from rgbdslam.landmarks.stage import LandmarkTracker

    rng = np.random.default_rng(1)
    X = scene(500, 4)
    desc = rng.integers(0, 256, size=(len(X), 32), dtype=np.uint8)
    P0, P1 = pose([0, 0, 0], [0, 0, 0]), pose([0.0, 0.03, 0.0], [0.05, 0.0, 0.0])
    f0, f1 = frame_features(P0, X, desc), frame_features(P1, X, desc)
    seen_by = {}
    for ba in (False, True):
        lt = LandmarkTracker(LandmarksConfig(local_ba=ba, new_min_distance=0.0), CAM)
        lt.add_keyframe(0, f0, P0)
        n0 = lt.map.n
        lt.add_keyframe(1, f1, P1)
        kf = lt.keyframes[-1]
        seen_by[ba] = (int((kf.lm < n0).sum()), lt.map.n - n0, len(kf.lm))
    both = len(np.intersect1d(f0.desc.view("V32")[:, 0], f1.desc.view("V32")[:, 0]))
    assert seen_by[False] == (0, len(f1.pts), len(f1.pts))  # every feature a new landmark
    old, made, total = seen_by[True]
    assert old == both > 200 and made == len(f1.pts) - both and total == len(f1.pts)
