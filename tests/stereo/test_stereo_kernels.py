"""The sparse stereo kernels (row matching, sub-pixel refinement) against the plain NumPy expressions they
replace, on real KITTI 06 pairs: equal bit for bit, so the poses of a stereo run do not move
(docs/speed.md "The stereo reader")."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import DATA, need
from rgbdslam.stereo.depth import match_rows, patch_sum, refine_disparity

KITTI = DATA / "kitti" / "odometry_06_head51"


def reference_match_rows(uv_l, desc_l, uv_r, desc_r, sc):
    """Row matching one left point at a time, as docs/stereo.md states it: the right points within
    ``row_tolerance`` rows at a disparity in range, in the stable order of their rows; the best distance
    (the first listed among equals) must be within ``max_hamming`` and below ``ratio`` x the second best
    (no second: always); then each right point keeps its best left point (the smaller index among equals)."""
    rank = np.empty(len(uv_r), np.int64)
    rank[np.argsort(uv_r[:, 1], kind="stable")] = np.arange(len(uv_r))
    bits = np.unpackbits(desc_r, axis=1)
    chosen: dict[int, tuple[int, int]] = {}  # right point -> (left point, distance)
    for a in range(len(uv_l)):
        d = uv_l[a, 0] - uv_r[:, 0]
        js = np.flatnonzero((np.abs(uv_l[a, 1] - uv_r[:, 1]) <= sc.row_tolerance) & (d >= sc.min_disparity)
                            & (d <= sc.max_disparity))
        if len(js) == 0:
            continue
        js = js[np.argsort(rank[js])]
        ham = (bits[js] != np.unpackbits(desc_l[a])).sum(axis=1)
        k = int(np.argmin(ham))
        second = np.delete(ham, k).min() if len(js) > 1 else 1 << 20
        if ham[k] <= sc.max_hamming and ham[k] < sc.ratio * second:
            b = int(js[k])
            if b not in chosen or ham[k] < chosen[b][1]:
                chosen[b] = (a, int(ham[k]))
    right = sorted(chosen)
    return np.array([chosen[b][0] for b in right], int), np.array(right, int)


def reference_sad(left, right, ul, vl, ur0, r, s, subpixel):
    """(M, 2s+1) SAD costs by fancy indexing and one NumPy sum over both patch axes."""
    n = 2 * r + 1
    dy = np.arange(-r, r + 1)
    rows = vl[:, None, None] + dy[None, :, None]
    L = left[rows, ul[:, None, None] + dy[None, None, :]].astype(np.float32)
    strip = right[rows, ur0[:, None, None] + np.arange(-r - s, r + s + 1)[None, None, :]].astype(np.float32)
    R = np.lib.stride_tricks.sliding_window_view(strip, n, axis=2)
    if subpixel == "zsad_v":
        L -= L.mean(axis=(1, 2), keepdims=True)
        col = np.cumsum(np.pad(strip.sum(axis=1), ((0, 0), (1, 0))), axis=1)
        R = R - ((col[:, n:] - col[:, :-n]) / np.float32(n * n))[:, None, :, None]
    else:
        L -= L[:, r:r + 1, r:r + 1]
        R = R - strip[:, r:r + 1, r:r + 2 * s + 1, None]
    return np.abs(R - L[:, :, None, :]).sum(axis=(1, 3))


def reference_refine(left, right, ul, vl, ur, r, s, subpixel):
    h, w = left.shape
    ul, vl, ur0 = ul.astype(np.int64), vl.astype(np.int64), np.rint(ur).astype(np.int64)
    ok = (vl - r >= 0) & (vl + r < h) & (ul - r >= 0) & (ul + r < w) & (ur0 - r - s >= 0) & (ur0 + r + s < w)
    idx = np.flatnonzero(ok)
    sad = reference_sad(left, right, ul[idx], vl[idx], ur0[idx], r, s, subpixel).astype(np.float64)
    best = sad.argmin(axis=1)
    b = np.clip(best, 1, 2 * s - 1)
    k = np.arange(len(idx))
    c1, c2, c3 = sad[k, b - 1], sad[k, b], sad[k, b + 1]
    den = 2.0 * (np.maximum(c1, c3) - c2) if subpixel == "zsad_v" else 2.0 * (c1 + c3 - 2.0 * c2)
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(den > 0, (c1 - c3) / den, 0.0)
    out = np.full(len(ul), np.nan)
    out[idx] = ur0[idx] + best - s + delta
    good = np.zeros(len(ul), bool)
    good[idx] = (best > 0) & (best < 2 * s) & (np.abs(delta) <= 1.0)
    return out, good


@pytest.fixture(scope="module")
def kitti_pairs():
    """Three KITTI 06 pairs with the kitti preset's left key points and the right image's ORB."""
    import dataclasses

    from rgbdslam.datasets import open_sequence
    from rgbdslam.frontend.features import detect, orb_features

    cfg = load_kitti()
    seq = open_sequence(need(KITTI), cfg)
    fc, sc = cfg.features, cfg.stereo
    fc_right = dataclasses.replace(fc, n_features=sc.right_features * fc.n_features, grid_rows=1, grid_cols=1)
    out = []
    for i in (0, 25, 50):
        left, right = seq.rectified_pair(i)
        det = detect(left, fc)
        uv_r, desc_r = orb_features(right, fc_right, attributes=False)[:2]
        out.append((left, right, det.uv_raw, det.desc, uv_r, desc_r))
    return sc, out


def load_kitti():
    from rgbdslam.config import load_config

    return load_config("kitti", [])


def test_row_matching_equals_the_sorted_reference_on_kitti(kitti_pairs):
    sc, pairs = kitti_pairs
    for left, right, uv_l, desc_l, uv_r, desc_r in pairs:
        il, ir = match_rows(uv_l, desc_l, uv_r, desc_r, sc)
        ref = reference_match_rows(uv_l, desc_l, uv_r, desc_r, sc)
        assert len(il) > 200  # real matches, not an empty agreement
        assert np.array_equal(il, ref[0]) and np.array_equal(ir, ref[1])


def test_refinement_equals_the_plain_numpy_expression_on_kitti(kitti_pairs):
    sc, pairs = kitti_pairs
    for left, right, uv_l, desc_l, uv_r, desc_r in pairs:
        il, ir = match_rows(uv_l, desc_l, uv_r, desc_r, sc)
        u0, v0 = np.rint(uv_l[il, 0]), np.rint(uv_l[il, 1])
        guess = uv_r[ir, 0] + (u0 - uv_l[il, 0])
        # the preset's patch (11x11, 8 to 15 columns: eight running sums), a short one (< 8) and a long one
        for r, s in ((sc.patch_radius, sc.search_radius), (2, 3), (9, 4)):
            for method in ("zsad_v", "centre_parabola"):
                ur, ok = refine_disparity(left, right, u0, v0, guess, r, s, method)
                ur_ref, ok_ref = reference_refine(left, right, u0, v0, guess, r, s, method)
                assert ok.sum() > 100
                assert np.array_equal(ok, ok_ref)
                assert np.array_equal(ur, ur_ref, equal_nan=True)


def test_patch_sum_is_numpys_sum_bit_for_bit():
    """Every stack length, through NumPy's 8-term blocks and its split above 128 terms, with values of very
    different size (where the order of additions shows in the last bits)."""
    rng = np.random.default_rng(0)
    for k in [*range(1, 40), 127, 128, 129, 136, 200, 300]:
        X = (rng.normal(size=(k, 6, 5)) * 10.0 ** rng.integers(-3, 4, size=(k, 6, 5))).astype(np.float32)
        want = np.ascontiguousarray(np.moveaxis(X, 0, -1)).sum(axis=-1)
        assert np.array_equal(patch_sum(X), want), k
    # and it does depend on the order: a plain running sum differs somewhere
    X = (rng.normal(size=(11, 50, 50)) * 10.0 ** rng.integers(-3, 4, size=(11, 50, 50))).astype(np.float32)
    running = X[0].copy()
    for x in X[1:]:
        running += x
    assert not np.array_equal(running, patch_sum(X))


@pytest.mark.data
def test_both_images_key_points_at_once_equal_one_after_the_other_on_kitti(kitti_pairs):
    """``detect_pair`` finds the left image's detections and the right image's key points in two threads
    (as ORB-SLAM extracts a pair): the same values as the sequential calls, and a frame read through it
    holds the same depth and key points as the pair prepared step by step."""
    from rgbdslam.frontend.features import detect
    from rgbdslam.stereo.depth import detect_pair, right_key_points, sparse_depth

    sc, pairs = kitti_pairs
    fc = load_kitti().features
    for left, right, uv_l, desc_l, uv_r, desc_r in pairs:
        det, (uv_r2, desc_r2) = detect_pair(left, right, fc, sc)
        ref = detect(left, fc)
        assert np.array_equal(det.uv_raw, ref.uv_raw) and np.array_equal(det.desc, ref.desc)
        assert np.array_equal(det.octave, ref.octave) and det.n_detected == ref.n_detected
        assert np.array_equal(uv_r2, uv_r) and np.array_equal(desc_r2, desc_r)
        r = right_key_points(right, fc, sc)
        assert np.array_equal(r[0], uv_r) and np.array_equal(r[1], desc_r)
    from rgbdslam.datasets import open_sequence

    cfg = load_kitti()
    seq = open_sequence(need(KITTI), cfg)
    seq.configure(cfg)
    frame = seq.load(25)
    left, right = seq.rectified_pair(25)
    ref = detect(left, cfg.features)
    depth = sparse_depth(left, right, seq.rig, ref.uv_raw, ref.desc, cfg.stereo, cfg.features)
    assert np.array_equal(frame.depth, depth) and np.count_nonzero(depth) > 300
    assert np.array_equal(frame.detections.desc, ref.desc)
