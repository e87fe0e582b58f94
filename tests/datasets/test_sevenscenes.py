"""The 7-Scenes reader on the data set's own files (redkitchen frames 0-299)."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from tests.conftest import DATA, cli, need
from rgbdslam.config import DatasetConfig, load_config
from rgbdslam.datasets import open_sequence
from rgbdslam.datasets.sevenscenes import SevenScenesSequence
from rgbdslam.pipeline import run_sequence

pytestmark = pytest.mark.data  # the 7-Scenes frames


SEVEN = DATA / "7scenes" / "frames_0000_0299"
AS_RECORDED = "fx: 585.0\nfy: 585.0\ncx: 320.0\ncy: 240.0\nsize: [640, 480]\ndepth_scale: 1000\n"


def test_reader_on_the_real_files(tmp_path):
    # the published intrinsics (the depth camera's) used for colour too, depth as recorded
    (tmp_path / "recorded.yaml").write_text(AS_RECORDED)
    seq = open_sequence(need(SEVEN), DatasetConfig(camera_file=str(tmp_path / "recorded.yaml")))
    assert isinstance(seq, SevenScenesSequence) and len(seq) == 300
    assert seq.timestamps[:3].tolist() == [0.0, 1 / 30, 2 / 30]
    c = seq.camera
    assert (c.fx, c.fy, c.cx, c.cy) == (585.0, 585.0, 320.0, 240.0) and seq.depth_scale == 1000
    assert seq.registration is None
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
    reg = open_sequence(SEVEN)
    assert reg.registration is not None and reg.camera.fx == 530
    np.testing.assert_allclose(reg.groundtruth().poses[123], T @ np.linalg.inv(reg.camera_setup.depth_to_color))


def test_the_shipped_camera_is_the_default_and_a_camera_file_wins(tmp_path):
    """Without --camera the 7-Scenes camera shipped in the package (colour fx 530, depth
    re-projected from the depth camera 585) is used, and `info` says where it came from;
    `--camera 7scenes` names it; a camera file of the user's wins."""
    seq = open_sequence(need(SEVEN))
    setup = seq.camera_setup
    assert (seq.camera.name, seq.camera.fx, seq.camera.fy) == ("7scenes", 530.0, 530.0)
    assert (setup.depth_camera.fx, setup.depth_camera.cx) == (585.0, 320.0) and seq.registration is not None
    assert not seq.camera.depth_registered  # two Kinect cameras: the landmark map's pose fits 3-D points
    assert setup.source == "the 7-Scenes camera shipped with rgbdslam (rgbdslam/cameras/7scenes.yaml)"
    res = cli(["info", SEVEN])
    assert res.exit_code == 0 and "(from the 7-Scenes camera shipped with rgbdslam" in res.output, res.output
    named = open_sequence(SEVEN, DatasetConfig(camera_file="7scenes"))
    assert named.camera.fx == 530.0 and named.camera_setup.source == "--camera 7scenes, shipped with rgbdslam"
    (tmp_path / "mine.yaml").write_text(AS_RECORDED.replace("585.0", "590.0"))
    res = cli(["info", SEVEN, "--camera", tmp_path / "mine.yaml"])
    assert res.exit_code == 0 and "fx 590.0" in res.output and f"(from --camera {tmp_path / 'mine.yaml'})" in res.output
    # a folder whose camera-intrinsics.txt says another depth camera: that one is re-projected from
    other = tmp_path / "seq"
    other.mkdir()
    for name in ("frame-000000.color.jpg", "frame-000000.depth.png"):
        shutil.copy(SEVEN / name, other / name)
    (other / "camera-intrinsics.txt").write_text("580 0 321\n0 581 239\n0 0 1\n")
    s = open_sequence(other).camera_setup
    assert (s.depth_camera.fx, s.depth_camera.fy, s.camera.fx) == (580.0, 581.0, 530.0)
    assert s.source.endswith("depth camera from camera-intrinsics.txt")


@pytest.mark.slow
def test_tracks_the_first_90_frames(tmp_path):
    """Accuracy on real frames with the default (shipped) camera: 0.0061 m (0.0062 with the
    depth camera's intrinsics for colour; frames 0-299: 0.0192 against 0.0303, docs/formats.md)."""
    cfg = load_config(None, ["dataset.max_frames=90", "mapping.enabled=false", "output.plots=false"])
    s = run_sequence(need(SEVEN), tmp_path / "raw", cfg, progress=False)
    assert s["tracked"] == 90 and s["evaluation"]["ate"]["rmse"] < 0.01, s["evaluation"]["ate"]
    # evaluate takes the sequence folder as ground truth
    res = cli(["evaluate", SEVEN, tmp_path / "raw" / "trajectory.tum", "--no-plots"])
    assert res.exit_code == 0 and "ATE" in res.output, res.output
