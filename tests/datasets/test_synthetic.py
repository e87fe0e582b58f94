"""Synthetic sequences: exact depth, consistent geometry between frames, ORB-friendly texture,
seeded sensor effects, the loop motion's closure and the `synth` command."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from rgbdslam.cli import main
from rgbdslam.config import DatasetConfig
from rgbdslam.datasets import open_sequence
from rgbdslam.datasets.synthetic import (
    DEPTH_SCALE,
    MOTIONS,
    ROOM,
    Rays,
    Scene,
    generate_sequence,
    make_trajectory,
    scaled_camera,
    scene_surfaces,
)
from rgbdslam.errors import InputError
from rgbdslam.geometry.se3 import inv, transform_points

Q = 1.0 / DEPTH_SCALE  # depth quantum (m)


@pytest.fixture(scope="module")
def xyz_seq(tmp_path_factory):
    out = tmp_path_factory.mktemp("syn") / "xyz"
    t = time.perf_counter()
    summary = generate_sequence(out, frames=8, motion="xyz", seed=1)
    print(f"\nsynthetic: 8 frames 640x480 generated in {time.perf_counter() - t:.2f} s")
    assert summary["frames"] == 8
    return out


def _backproject_world(frame, pose, uv):
    """World points of integer pixels ``uv`` (N,2) using the frame's written depth."""
    z = frame.depth[uv[:, 1], uv[:, 0]].astype(np.float64)
    ideal = frame.camera.undistort_points(uv.astype(np.float64))
    return transform_points(pose, frame.camera.backproject(ideal, z)), z


def _check_points_on_surfaces(seq, i, n=400, seed=0):
    frame = seq.load(i)
    pose = seq.groundtruth().poses[i]
    rng = np.random.default_rng(seed)
    uv = np.stack([rng.integers(0, frame.camera.width, n), rng.integers(0, frame.camera.height, n)], axis=1)
    scene = Scene(0)  # geometry does not depend on the seed
    _, _, hit = scene.render(Rays(frame.camera), pose)
    P, z = _backproject_world(frame, pose, uv)
    assert (z > 0).all()
    ids = hit[uv[:, 1], uv[:, 0]]
    surfaces = scene_surfaces()
    rays = np.c_[frame.camera.undistort_points(uv.astype(float)), np.ones(n)]
    ray_len = np.linalg.norm((rays[:, :2] - [frame.camera.cx, frame.camera.cy]) / [frame.camera.fx, frame.camera.fy], axis=1)
    for k in np.unique(ids):
        m = ids == k
        dist, inside = surfaces[k].contains(P[m], tol=1e-3)
        # the written depth is off by at most half a quantum along the optical axis
        assert (dist <= 0.5 * Q * np.sqrt(1 + ray_len[m] ** 2) + 1e-7).all(), surfaces[k].name
        assert inside.all(), surfaces[k].name


def test_depth_is_exact_on_the_scene_planes(xyz_seq):
    seq = open_sequence(xyz_seq)
    assert len(seq) == 8 and seq.camera.name == "ros_default"
    for i in (0, 7):
        _check_points_on_surfaces(seq, i, seed=i)


def test_depth_exact_with_distortion_and_other_size(tmp_path):
    out = tmp_path / "fr1"
    generate_sequence(out, frames=2, motion="rpy", camera="fr1", width=320, height=240, seed=2)
    seq = open_sequence(out)
    assert (seq.camera.width, seq.camera.height) == (320, 240)
    assert seq.camera.fx == pytest.approx(517.3 / 2) and seq.camera.dist[0] == pytest.approx(0.2624)
    _check_points_on_surfaces(seq, 1, seed=5)


