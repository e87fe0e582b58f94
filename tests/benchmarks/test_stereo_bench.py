"""benchmarks/stereo.py: the ORB-SLAM3 stereo settings written for a KITTI-layout folder."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from benchmarks import common
from benchmarks.stereo import orb_stereo_settings


def test_orb_stereo_settings_take_the_folders_calibration_and_size(tmp_path):
    if not common.orb_settings("kitti").exists():
        pytest.skip(f"the peer's settings are not here ({common.orb_settings('kitti')})")
    seq = tmp_path / "sequences" / "00"
    (seq / "image_0").mkdir(parents=True)
    cv2.imwrite(str(seq / "image_0" / "000000.png"), np.zeros((376, 1241), np.uint8))
    # fx 718.856, cx 620, cy 187.5, B = 388.18224 / 718.856 = 0.54 m (the synthetic highway's rig)
    (seq / "calib.txt").write_text("P0: 718.856 0 620 0 0 718.856 187.5 0 0 0 1 0\n"
                                   "P1: 718.856 0 620 -388.18224 0 718.856 187.5 0 0 0 1 0\n")
    text = orb_stereo_settings(seq, tmp_path / "orb.yaml").read_text()
    for cam in ("Camera1", "Camera2"):
        assert f"{cam}.fx: 718.856000\n{cam}.fy: 718.856000\n{cam}.cx: 620.000000\n{cam}.cy: 187.500000\n" in text
    assert "Camera.width: 1241\n" in text and "Camera.height: 376\n" in text
    assert "Stereo.b: 0.540000\n" in text and "data: [1.0, 0.0, 0.0, 0.540000," in text
    assert "707.0912" not in text and "0.53715" not in text  # nothing of KITTI 04-12's camera is left
    assert "Stereo.ThDepth: 40.0" in text and "ORBextractor.nFeatures: 2000" in text  # the rest is KITTI 04-12's


def test_stereo_frames_step_errors_by_hand():
    """benchmarks/stereo_frames.py: each frame's own step error in the camera's axes, and the SE(3) ATE."""
    from benchmarks.stereo_frames import ate_se3, sim3_scale, step_errors
    from rgbdslam.geometry.se3 import make_pose
    from scipy.spatial.transform import Rotation

    # ground truth: 3 m forward (z) per frame; the estimate's second step is 0.1 m short and turned 1 deg about y
    G = np.stack([make_pose(np.eye(3), [0.0, 0.0, 3.0 * k]) for k in range(3)])
    turn = Rotation.from_euler("y", 1.0, degrees=True).as_matrix()
    E = np.stack([G[0], G[1], G[1] @ make_pose(turn, [0.0, 0.0, 2.9])])
    err = step_errors(E, G)
    assert np.allclose(err[:2], 0.0)
    assert np.allclose(err[2, :3], [0.0, 0.0, -0.1]) and err[2, 3] == pytest.approx(0.1)  # G_step^-1 E_step
    assert err[2, 4] == pytest.approx(1.0) and np.allclose(err[2, 5:], [0.0, 1.0, 0.0])  # about y, as turned
    # a rigidly moved copy has no ATE; positions on a unit square's corners scaled by 1.1 (a scale error, which a
    # rigid alignment cannot take out; by symmetry it aligns with the identity) leave 0.1 m at every position
    T = make_pose(turn, [5.0, -2.0, 1.0])
    assert ate_se3(np.stack([T @ g for g in G]), G) == pytest.approx(0.0, abs=1e-9)
    S = np.stack([make_pose(np.eye(3), p) for p in ([1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0])])
    S2 = S.copy()
    S2[:, :3, 3] *= 1.1
    assert ate_se3(S2, S) == pytest.approx(0.1)
    assert sim3_scale(S2, S) == pytest.approx(1.0 / 1.1) and sim3_scale(S, S) == pytest.approx(1.0)  # < 1: too long


@pytest.mark.parametrize("delta, k", [(0.2, 0.0), (0.0, 0.01), (-0.15, 0.005)])
def test_disparity_error_fit_recovers_an_offset_and_a_scale(delta, k):
    """Points seen by a KITTI-like rig (fx B = 388.18 px m) at 5-80 m, moved by a known motion: frame i's
    stereo points come from disparities d = (1 + k) fx B / z + delta, the later frame's bearings are exact;
    the fit returns (delta, k), and the one-parameter fits are the exact ones when the other is nil."""
    from benchmarks.stereo_scale import disparity_error_fit
    from scipy.spatial.transform import Rotation

    from rgbdslam.geometry.se3 import make_pose

    rng = np.random.default_rng(3)
    fb = 388.18224
    pairs = []
    for i in range(4):
        z = rng.uniform(5.0, 80.0, 300)
        P = np.column_stack([rng.uniform(-0.8, 0.8, 300) * z, rng.uniform(-0.25, 0.25, 300) * z, z])
        T = make_pose(Rotation.from_rotvec([0.01 * i, 0.02, -0.01]).as_matrix(), np.array([0.3, -0.05, -1.2 - 0.5 * i]))
        Q = P @ T[:3, :3].T + T[:3, 3]
        d = (1.0 + k) * fb / z + delta
        pairs.append((T, P / z[:, None] * (fb / d)[:, None], Q))
    f = disparity_error_fit(pairs, fb)
    assert f["n"] == 1200
    assert f["offset_scale"][0] == pytest.approx(delta, abs=1e-6)
    assert f["offset_scale"][1] == pytest.approx(k, abs=1e-7)
    if k == 0.0:
        assert f["offset"][0] == pytest.approx(delta, abs=1e-6)
    if delta == 0.0:
        assert f["scale"][0] == pytest.approx(k, abs=1e-7)
