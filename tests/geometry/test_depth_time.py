"""Depth read at the colour image's time (geometry/depth_time.py): hand-worked cases, and the
front end on a synthetic sequence whose depth images are taken 10 ms after the colour ones."""

from __future__ import annotations

import numpy as np
import pytest

from rgbdslam.geometry.camera import CAMERAS, Camera
from rgbdslam.geometry.depth_time import depth_at_colour_time, sample_depth
from rgbdslam.geometry.se3 import make_pose

CAM = Camera(500.0, 500.0, 320.0, 240.0, 640, 480)


def test_camera_distort_points_inverts_undistort():
    cam = CAMERAS["fr1"]
    uv = np.array([[20.0, 30.0], [320.0, 240.0], [600.0, 450.0], [100.0, 400.0]])
    np.testing.assert_allclose(cam.distort_points(cam.undistort_points(uv)), uv, atol=0.02)
    np.testing.assert_array_equal(CAM.distort_points(uv), uv)  # no distortion: unchanged


def test_sample_depth_rounds_and_gives_zero_outside():
    depth = np.arange(12, dtype=np.float32).reshape(3, 4)
    z = sample_depth(depth, np.array([[0.4, 0.4], [2.6, 1.2], [3.0, 2.0], [-0.6, 0.0], [4.0, 0.0], [np.nan, 1.0]]))
    np.testing.assert_array_equal(z, [0.0, 7.0, 11.0, 0.0, 0.0, 0.0])


def test_camera_nearer_at_the_depth_time_reads_less_and_gets_it_back():
    """A wall 2 m ahead; when the depth image is taken the camera is 5 cm nearer, so the image reads
    1.95 m everywhere: the key points' depth at the colour time is 1.95 + 0.05 = 2.0 m."""
    depth = np.full((480, 640), 1.95, np.float32)
    D = make_pose(np.eye(3), [0.0, 0.0, 0.05])  # depth-time camera in the colour-time camera
    uv = np.array([[320.0, 240.0], [100.0, 50.0], [600.0, 400.0]])
    z = depth_at_colour_time(uv, depth, CAM, D, z0=np.full(3, 1.95))
    np.testing.assert_allclose(z, 2.0, atol=1e-9)


def test_turned_camera_reads_the_depth_across_an_edge():
    """The depth-time camera is turned about y by θ with tan θ = 0.02: the scene point on the colour
    image's centre is seen at u = cx - f·tan θ = 310 in the depth image. Depth there (u < 315) is
    1 m, to the right 2 m: the plain lookup at u = 320 reads the wrong side (2 m); the compensation
    reads 1 m along the depth camera's ray (-tan θ, 0, 1), which the rotation takes back onto the
    colour ray at z = cos θ·1 + sin θ·tan θ = 1/cos θ = sqrt(1 + 0.02²)."""
    t = 0.02
    c, s = 1 / np.sqrt(1 + t * t), t / np.sqrt(1 + t * t)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    depth = np.full((480, 640), 2.0, np.float32)
    depth[:, :315] = 1.0
    uv = np.array([[320.0, 240.0]])
    assert sample_depth(depth, uv)[0] == 2.0  # what the key point's own pixel says
    z = depth_at_colour_time(uv, depth, CAM, make_pose(R, [0, 0, 0]), z0=np.array([2.0]))
    np.testing.assert_allclose(z, [np.sqrt(1 + t * t)], rtol=1e-12)


def test_no_depth_where_the_point_was_gives_zero():
    depth = np.full((480, 640), 2.0, np.float32)
    depth[:, :315] = 0.0  # hole where the point is at the depth time
    t = 0.02
    c, s = 1 / np.sqrt(1 + t * t), t / np.sqrt(1 + t * t)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    z = depth_at_colour_time(np.array([[320.0, 240.0], [400.0, 240.0]]), depth, CAM, make_pose(R, [0, 0, 0]),
                             z0=np.array([2.0, 2.0]))
    assert z[0] == 0.0 and z[1] > 1.9


def test_identity_motion_reads_the_key_points_own_pixel():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 4.0, (480, 640)).astype(np.float32)
    uv = rng.uniform([0, 0], [639, 479], (200, 2))
    z = depth_at_colour_time(uv, depth, CAM, np.eye(4), z0=np.full(200, 2.0))
    np.testing.assert_array_equal(z, sample_depth(depth, uv))


@pytest.fixture(scope="module")
def delayed_rpy(tmp_path_factory):
    from rgbdslam.datasets.synthetic import generate_sequence

    out = tmp_path_factory.mktemp("delay") / "rpy_d10"
    generate_sequence(out, frames=40, motion="rpy", width=320, height=240, seed=0, depth_delay=0.010)
    return out


