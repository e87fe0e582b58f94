"""Loop closure: sharpness gate, descriptor index, acceptance and rejection of loops."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rgbdslam.config import Config
from rgbdslam.frontend.features import FrameFeatures
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import inv, make_pose, transform_points
from rgbdslam.loop.detector import LoopCloser, build_loop_closer
from rgbdslam.loop.gate import SharpnessGate
from rgbdslam.loop.index import BruteIndex, LshIndex

CAM = Camera(525.0, 525.0, 319.5, 239.5, 640, 480)


def test_sharpness_gate_hand_counts():
    g = SharpnessGate(factor=1.2, window=4, min_history=3)
    seq = [100, 100, 100, 121, 120, 130, 140, 200]
    # history before each call: -, [100], [100,100], [100]*3 (median 100 -> >120),
    # [100,100,100,121] (median 100 -> 120 is not > 120), [100,100,121,120] (median 110.5 -> 132.6),
    # [100,121,120,130] (median 120.5 -> 144.6), [121,120,130,140] (median 125.5 -> 150.6)
    assert [g(n) for n in seq] == [False, False, False, True, False, False, False, True]
    assert g.n_sharp == 2 and g.n_seen == 8


def random_desc(rng, n):
    return rng.integers(0, 256, (n, 32), dtype=np.uint8)


def flip_bits(rng, desc, n_flips):
    bits = np.unpackbits(desc, axis=1)
    for row in bits:
        row[rng.choice(256, n_flips, replace=False)] ^= 1
    return np.packbits(bits, axis=1)


def test_lsh_votes_find_the_right_keyframe():
    rng = np.random.default_rng(1)
    lsh, brute = LshIndex(8, 20, seed=0), BruteIndex(64)
    descs = [random_desc(rng, 500) for _ in range(30)]
    for k, d in enumerate(descs):
        lsh.add(k, d)
        brute.add(k, d)
    assert len(lsh.runs) <= 6  # logarithmic method: few sorted runs
    q = flip_bits(rng, descs[17][:300], 20)
    v = lsh.votes(q)
    assert v.argmax() == 17 and v[17] > 100
    assert np.delete(v, 17).max() < 8
    assert brute.votes(q).argmax() == 17
    assert lsh.votes(random_desc(rng, 300)).max() < 8


def test_lsh_bulk_add_gives_the_same_votes():
    """A loaded map's keyframes indexed in one pass (add_many) vote exactly as added one by one,
    before and after more keyframes come one by one (the runs keep merging)."""
    rng = np.random.default_rng(3)
    descs = [random_desc(rng, int(n)) for n in rng.integers(0, 400, 25)]  # one keyframe without features
    descs[4] = descs[4][:0]
    one, bulk = LshIndex(8, 12, seed=1), LshIndex(8, 12, seed=1)  # 12 bits: many shared buckets
    for k, d in enumerate(descs):
        one.add(k, d)
    bulk.add_many(np.concatenate(descs), np.concatenate([[0], np.cumsum([len(d) for d in descs])]))
    assert bulk.n_keyframes == one.n_keyframes == 25 and bulk.size == one.size
    q = np.concatenate([flip_bits(rng, descs[9][:200], 30), random_desc(rng, 100)])
    assert np.array_equal(bulk.votes(q), one.votes(q)) and bulk.votes(q).max() > 0
    for k in range(25, 40):  # a session's own keyframes after the map's
        d = random_desc(rng, 300)
        one.add(k, d)
        bulk.add(k, d)
    q = random_desc(rng, 500)
    assert np.array_equal(bulk.votes(q), one.votes(q)) and bulk.size == one.size
    brute = BruteIndex(64)
    brute.add_many(np.concatenate(descs[:3]), [0, len(descs[0]), len(descs[0]) + len(descs[1]),
                                               sum(len(d) for d in descs[:3])])
    assert brute.n_keyframes == 3 and brute.votes(descs[1][:50]).argmax() == 1


def make_place(rng, n=400):
    """Random 3-D points in front of the camera (world = camera of the first view) + descriptors."""
    P = np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.0, 1.0, n), rng.uniform(1.5, 4.0, n)])
    return P, random_desc(rng, n)


def view(index, P_world, desc, pose, rng, flips=8):
    """FrameFeatures of world points seen from camera-to-world ``pose``."""
    pc = transform_points(inv(pose), P_world)
    uv = CAM.project(pc)
    inside = (pc[:, 2] > 0.3) & (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
    pc, uv = pc[inside], uv[inside]
    d = flip_bits(rng, desc[inside], flips)
    pc = pc + rng.normal(0, 0.002, pc.shape)
    return FrameFeatures(index=index, timestamp=float(index), uv=uv, desc=d, pts=pc,
                         valid=np.ones(len(pc), bool), n_detected=len(pc), uv_raw=uv)


def loop_config() -> Config:
    cfg = Config()
    cfg.loop.enabled = True
    cfg.loop.skip_recent = 2
    cfg.loop.min_votes = 20
    cfg.loop.min_inliers = 40
    cfg.loop.max_residual = 0.02
    cfg.registration.method = "isvd"
    return cfg


@pytest.fixture()
def mapped():
    """A loop closer whose map holds place A (keyframe 0) and four other places."""
    rng = np.random.default_rng(7)
    cfg = loop_config()
    lc = build_loop_closer(cfg)
    places = [make_place(rng) for _ in range(5)]
    poses = [make_pose(np.eye(3), [0.5 * k, 0, 0]) for k in range(5)]
    for k, ((P, d), pose) in enumerate(zip(places, poses)):
        # place k is expressed in the frame of its keyframe's pose
        lc.add_keyframe(view(10 * k, transform_points(pose, P), d, pose, rng), pose)
    return lc, places, poses, rng


def revisit_pose(dx=0.05, yaw_deg=4.0):
    return make_pose(Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix(), [dx, 0.02, -0.03])


def test_true_revisit_is_accepted(mapped):
    lc, places, poses, rng = mapped
    P, d = places[0]
    true_pose = revisit_pose()
    cur = view(100, P, d, true_pose, rng)
    drift = make_pose(Rotation.from_euler("z", 2.0, degrees=True).as_matrix(), [0.08, -0.05, 0.0])
    edges = lc.detect(cur, drift @ true_pose)  # the odometry estimate has drifted a little
    assert len(edges) == 1
    e = edges[0]
    assert (e.i, e.j) == (0, 100)
    T_true = inv(poses[0]) @ true_pose
    assert np.linalg.norm(e.T_ij[:3, 3] - T_true[:3, 3]) < 0.01
    assert np.allclose(e.T_ij[:3, :3], T_true[:3, :3], atol=0.01)
    assert e.n_inliers >= 40 and e.residual < 0.02
    assert e.information.shape == (6, 6) and np.all(np.linalg.eigvalsh(e.information) > 0)
    assert lc.stats["n_accepted"] == 1 and lc.stats["n_queries"] == 1


def test_different_place_with_random_descriptors_is_rejected(mapped):
    lc, places, poses, rng = mapped
    P, _ = make_place(rng)
    cur = view(100, P, random_desc(rng, len(P)), revisit_pose(), rng)
    assert lc.detect(cur, revisit_pose()) == []
    assert lc.stats["n_candidates"] == 0


def test_same_descriptors_inconsistent_geometry_is_rejected(mapped):
    lc, places, poses, rng = mapped
    P, d = places[0]
    cur = view(100, P, d, revisit_pose(), rng)
    cur.pts = cur.pts[rng.permutation(len(cur.pts))]  # descriptors match, 3-D layout does not
    assert lc.detect(cur, revisit_pose()) == []
    assert lc.stats["n_candidates"] >= 1 and lc.stats["n_accepted"] == 0


def test_loop_disagreeing_with_the_estimate_is_rejected(mapped):
    lc, places, poses, rng = mapped
    P, d = places[0]
    true_pose = revisit_pose()
    cur = view(100, P, d, true_pose, rng)
    far = make_pose(np.eye(3), [0.0, 0.0, 3.0]) @ true_pose  # the estimate says we are 3 m away
    assert lc.detect(cur, far) == []
    assert lc.stats["n_rejected_consistency"] == 1


def test_recent_keyframes_are_skipped(mapped):
    lc, places, poses, rng = mapped
    P, d = places[4]  # the newest keyframe: within skip_recent
    cur = view(100, transform_points(poses[4], P), d, poses[4], rng)
    assert lc.candidates(cur) == []


def test_relocalisation_after_a_restart(mapped):
    """After new_segment the estimate says nothing about older keyframes: geometrically sound
    matches are accepted whatever the estimate, even to a recent keyframe, once a second one
    (here the next frame) confirms the first; the link fixes the offset between the segments,
    and later loops to that segment must agree with the offset."""
    lc, places, poses, rng = mapped
    lc.new_segment()
    assert lc.relocalizing and lc.stats["n_segments"] == 2
    # the restarted front end believes it is somewhere unrelated (3 m away, turned 90 degrees)
    to_new = make_pose(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [3.0, -2.0, 0.5])
    true_pose = poses[4] @ revisit_pose()
    P, d = places[4]  # the newest keyframe: skipped as "recent" in normal mode, a candidate now
    first = view(200, transform_points(poses[4], P), d, true_pose, rng)
    lc.add_keyframe(first, to_new @ true_pose)  # the new segment's first keyframe
    assert lc.detect(first, to_new @ true_pose) == []  # sound, but waits for a confirmation
    assert lc.relocalizing and lc.stats["n_accepted"] == 0
    moved = true_pose @ make_pose(np.eye(3), [0.02, 0.0, 0.01])
    edges = lc.detect(view(201, transform_points(poses[4], P), d, moved, rng), to_new @ moved)
    assert [(e.i, e.j) for e in edges] == [(40, 201)]
    assert not lc.relocalizing and lc.stats["n_relocalized"] == 1
    true_pose = moved
    T_true = inv(poses[4]) @ true_pose
    assert np.linalg.norm(edges[0].T_ij[:3, 3] - T_true[:3, 3]) < 0.01
    # a later revisit of place 0: consistent with the offset -> accepted ...
    P0, d0 = places[0]
    pose0 = revisit_pose()
    cur = view(210, P0, d0, pose0, rng)
    assert [(e.i, e.j) for e in lc.detect(cur, to_new @ pose0)] == [(0, 210)]
    # the keyframe just before the loss is not "recent" for the new segment (skip_recent = 2 here)
    cur = view(215, transform_points(poses[4], P), d, true_pose, rng)
    assert [(e.i, e.j) for e in lc.detect(cur, to_new @ true_pose)] == [(40, 215)]
    # ... but if the new segment's estimate contradicts the offset by 3 m it is rejected
    cur = view(220, P0, d0, pose0, rng)
    rejected = lc.stats["n_rejected_consistency"]
    assert lc.detect(cur, make_pose(np.eye(3), [0, 0, 3.0]) @ to_new @ pose0) == []
    assert lc.stats["n_rejected_consistency"] == rejected + 1


def _twin_then_true(lc, places, poses, rng):
    """After a restart the camera first sees a twin of place 4 one metre away (same structure,
    same descriptors: a geometrically perfect false match), then moves to the real place 4."""
    lc.new_segment()
    to_new = make_pose(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [3.0, -2.0, 0.5])
    twin = make_pose(np.eye(3), [1.0, 0.0, 0.0])
    P, d = places[4]
    out = []
    for j, world in ((200, twin @ poses[4] @ revisit_pose()), (205, poses[4] @ revisit_pose(0.08)),
                     (206, poses[4] @ revisit_pose(0.09))):
        points = transform_points((twin if j == 200 else np.eye(4)) @ poses[4], P)
        out.append(lc.detect(view(j, points, d, world, rng), to_new @ world))
    return out, to_new


def test_a_false_relocalisation_waits_and_the_true_one_links(mapped):
    lc, places, poses, rng = mapped
    (at_twin, first_true, second_true), to_new = _twin_then_true(lc, places, poses, rng)
    assert at_twin == [] and first_true == []  # the twin and the real place disagree by 1 m
    assert [(e.i, e.j) for e in second_true] == [(40, 206)]  # two true matches agree
    to_old = lc._links[0][0]  # maps new-segment to old-segment coordinates: inverse of to_new
    assert np.allclose(to_old, inv(to_new), atol=0.02)


def test_without_confirmation_the_twin_links_wrongly(mapped):
    """relocalize_confirm = 1 (the behaviour before 2026-11-30): the first sound match links,
    the twin's, one metre off; the true matches that follow are then rejected as inconsistent."""
    lc, places, poses, rng = mapped
    lc.lc.relocalize_confirm = 1
    (at_twin, first_true, second_true), to_new = _twin_then_true(lc, places, poses, rng)
    assert [(e.i, e.j) for e in at_twin] == [(40, 200)]
    assert np.linalg.norm(lc._links[0][0][:3, 3] - inv(to_new)[:3, 3]) > 0.9
    assert first_true == [] and second_true == [] and lc.stats["n_rejected_consistency"] == 2


