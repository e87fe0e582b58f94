"""Rerun recordings: written by RerunLogger / record_run and read back with Rerun's own `rerun rrd print`."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from rgbdslam.cli import main
from rgbdslam.config import Config
from rgbdslam.datasets.base import Frame
from rgbdslam.errors import RgbdslamError
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import make_pose
from rgbdslam.io.trajectory import Trajectory, write_tum
from rgbdslam.viz.rerun_log import RerunLogger, rerun_executable

CAM = Camera(100.0, 100.0, 80.0, 60.0, 160, 120)


def entity_paths(rrd: Path) -> set[str]:
    """Entity paths in an .rrd, as Rerun's own CLI reports them."""
    out = subprocess.run([rerun_executable(), "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-500:]
    return set(re.findall(r" - (/\S+) - ", out.stdout))


def _frame(i: int) -> Frame:
    rng = np.random.default_rng(i)
    rgb = rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)
    depth = np.full((120, 160), 1.0 + 0.1 * i, np.float32)
    return Frame(i, 10.0 + i / 30, rgb, depth, CAM)


def _result(i: int, lost: bool = False):
    feats = SimpleNamespace(uv=np.array([[10.0, 20.0], [50.0, 60.0]]), valid=np.array([True, False]),
                            uv_raw=np.zeros((0, 2)))
    pose = None if lost else make_pose(np.eye(3), [0.05 * i, 0, 0])
    return SimpleNamespace(index=i, timestamp=10.0 + i / 30, pose=pose, lost=lost, features=feats,
                           n_matches=100 + i, n_inliers=80 + i, timings={"features": 0.01, "registration": 0.002})


def test_logger_records_all_entities(tmp_path):
    cfg = Config()
    cfg.output.rerun_image_width = 80  # half size: 80 x 60 images
    gt = Trajectory(10.0 + np.arange(4) / 30, np.array([make_pose(np.eye(3), [0.05 * i, 0.01, 0]) for i in range(4)]))
    rrd = tmp_path / "run.rrd"
    log = RerunLogger(cfg, CAM, gt, spawn=False, save_path=rrd)
    assert log.img_size == (80, 60)
    for i in range(4):
        log.log_frame(_frame(i), _result(i, lost=(i == 2)))
    log.log_inlier_matches(3, np.array([[1.0, 2.0]]), np.array([[3.0, 4.0]]))
    log.log_loop(0, 3, _result(0).pose, _result(3).pose)
    log.log_trajectory("estimate", Trajectory(gt.timestamps, gt.poses))
    log.log_map(np.zeros((5, 3)), np.full((5, 3), 200, np.uint8))
    log.close()
    # first-frame alignment: gt pose 0 is moved onto estimated pose 0 (a shift of -0.01 in y)
    assert np.allclose(log.gt_align[:3, 3], [0, -0.01, 0])
    paths = entity_paths(rrd)
    expected = {
        "/world",  # view coordinates (RDF): the first pose is the identity, so the world is the first camera
        "/world/camera", "/world/camera/image", "/world/camera/image/rgb", "/world/camera/image/depth",
        "/world/camera/image/keypoints", "/world/camera/image/matches", "/world/trajectory/live",
        "/world/trajectory/groundtruth", "/world/trajectory/estimate", "/world/loops", "/world/map",
        "/timings/features", "/timings/registration", "/stats/n_inliers", "/stats/lost",
    }
    assert expected <= paths, expected - paths


def test_spawn_without_display_fails_in_one_line(tmp_path, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(RgbdslamError, match="--rerun-save") as e:
        RerunLogger(Config(), CAM, None, spawn=True, save_path=None)
    assert "\n" not in str(e.value)
    # with a file to save to, the run goes on and only records
    log = RerunLogger(Config(), CAM, None, spawn=True, save_path=tmp_path / "x.rrd")
    log.log_frame(_frame(0), _result(0))
    log.close()
    assert "/world/camera" in entity_paths(tmp_path / "x.rrd")


def test_view_run_folder_without_display_writes_recording(tmp_path, monkeypatch):
    from test_mapping import POSES, _write_tum_folder  # the hand-rendered plane sequence

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    seq, run = tmp_path / "seq", tmp_path / "run"
    stamps = [100.0, 100.5, 101.0]
    _write_tum_folder(seq, POSES, stamps)
    run.mkdir()
    write_tum(Trajectory(stamps, np.array(POSES)), run / "trajectory.tum")
    write_tum(Trajectory(stamps, np.array(POSES)), run / "odometry.tum")
    (run / "run.json").write_text(json.dumps({"sequence": str(seq), "keyframes": [0, 2], "loops": [[0, 2]]}))
    runner = CliRunner()
    res = runner.invoke(main, ["fuse", str(run), "-q", "--set", "mapping.map2d=false"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(main, ["view", str(run), "-q"])
    assert res.exit_code == 0, res.output
    rrd = run / "recording.rrd"
    assert rrd.is_file() and "no display" in res.output and str(rrd.resolve()) in res.output.replace("\n", "")
    paths = entity_paths(rrd)
    assert {"/world/map", "/world/trajectory/estimate", "/world/trajectory/odometry", "/world/loops",
            "/world/camera", "/world/camera/image/rgb", "/world/camera/image/depth"} <= paths
    # an existing recording is reused, not rebuilt; an .rrd path is opened as it is
    mtime = rrd.stat().st_mtime_ns
    assert runner.invoke(main, ["view", str(run)]).exit_code == 0 and rrd.stat().st_mtime_ns == mtime
    assert runner.invoke(main, ["view", str(rrd)]).exit_code == 0
    bad = runner.invoke(main, ["view", str(tmp_path / "nothing")])
    assert bad.exit_code == 2 and "does not exist" in bad.output