def test_hand_worked_wall_depth_and_drift(tmp_path):
    """From (0, 0, 1.4) looking along +x the wall x = 3 is exactly 3 m away at every pixel seeing it."""
    cam = scaled_camera("ros_default", 640, 480)
    poses = make_trajectory("static", 1)
    np.testing.assert_allclose(poses[0][:3, 3], [0, 0, 1.4])
    np.testing.assert_allclose(poses[0][:3, 2], [1, 0, 0], atol=1e-12)  # optical axis = +x
    np.testing.assert_allclose(poses[0][:3, 1], [0, 0, -1], atol=1e-12)  # image y = down
    _, depth, hit = Scene(0).render(Rays(cam), poses[0])
    wall = [s.name for s in scene_surfaces()].index("wall_xmax")
    assert hit[240, 320] == wall
    assert (hit == wall).sum() > 10000
    np.testing.assert_allclose(depth[hit == wall], 3.0, atol=1e-12)
    generate_sequence(tmp_path / "d", frames=1, motion="static", drift=0.02)
    f = open_sequence(tmp_path / "d").load(0)
    assert f.depth[240, 320] == np.float32(round(3.06 * DEPTH_SCALE) / DEPTH_SCALE)
    f = open_sequence(tmp_path / "d", DatasetConfig(depth_correction=1 / 1.02)).load(0)
    assert abs(f.depth[240, 320] - 3.0) < 1e-6


def test_reprojection_between_frames_agrees_to_quantisation(xyz_seq):
    seq = open_sequence(xyz_seq)
    gt = seq.groundtruth()
    f0, f5 = seq.load(0), seq.load(5)
    cam = f0.camera
    v, u = np.nonzero(f5.depth > 0)
    P5 = cam.backproject(np.c_[u, v], f5.depth[v, u])
    P0 = transform_points(inv(gt.poses[0]) @ gt.poses[5], P5)
    uv0 = cam.project(P0)
    x, y = uv0[:, 0], uv0[:, 1]
    ok = (x >= 0) & (x < cam.width - 1) & (y >= 0) & (y < cam.height - 1)
    x, y, z_pred = x[ok], y[ok], P0[ok, 2]
    # inverse depth is affine in the image on a plane: bilinear interpolation of 1/z is exact
    inv0 = np.where(f0.depth > 0, 1.0 / np.maximum(f0.depth, 1e-9), np.nan).astype(np.float64)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    w = (inv0[y0, x0] * (1 - fx) + inv0[y0, x0 + 1] * fx) * (1 - fy) + (inv0[y0 + 1, x0] * (1 - fx) + inv0[y0 + 1, x0 + 1] * fx) * fy
    z_obs = 1.0 / w
    err = np.abs(z_obs - z_pred)
    assert ok.mean() > 0.8  # the two views overlap
    frac = np.mean(err <= Q + 1e-6)
    assert frac > 0.97, f"only {frac:.3f} of reprojected pixels agree within 1/5000 m"
    assert np.nanmedian(err) < 0.5 * Q


def test_orb_finds_many_features(tmp_path):
    out = tmp_path / "loop"
    generate_sequence(out, frames=12, motion="loop", noise=True, seed=0, width=640, height=480)
    seq = open_sequence(out)
    orb = cv2.ORB_create(nfeatures=2000)
    for i in range(0, 12, 2):
        kp = orb.detect(cv2.cvtColor(seq.load(i).rgb, cv2.COLOR_RGB2GRAY), None)
        assert len(kp) > 500, f"frame {i}: {len(kp)} ORB features"


def test_loop_returns_to_the_start_view(tmp_path):
    poses = make_trajectory("loop", 60)
    np.testing.assert_allclose(poses[-1], poses[0], atol=1e-12)
    # it goes round the room: the camera looks in every direction on the way
    yaw = np.degrees(np.arctan2(poses[:, 1, 2], poses[:, 0, 2]))
    assert np.ptp(np.unwrap(np.radians(yaw))) > np.radians(350)
    generate_sequence(tmp_path / "l", frames=9, motion="loop", width=160, height=120)
    seq = open_sequence(tmp_path / "l")
    first, last = seq.load(0), seq.load(8)
    # identical up to pixels whose ray grazes a surface edge (the poses differ by ~1e-16)
    assert np.mean(np.any(first.rgb != last.rgb, axis=2)) < 0.002
    assert np.mean(first.depth != last.depth) < 0.002
    assert np.abs(seq.load(0).rgb.astype(int) - seq.load(4).rgb).mean() > 20