def test_unconfirmed_relocalisation_matches_expire(mapped):
    lc, places, poses, rng = mapped
    lc.lc.relocalize_window = 3
    lc.new_segment()
    P, d = places[4]
    pose = poses[4] @ revisit_pose()
    assert lc.detect(view(200, transform_points(poses[4], P), d, pose, rng), pose) == []
    # three frames later the first match is out of the window: the second one waits alone
    assert lc.detect(view(203, transform_points(poses[4], P), d, pose, rng), pose) == []
    assert lc.stats["n_relocalize_unconfirmed"] == 1 and lc.relocalizing


def test_no_relocalisation_without_a_restart(mapped):
    """The same sound match with an estimate 3 m off: rejected on consistency while tracking,
    kept (waiting for its confirmation) only after a restart, where the estimate means nothing."""
    lc, places, poses, rng = mapped
    P, d = places[0]  # not a recent keyframe: a candidate in both modes
    far = make_pose(np.eye(3), [3.0, 0.0, 0.0])
    for k, relocalizing in enumerate((False, True)):
        if relocalizing:
            lc.new_segment()
        cur = view(200 + k, P, d, revisit_pose(), rng)
        assert lc.relocalizing == relocalizing
        assert lc.detect(cur, far @ revisit_pose()) == []
        assert lc.stats["n_verified"] == k + 1 and lc.stats["n_rejected_consistency"] == 1
    assert len(lc._pending) == 1 and lc._pending[0][0] == 201


