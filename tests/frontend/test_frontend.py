"""The front end on real TUM frames: accuracy against ground truth, tracking loss, determinism."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from rgbdslam.config import Config
from rgbdslam.datasets import open_sequence
from rgbdslam.frontend.features import count_detections, extract_features, lift
from rgbdslam.frontend.odometry import build_frontend
from rgbdslam.frontend.pairwise import build_pair_registration
from rgbdslam.geometry.se3 import inv, rotation_angle


@pytest.fixture(scope="module")
def desk(request):
    from tests.conftest import TUM_DESK9, need

    seq = open_sequence(need(TUM_DESK9))
    return seq, [seq.load(i) for i in range(len(seq))]


def gt_pose(gt, t: float) -> np.ndarray:
    """Ground-truth pose at time t, interpolated (linear translation, slerp rotation)."""
    i = int(np.searchsorted(gt.timestamps, t))
    t0, t1 = gt.timestamps[i - 1], gt.timestamps[i]
    a = (t - t0) / (t1 - t0)
    P = np.eye(4)
    P[:3, 3] = (1 - a) * gt.poses[i - 1, :3, 3] + a * gt.poses[i, :3, 3]
    P[:3, :3] = Slerp([0, 1], Rotation.from_matrix(gt.poses[i - 1 : i + 1, :3, :3]))(a).as_matrix()
    return P


def rel_error(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    E = inv(A) @ B
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(rotation_angle(E[:3, :3])))


def register_pair(desk, cfg: Config, i: int, j: int):
    """Register frame j against frame i; assert it agrees with the ground truth (1.5 cm / 1 deg)."""
    seq, frames = desk
    gt = seq.groundtruth()
    a, b = frames[i], frames[j]
    fa, fb = extract_features(a, cfg.features, cfg.matching), extract_features(b, cfg.features, cfg.matching)
    res = build_pair_registration(cfg)(fa, fb)
    assert res is not None
    rel_gt = inv(gt_pose(gt, a.timestamp)) @ gt_pose(gt, b.timestamp)  # pose of b in a's frame
    assert np.linalg.norm(rel_gt[:3, 3]) > 0.015  # the pair really moved
    dt, dr = rel_error(rel_gt, inv(res.T))
    assert dt < 0.015 and dr < 1.0, (dt, dr)
    return fa, fb, res


@pytest.mark.data
@pytest.mark.parametrize("method", ["ransac", "isvd", "islam"])
def test_register_two_real_frames_matches_groundtruth(desk, method):
    cfg = Config()
    cfg.registration.method = method
    fa, fb, res = register_pair(desk, cfg, 0, 4)
    assert res.n_inliers >= 50
    # pairs index depth-valid features of both frames
    assert fa.valid[res.pairs[:, 0]].all() and fb.valid[res.pairs[:, 1]].all()
    assert np.all(np.linalg.eigvalsh(res.information) > 0)


@pytest.mark.data
def test_frontend_tracks_desk_and_survives_zero_depth(desk):
    seq, frames = desk
    gt = seq.groundtruth()
    cfg = Config()
    fe = build_frontend(cfg, seq.camera)
    blank = dataclasses.replace(frames[3], depth=np.zeros_like(frames[3].depth))
    results = [fe.track(f) for f in frames[:3]] + [fe.track(blank)] + [fe.track(f) for f in frames[4:]]
    assert [r.lost for r in results] == [False] * 3 + [True] + [False] * 5
    assert results[3].pose is None and results[3].relative is None
    assert results[4].relative is not None  # relative to frame 2, the last tracked one
    P0 = gt_pose(gt, frames[0].timestamp)
    for r in results:
        if r.lost:
            continue
        dt, dr = rel_error(inv(P0) @ gt_pose(gt, r.timestamp), r.pose)
        assert dt < 0.03 and dr < 2.5, (r.index, dt, dr)  # accumulated drift over <= 8 frames
    for r in results:
        assert set(r.timings) >= {"features", "matching", "registration", "fusion"}
    # the relative of frame 4 chains onto frame 2's pose
    assert np.allclose(results[2].pose @ results[4].relative, results[4].pose)


@pytest.mark.data
def test_frontend_deterministic(desk):
    seq, frames = desk
    cfg = Config()
    runs = []
    for _ in range(2):
        fe = build_frontend(cfg, seq.camera)
        runs.append(np.stack([fe.track(f).pose for f in frames]))
    assert np.array_equal(runs[0], runs[1])


@pytest.mark.data
def test_lift_and_set_depth(desk):
    seq, frames = desk
    cfg = Config()
    f = extract_features(frames[0], cfg.features, cfg.matching)
    assert len(f.desc) > 300 and f.n_detected > 100
    assert f.valid.sum() > 0.5 * len(f.valid)
    assert np.isnan(f.pts[~f.valid]).all()
    # doubling the depth doubles the points; with max_depth lowered to 2.8 m, the key points whose
    # doubled depth (read at the rounded distorted key point) exceeds 2.8 m become invalid
    p, was_valid = f.pts.copy(), f.valid.copy()
    cam = seq.camera
    u = np.clip(np.rint(f.uv_raw[:, 0]).astype(int), 0, cam.width - 1)
    v = np.clip(np.rint(f.uv_raw[:, 1]).astype(int), 0, cam.height - 1)
    z2 = 2.0 * frames[0].depth[v, u].astype(np.float64)
    cfg2 = Config()
    cfg2.matching.max_depth = 2.8
    expect = (z2 >= cfg2.matching.min_depth) & (z2 <= 2.8)
    beyond = was_valid & (z2 > 2.8)
    assert expect.sum() > 0.2 * len(f.uv) and beyond.sum() > 0.2 * len(f.uv)  # both cases well populated
    lift(f, frames[0].depth * 2, cam, cfg2.matching)
    np.testing.assert_array_equal(f.valid, expect)
    assert not f.valid[beyond].any() and np.isnan(f.pts[beyond]).all()
    assert np.isnan(f.pts[~f.valid]).all()
    ok = f.valid & was_valid
    assert ok.sum() > 0.2 * len(f.uv)
    np.testing.assert_allclose(f.pts[ok], 2 * p[ok], rtol=1e-12)
    # pinhole back-projection of the undistorted key point at the doubled depth
    np.testing.assert_allclose(f.pts[ok, 2], z2[ok], rtol=1e-12)
    np.testing.assert_allclose(f.pts[ok, 0], (f.uv[ok, 0] - cam.cx) / cam.fx * z2[ok], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(f.pts[ok, 1], (f.uv[ok, 1] - cam.cy) / cam.fy * z2[ok], rtol=1e-9, atol=1e-12)
    # set_depth replaces a reference's depth: all-zero depth leaves it without points
    fe = build_frontend(cfg, seq.camera)
    fe.track(frames[0])
    fe.set_depth(frames[0].index, np.zeros_like(frames[0].depth))
    assert fe.refs[-1].features.valid.sum() == 0


def test_features_with_other_points_search_the_new_points(desk):
    """with_points: a copy whose k-d tree is built from the new points (the original's cached tree,
    already built, stays with the original)."""
    _, frames = desk
    cfg = Config()
    f = extract_features(frames[0], cfg.features, cfg.matching)
    near = f.pts * 0.5
    f.tree  # noqa: B018 - the original's tree, built and cached
    g = f.with_points(near)
    assert g.pts is not f.pts and np.array_equal(g.desc, f.desc) and np.array_equal(g.valid, f.valid)
    d, k2 = g.tree.query(near[g.valid])
    assert np.all(d == 0) and np.array_equal(g.pts[g.tree_index[k2]], near[g.valid])  # duplicates: any of them
    assert np.array_equal(f.tree.data, f.pts[f.valid]) and not np.array_equal(g.tree.data, f.tree.data)
    with pytest.raises(ValueError, match="with_points needs"):
        f.with_points(near[:5])


def test_hamming_matrix_matches_opencv_norm():
    import cv2

    from rgbdslam.frontend.features import descriptor_words
    from rgbdslam.frontend.matching import hamming_matrix

    rng = np.random.default_rng(7)
    a = rng.integers(0, 256, (20, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (15, 32), dtype=np.uint8)
    b[3] = a[5]  # identical descriptor -> distance 0
    d = hamming_matrix(descriptor_words(a), descriptor_words(b))
    ref = np.array([[cv2.norm(x, y, cv2.NORM_HAMMING) for y in b] for x in a])
    assert np.array_equal(d, ref)
    assert d[5, 3] == 0


def test_point_information_equals_jacobian_product():
    from rgbdslam.frontend.registration import point_information

    rng = np.random.default_rng(8)
    P = rng.uniform(-1, 1, (10, 3)) + [0, 0, 2]
    H = np.zeros((6, 6))
    for p in P:
        px = np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
        J = np.hstack([-px, np.eye(3)])
        H += J.T @ J
    assert np.allclose(point_information(P, 0.01), H / 1e-4)


@pytest.mark.data
@pytest.mark.parametrize("prefilter", ["none", "homography", "fundamental"])
def test_prefilter_variants_register_real_pair(desk, prefilter):
    cfg = Config()
    cfg.matching.prefilter = prefilter
    cfg.matching.prefilter_threshold = {"none": 0.0, "homography": 3.0, "fundamental": 1.0}[prefilter]
    register_pair(desk, cfg, 1, 3)


@pytest.mark.data
def test_guided_match_is_mutual_and_consistent(desk):
    from rgbdslam.frontend.matching import guided_match

    seq, frames = desk
    cfg = Config()
    fa, fb = extract_features(frames[0], cfg.features, cfg.matching), extract_features(frames[2], cfg.features, cfg.matching)
    full = build_pair_registration(cfg)(fa, fb)
    ia, ib = guided_match(fa, fb, full.T, 0.05, cfg.matching)
    assert len(ia) >= full.n_inliers * 0.8
    assert len(np.unique(ia)) == len(ia) and len(np.unique(ib)) == len(ib)
    # every guided pair is within the radius under the prediction, and matches the descriptors
    moved = fa.pts[ia] @ full.T[:3, :3].T + full.T[:3, 3]
    assert np.all(np.linalg.norm(moved - fb.pts[ib], axis=1) <= 0.05 + 1e-12)
    # a registration guided by a wrong prediction (30 cm off) finds no consistent pairs
    off = full.T.copy()
    off[0, 3] += 0.3
    assert len(guided_match(fa, fb, off, 0.05, cfg.matching)[0]) < 0.2 * len(ia)


@pytest.mark.data
def test_restart_after_max_lost_and_no_origin_without_depth(desk):
    from tests.conftest import TUM_RPY200, need

    seq, frames = desk
    other = open_sequence(need(TUM_RPY200))
    # fr1/rpy frames: the same office seen from elsewhere; any registration against the desk
    # frames is a jump far beyond the motion gate, so they are lost until the restart.
    alien = [other.load(i) for i in (0, 1, 2)]
    cfg = Config()
    cfg.registration.max_lost = 2
    fe = build_frontend(cfg, seq.camera)
    blank = dataclasses.replace(frames[0], depth=np.zeros_like(frames[0].depth))
    r0 = fe.track(blank)
    assert r0.lost and not fe.refs  # no origin from a frame without depth
    r1 = fe.track(frames[1])
    assert not r1.lost and np.array_equal(r1.pose, np.eye(4))
    r2 = fe.track(frames[2])
    a1 = fe.track(alien[0])
    assert a1.lost and not a1.reset
    a2 = fe.track(alien[1])  # second lost frame in a row: restart at the last tracked pose
    assert not a2.lost and a2.reset
    assert np.array_equal(a2.pose, r2.pose) and np.array_equal(a2.relative, np.eye(4))
    a3 = fe.track(alien[2])  # tracks against the restarted reference
    assert not a3.lost and not a3.reset
    assert len(fe.refs) == 2


@pytest.mark.data
def test_ratio_test_and_grid_bucketing(desk):
    from rgbdslam.frontend.features import _bucket
    from rgbdslam.frontend.matching import match_descriptors

    seq, frames = desk
    cfg = Config()
    fa, fb = extract_features(frames[0], cfg.features, cfg.matching), extract_features(frames[1], cfg.features, cfg.matching)
    ia, ib = match_descriptors(fa.desc, fb.desc, cfg.matching)
    cfg.matching.ratio = 0.8
    ra, rb = match_descriptors(fa.desc, fb.desc, cfg.matching)
    assert 0 < len(ra) < len(ia)
    assert set(zip(ra.tolist(), rb.tolist())) <= set(zip(ia.tolist(), ib.tolist()))  # cross-check + ratio
    # bucketing: at most n_features / cells strongest key points per cell
    cfg.features.grid_rows, cfg.features.grid_cols, cfg.features.n_features = 2, 2, 8
    uv = np.array([[10, 10], [20, 20], [30, 30], [400, 10], [10, 300], [11, 11], [500, 400.0]])
    resp = np.array([1, 5, 3, 1, 1, 4, 2], np.float32)
    assert _bucket(uv, resp, cfg.features, (480, 640)).tolist() == [1, 3, 4, 5, 6]


@pytest.mark.data
def test_detection_count_falls_with_blur_and_opens_the_gate(desk):
    """The sharpness gate's measure (docs/references.md §4) must see blur: ORB's kept count cannot
    (it is capped at n_features), the uncapped detection count can."""
    import dataclasses

    import cv2

    from rgbdslam.loop.gate import SharpnessGate

    seq, frames = desk
    cfg = Config()
    sharp = frames[0]
    counts, kept = [], []
    for sigma in (2.0, 1.5, 1.0, 0.0):
        rgb = cv2.GaussianBlur(sharp.rgb, (0, 0), sigma) if sigma else sharp.rgb
        f = extract_features(dataclasses.replace(sharp, rgb=rgb), cfg.features, cfg.matching)
        counts.append(f.n_detected)
        kept.append(len(f.desc))
    assert counts == sorted(counts) and counts[-1] > 2 * counts[0]  # monotone in blur, large effect
    # a slight blur (sigma 1 px) is invisible to the capped count, not to the detection count
    assert kept[2] == kept[3] == cfg.features.n_features and counts[3] > 2 * counts[2]
    gate = SharpnessGate(1.2, 20, min_history=3)
    assert [gate(c) for c in counts] == [False, False, False, True]
    # an image too small for ORB's border has nothing to detect
    assert count_detections(np.zeros((40, 40), np.uint8), cfg.features) == 0


@pytest.mark.data
def test_detections_made_ahead_are_used_only_for_their_config(desk, monkeypatch):
    import dataclasses

    import rgbdslam.frontend.features as features
    from rgbdslam.frontend.features import detect, with_detections

    seq, frames = desk
    cfg = Config()
    plain = extract_features(frames[1], cfg.features, cfg.matching)
    ahead = with_detections(dataclasses.replace(frames[1]), cfg.features)
    assert ahead.detections is not None
    calls = []  # detect() is deterministic: only its calls show whether the detections made ahead were used
    monkeypatch.setattr(features, "detect", lambda *a, **k: calls.append(1) or detect(*a, **k))
    f = extract_features(ahead, cfg.features, cfg.matching)
    assert calls == []  # used, not made again
    for name in ("uv", "uv_raw", "desc", "response", "valid"):
        assert np.array_equal(getattr(f, name), getattr(plain, name)), name
    assert f.n_detected == plain.n_detected
    # detections made with other ORB settings are not reused
    other = Config()
    other.features.n_features = 300
    stale = dataclasses.replace(frames[1], detections=detect(frames[1].rgb, other.features))
    assert len(extract_features(stale, cfg.features, cfg.matching).desc) == len(plain.desc) != 300
    assert calls == [1]
    # nor are detections of another image (a frame copied with a new colour image)
    other_image = dataclasses.replace(ahead, rgb=frames[2].rgb)
    assert other_image.detections is ahead.detections
    assert np.array_equal(extract_features(other_image, cfg.features, cfg.matching).desc,
                          extract_features(dataclasses.replace(frames[2]), cfg.features, cfg.matching).desc)
    assert calls == [1, 1, 1]


@pytest.mark.data
def test_newest_reference_guided_by_a_good_prediction(rpy200):
    """registration.predicted_gate: at 30 Hz the newest reference is matched around the
    prediction on most frames, as accurately as by brute force; at a third of the frame rate the
    predictions are poor and brute force is used."""
    from rgbdslam.evaluation.ate import ate as ate_of
    from rgbdslam.io.trajectory import Trajectory

    seq = open_sequence(rpy200)
    gt = seq.groundtruth()
    frames = [seq.load(i) for i in range(90)]

    def track(cfg, step):
        fe = build_frontend(cfg, seq.camera)
        res = [fe.track(f) for f in frames[::step]]
        ok = [r for r in res if not r.lost]
        traj = Trajectory(np.array([r.timestamp for r in ok]), np.array([r.pose for r in ok]))
        return fe.n_newest_guided, len(res), ate_of(gt, traj).rmse

    guided, n, ate_guided = track(Config(), 1)
    off = Config()
    off.registration.predicted_gate = None
    none, _, ate_brute = track(off, 1)
    assert none == 0 and guided > 0.5 * n
    assert ate_guided < 1.1 * ate_brute
    guided3, n3, _ = track(Config(), 3)
    assert guided3 < 0.3 * n3  # 10 Hz: the previous prediction is rarely good enough


@pytest.mark.data
def test_a_new_registration_strategy_plugs_in_without_touching_the_loop(desk):
    """A strategy is one class with ``select``: here plain least squares on every pre-filtered
    pair (no outlier loop). Given to the front end and the loop closer through the pairwise
    registration, it tracks real frames; the per-frame loop is unchanged."""
    from rgbdslam.frontend.pairwise import PairRegistration
    from rgbdslam.frontend.registration import Registration

    calls = []

    class AllPairs(Registration):
        name = "all_pairs"

        def select(self, S, D, keep):
            calls.append(int(keep.sum()))
            return keep, None

    seq, frames = desk
    cfg = Config()
    strategy = AllPairs(cfg.registration)
    fe = build_frontend(cfg, seq.camera, PairRegistration(cfg.matching, strategy, cfg.registration.seed))
    assert fe.mp == 1  # not multi_reference: the previous frame only
    gt = seq.groundtruth()
    poses = [fe.track(f).pose for f in frames[:4]]
    assert len(calls) == 3 and min(calls) > 50
    rel_gt = inv(gt_pose(gt, frames[0].timestamp)) @ gt_pose(gt, frames[3].timestamp)
    dt, dr = rel_error(rel_gt, poses[3])
    assert dt < 0.03 and dr < 2.0, (dt, dr)


@pytest.mark.data
@pytest.mark.parametrize("which", ["tum", "kitti"])
def test_detect_then_compute_equals_detect_and_compute(which):
    """orb_features with a grid detects, keeps the strongest per cell and computes descriptors only
    for those: points, descriptors and responses equal detectAndCompute on all points (as before)
    then the same selection, on a real TUM frame (4x4 grid) and a KITTI frame (kitti preset's grid)."""
    import cv2

    from rgbdslam.config import load_config
    from rgbdslam.frontend.features import _bucket, _orb, orb_features
    from tests.conftest import DATA, TUM_DESK9, need

    if which == "tum":
        fc = dataclasses.replace(load_config(None).features, grid_rows=4, grid_cols=4)  # default: no grid
        img = cv2.imread(str(sorted((need(TUM_DESK9) / "rgb").glob("*.png"))[0]), cv2.IMREAD_GRAYSCALE)
    else:
        fc = load_config("kitti").features
        img = cv2.imread(str(need(DATA / "kitti" / "odometry_06_head51") / "sequences" / "06" / "image_0" /
                             "000010.png"), cv2.IMREAD_GRAYSCALE)
    assert fc.grid_rows * fc.grid_cols > 1
    uv, desc, resp, octave = orb_features(img, fc)
    kps, ref = _orb(fc, 2 * fc.n_features).detectAndCompute(img, None)
    ref_uv = cv2.KeyPoint_convert(kps).astype(np.float64)
    ref_resp = np.array([k.response for k in kps], dtype=np.float32)
    keep = _bucket(ref_uv, ref_resp, fc, img.shape)
    assert len(uv) > 500
    assert np.array_equal(uv, ref_uv[keep]) and np.array_equal(resp, ref_resp[keep])
    assert np.array_equal(desc, ref[keep])
    assert np.array_equal(octave, np.array([k.octave for k in kps])[keep])


def test_depth_edges_by_hand():
    """A 2 m wall with a 1 m box in its left half, a hole at (7, 7): radius 1, jump 5 %."""
    from rgbdslam.frontend.features import depth_edges

    d = np.full((10, 10), 2.0)
    d[:, :4] = 1.0  # columns 0-3 near, 4-9 far: the outline runs between columns 3 and 4
    d[7, 7] = 0.0
    d[1, 8] = 2.09  # 4.5 % of 2 m: noise, not an edge
    u = np.array([1, 3, 4, 6, 7, 8, 9, 7, 0])
    v = np.array([1, 1, 1, 1, 6, 7, 0, 7, 9])
    edge = depth_edges(d, u, v, radius=1, jump=0.05)
    # (1,1) inside the box; (3,1) and (4,1) on either side of the outline; (6,1) on the wall;
    # (7,6) and (8,7) next to the hole; (9,0) at the corner beside the 2.09 pixel (|0.09| <= 0.1);
    # (7,7) is the hole itself (no depth: not flagged); (0,9) at the border (clipped window, box only)
    np.testing.assert_array_equal(edge, [False, True, True, False, True, True, False, False, False])
    # radius 2 reaches the outline from (6,1)? no (columns 4-8); from column 5 yes
    assert depth_edges(d, np.array([5, 6]), np.array([1, 1]), radius=2, jump=0.05).tolist() == [True, False]
    # a larger jump tolerance keeps the 2.09 step smooth and a 1 m step an edge (50 % of 2 m > 40 %)
    assert depth_edges(d, np.array([4]), np.array([4]), radius=1, jump=0.4).tolist() == [True]
    assert depth_edges(d, np.array([4]), np.array([4]), radius=1, jump=1.01).tolist() == [False]


def test_depth_edge_radius_grows_with_the_pyramid_level():
    """One radius per key point: ceil(r * scale**octave); (6,1) is 2 columns from the outline."""
    from rgbdslam.frontend.features import FrameFeatures, depth_edges, edge_radii

    d = np.full((10, 10), 2.0)
    d[:, :4] = 1.0
    feats = FrameFeatures(0, 0.0, np.zeros((4, 2)), np.zeros((4, 32), np.uint8), np.zeros((4, 3)),
                          np.ones(4, bool), 4, octave=np.array([0, 1, 4, 7], np.int8), pyramid_scale=1.2)
    # 1 * 1.2**k rounded up: 1, 2 (1.2), 3 (2.07), 4 (3.58)
    assert edge_radii(feats, 1).tolist() == [1, 2, 3, 4]
    assert edge_radii(feats, 2).tolist() == [2, 3, 5, 8]
    u, v = np.array([6, 6, 6, 6]), np.array([1, 1, 1, 1])
    assert depth_edges(d, u, v, np.array([1, 2, 3, 4]), 0.05).tolist() == [False, False, True, True]
    assert depth_edges(d, u, v, 3, 0.05).tolist() == [True] * 4  # one radius for all, as before


@pytest.mark.data
def test_depth_edge_points_keep_their_depth_but_not_their_landmarks(desk):
    _, frames = desk
    cfg = Config()
    cfg.matching.depth_edge_radius = 0
    plain = extract_features(frames[0], cfg.features, cfg.matching)
    assert not plain.edge.any()
    cfg.matching.depth_edge_radius = 2
    f = extract_features(frames[0], cfg.features, cfg.matching)
    assert 0 < f.edge.sum() < 0.5 * plain.valid.sum()  # a real desk frame has outlines, most points are not on them
    np.testing.assert_array_equal(f.valid, plain.valid)  # matching and the inlier choice keep them
    np.testing.assert_array_equal(f.map_valid, plain.valid & ~f.edge)  # the landmark map does not