def test_a_second_session_starts_elsewhere_in_the_same_room(tmp_path):
    """--phase starts the path further on, --time-offset shifts the stamps; one seed, one room."""
    full = make_trajectory("loop", 101)
    np.testing.assert_allclose(make_trajectory("loop", 101, phase=0.5)[:51], full[50:], atol=1e-12)
    np.testing.assert_allclose(make_trajectory("xyz", 41, phase=0.25)[:31], make_trajectory("xyz", 41)[10:], atol=1e-12)
    generate_sequence(tmp_path / "a", frames=21, motion="loop", width=160, height=120, seed=4)
    generate_sequence(tmp_path / "b", frames=11, motion="loop", width=160, height=120, seed=4, phase=0.5,
                      time_offset=100.0)
    a, b = open_sequence(tmp_path / "a"), open_sequence(tmp_path / "b")
    assert b.timestamps[0] - a.timestamps[0] == pytest.approx(100.0)
    np.testing.assert_allclose(b.groundtruth().poses[0], a.groundtruth().poses[10], atol=1e-6)
    # the same place seen in both sessions: the same image
    assert np.mean(np.any(a.load(10).rgb != b.load(0).rgb, axis=2)) < 0.002
    with pytest.raises(InputError, match="--phase must be a fraction"):
        generate_sequence(tmp_path / "c", frames=2, phase=1.5)


@pytest.mark.parametrize("motion", MOTIONS)
def test_motions_stay_inside_looking_at_surfaces(motion):
    poses = make_trajectory(motion, 300)
    lo, hi = ROOM
    pos = poses[:, :3, 3]
    assert ((pos > lo + 0.5) & (pos < hi - 0.5)).all()
    np.testing.assert_allclose(poses[:, :3, :3] @ np.swapaxes(poses[:, :3, :3], 1, 2), np.tile(np.eye(3), (300, 1, 1)), atol=1e-12)
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    # smooth: < 3 cm per frame at 30 Hz; the figure eight is a fast hand-held motion, <= 1.5 m/s
    assert steps.max() < (0.05 if motion == "figure8" else 0.03)
    rel = np.swapaxes(poses[:1, :3, :3], 1, 2) @ poses[:, :3, :3]  # rotation from the first pose
    if motion == "static":
        np.testing.assert_array_equal(poses, np.broadcast_to(poses[0], poses.shape))  # no motion at all
    elif motion == "rpy":
        # rotation about the optical centre: the camera stays put ...
        np.testing.assert_allclose(pos, np.broadcast_to(pos[0], pos.shape), atol=1e-12)
        # ... and turns +-20 deg about each camera axis (R = R0 Ry(yaw) Rx(pitch) Rz(roll); in
        # 10 s at 30 Hz every sine with period 4-6 s reaches its extremes within 1/60 s)
        yaw, pitch, roll = np.degrees(Rotation.from_matrix(rel).as_euler("YXZ")).T
        for name, a in (("yaw", yaw), ("pitch", pitch), ("roll", roll)):
            assert np.abs(a).max() <= 20.0 + 1e-9, name
            assert a.max() > 19.9 and a.min() < -19.9, (name, a.min(), a.max())
        # smooth: the angular speed is at most the sum of the axes' peak rates,
        # 20 deg * 2 pi * (1/4 + 1/5 + 1/6) / s = 77.5 deg/s, i.e. 2.58 deg per frame at 30 Hz
        step_rot = np.swapaxes(poses[:-1, :3, :3], 1, 2) @ poses[1:, :3, :3]
        assert np.degrees(Rotation.from_matrix(step_rot).magnitude()).max() < 2.6
    else:
        assert steps.sum() > 0.05
    cam = scaled_camera("ros_default", 80, 60)
    rays, scene = Rays(cam), Scene(0, surfaces=scene_surfaces())
    for k in range(0, 300, 30):
        _, depth, hit = scene.render(rays, poses[k])
        assert (hit >= 0).all()
        assert 0.8 <= np.median(depth) <= 4.0 and depth.min() > 0.3


