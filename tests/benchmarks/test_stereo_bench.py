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
