"""Stale landmarks (issue 17, the revisit): landmarks not seen for ``stale_after`` frames come from an
earlier visit and carry that visit's drift; the map pose leaves them out unless they agree."""

from __future__ import annotations

import numpy as np

from rgbdslam.config import LandmarksConfig
from rgbdslam.geometry.se3 import inv
from rgbdslam.landmarks.stage import LandmarkTracker, pose_chi2
from tests.landmarks.scenes import CAM, drifted_revisit
from tests.landmarks.scenes import frame_features as _frame
from tests.landmarks.scenes import pose as _pose
from tests.landmarks.scenes import scene as _scene


def test_pose_chi2_by_hand():
    # η = (0, 0, 0, 0.01, 0, 0), C = H1⁻¹ + H2⁻¹ = 2e-4 I: η² / 2e-4 = 1e-4 / 2e-4 = 0.5
    H = np.eye(6) * 1e4
    assert np.isclose(pose_chi2(np.eye(4), H, _pose([0, 0, 0], [0.01, 0, 0]), H), 0.5)
    # a rotation of 0.01 rad about z with H1 = 1e4, H2 = 3e4: C = (1 + 1/3) 1e-4, χ² = 1e-4 / C = 0.75
    assert np.isclose(pose_chi2(np.eye(4), H, _pose([0, 0, 0.01], [0, 0, 0]), 3 * H), 0.75)


def _tracker(X, desc, shift, **kw):
    """A map of ``X``: the first half made at frame 0 and last seen then (stale at frame 100), moved by
    the rigid ``shift`` (the drift between the two visits), the second half made and seen at frame 95."""
    cfg = LandmarksConfig(enabled=True, mode="seed", min_seen=1, **kw)
    tr = LandmarkTracker(cfg, CAM)
    cov = np.tile(np.eye(3) * 1e-6, (len(X), 1, 1))
    h = len(X) // 2
    Xs = X[:h] @ shift[:3, :3].T + shift[:3, 3]
    tr.map.add(Xs, cov[:h], desc[:h], 0, 0)
    tr.map.end_step(0)
    tr.map.add(X[h:], cov[h:], desc[h:], 95, 95)
    tr.map.end_step(95)
    return tr