def test_seeded_noise_dropout_and_reproducibility(tmp_path):
    kw = dict(frames=2, motion="static", width=320, height=240)
    generate_sequence(tmp_path / "clean", **kw, seed=4)
    generate_sequence(tmp_path / "noisy", **kw, seed=4, noise=True)
    generate_sequence(tmp_path / "noisy2", **kw, seed=4, noise=True)
    generate_sequence(tmp_path / "holes", **kw, seed=4, dropout=0.2)
    generate_sequence(tmp_path / "other", **kw, seed=5)
    clean, noisy = open_sequence(tmp_path / "clean").load(1), open_sequence(tmp_path / "noisy").load(1)
    wall = np.abs(clean.depth - 3.0) < 1e-6  # pixels on the wall x = 3 (z = 3 m)
    d = (noisy.depth - clean.depth)[wall]
    expected = 0.0012 + 0.0019 * (3.0 - 0.4) ** 2
    assert wall.sum() > 5000 and abs(d.std() / expected - 1) < 0.1 and abs(d.mean()) < 0.002
    for name in ("rgb", "depth"):
        a = sorted((tmp_path / "noisy" / name).iterdir())
        b = sorted((tmp_path / "noisy2" / name).iterdir())
        assert [p.read_bytes() for p in a] == [p.read_bytes() for p in b]
    holes = open_sequence(tmp_path / "holes").load(1)
    assert abs((holes.depth == 0).mean() - 0.2) < 0.03
    np.testing.assert_array_equal(holes.depth[holes.depth > 0], clean.depth[holes.depth > 0])
    other = open_sequence(tmp_path / "other").load(1)
    np.testing.assert_array_equal(other.depth, clean.depth)  # same room ...
    assert np.abs(other.rgb.astype(int) - clean.rgb).mean() > 20  # ... other textures


def test_bad_arguments_and_foreign_folder(tmp_path):
    with pytest.raises(InputError, match="unknown motion"):
        generate_sequence(tmp_path / "a", frames=2, motion="spin")
    with pytest.raises(InputError, match="dropout"):
        generate_sequence(tmp_path / "a", frames=2, dropout=1.5)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("x")
    with pytest.raises(InputError, match="not empty"):
        generate_sequence(tmp_path / "mine", frames=1)
    assert (tmp_path / "mine" / "notes.txt").read_text() == "x"


def test_synth_command(tmp_path):
    out = tmp_path / "cli"
    res = CliRunner().invoke(main, ["synth", str(out), "--frames", "3", "--motion", "circle", "--size", "160", "120", "--seed", "2"])
    assert res.exit_code == 0, res.output
    assert len(open_sequence(out)) == 3 and len(open_sequence(out).groundtruth()) == 3
    # regenerating into the same folder replaces the old sequence
    res = CliRunner().invoke(main, ["synth", str(out), "-n", "2", "--size", "160", "120"])
    assert res.exit_code == 0 and len(list((out / "rgb").iterdir())) == 2
    # an out-of-range option reaches the library's InputError: the CLI turns it into exit code 2
    # and one "error: ..." line (an uncaught exception would be res.exception, exit code 1)
    res = CliRunner().invoke(main, ["synth", str(tmp_path / "bad"), "--dropout", "1.5"])
    assert isinstance(res.exception, SystemExit) and res.exception.code == 2 and res.exit_code == 2
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    assert "dropout" in lines[0] and "1.5" in lines[0] and "[0, 1)" in lines[0]
    assert res.stderr.strip() == lines[0]
    assert not (tmp_path / "bad").exists()  # rejected before anything is written


# ----------------------------------------------------------------------------- an existing sequence is safe


