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
    from tests.mapping.test_mapping import POSES

    seq, run = _plane_run_with_recording(tmp_path, monkeypatch)
    stamps = [100.0, 100.5, 101.0]
    write_tum(Trajectory(stamps, np.array(POSES)), run / "odometry.tum")
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


# ----------------------------------------------------------------------------- failures keep earlier recordings


def _hidden(folder: Path) -> list[str]:
    """Hidden (temporary) files; a run folder's lock file (rgbdslam.runfolder.folder) and an output
    folder's manifest (rgbdslam.io.manifest) are not."""
    from rgbdslam.runfolder.folder import LOCK_NAME
    from rgbdslam.io.manifest import MANIFEST

    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".") and p.name not in (LOCK_NAME, MANIFEST))


def test_logger_replaces_the_file_only_when_closed(tmp_path):
    """The recording goes to a temporary file beside --rerun-save; close() renames it over the
    target. A logger that is dropped unclosed (a run that failed) or aborted leaves the earlier
    recording byte for byte and no temporary file."""
    import gc

    good = tmp_path / "good.rrd"
    log = RerunLogger(Config(), CAM, None, spawn=False, save_path=good)
    for i in range(3):
        log.log_frame(_frame(i), _result(i))
    assert not good.exists() and len(_hidden(tmp_path)) == 1  # only the temporary file so far
    log.close()
    before = good.read_bytes()
    assert "/world/camera/image/rgb" in entity_paths(good) and _hidden(tmp_path) == []

    failed = RerunLogger(Config(), CAM, None, spawn=False, save_path=good)  # a run that fails part-way
    failed.log_frame(_frame(0), _result(0))
    del failed
    gc.collect()
    assert good.read_bytes() == before and _hidden(tmp_path) == []

    aborted = RerunLogger(Config(), CAM, None, spawn=False, save_path=good)
    aborted.log_frame(_frame(0), _result(0))
    aborted.abort()
    assert good.read_bytes() == before and _hidden(tmp_path) == []


def test_failed_run_keeps_earlier_rerun_save(tmp_path):
    """`rgbdslam run SEQ --rerun-save good.rrd` that fails (here: no depth, nothing can be tracked)
    leaves the good.rrd of an earlier run as it was (it used to be replaced by the failed run's
    recording)."""
    import gc
    import shutil

    import cv2

    from rgbdslam.datasets.synthetic import generate_sequence

    seq, good = tmp_path / "seq", tmp_path / "good.rrd"
    generate_sequence(seq, frames=4, motion="xyz", width=160, height=120)
    runner = CliRunner()
    res = runner.invoke(main, ["run", str(seq), "-o", str(tmp_path / "run"), "-q", "--rerun-save", str(good)])
    assert res.exit_code == 0, res.output
    before = good.read_bytes()
    shutil.copytree(seq, tmp_path / "nodepth")
    for p in (tmp_path / "nodepth" / "depth").glob("*.png"):
        cv2.imwrite(str(p), np.zeros((120, 160), np.uint16))
    res = runner.invoke(main, ["run", str(tmp_path / "nodepth"), "-o", str(tmp_path / "run2"), "-q",
                               "--rerun-save", str(good)])
    assert isinstance(res.exception, SystemExit) and res.exit_code == 3, res.output
    assert "could be tracked" in res.stderr.strip().splitlines()[-1]
    del res
    gc.collect()  # the failed run's logger is dropped unclosed: its temporary file goes with it
    assert good.read_bytes() == before and _hidden(tmp_path) == []


def _plane_run_with_recording(tmp_path, monkeypatch):
    from tests.mapping.test_mapping import POSES, _write_tum_folder  # the hand-rendered plane sequence

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    seq, run = tmp_path / "seq", tmp_path / "run"
    stamps = [100.0, 100.5, 101.0]
    _write_tum_folder(seq, POSES, stamps)
    run.mkdir()
    write_tum(Trajectory(stamps, np.array(POSES)), run / "trajectory.tum")
    (run / "run.json").write_text(json.dumps({"sequence": str(seq), "keyframes": [0, 2], "loops": [[0, 2]]}))
    from rgbdslam.config import Config, save_config

    save_config(Config(), run / "config.yaml")  # as every run folder has (else view warns)
    return seq, run


def test_view_failure_leaves_no_temporary_files_and_keeps_earlier_save(tmp_path, monkeypatch):
    seq, run = _plane_run_with_recording(tmp_path, monkeypatch)
    runner = CliRunner()
    out = tmp_path / "out"  # no .rrd suffix: the temporary file used to be ./.out.tmp
    assert runner.invoke(main, ["view", str(run), "--save", str(out), "-q"]).exit_code == 0
    assert runner.invoke(main, ["view", str(run), "-q"]).exit_code == 0
    saved, recording = out.read_bytes(), (run / "recording.rrd").read_bytes()
    bad = sorted((seq / "rgb").iterdir())[2]  # keyframe 2 cannot be read: recording fails part-way
    bad.write_bytes(b"not a png")
    for args in (["view", str(run), "--save", str(out), "-q"],
                 ["view", str(run), "--save", str(run / "recording.rrd"), "-q"]):
        res = runner.invoke(main, args)
        assert isinstance(res.exception, SystemExit) and res.exit_code == 2, res.output
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and str(bad) in lines[0], res.stderr
    assert out.read_bytes() == saved and (run / "recording.rrd").read_bytes() == recording
    assert _hidden(tmp_path) == [] and _hidden(run) == []


@pytest.mark.parametrize("edit, message", [
    ({"sequence": 5}, "'sequence' must be the path of the sequence folder as a string; got 5"),
    ({"keyframes": ["a"]}, "'keyframes' must be a list of frame numbers (whole numbers); found 'a'"),
    ({"loops": [[0]]}, "'loops' must be a list of frame-number pairs [i, j]; got [[0]]"),
])
def test_view_hand_edited_run_json_is_one_line(tmp_path, monkeypatch, edit, message):
    seq, run = _plane_run_with_recording(tmp_path, monkeypatch)
    info = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps({**info, **edit}))
    res = CliRunner().invoke(main, ["view", str(run), "-q"])
    assert isinstance(res.exception, SystemExit) and res.exit_code == 2, res.output
    assert res.stderr.strip() == (f"error: {run / 'run.json'}: {message}; re-run `rgbdslam run` to rewrite it, "
                                  f"or correct the field")
    assert not (run / "recording.rrd").exists() and _hidden(run) == []


@pytest.mark.parametrize("value", ["nan", "inf", "-1", "0"])
def test_serve_for_must_be_a_finite_time(tmp_path, value):
    """`view --web --serve-for nan` served for ever (every time-out comparison with NaN is false)."""
    from tests.conftest import assert_cli_error, cli

    rrd = tmp_path / "x.rrd"
    rrd.write_bytes(b"")
    assert_cli_error(cli(["view", rrd, "--web", "--serve-for", value]),
                     f"--serve-for: the time to serve must be a finite number above 0 and at most 3.2e+07; "
                     f"got {float(value)!r}")
