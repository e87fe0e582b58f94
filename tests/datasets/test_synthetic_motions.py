"""The figure-eight and revisit motions and the motion blur of the synthetic generator: the
paths close, the revisit repeats the first visit exactly and out of its sight in between, the
blur is deterministic and really blurs, RGB-D and stereo ground truth is the path."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from rgbdslam.cli import main
from rgbdslam.datasets import open_sequence
from rgbdslam.datasets.synthetic import (
    FPS,
    MOTIONS,
    Rays,
    Scene,
    exposure_frames,
    generate_sequence,
    make_trajectory,
    render_exposure,
    revisit_ranges,
    scaled_camera,
    scene_surfaces,
    trajectory_at,
)
from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence
from rgbdslam.errors import InputError
from rgbdslam.geometry.se3 import inv, rotation_angle


def _speeds(poses):
    """Per-frame translation (m/s) and rotation (deg/s) at 30 Hz."""
    v = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) * FPS
    w = np.degrees(rotation_angle(np.swapaxes(poses[:-1, :3, :3], 1, 2) @ poses[1:, :3, :3])) * FPS
    return v, w


def _sharpness(img) -> float:
    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    return float(cv2.Laplacian(g, cv2.CV_64F).var())


def test_cli_offers_every_motion():
    choices = next(p for p in main.commands["synth"].params if p.name == "motion").type.choices
    # every RGB-D motion, and the stereo-only highway (rgbdslam.datasets.synthetic_highway)
    assert tuple(choices) == MOTIONS[:5] + ("figure8", "revisit", "orbit", "highway")
    assert set(choices) == set(MOTIONS) | {"highway"}


@pytest.mark.parametrize("frames, laps", [(150, 1), (300, 2), (1500, 10)])
def test_figure8_closes_at_handheld_speed(frames, laps):
    poses = make_trajectory("figure8", frames)
    np.testing.assert_allclose(poses[-1], poses[0], atol=1e-12)  # back at the start pose on the last frame
    v, w = _speeds(poses)
    # ~1 m/s and ~75 deg/s whatever the length: the number of 5 s laps is rounded
    assert 0.9 < v.mean() < 1.15 and v.max() < 1.55 and v.min() > 0.5, (v.mean(), v.max(), v.min())
    assert 65 < w.mean() < 85 and w.max() < 125, (w.mean(), w.max())
    # it crosses itself: the centre of the room is passed twice per lap, in two directions
    pos = poses[:, :3, 3]
    near = np.flatnonzero(np.linalg.norm(pos[:, :2], axis=1) < 0.03)
    assert len(np.unique(near // 5)) >= 2 * laps - 1
    # the camera looks all around: one full turn of heading per lap
    yaw = np.unwrap(np.arctan2(poses[:, 1, 2], poses[:, 0, 2]))
    assert yaw[-1] - yaw[0] == pytest.approx(2 * np.pi * laps, abs=1e-9)


def test_revisit_repeats_the_first_visit_after_going_out_of_sight():
    frames = 150
    r = revisit_ranges(frames)
    assert r == {"first_visit": [0, 21], "revisit": [128, 149], "revisit_offset": 128}
    poses = make_trajectory("revisit", frames)
    off = r["revisit_offset"]
    n = r["first_visit"][1] + 1
    assert off >= 100  # every revisit frame is >= 100 frames after its first-visit frame
    np.testing.assert_array_equal(poses[off:off + n], poses[:n])  # same place, same view, pose for pose
    assert np.linalg.norm(poses[n // 2, :3, 3] - poses[0, :3, 3]) > 0.02  # the visit itself moves
    v, w = _speeds(poses)
    assert v.max() < 1.2 and w.max() < 90
    # in between, the camera goes where it sees none of the first visit's surface points
    cam = scaled_camera("ros_default", 80, 60)
    rays, scene = Rays(cam), Scene(0)
    world = []
    for k in range(0, n, 3):
        _, depth, _ = scene.render(rays, poses[k])
        P = np.stack([rays.x * depth, rays.y * depth, depth], -1).reshape(-1, 3)
        world.append(P @ poses[k][:3, :3].T + poses[k][:3, 3])
    world = np.concatenate(world)

    def seen(k):
        _, depth, _ = scene.render(rays, poses[k])
        c = (world - poses[k][:3, 3]) @ poses[k][:3, :3]
        z = np.maximum(c[:, 2], 1e-3)
        u, v = cam.fx * c[:, 0] / z + cam.cx, cam.fy * c[:, 1] / z + cam.cy
        ok = (c[:, 2] > 0.1) & (u > -0.5) & (u < cam.width - 0.5) & (v > -0.5) & (v < cam.height - 0.5)
        ui = np.clip(np.round(u).astype(int), 0, cam.width - 1)
        vi = np.clip(np.round(v).astype(int), 0, cam.height - 1)
        return np.mean(ok & (np.abs(depth[vi, ui] - c[:, 2]) < 0.02))

    assert seen(10) > 0.3 and seen(off + 10) == pytest.approx(seen(10))
    away = [seen(k) for k in range(55, 96, 10)]
    assert max(away) == 0.0, away


def test_revisit_sequence_records_its_visits_and_repeats_its_images(tmp_path):
    generate_sequence(tmp_path / "r", frames=20, motion="revisit", width=64, height=48, seed=3)
    meta = yaml.safe_load((tmp_path / "r" / "synthetic.yaml").read_text())
    assert meta["first_visit"] == [0, 2] and meta["revisit"] == [17, 19] and meta["revisit_offset"] == 17
    assert "motion_blur" not in meta  # sharp unless asked
    seq = open_sequence(tmp_path / "r")
    gt = seq.groundtruth().poses
    np.testing.assert_allclose(gt, make_trajectory("revisit", 20), atol=1e-6)  # the written ground truth
    np.testing.assert_allclose(gt[17:], gt[:3], atol=1e-9)
    for k in range(3):  # the same view: the same image (up to pixels grazing an edge)
        a, b = seq.load(k), seq.load(17 + k)
        assert np.mean(np.any(a.rgb != b.rgb, axis=2)) < 0.003 and np.mean(a.depth != b.depth) < 0.003


def test_motion_blur_is_deterministic_and_lowers_sharpness():
    """16 ms at the figure eight's speed (150 frames, ~1 m/s, ~75 deg/s), 160x120: the colour is
    the mean of sub-frames along the motion; depth and surfaces stay the frame's own, exact."""
    cam = scaled_camera("ros_default", 160, 120)
    rays, scene = Rays(cam), Scene(2)
    pose_at = lambda u: trajectory_at("figure8", u, 150)  # noqa: E731
    ratios = []
    for k in (10, 60, 110):
        sharp, d0, h0, s0 = render_exposure(scene, rays, pose_at, k, 0.0)
        blur, d1, h1, streak = render_exposure(scene, rays, pose_at, k, exposure_frames(16.0))
        again = render_exposure(scene, rays, pose_at, k, exposure_frames(16.0))
        np.testing.assert_array_equal(again[0], blur)  # deterministic
        np.testing.assert_array_equal(d1, d0)
        np.testing.assert_array_equal(h1, h0)
        assert s0 == 0.0 and 2.0 < streak < 15.0, streak  # ~1/4 of the 640x480 streaks
        ratios.append(_sharpness(blur) / _sharpness(sharp))
        # the blur is the mean colour along the motion: the image mean hardly changes
        assert abs(blur.mean() - sharp.mean()) < 2.0
    assert max(ratios) < 0.6 and np.median(ratios) < 0.5, ratios
    # a longer exposure blurs more
    k = 60
    longer = render_exposure(scene, rays, pose_at, k, exposure_frames(33.0))[0]
    shorter = render_exposure(scene, rays, pose_at, k, exposure_frames(8.0))[0]
    assert _sharpness(longer) < _sharpness(shorter)


