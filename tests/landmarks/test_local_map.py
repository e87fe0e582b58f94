"""The covisibility local map (``landmarks.local_map_shared``): a frame is tracked against the landmarks
of its reference keyframe and of the keyframes sharing enough landmarks with it."""

from __future__ import annotations

import numpy as np

from rgbdslam.config import LandmarksConfig
from rgbdslam.landmarks.stage import LandmarkTracker
from tests.landmarks.scenes import CAM, drifted_revisit


def test_local_map_is_the_reference_keyframe_and_its_covisible_keyframes():
    # reference keyframe 12 observes {3, 4, 5, 6}; keyframe 5 shares {3, 4} (2: in), keyframe 0 shares
    # {3} (1: out), keyframe 9 nothing (out): the local map is {3, 4, 5, 6} ∪ {2, 3, 4} = {2, ..., 6}
    tr = LandmarkTracker(LandmarksConfig(enabled=True, local_map_shared=2), CAM)
    tr.map.add(np.ones((12, 3)), np.tile(np.eye(3), (12, 1, 1)), np.zeros((12, 32), np.uint8), 0, 0)
    for k, ids in ((0, [0, 1, 2, 3]), (5, [2, 3, 4]), (9, [10, 11]), (12, [3, 4, 5, 6])):
        tr.observe(k, np.array(ids))
    assert np.flatnonzero(tr.local_map()).tolist() == [2, 3, 4, 5, 6]
    assert LandmarkTracker(LandmarksConfig(enabled=True, local_map_shared=0), CAM).local_map() is None  # every landmark


def test_landmarks_of_keyframes_outside_the_local_map_do_not_pull_the_map_pose():
    """Half the landmarks were made by keyframe 0 and sit 1.5 cm / 0.3° off (an earlier visit's drift);
    the other half by keyframes 95 and 96, which share them. The frame at ``truth`` (reference keyframe 96)
    sees both halves: without the local map the pose is pulled towards the shifted half, with it the pose
    rests on keyframe 95/96's landmarks alone (the stale rule off in both, so only the local map decides)."""
    X, desc, truth, shift, feats = drifted_revisit()
    h = len(X) // 2

    def tracker(shared):
        tr = LandmarkTracker(LandmarksConfig(enabled=True, mode="seed", min_seen=1, stale_after=0,
                                             local_map_shared=shared), CAM)
        cov = np.tile(np.eye(3) * 1e-6, (len(X), 1, 1))
        old = tr.map.add(X[:h] @ shift[:3, :3].T + shift[:3, 3], cov[:h], desc[:h], 0, 0)
        new = tr.map.add(X[h:], cov[h:], desc[h:], 95, 95)
        tr.map.end_step(95)
        for k, ids in ((0, old), (95, new), (96, new[::2])):
            tr.observe(k, ids)
        return tr

    mixed = tracker(0).track(100, feats, truth)
    assert np.linalg.norm(mixed[:3, 3] - truth[:3, 3]) > 2e-3
    tr = tracker(10)
    P = tr.track(100, feats, truth)
    assert np.linalg.norm(P[:3, 3] - truth[:3, 3]) < 1e-4
    assert np.all(tr.map.first[tr._last[2]] == 95)


def test_local_map_from_the_observers_equals_the_count_over_every_keyframe():
    """The local map is found from the keyframes that observe the reference's landmarks; it is the
    definition over every keyframe (shared count with repeats, a keyframe observed again replacing its
    ids), on 300 random keyframes, after each one."""
    rng = np.random.default_rng(3)
    tr = LandmarkTracker(LandmarksConfig(enabled=True, local_map_shared=4), CAM)
    tr.map.add(np.ones((2000, 3)), np.tile(np.eye(3), (2000, 1, 1)), np.zeros((2000, 32), np.uint8), 0, 0)
    obs: dict[int, np.ndarray] = {}
    for step in range(300):
        k = int(rng.integers(0, step + 1)) if step % 50 == 49 else step  # now and then a keyframe again
        centre = int(rng.integers(0, 1900))
        ids = centre + rng.integers(0, 100, int(rng.integers(0, 40)))  # repeats possible
        obs[k] = ids
        tr.observe(k, ids)
        ref = np.zeros(2000, bool)
        ref[obs[max(obs)]] = True
        expect = ref.copy()
        for o in obs.values():
            if np.count_nonzero(ref[o]) >= 4:
                expect[o] = True
        assert np.array_equal(tr.local_map(), expect), step
