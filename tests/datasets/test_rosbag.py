"""ROS bags (ROS 1, ROS 2 sqlite3 and mcap, RealSense SDK layout) written here from real TUM
frames with rosbags' own writers, read back by the bag reader and run through SLAM: the
trajectory must equal the run on the TUM folder itself."""

from __future__ import annotations


import numpy as np
import pytest
import yaml

from rgbdslam.datasets.testing import write_bag
from tests.conftest import TUM_DESK9, TUM_RPY200, cli, need
from rgbdslam.config import load_config
from rgbdslam.datasets import open_sequence
from rgbdslam.datasets.rosbag import RosbagSequence, decode_depth
from rgbdslam.datasets.tum import TumSequence
from rgbdslam.geometry.camera import CAMERAS
from rgbdslam.geometry.depth_registration import DepthRegistration
from rgbdslam.io.trajectory import read_tum
from rgbdslam.pipeline import run_sequence

pytestmark = pytest.mark.data  # real TUM frames written into bags

FRAMES = 30



def _cfg(*extra):
    # a bag's CameraInfo has no rolling-shutter readout: the runs use fr1's, as the folder run does
    return load_config(None, ["mapping.enabled=false", "output.plots=false", f"dataset.max_frames={FRAMES}",
                              f"features.rolling_shutter={CAMERAS['fr1'].readout}", *extra])


@pytest.fixture(scope="module")
def folder_run(tmp_path_factory):
    """SLAM on the first 30 frames of fr1/rpy, read from the TUM folder."""
    out = tmp_path_factory.mktemp("folder")
    run_sequence(need(TUM_RPY200), out, _cfg(), progress=False)
    return read_tum(out / "trajectory.tum")


# kind, colour, depth, extra config: every bag keeps the folder's pixel values exactly
CASES = [
    ("ros1", "rgb8", "16UC1", ["dataset.depth_scale=5000"]),  # raw TUM units: the scale is set by config
    ("ros2", "bgr8", "32FC1", []),  # metres, float
    ("mcap", "png", "compressedDepth", ["dataset.depth_scale=5000"]),  # CompressedImage colour and depth
    ("realsense", "rgb8", "mono16", []),  # RealSense layout: the recording's 'Depth Units' option gives the scale
]


@pytest.mark.slow
@pytest.mark.parametrize("kind,color,depth,extra", CASES, ids=[c[0] for c in CASES])
def test_bag_run_equals_folder_run(tmp_path, folder_run, kind, color, depth, extra):
    bag = write_bag(TUM_RPY200, tmp_path / ("rec.bag" if kind in ("ros1", "realsense") else "rec"), kind,
                    color=color, depth=depth if depth != "mono16" else "16UC1", frames=FRAMES + 2)
    seq = open_sequence(bag, _cfg(*extra).dataset)
    assert isinstance(seq, RosbagSequence) and len(seq) == FRAMES
    assert seq.camera_setup.source.startswith("CameraInfo on ")
    run_sequence(bag, tmp_path / "run", _cfg(*extra), progress=False)
    est = read_tum(tmp_path / "run" / "trajectory.tum")
    assert len(est) == len(folder_run) == FRAMES
    np.testing.assert_allclose(est.timestamps, folder_run.timestamps, atol=1e-6)
    np.testing.assert_allclose(est.poses, folder_run.poses, atol=1e-9)
    # and the run is not trivially equal: the camera turned (fr1/rpy)
    assert np.linalg.norm(folder_run.poses[-1][:3, :3] - np.eye(3)) > 0.05


def test_frames_equal_folder_frames(tmp_path):
    """Pixel for pixel: colour, depth in metres, camera and stamps (ROS 2 mcap, raw images)."""
    bag = write_bag(TUM_DESK9, tmp_path / "rec", "mcap", color="rgb8", depth="32FC1")
    seq, tum = open_sequence(bag), TumSequence(TUM_DESK9)
    assert len(seq) == len(tum) == 9
    assert seq.camera.K.tolist() == tum.camera.K.tolist() and seq.camera.dist == tum.camera.dist
    for i in (0, 4, 8):
        a, b = seq.load(i), tum.load(i)
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)
        assert abs(a.timestamp - b.timestamp) < 1e-6
    seq.load(2)  # going back re-reads from the start
    assert np.array_equal(seq.load(3).depth, tum.load(3).depth)


