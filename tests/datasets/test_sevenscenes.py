"""The 7-Scenes reader on the data set's own files (redkitchen frames 0-299)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.conftest import DATA, REPO, cli, need
from rgbdslam.config import DatasetConfig, load_config
from rgbdslam.datasets import open_sequence
from rgbdslam.datasets.sevenscenes import SevenScenesSequence
from rgbdslam.pipeline import run_sequence

pytestmark = pytest.mark.data  # the 7-Scenes frames


SEVEN = DATA / "7scenes" / "frames_0000_0299"
REPO_CAMERA = REPO / "configs" / "7scenes_camera.yaml"


def test_reader_on_the_real_files():
    seq = open_sequence(need(SEVEN))
    assert isinstance(seq, SevenScenesSequence) and len(seq) == 300
    assert seq.timestamps[:3].tolist() == [0.0, 1 / 30, 2 / 30]
    c = seq.camera
    assert (c.fx, c.fy, c.cx, c.cy) == (585.0, 585.0, 320.0, 240.0) and seq.depth_scale == 1000
    f = seq.load(33)
    raw = cv2.imread(str(SEVEN / "frame-000033.depth.png"), cv2.IMREAD_UNCHANGED)
    assert (raw == 65535).sum() == 46  # the data set's "no measurement" (frames 33, 163, 233, 234 have it)
    assert np.array_equal(f.depth == 0, (raw == 0) | (raw == 65535))
    ok = (raw > 0) & (raw < 65535)
    np.testing.assert_allclose(f.depth[ok], raw[ok] / 1000.0, rtol=1e-6)
    gt = seq.groundtruth()
    assert len(gt) == 300
    T = np.loadtxt(SEVEN / "frame-000123.pose.txt")
    np.testing.assert_allclose(gt.poses[123], T)
    # with depth re-projected into colour, the ground truth moves to the colour camera too
    reg = open_sequence(SEVEN, DatasetConfig(camera_file=str(REPO_CAMERA)))
    assert reg.registration is not None and reg.camera.fx == 530
    np.testing.assert_allclose(reg.groundtruth().poses[123], T @ np.linalg.inv(reg.camera_setup.depth_to_color))


@pytest.mark.slow
def test_tracks_the_first_90_frames(tmp_path):
    """Accuracy on real frames, depth as recorded and re-projected (docs/benchmarks.md has 0-299)."""
    cfg = load_config(None, ["dataset.max_frames=90", "mapping.enabled=false", "output.plots=false"])
    s = run_sequence(need(SEVEN), tmp_path / "raw", cfg, progress=False)
    assert s["tracked"] == 90 and s["evaluation"]["ate"]["rmse"] < 0.03, s["evaluation"]["ate"]
    # evaluate takes the sequence folder as ground truth
    res = cli(["evaluate", SEVEN, tmp_path / "raw" / "trajectory.tum", "--no-plots"])
    assert res.exit_code == 0 and "ATE" in res.output, res.output