def test_stale_landmarks_with_other_drift_are_left_out_of_the_map_pose():
    """The frame at ``truth`` sees both halves; the stale half sits 1.5 cm / 0.3° off (the first visit's
    coordinates). Mixed, the pose is a compromise between the two; with stale_after the pose is the
    current landmarks' (the truth), the stale matches are counted as left out, and their features
    may make new landmarks (their candidates no longer block them)."""
    X, desc, truth, shift, feats = drifted_revisit()
    mixed = LandmarkTracker.track(_tracker(X, desc, shift, stale_after=0), 100, feats, truth)
    assert np.linalg.norm(mixed[:3, 3] - truth[:3, 3]) > 2e-3  # pulled towards the stale copy
    tr = _tracker(X, desc, shift, stale_after=30, stale_check=True)
    P = tr.track(100, feats, truth)
    assert np.linalg.norm(P[:3, 3] - truth[:3, 3]) < 1e-4
    s = tr.summary()
    assert s["stale_left_out"] >= 150 and s["stale_joined"] == 0
    assert np.all(tr.map.first[tr._last[2]] == 95)  # the inliers: current landmarks only
    assert np.all(tr.map.last[tr._last_matches.cand_ids] >= 70)  # stale candidates no longer block new ones
    tr.map.end_step(100)  # seen at 95 and re-observed now; the stale half still last seen at 0
    assert np.all(tr.map.last[: len(X) // 2] == 0)


def test_stale_landmarks_that_agree_join_the_map_pose():
    """The same map without drift between the visits: the stale half's own pose agrees with the current
    one (χ² under the gate), so it joins and the pose uses every landmark; with stale_check off it
    would be left out all the same."""
    rng = np.random.default_rng(5)
    X = _scene(600, 7)
    desc = rng.integers(0, 256, size=(len(X), 32), dtype=np.uint8)
    truth = _pose([0.0, 0.01, 0.0], [0.02, 0.0, 0.0])
    feats = _frame(truth, X, desc)
    tr = _tracker(X, desc, np.eye(4), stale_after=30, stale_check=True)
    P = tr.track(100, feats, truth @ _pose([0, 0, 0], [0.002, 0, 0]))
    assert np.linalg.norm((inv(truth) @ P)[:3, 3]) < 1e-4
    s = tr.summary()
    assert s["stale_joined"] == 1 and s["stale_left_out"] == 0
    assert np.any(tr.map.first[tr._last[2]] == 0)
    off = _tracker(X, desc, np.eye(4), stale_after=30, stale_check=False)
    off.track(100, feats, truth)
    assert off.summary()["stale_left_out"] >= 150 and off.summary()["stale_joined"] == 0


def test_a_loop_the_map_already_closed_is_held_by_the_map():
    """holds(j, i): frame j's map inliers include >= map_loop_landmarks landmarks first seen at or before
    frame i (the loop's older end) — counted by hand: 40 landmarks first seen at 0, 40 at 60. Never
    when i is no keyframe of this map (a saved map's keyframe: its id, 2^40 + k, is past every frame)."""
    tr = LandmarkTracker(LandmarksConfig(enabled=True, map_loop_landmarks=30), CAM)
    for k in (0, 10, 60):
        tr.kf_pose[k] = np.eye(4)
    X = _scene(80, 2)
    cov = np.tile(np.eye(3) * 1e-6, (80, 1, 1))
    desc = np.zeros((80, 32), np.uint8)
    tr.map.add(X[:40], cov[:40], desc[:40], 0, 0)
    tr.map.add(X[40:], cov[40:], desc[40:], 60, 60)
    tr._last = (130, np.arange(80), np.arange(80))
    assert tr.holds(130, 0)  # 40 >= 30 landmarks existed at frame 0
    assert not tr.holds(130, (1 << 40) + 3)  # a saved map's keyframe: none of these landmarks is its
    tr._last = (130, np.arange(60), np.arange(20, 80))  # 20 of them first seen at 0: fewer than 30
    assert not tr.holds(130, 10)
    assert tr.holds(130, 60)  # all 60 existed at frame 60
    assert not tr.holds(131, 60)  # no map pose for frame 131
    tr.cfg.map_loop_landmarks = 0
    assert not tr.holds(130, 60)
    assert tr.summary()["loops_held"] == 2


def test_loop_edge_is_re_measured_against_the_older_ends_landmarks():
    """loop_refine: keyframe 0 (at A0) made the first half of the map at the true coordinates; the
    second half, made at frame 95, sits 2 cm off (drift). A loop edge 0 -> 100 from a registration
    1.5 cm / 0.3° off the truth comes back as A0⁻¹ · truth (< 0.1 mm): only the landmarks first seen
    within loop_window of keyframe 0 are searched, with the edge's pose as the prediction. Without
    landmarks near keyframe 0 (keyframe 0 unknown to the map) the edge stays as it was."""
    from rgbdslam.loop.detector import LoopEdge

    rng = np.random.default_rng(5)
    X = _scene(600, 7)
    desc = rng.integers(0, 256, size=(len(X), 32), dtype=np.uint8)
    truth = _pose([0.0, 0.01, 0.0], [0.02, 0.0, 0.0])
    A0 = _pose([0.0, -0.2, 0.0], [-0.3, 0.0, 0.1])
    err = _pose([0.0, 0.0, np.radians(0.3)], [0.015, 0.0, 0.0])
    drift = _pose([0.0, 0.0, 0.0], [0.02, 0.0, 0.0])
    tr = _tracker(X, desc, np.eye(4), stale_after=30, loop_refine=True)  # first half at X, made at frame 0
    h = len(X) // 2
    tr.map.pos[h:len(X)] = X[h:] @ drift[:3, :3].T + drift[:3, 3]  # the half made at 95: drifted
    tr.kf_pose[0] = A0
    feats = _frame(truth, X, desc)
    e = LoopEdge(0, 100, inv(A0) @ truth @ err, np.eye(6) * 1e4, 200, 0.01)
    r = tr.refine_loop(100, feats, e)
    assert np.linalg.norm((inv(inv(A0) @ truth) @ r.T_ij)[:3, 3]) < 1e-4
    assert 100 <= r.n_inliers <= h and np.all(np.linalg.eigvalsh(r.information) > 0) and (r.i, r.j) == (0, 100)
    assert tr.summary()["loops_refined"] == 1
    assert np.isclose(tr.summary()["loop_refine_median_m"], np.linalg.norm(err[:3, 3]), atol=2e-3)
    other = LoopEdge(7, 100, e.T_ij, e.information, 200, 0.01)  # keyframe 7: not one the map made
    assert tr.refine_loop(100, feats, other) is other and tr.summary()["loops_refined"] == 1


def _seen_scene(seed):
    """(rng, scene points, descriptors, true pose, the frame's features there)."""
    rng = np.random.default_rng(seed)
    X = _scene(600, 7)
    desc = rng.integers(0, 256, size=(len(X), 32), dtype=np.uint8)
    truth = _pose([0.0, 0.01, 0.0], [0.02, 0.0, 0.0])
    return rng, X, desc, truth, _frame(truth, X, desc)


def test_a_failed_pose_from_the_current_matches_is_not_tried_again():
    """The current landmarks (the second half) are matched but 3-D inconsistent (each moved along its
    viewing ray by 0.2-1.5 m: the pixels agree, the points do not), so no pose comes from them; the
    stale half agrees with the truth but has nothing to be compared with, so it stays out. The frame
    keeps the registration's pose, and the map pose is estimated once, from the current matches: not
    from the stale ones (nothing to compare their pose with) and not a second time from the same
    current matches (the stale check's failed try is the answer). Before: three estimates."""
    rng, X, desc, truth, feats = _seen_scene(6)
    tr = _tracker(X, desc, np.eye(4), stale_after=30, stale_check=True)
    h = len(X) // 2
    Tcw = inv(truth)
    Xc = tr.map.pos[h:len(X)] @ Tcw[:3, :3].T + Tcw[:3, 3]
    dz = rng.uniform(0.2, 1.5, len(Xc)) * rng.choice([-1.0, 1.0], len(Xc))
    Xc *= np.maximum(Xc[:, 2] + dz, 0.5)[:, None] / Xc[:, 2:3]  # along the ray: the same pixel
    tr.map.pos[h:len(X)] = Xc @ truth[:3, :3].T + truth[:3, 3]
    calls = []
    estimate = tr._estimate

    def counted(feats, m, pose):
        out = estimate(feats, m, pose)
        calls.append((len(m.lm), out is not None))
        return out

    tr._estimate = counted
    given = truth @ _pose([0, 0, 0], [0.002, 0, 0])
    P = tr.track(100, feats, given)
    assert P is given  # no map pose
    assert len(calls) == 1 and calls[0][0] >= 150 and not calls[0][1]  # the current matches: tried, failed
    s = tr.summary()
    assert s["map_poses"] == 0 and s["stale_joined"] == 0 and s["stale_left_out"] >= 150