def test_16bit_depth_is_millimetres_by_default():
    class Msg:
        encoding, height, width, step, is_bigendian = "16UC1", 1, 3, 6, 0
        data = np.array([0, 1000, 65535], "<u2").view(np.uint8)

    d = decode_depth("sensor_msgs/msg/Image", Msg, "/d", 1e-3)
    assert d.tolist() == [[0.0, 1.0, pytest.approx(65.535)]]
    Msg.encoding, Msg.step = "32FC1", 12
    Msg.data = np.array([np.nan, 1.5, -1], "<f4").view(np.uint8)
    assert decode_depth("sensor_msgs/msg/Image", Msg, "/d", 1e-3).tolist() == [[0.0, 1.5, 0.0]]


def test_realsense_depth_is_registered_with_the_recordings_extrinsic(tmp_path):
    """A RealSense recording whose depth stream sits 2 cm beside the colour camera: the reader
    re-projects each depth image with the tf the recording carries (depth-to-colour)."""
    T = np.eye(4)
    T[:3, 3] = [0.02, 0.0, 0.0]
    cam = TumSequence(TUM_DESK9).camera
    from dataclasses import replace

    dcam = replace(cam, fx=cam.fx + 20, name="depth")  # a different depth camera: not registered
    bag = write_bag(TUM_DESK9, tmp_path / "rs.bag", "realsense", frames=3, depth_info_camera=dcam, depth_to_color=T)
    seq = open_sequence(bag)
    assert seq.registration is not None
    np.testing.assert_allclose(seq.camera_setup.depth_to_color, T, atol=1e-7)
    raw = TumSequence(TUM_DESK9).load(1).depth
    want = DepthRegistration(seq.camera_setup.depth_camera, cam, T)(raw)
    assert np.array_equal(seq.load(1).depth, want)


def _cli(*args):
    return cli(args)


def _one_error(res, *phrases):
    assert isinstance(res.exception, SystemExit) and res.exit_code == 2, (res.exception, res.output)
    lines = [x for x in res.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    for p in phrases:
        assert p in lines[0], lines[0]


def test_bad_bags_are_one_error_line_each(tmp_path):
    nodepth = write_bag(TUM_DESK9, tmp_path / "nodepth.bag", "ros1", depth="none", frames=2)
    _one_error(_cli("run", nodepth, "-o", tmp_path / "o1"), "no depth image topic")
    weird = write_bag(TUM_DESK9, tmp_path / "weird.bag", "ros1", depth="yuv422", frames=2)
    _one_error(_cli("run", weird, "-o", tmp_path / "o2"), "unsupported encodings", "yuv422")
    two = write_bag(TUM_DESK9, tmp_path / "two.bag", "ros1", frames=2, extra_color_topic=True)
    _one_error(_cli("info", two), "2 colour image topics", "/camera/ir/image_raw", "dataset.rgb_topic")
    _one_error(_cli("info", two, "--set", "dataset.rgb_topic=/nope"), "'/nope' is not an image topic")
    res = _cli("info", two, "--set", "dataset.rgb_topic=/camera/color/image_raw")
    assert res.exit_code == 0 and "frames      2" in res.stdout, res.output
    cam = tmp_path / "small.yaml"
    cam.write_text(yaml.safe_dump({"fx": 250, "fy": 250, "cx": 160, "cy": 120, "size": [320, 240]}))
    _one_error(_cli("run", two, "--camera", cam, "--set", "dataset.rgb_topic=/camera/color/image_raw", "-o",
                    tmp_path / "o3"), "are 640x480 but the camera", "320x240")
    ros2 = write_bag(TUM_DESK9, tmp_path / "r2", "mcap", frames=2)
    lone = tmp_path / "lone.mcap"
    lone.write_bytes((ros2 / "r2.mcap").read_bytes())
    _one_error(_cli("info", lone), "metadata.yaml")
    (ros2 / "r2.mcap").write_bytes(b"garbage")
    _one_error(_cli("info", ros2), "cannot be read as a ROS bag")


@pytest.mark.slow
def test_realsense_sdk_recording_equals_folder_run(tmp_path, folder_run):
    """A recording made by the RealSense SDK's own recorder (pyrealsense2 2.59: a lone ROS 2
    .db3 with compressed images, text options and frame times in image/metadata), read by the
    bag reader: the folder run's trajectory (the SDK stores the intrinsics as float32, hence
    the tolerance)."""
    from rgbdslam.datasets.testing import write_realsense_recording

    rec = write_realsense_recording(TUM_RPY200, tmp_path / "rs.db3", frames=FRAMES + 2)
    seq = open_sequence(rec, _cfg().dataset)
    assert len(seq) == FRAMES and seq.color.topic.endswith("Color_0/image/data/compressed")
    tum = TumSequence(TUM_RPY200)
    a, b = seq.load(5), tum.load(5)
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth) and abs(a.timestamp - b.timestamp) < 1e-6
    run_sequence(rec, tmp_path / "run", _cfg(), progress=False)
    est = read_tum(tmp_path / "run" / "trajectory.tum")
    np.testing.assert_allclose(est.timestamps, folder_run.timestamps, atol=1e-6)
    np.testing.assert_allclose(est.poses, folder_run.poses, atol=1e-6)


