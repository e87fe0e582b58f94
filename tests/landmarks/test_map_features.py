"""landmarks.n_features: the landmark map gets more key points than the registration (issue 17).

Frames are detected with ``landmarks.n_features`` ORB key points; the registration, loop closure and
keyframes keep the strongest ``features.n_features`` of them per pyramid level (ORB's own budget),
the landmark map matches and makes landmarks from all of them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from rgbdslam.config import load_config
from rgbdslam.frontend.features import detect, extract_features, orb_level_budget, strongest, subset


def test_orb_level_budget_by_hand():
    # 1000 over 8 levels at 1.2: f = 1/1.2, first level 1000 (1 - f) / (1 - f^8) = 217.17 -> 217,
    # then x f each: 180.98 -> 181, 150.82 -> 151, 125.68 -> 126, 104.73 -> 105, 87.28 -> 87,
    # 72.73 -> 73; the top level the rest: 1000 - 940 = 60
    assert orb_level_budget(1000, 1.2, 8).tolist() == [217, 181, 151, 126, 105, 87, 73, 60]
    # two levels at 2: 30 (1 - 1/2) / (1 - 1/4) = 20, the rest 10
    assert orb_level_budget(30, 2.0, 2).tolist() == [20, 10]


def _features(n: int, octave: list[int], response: list[float]):
    from rgbdslam.frontend.features import FrameFeatures

    uv = np.stack([np.arange(n, dtype=float), np.zeros(n)], axis=1)
    return FrameFeatures(index=0, timestamp=0.0, uv=uv, desc=np.arange(n * 32, dtype=np.uint8).reshape(n, 32),
                         pts=np.c_[uv, np.ones(n)], valid=np.ones(n, bool), n_detected=n, uv_raw=uv.copy(),
                         response=np.array(response, np.float32), octave=np.array(octave, np.int8),
                         edge=np.zeros(n, bool))


def test_strongest_keeps_each_levels_budget_by_response():
    fc = replace(load_config(None, []).features, n_features=3, scale_factor=2.0, n_levels=2)  # budget [2, 1]
    f = _features(6, [0, 0, 0, 1, 1, 0], [5.0, 9.0, 1.0, 2.0, 3.0, 7.0])
    idx = strongest(f, fc)
    assert idx.tolist() == [1, 4, 5]  # level 0: responses 9 and 7; level 1: 3
    s = subset(f, idx)
    assert np.array_equal(s.desc, f.desc[[1, 4, 5]]) and np.array_equal(s.uv, f.uv[[1, 4, 5]])
    assert np.array_equal(s.octave, [0, 1, 0]) and s.edge.tolist() == [False] * 3 and s.index == f.index
    assert s._tree is None


@pytest.mark.data
def test_strongest_of_more_key_points_is_orbs_own_choice_on_a_real_frame(desk9):
    from rgbdslam.datasets import open_sequence

    cfg = load_config(None, [])
    frame = open_sequence(desk9, cfg)[0]
    fc = cfg.features
    own = detect(frame.rgb, fc)  # ORB asked for 1000
    full = extract_features(frame, replace(fc, n_features=2000), cfg.matching)
    idx = strongest(full, fc)
    # OpenCV's ORB fills every level's budget on this frame; the subset has the same counts
    assert np.bincount(own.octave, minlength=8).tolist() == orb_level_budget(1000, 1.2, 8).tolist()
    assert np.bincount(full.octave[idx], minlength=8).tolist() == orb_level_budget(1000, 1.2, 8).tolist()
    assert len(full.uv) > 1800  # (some upper levels have fewer corners than their budget of 2000)
    # and nearly the same key points (ORB pre-selects by FAST score before the Harris response)
    a = {tuple(p) for p in np.round(own.uv_raw, 2)}
    b = {tuple(p) for p in np.round(full.uv_raw[idx], 2)}
    assert len(a & b) >= 0.95 * len(a)


@pytest.mark.data
def test_landmark_map_gets_every_key_point_the_registration_the_strongest(desk9):
    from rgbdslam.datasets import open_sequence
    from rgbdslam.slam import SLAM

    runs = {}
    for n in (0, 2000):
        cfg = load_config(None, ["landmarks.enabled=true", f"landmarks.n_features={n}"])
        seq = open_sequence(desk9, cfg)
        slam = SLAM(cfg, seq.camera)
        res = [slam.track(seq[i]) for i in range(len(seq))]
        runs[n] = (slam, res)
    slam0, res0 = runs[0]
    slam2, res2 = runs[2000]
    for r in res2:
        assert r.map_features is not None and len(r.map_features.uv) > 1800
        assert len(r.features.uv) <= 1000
        # the registration's key points are the full set's strongest, row for row
        idx = strongest(r.map_features, slam2.cfg.features)
        assert np.array_equal(r.features.desc, r.map_features.desc[idx])
        assert np.array_equal(r.features.uv, r.map_features.uv[idx])
    assert all(r.map_features is None for r in res0)
    # the map made landmarks from all of them: about twice as many, and matched more per frame
    s0, s2 = slam0.landmarks.summary(), slam2.landmarks.summary()
    assert s2["made"] > 1.6 * s0["made"]
    assert s2["median_inliers"] > 1.5 * s0["median_inliers"]


@pytest.mark.data
def test_key_points_a_reader_made_itself_are_kept(desk9):
    """Sparse stereo finds the key points in the reader and has depth at theirs only: a frame that
    carries detections made with the registration's budget is not re-detected for the map."""
    from rgbdslam.datasets import open_sequence
    from rgbdslam.frontend.features import with_detections
    from rgbdslam.frontend.odometry import build_frontend

    cfg = load_config(None, ["landmarks.enabled=true", "landmarks.n_features=2000"])
    seq = open_sequence(desk9, cfg)
    fe = build_frontend(cfg, seq.camera)
    own = with_detections(seq[0], cfg.features)  # as a sparse-stereo reader attaches them
    r = fe.track(own)
    assert r.map_features is None and len(r.features.uv) == len(own.detections.uv_raw) == 1000
    r = fe.track(seq[1])  # no detections of its own: the map gets more
    assert r.map_features is not None and len(r.map_features.uv) > 1800 and len(r.features.uv) == 1000
    assert not seq.own_key_points


def test_sparse_stereo_reader_owns_its_key_points(tmp_path):
    from rgbdslam.datasets import open_sequence
    from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence

    generate_stereo_sequence(tmp_path / "e", 0.12, "euroc", frames=2, motion="loop", noise=False, seed=1)
    assert open_sequence(tmp_path / "e", load_config(None, ["stereo.depth=sparse"])).own_key_points
    assert not open_sequence(tmp_path / "e", load_config(None, ["stereo.depth=sgbm"])).own_key_points