def _tree(folder) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("args, message", [
    (["--seed", "-1"], "--seed must be a whole number >= 0 (got -1)"),
    (["--size", "100000", "100000"], "image size 100000x100000 is out of range; --size W H must be whole numbers "
                                     "from 16 to 4096 (e.g. --size 640 480)"),
    (["--size", "8", "8"], "image size 8x8 is out of range; --size W H must be whole numbers from 16 to 4096 "
                           "(e.g. --size 640 480)"),
    (["--frames", "0"], "--frames must be a whole number from 1 to 100000 (got 0)"),
    (["--dropout", "nan"], "dropout must be in [0, 1) (got nan)"),
    (["--drift", "0.5"], "drift must be a small relative depth error in (-0.5, 0.5) (got 0.5)"),
])
def test_bad_parameters_leave_the_existing_sequence(tmp_path, args, message):
    """Every parameter is checked before the output folder is touched: `synth S --seed -1` used to
    delete the sequence S and then fail with a traceback (--size 100000 100000: MemoryError)."""
    out = tmp_path / "S"
    generate_sequence(out, frames=2, motion="static", width=32, height=24)
    before = _tree(out)
    res = CliRunner().invoke(main, ["synth", str(out), "--frames", "5", *args] if "--frames" not in args
                             else ["synth", str(out), *args])
    assert isinstance(res.exception, SystemExit) and res.exit_code == 2, res.output
    assert res.stderr.strip() == f"error: {message}" and res.output.strip() == f"error: {message}"
    assert _tree(out) == before and sorted(p.name for p in tmp_path.iterdir()) == ["S"]


@pytest.mark.parametrize("failure", [KeyboardInterrupt, InputError])
def test_failure_or_ctrl_c_while_rendering_keeps_the_old_sequence(tmp_path, monkeypatch, failure):
    """The new sequence is rendered into a temporary sibling folder that replaces S only when
    complete: Ctrl-C (or a write error) part-way leaves S as it was and no partial folder."""
    from rgbdslam.datasets import synthetic

    out = tmp_path / "S"
    generate_sequence(out, frames=2, motion="static", width=32, height=24)
    before = _tree(out)
    real, calls = synthetic._write_frame, []

    def write_then_fail(*a, **kw):
        calls.append(1)
        if len(calls) == 2:
            raise failure("cannot write frame 1") if failure is InputError else failure()
        return real(*a, **kw)

    monkeypatch.setattr(synthetic, "_write_frame", write_then_fail)
    with pytest.raises(failure):
        generate_sequence(out, frames=4, motion="xyz", width=32, height=24, seed=3)
    assert _tree(out) == before and sorted(p.name for p in tmp_path.iterdir()) == ["S"]
    assert len(open_sequence(out)) == 2


def test_regenerating_replaces_the_frames_and_keeps_other_files(tmp_path):
    out = tmp_path / "S"
    generate_sequence(out, frames=3, motion="static", width=32, height=24)
    (out / "notes.txt").write_text("mine")
    generate_sequence(out, frames=2, motion="xyz", width=48, height=32, seed=1)
    seq = open_sequence(out)
    assert len(seq) == 2 and (seq.camera.width, seq.camera.height) == (48, 32)
    assert len(list((out / "rgb").iterdir())) == 2 and (out / "notes.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["S"]
    new = tmp_path / "T"
    generate_sequence(new, frames=1, motion="static", width=32, height=24)
    assert new.stat().st_mode & 0o055  # a plain folder's permissions, not the temporary folder's 0700


def test_ctrl_c_during_the_swap_finishes_it_and_leaves_no_copy(tmp_path, monkeypatch):
    """SIGINT while the finished sequence is renamed into place: the renames complete, then the
    interrupt is raised; no hidden copy of the earlier sequence is left beside it."""
    import os
    import signal

    import rgbdslam.datasets.synthetic as syn

    out = tmp_path / "seq"
    generate_sequence(out, frames=3, width=64, height=48, seed=1)
    real_replace, sent = os.replace, []

    def replace(a, b):  # os is one module: only the swap's first rename into .replaced triggers it
        if not sent and ".replaced" in str(b):
            sent.append(1)
            os.kill(os.getpid(), signal.SIGINT)  # delivered now, held back until the renames are done
        return real_replace(a, b)

    monkeypatch.setattr(syn.os, "replace", replace)
    with pytest.raises(KeyboardInterrupt):
        generate_sequence(out, frames=4, width=64, height=48, seed=2)
    assert sent and len((out / "rgb.txt").read_text().split("rgb/")) - 1 == 4  # the new sequence, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]  # no .seq.partial-* left, beside or inside
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == [".rgbdslam-manifest.json"]
    generate_sequence(out, frames=3, width=64, height=48, seed=3)  # the manifest lists the new sequence: replaced