def test_camera_info_values_are_checked_as_read(tmp_path):
    """A CameraInfo with K = inf, a negative size or absurd distortion is one line naming the topic
    before any frame is read (it ran and failed per frame)."""
    from dataclasses import replace

    cam = TumSequence(TUM_DESK9).camera
    for i, (bad, words) in enumerate(((replace(cam, fx=float("inf")), "fx must be a finite number"),
                                      (replace(cam, cx=1e200), "cx must be a finite number"),
                                      (replace(cam, dist=(1e10, 0.0, 0.0, 0.0, 0.0)), "distortion coefficient 1"))):
        bag = write_bag(TUM_DESK9, tmp_path / f"b{i}", "ros2", frames=2, color_info_camera=bad)
        _one_error(_cli("info", bag), "/camera/color/camera_info", words)


@pytest.mark.parametrize("data", [b"", b"\x07\x07\x07\x07garbage"])
def test_an_empty_or_corrupt_message_is_one_line_naming_its_topic(tmp_path, data):
    """rosbags' SerdeError ("Invalid or unsupported CDR encapsulation") for a damaged message of a
    ROS 2 bag reached the user as a traceback."""
    import sqlite3

    bag = write_bag(TUM_DESK9, tmp_path / "r2", "ros2", frames=2)
    db = next(bag.glob("*.db3"))
    with sqlite3.connect(db) as con:
        tid = con.execute("SELECT id FROM topics WHERE name = '/camera/color/image_raw'").fetchone()[0]
        first = con.execute("SELECT min(id) FROM messages WHERE topic_id = ?", (tid,)).fetchone()[0]
        con.execute("UPDATE messages SET data = ? WHERE id = ?", (data, first))
    _one_error(_cli("info", bag), f"{bag}: a message on /camera/color/image_raw cannot be decoded")


def test_a_topic_of_the_wrong_kind_is_refused_up_front(tmp_path):
    """A depth topic given as the colour topic failed on every frame (exit 3) instead of once."""
    bag = write_bag(TUM_DESK9, tmp_path / "r2", "ros2", frames=2)
    _one_error(_cli("info", bag, "--set", "dataset.rgb_topic=/camera/depth/image_raw"),
               "dataset.rgb_topic '/camera/depth/image_raw' is a depth topic", "colour topics of",
               "/camera/color/image_raw")
    _one_error(_cli("info", bag, "--set", "dataset.depth_topic=/camera/color/image_raw"),
               "dataset.depth_topic '/camera/color/image_raw' is a colour topic")