def test_figure8_sequence_is_blurred_by_default_and_reproducible(tmp_path):
    kw = dict(frames=5, motion="figure8", width=48, height=32, seed=1, noise=True)
    generate_sequence(tmp_path / "a", **kw)
    generate_sequence(tmp_path / "b", **kw)
    generate_sequence(tmp_path / "sharp", **kw, blur=0)
    meta = yaml.safe_load((tmp_path / "a" / "synthetic.yaml").read_text())
    assert meta["motion_blur"]["exposure_ms"] == 16.0 and meta["motion_blur"]["streak_px_max"] > 0
    assert "motion_blur" not in yaml.safe_load((tmp_path / "sharp" / "synthetic.yaml").read_text())
    for name in ("rgb", "depth"):
        a = sorted((tmp_path / "a" / name).iterdir())
        assert [p.read_bytes() for p in a] == [p.read_bytes() for p in sorted((tmp_path / "b" / name).iterdir())]
    blurred, sharp = open_sequence(tmp_path / "a"), open_sequence(tmp_path / "sharp")
    np.testing.assert_allclose(blurred.groundtruth().poses, make_trajectory("figure8", 5), atol=1e-6)
    assert np.mean([_sharpness(blurred.load(k).rgb) / _sharpness(sharp.load(k).rgb) for k in range(5)]) < 0.7
    np.testing.assert_array_equal(blurred.load(3).depth, sharp.load(3).depth)  # same noise draws, sharp depth