def test_query_gap_makes_a_search_due():
    from types import SimpleNamespace

    cfg = loop_config()
    cfg.loop.query_gap = 3
    lc = LoopCloser(cfg.loop, register=lambda *a: None)
    assert lc.due(3) and not lc.due(2)  # nothing searched yet: due from frame query_gap on
    lc.detect(SimpleNamespace(index=10, desc=np.zeros((0, 32), np.uint8)), np.eye(4))
    assert [lc.due(i) for i in (11, 12, 13, 20)] == [False, False, True, True]
    cfg.loop.query_gap = 0  # the thesis' gate alone: never due
    assert not LoopCloser(cfg.loop, register=lambda *a: None).due(1000)


def test_observe_uses_the_configured_measure():
    from types import SimpleNamespace

    cfg = loop_config()
    cfg.loop.sharpness_window, cfg.loop.sharpness_min_history = 3, 3

    def feats(n, resp):
        return SimpleNamespace(n_detected=n, desc=np.zeros((n, 32), np.uint8), response=np.full(n, resp))

    cfg.loop.sharpness_measure = "response"
    lc = LoopCloser(cfg.loop, register=lambda *a: None)
    # capped counts (all 100) but the responses of the 4th frame are 30 % stronger
    assert [lc.observe(feats(100, r)) for r in (0.010, 0.010, 0.010, 0.013)] == [False, False, False, True]
    cfg.loop.sharpness_measure = "n_detected"
    lc = LoopCloser(cfg.loop, register=lambda *a: None)
    assert [lc.observe(feats(100, r)) for r in (0.010, 0.010, 0.010, 0.013)] == [False] * 4
    assert lc.observe(feats(121, 0.01)) is True and lc.stats["n_sharp"] == 1