def test_generator_writes_the_depth_stamps_and_the_reader_the_delay(delayed_rpy):
    from rgbdslam.datasets import open_sequence

    seq = open_sequence(delayed_rpy)
    f = seq.load(5)
    assert f.depth_delay == pytest.approx(0.010, abs=2e-6)
    np.testing.assert_allclose(seq.depth_timestamps - seq.timestamps, 0.010, atol=2e-6)


def test_front_end_with_a_10ms_depth_delay_tracks_only_when_compensated(delayed_rpy):
    """rpy motion, no noise, 320x240, depth 10 ms late: ignoring the delay drifts by a centimetre over
    40 frames; the constant-velocity compensation (features.depth_delay = predict) roughly halves it."""
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.evaluation.ate import ate
    from rgbdslam.io.trajectory import Trajectory
    from rgbdslam.frontend.odometry import build_frontend

    seq = open_sequence(delayed_rpy)
    gt = seq.groundtruth()
    errs = {}
    for mode in ("ignore", "predict"):
        cfg = load_config(None, [f"features.depth_delay={mode}"])
        fe = build_frontend(cfg, seq.camera)
        poses = np.stack([fe.track(seq.load(i)).pose for i in range(len(seq))])
        errs[mode] = ate(gt, Trajectory(seq.timestamps, poses)).rmse
    # measured: ignore 11.1 mm, predict 6.3 mm (the noise-free sequence without delay: ~1-2 mm)
    assert errs["predict"] < 0.008, errs
    assert errs["ignore"] > 1.5 * errs["predict"], errs


# ------------------------------------------------------------------ rolling shutter


def test_row_motions_scale_the_velocity_by_each_rows_time():
    """V: 0.03 rad about y and 3 cm along x in 1/30 s; readout 30 ms over 480 rows. Row 0 is read
    15 ms before the middle row: factor -0.015 * 30 = -0.45 (rotation -0.0135 rad, t -13.5 mm);
    row 240 is the middle (identity); row 480 +0.45."""
    from rgbdslam.geometry.depth_time import row_motions

    a = 0.03
    V = make_pose(np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]), [0.03, 0, 0])
    R, t = row_motions(np.array([0.0, 240.0, 480.0]), 480, 0.030, V, 1 / 30)
    for k, f in enumerate([-0.45, 0.0, 0.45]):
        b = a * f
        np.testing.assert_allclose(R[k], [[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]], atol=1e-12)
        np.testing.assert_allclose(t[k], [0.03 * f, 0, 0], atol=1e-12)


def test_shutter_corrected_pixel_of_a_turned_row():
    """The centre pixel's ray (0, 0, 1) turned by b about y is (sin b, 0, cos b): u = cx + f tan b."""
    from rgbdslam.geometry.depth_time import shutter_corrected_pixels

    b = 0.0135
    R = np.array([[[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]]])
    uv = shutter_corrected_pixels(np.array([[320.0, 240.0]]), CAM, R)
    np.testing.assert_allclose(uv, [[320.0 + 500.0 * np.tan(b), 240.0]], atol=1e-9)


def _frame(rows: np.ndarray, depth: float = 2.0):
    """A blank frame with one key point per row in ``rows`` (column 320), with ready detections."""
    from rgbdslam.config import FeaturesConfig
    from rgbdslam.datasets.base import Frame
    from rgbdslam.frontend.features import Detections

    rgb = np.zeros((480, 640, 3), np.uint8)
    uv = np.column_stack([np.full(len(rows), 320.0), rows])
    det = Detections(uv, np.zeros((len(rows), 32), np.uint8), np.ones(len(rows), np.float32), len(rows),
                     FeaturesConfig(), rgb, np.zeros(len(rows), np.int8))
    return Frame(0, 0.0, rgb, np.full((480, 640), depth, np.float32), CAM, detections=det)