@pytest.mark.parametrize("layout", ["kitti", "euroc"])
def test_stereo_new_motions_ground_truth_and_blur(tmp_path, layout):
    for motion, frames in (("revisit", 14), ("figure8", 3)):
        out = tmp_path / f"{layout}_{motion}"
        generate_stereo_sequence(out, 0.1, layout, frames=frames, motion=motion, seed=0, width=64, height=48)
        seq = open_sequence(out)
        gt = seq.groundtruth().poses
        want = make_trajectory(motion, frames)
        np.testing.assert_allclose(inv(gt[0]) @ gt, inv(want[0]) @ want, atol=1e-6)
        meta = yaml.safe_load((out / "synthetic.yaml").read_text())
        assert ("motion_blur" in meta) == (motion == "figure8")
        if motion == "revisit":
            assert meta["revisit_offset"] == 12
            np.testing.assert_array_equal(seq.load(12).rgb, seq.load(0).rgb)
    sharp = tmp_path / "sharp"
    generate_stereo_sequence(sharp, 0.1, "kitti", frames=3, motion="figure8", seed=0, width=64, height=48, blur=0.0)
    a, b = open_sequence(tmp_path / f"{layout}_figure8"), open_sequence(sharp)
    assert _sharpness(a.load(1).rgb) < 0.7 * _sharpness(b.load(1).rgb)


@pytest.mark.parametrize("args, message", [
    (["--motion", "figure8", "--blur", "40"], "--blur must be an exposure time in milliseconds from 0 (sharp) to "
                                              "33.3 (one frame at 30 Hz) (got 40.0)"),
    (["--blur", "-1"], "--blur must be an exposure time in milliseconds from 0 (sharp) to 33.3 (one frame at 30 Hz) "
                       "(got -1.0)"),
    (["--motion", "revisit", "--phase", "0.5"], "--phase moves the start along a periodic path; --motion revisit has a "
                                                "fixed first visit and revisit (leave --phase out)"),
    (["--motion", "revisit", "-n", "5"], "--motion revisit needs at least 12 frames (visit, away, revisit); use "
                                         "--frames 150 or more for a revisit >= 100 frames later (got 5)"),
    (["--motion", "revisit", "-n", "5", "--stereo", "0.1"], "--motion revisit needs at least 12 frames (visit, away, "
                                                            "revisit); use --frames 150 or more for a revisit >= 100 "
                                                            "frames later (got 5)"),
    (["--blur", "nan", "--stereo", "0.1"], "--blur must be an exposure time in milliseconds from 0 (sharp) to 33.3 "
                                           "(one frame at 30 Hz) (got nan)"),
])
def test_bad_motion_options_one_error_line(tmp_path, args, message):
    res = CliRunner().invoke(main, ["synth", str(tmp_path / "x"), *args])
    assert res.exit_code == 2 and res.output.strip() == f"error: {message}", res.output
    assert not (tmp_path / "x").exists()