# ------------------------------------------------------------------ real frames (TUM fr1)


from tests.conftest import DATA  # noqa: E402
RPY = DATA / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
DESK = DATA / "tum" / "rgbd_dataset_freiburg1_desk_9frames"


@pytest.mark.data
@pytest.mark.usefixtures("desk9", "rpy200")
def test_real_revisit_accepted_and_other_room_rejected():
    from rgbdslam.datasets import open_sequence
    from rgbdslam.frontend.features import extract_features
    from rgbdslam.geometry.se3 import rotation_angle

    cfg = Config()
    cfg.loop.enabled = True
    cfg.loop.skip_recent = 0
    rpy = open_sequence(RPY, cfg.dataset)
    desk = open_sequence(DESK, cfg.dataset)
    gt = rpy.groundtruth()

    def gt_pose(i):
        return gt.poses[int(np.argmin(np.abs(gt.timestamps - rpy.timestamps[i])))]

    lc = build_loop_closer(cfg)
    lc.add_keyframe(extract_features(rpy.load(0), cfg.features, cfg.matching), gt_pose(0))
    # frame 109 comes back to the view of frame 0 after the roll/pitch/yaw swings
    edges = lc.detect(extract_features(rpy.load(109), cfg.features, cfg.matching), gt_pose(109))
    assert len(edges) == 1 and (edges[0].i, edges[0].j) == (0, 109)
    err = inv(inv(gt_pose(0)) @ gt_pose(109)) @ edges[0].T_ij
    # (ground truth is the nearest mocap sample: a few ms off during fast rotation)
    assert np.linalg.norm(err[:3, 3]) < 0.03 and np.degrees(rotation_angle(err[:3, :3])) < 3.0
    # a frame of another room (fr1/desk) must not close a loop with it
    assert lc.detect(extract_features(desk.load(4), cfg.features, cfg.matching), gt_pose(109)) == []
    assert lc.stats["n_accepted"] == 1