def test_extract_features_moves_each_key_point_to_the_frames_time():
    """Rotation about y at 0.9 rad/s, readout 30 ms: the key point on row 0 (read 15 ms early) is
    moved by R(-0.0135) about y, its 3-D point too (depth 2 m along its observed ray); the middle
    row's stays; ``features.rolling_shutter = 0`` leaves both alone; None takes the camera's readout."""
    import dataclasses

    from rgbdslam.config import FeaturesConfig, MatchingConfig
    from rgbdslam.frontend.features import extract_features, lift

    a = 0.03
    V = make_pose(np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]), [0, 0, 0])
    frame = _frame(np.array([0.0, 240.0]))
    mc = MatchingConfig()

    def features(fc):  # the ready detections are used only when made with the same features config
        frame.detections = dataclasses.replace(frame.detections, config=fc)
        return extract_features(frame, fc, mc, velocity=(V, 1 / 30))

    f = features(FeaturesConfig(rolling_shutter=0.030))
    b = -0.0135
    # the ray (0, -0.48, 1) of row 0 turned: (sin b, -0.48, cos b) -> u = cx + f tan b, v = cy - 240 / cos b
    np.testing.assert_allclose(f.uv[0], [320.0 + 500.0 * np.tan(b), 240.0 - 240.0 / np.cos(b)], atol=1e-9)
    np.testing.assert_allclose(f.uv[1], [320.0, 240.0], atol=1e-12)
    X = CAM.backproject(np.array([[320.0, 0.0]]), np.array([2.0]))[0]
    Rb = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    np.testing.assert_allclose(f.pts[0], Rb @ X, atol=1e-12)
    np.testing.assert_allclose(f.pts[1], [0.0, 0.0, 2.0], atol=1e-12)
    lift(f, frame.depth, CAM, mc)  # a re-lift (DIF) keeps the correction
    np.testing.assert_allclose(f.pts[0], Rb @ X, atol=1e-12)
    off = features(FeaturesConfig(rolling_shutter=0.0))
    np.testing.assert_allclose(off.pts[0], X, atol=1e-12)
    from rgbdslam.frontend.features import reshutter

    again = features(FeaturesConfig(rolling_shutter=0.030))
    reshutter(again, frame.depth, CAM, mc, np.eye(4), 1 / 30)  # no motion after all: nothing to undo
    np.testing.assert_allclose(again.uv, [[320.0, 0.0], [320.0, 240.0]], atol=1e-12)
    np.testing.assert_allclose(again.pts[0], X, atol=1e-12)
    reshutter(again, frame.depth, CAM, mc, V, 1 / 30)  # the same motion again: the same answer as before
    np.testing.assert_allclose(again.pts, f.pts, atol=1e-12)
    frame.camera = dataclasses.replace(CAM, readout=0.030)  # None: the camera's own readout
    auto = features(FeaturesConfig())
    np.testing.assert_allclose(auto.pts[0], Rb @ X, atol=1e-12)


def test_camera_file_rolling_shutter(tmp_path):
    from rgbdslam.datasets.camera_file import read_camera_file
    from rgbdslam.errors import InputError

    p = tmp_path / "cam.yaml"
    p.write_text("camera: fr1\n")
    assert read_camera_file(p).camera.readout == CAMERAS["fr1"].readout
    p.write_text("fx: 500\nfy: 500\ncx: 320\ncy: 240\nrolling_shutter: 0.02\n")
    assert read_camera_file(p).camera.readout == 0.02
    p.write_text("camera: fr1\nrolling_shutter: 0\n")
    assert read_camera_file(p).camera.readout == 0.0
    p.write_text("camera: fr1\nrolling_shutter: 0.5\n")
    with pytest.raises(InputError, match="rolling_shutter must be the readout time"):
        read_camera_file(p)


@pytest.mark.data
def test_fr1_rolling_shutter_reduces_the_rotation_drift_of_the_front_end(rpy200):
    """fr1/rpy frames 140-199 (fast roll/pitch/yaw), front end only: the rotation error of every pose
    against the first (ground truth) has an RMS of 1.87 deg without the rolling-shutter correction
    and 1.02 deg with the fr1 camera's readout (17.5 ms, chosen without ground truth). Measured on
    other 60-frame windows: 100-160 1.99 -> 1.11, 40-100 2.96 -> 2.58, 60-120 2.65 -> 2.49, but
    0-60 2.43 -> 2.93 deg (docs/slam.md "Rolling shutter")."""
    from scipy.spatial.transform import Rotation

    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.frontend.odometry import build_frontend
    from rgbdslam.geometry.se3 import inv
    from tests.frontend.test_frontend import gt_pose

    seq = open_sequence(rpy200)
    assert seq.camera.readout == pytest.approx(0.0175)  # the freiburg1 camera's, from the folder name
    gt = seq.groundtruth()
    frames = [seq.load(i) for i in range(140, 200)]
    G = [gt_pose(gt, f.timestamp) for f in frames]
    rms = {}
    for rs in (0.0, None):
        fe = build_frontend(load_config(None, [] if rs is None else [f"features.rolling_shutter={rs}"]), seq.camera)
        P = [fe.track(f).pose for f in frames]
        err = [np.linalg.norm(Rotation.from_matrix((inv(G[0]) @ G[k])[:3, :3].T @ (inv(P[0]) @ P[k])[:3, :3]).as_rotvec())
               for k in range(len(P))]
        rms[rs] = float(np.degrees(np.sqrt(np.mean(np.square(err)))))
    assert rms[None] < 0.7 * rms[0.0], rms