def test_synth_cli_figure8_and_revisit(tmp_path):
    res = CliRunner().invoke(main, ["synth", str(tmp_path / "f"), "--motion", "figure8", "-n", "3", "--size", "32",
                                    "24", "--blur", "8"])
    assert res.exit_code == 0, res.output
    assert "motion blur 8 ms" in res.output
    assert yaml.safe_load((tmp_path / "f" / "synthetic.yaml").read_text())["motion_blur"]["exposure_ms"] == 8.0
    res = CliRunner().invoke(main, ["synth", str(tmp_path / "r"), "--motion", "revisit", "-n", "12", "--size", "32",
                                    "24", "--stereo", "0.1", "--layout", "euroc"])
    assert res.exit_code == 0, res.output
    assert len(open_sequence(tmp_path / "r")) == 12
    with pytest.raises(InputError, match="--blur must be"):
        generate_sequence(tmp_path / "z", frames=2, blur=True)


def test_bench_landmarks_takes_the_visits_from_synthetic_yaml(tmp_path):
    """benchmarks.landmarks' revisit table: the revisit motion's recorded ranges, else the
    first and last 15 % of the frames."""
    from benchmarks import landmarks as mod

    (tmp_path / "synthetic.yaml").write_text(yaml.safe_dump({"frames": 150, "motion": "revisit",
                                                             **revisit_ranges(150)}))
    assert mod.visit_ranges(tmp_path, 150) == (range(0, 22), range(128, 150))
    assert mod.visit_ranges(tmp_path, 140) == (range(0, 21), range(119, 140))  # not this sequence's: fallback
    assert mod.visit_ranges(tmp_path / "none", 100) == (range(0, 15), range(85, 100))
    assert "revisit" in mod.LOOP_TYPE and "figure8" in mod.LOOP_TYPE


def test_orbit_hall_is_far_and_bare_but_for_a_few_frames(tmp_path):
    """The orbit's room is fr3/teddy's: beyond the near figure a quarter of the image is room 6-10 m
    away, bare but for door and window frames (a tenth of those pixels, all 6-10 m away); the written
    depth keeps them (the orbit's sensor reaches 10 m), while the other motions' stops at 4.5 m."""
    surfaces = scene_surfaces("orbit")
    bare = np.array([s.bare for s in surfaces])
    scene, rays = Scene(0, surfaces), Rays(scaled_camera("ros_default", 640, 480))
    for pose in make_trajectory("orbit", 60)[::30]:
        _, depth, ids = scene.render(rays, pose)
        far = depth > 6.0
        textured = far & ~bare[ids]
        assert 0.15 < far.mean() < 0.5
        assert 0.03 < textured.sum() / far.sum() < 0.2  # sparse: most far pixels are bare wall and floor
        assert 6.0 < depth[textured].min() and depth[textured].max() < 10.0
    generate_sequence(tmp_path / "orbit", frames=2, motion="orbit", noise=True, seed=0)
    generate_sequence(tmp_path / "loop", frames=2, motion="loop", noise=True, seed=0)
    depth = lambda name: cv2.imread(str(next((tmp_path / name / "depth").iterdir())), cv2.IMREAD_UNCHANGED) / 5000.0  # noqa: E731
    assert (depth("orbit") > 6.0).mean() > 0.1  # written, not clipped at the other motions' 4.5 m