def test_stop_at_first_verifies_fewer_candidates_but_not_while_relocalising(mapped):
    """A frame that sees places 0 and 1 verifies against both keyframes; with stop_at_first the
    first sound one (most votes) ends the search, except while relocalising (every match counts)."""
    lc, places, poses, rng = mapped
    lc.lc.skip_recent = 0
    world = np.vstack([transform_points(poses[k], places[k][0]) for k in (0, 1)])
    desc = np.vstack([places[0][1], places[1][1]])
    pose = make_pose(np.eye(3), [0.25, 0.0, -1.5])  # backed off so that both places are in view
    cur = view(100, world, desc, pose, rng)
    assert len(lc.candidates(cur)) == 2
    assert [(e.i, e.j) for e in lc.detect(cur, pose)] in ([(0, 100)], [(10, 100)])
    assert lc.stats["n_verified"] == 2
    lc.lc.stop_at_first = True
    assert len(lc.detect(cur, pose)) == 1 and lc.stats["n_verified"] == 3
    lc.new_segment()
    lc.detect(cur, pose)
    assert lc.stats["n_verified"] == 5  # relocalising: both verified again


def test_a_third_segment_needs_confirmation_too(mapped):
    """After the current segment is linked to segment 0, a single sound match into segment 1
    (never linked, so there is nothing to check it against) must wait for a second one."""
    lc, places, poses, rng = mapped
    P, d = places[3]
    lc.new_segment()  # segment 1: one keyframe seeing place 3 (unrelated coordinates)
    far = make_pose(np.eye(3), [7.0, 0, 0])
    lc.add_keyframe(view(50, transform_points(poses[3], P), d, poses[3], rng), far @ poses[3])
    lc.new_segment()  # segment 2 (current): relocalise to segment 0 with two agreeing frames
    P0, d0 = places[0]
    to_new = make_pose(np.eye(3), [0.0, 3.0, 0.0])
    for j in (60, 61):
        pose = revisit_pose(0.05 + 0.01 * (j - 60))
        out = lc.detect(view(j, P0, d0, pose, rng), to_new @ pose)
    assert [(e.i, e.j) for e in out] == [(0, 61)] and set(lc._links) == {0}
    # the camera now sees place 3: keyframe 30 (segment 0, linked) and 50 (segment 1, not linked)
    lc.lc.max_loops_per_frame = 2
    pose = poses[3] @ revisit_pose()
    edges = lc.detect(view(70, transform_points(poses[3], P), d, pose, rng), to_new @ pose)
    assert [(e.i, e.j) for e in edges] == [(30, 70)] and 1 not in lc._links  # segment 1 waits
    pose2 = poses[3] @ revisit_pose(0.07)
    edges = lc.detect(view(71, transform_points(poses[3], P), d, pose2, rng), to_new @ pose2)
    assert sorted((e.i, e.j) for e in edges) == [(30, 71), (50, 71)] and set(lc._links) == {0, 1}
