"""DIF depth filter (docs/references.md §3) on hand-made depth images."""

from __future__ import annotations

import numpy as np
import pytest

from rgbdslam.config import DepthFilterConfig
from rgbdslam.frontend.depth_filter import DepthFilter
from rgbdslam.geometry.camera import Camera

CAM = Camera(100.0, 100.0, 31.5, 23.5, 64, 48)


def make(**kw) -> DepthFilter:
    cfg = DepthFilterConfig(enabled=True, window=0, spatial_radius=1, tolerance_a=0.01, tolerance_b=0.0035,
                            min_support=3, min_depth=0.3, max_depth=5.0)
    for k, v in kw.items():
        setattr(cfg, k, v)
    return DepthFilter(cfg, CAM)


def plane(z: float = 2.0) -> np.ndarray:
    return np.full((48, 64), z, np.float32)


def test_agreeing_values_are_averaged_exactly():
    d = plane()
    d[10, 10] = 2.018  # within tol(2) = 0.01 + 0.0035 * 4 = 0.024
    out = make()(d, np.eye(4))
    # the pixel itself: own value + its 8 agreeing neighbours
    assert out[10, 10] == pytest.approx((2.018 + 8 * 2.0) / 9, abs=1e-6)
    # a neighbour: itself, 7 plane neighbours and the 2.018 pixel
    assert out[10, 11] == pytest.approx((2.018 + 8 * 2.0) / 9, abs=1e-6)
    assert out[10, 12] == pytest.approx(2.0, abs=1e-6)
    # a corner has only 3 neighbours (zero padding never agrees) and is kept
    assert out[0, 0] == pytest.approx(2.0, abs=1e-6)


def test_outlier_pixel_removed_without_contaminating_neighbours():
    d = plane()
    d[20, 30] = 2.5
    out = make()(d, np.eye(4))
    assert out[20, 30] == 0.0
    assert np.allclose(out[19:22, 29:32][np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], bool)], 2.0)


def test_flying_pixels_at_a_depth_edge_removed():
    d = plane(3.0)
    d[:, :30] = 1.0
    d[:, 30] = 2.0  # a column of "flying" pixels between foreground and background
    out = make()(d, np.eye(4))
    assert np.all(out[:, 30] == 0.0)
    assert np.allclose(out[:, :30], 1.0) and np.allclose(out[:, 31:], 3.0)


def test_zeros_stay_zero_and_range_is_enforced():
    d = plane()
    d[5:8, 5:8] = 0.0
    d[40, 40] = 7.0  # beyond max_depth
    d[30:33, 50:53] = 0.2  # below min_depth (a 3x3 block that would otherwise support itself)
    out = make()(d, np.eye(4))
    assert np.all(out[5:8, 5:8] == 0.0)
    assert out[40, 40] == 0.0 and np.all(out[30:33, 50:53] == 0.0)
    assert np.allclose(out[5:8, 9], 2.0)  # next to the hole: still supported, unchanged
    assert np.count_nonzero(out) == d.size - 9 - 1 - 9


@pytest.mark.parametrize("t", [(0.0, 0.0, 0.1), (0.05, -0.03, 0.0)])
def test_warp_of_a_plane_under_pure_translation(t):
    f = make()
    old = plane(2.0)
    pose_cur = np.eye(4)
    pose_cur[:3, 3] = t  # camera-to-world: the camera moved by t
    cur = plane(2.0 - t[2])
    warped = f.warp(old, np.linalg.inv(pose_cur), cur)
    # pixels whose ray hits the old image: the old plane seen from the new pose
    inside = warped > 0
    assert inside.mean() > 0.7
    assert np.allclose(warped[inside], 2.0 - t[2], atol=1e-5)
    # the outside border is where the old image had no pixel
    if t[0] > 0:
        assert np.all(warped[:, -1] == 0)


def test_temporal_averaging_with_known_pose():
    f = make(window=1, spatial_radius=0, min_support=1)
    pose0 = np.eye(4)
    first = f(plane(2.0), pose0)
    assert np.all(first == 2.0)  # nothing to verify against yet: kept as measured
    f.history.clear()
    f.history.append((plane(2.0), pose0))  # a filtered previous frame
    pose1 = np.eye(4)
    pose1[:3, 3] = (0.0, 0.0, 0.1)
    cur = plane(1.91)  # measured 1 cm too far; the warped old frame says 1.90
    cur[0, 0] = 1.5  # disagrees with the warped old depth: no support, removed
    out = f(cur, pose1)
    inside = out > 0
    assert inside.mean() > 0.9
    assert np.allclose(out[inside], (1.91 + 1.90) / 2, atol=1e-5)
    assert out[0, 0] == 0.0
    assert len(f.history) == 1 and f.history[0][0] is out


def test_impossible_min_support_is_a_config_error():
    from rgbdslam.errors import ConfigError

    with pytest.raises(ConfigError, match="min_support"):
        make(window=2, spatial_radius=0, min_support=3)


@pytest.mark.data
def test_real_tum_frames_keep_most_depth_and_never_invent_any():
    from tests.conftest import TUM_DESK9, need
    from rgbdslam.config import Config
    from rgbdslam.datasets import open_sequence

    root = need(TUM_DESK9)
    cfg = Config()
    seq = open_sequence(root, cfg.dataset)
    gt = seq.groundtruth()
    f = DepthFilter(DepthFilterConfig(enabled=True), seq.camera)
    for i in range(3):
        frame = seq.load(i)
        pose = gt.poses[int(np.argmin(np.abs(gt.timestamps - frame.timestamp)))]
        out = f(frame.depth, pose)
        raw = frame.depth
        in_range = (raw >= 0.3) & (raw <= 5.0)
        assert np.all(out[~in_range] == 0)  # zero stays zero, range enforced
        kept = np.count_nonzero(out) / np.count_nonzero(in_range)
        assert kept > 0.95  # only isolated / edge pixels go
        both = out > 0
        tol = 0.01 + 0.0035 * raw[both] ** 2
        assert np.all(np.abs(out[both] - raw[both]) <= tol + 1e-6)  # averages of agreeing samples only
