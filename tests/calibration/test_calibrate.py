"""``rgbdslam calibrate``: the depth-to-colour search and the rolling-shutter readout, on real frames
(7-Scenes' unregistered Kinect; TUM fr1, whose readout is known), their files read back into a run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import rgbdslam
from rgbdslam.calibration.depth_to_color import edge_points, score
from rgbdslam.calibration.rolling_shutter import loop_discrepancies
from rgbdslam.datasets.camera_file import read_camera_file
from rgbdslam.geometry.camera import CAMERAS, Camera
from tests.conftest import DATA, cli, need

SEVEN = DATA / "7scenes" / "frames_0000_0299"
RPY200 = DATA / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
SHIPPED = str(Path(rgbdslam.__file__).parent / "cameras" / "7scenes.yaml")  # whatever the working folder


def test_edge_points_and_score_by_hand():
    """A wall at 2 m (columns 0-4) in front of one at 4 m: the outline is column 4 at 2 m; its
    points projected with the right focal length land on the one column where the gradient is."""
    cam = Camera(100.0, 100.0, 5.0, 5.0, 10, 10)
    depth = np.full((10, 10), 4.0)
    depth[:, :5] = 2.0
    P = edge_points(depth, cam)
    assert P.shape == (10, 3)
    assert np.allclose(P[:, 2], 2.0) and np.allclose(P[:, 0], (4 - 5.0) * 2.0 / 100.0)
    grad = np.zeros((10, 10), np.float32)
    grad[:, 4] = 1.0
    assert score([(P, grad)], 100.0, 5.0, 5.0) == 1.0
    assert score([(P, grad)], 100.0, 5.0, 5.0, tx=0.02) == 0.0  # moved one pixel: no edge there
    T = np.eye(4)
    T[0, 3] = 0.02
    assert score([(P, grad)], 100.0, 6.0, 5.0, T=T) == 0.0 and score([(P, grad)], 100.0, 4.0, 5.0, T=T) == 1.0


@pytest.mark.data
def test_depth_to_color_finds_the_7scenes_colour_camera_and_its_file_runs(tmp_path):
    """7-Scenes' colour focal length is 530 px (the shipped camera: 3.03 -> 1.92 cm ATE on frames
    0-299), its depth camera about 2 cm to the side; a coarse search on 6 frames finds both, and the
    file it writes is a camera file a run takes."""
    cam_file = tmp_path / "kinect.yaml"
    res = cli(["calibrate", "depth-to-color", need(SEVEN), "--frames", "6", "--focal", "500:600:10",
               "--tx", "-0.04:0.02:0.02", "--ty", "0:0:0.01", "--out", cam_file, "--check", SHIPPED])
    assert res.exit_code == 0, res.output
    recorded = float(res.output.split("as recorded (colour = depth camera, no offset): score ")[1].split()[0])
    best = float(res.output.split("\nscore ")[1].split(":")[0])
    assert best > 1.5 * recorded  # the outlines land on edges, not beside them
    setup = read_camera_file(cam_file)
    assert setup.camera.fx == setup.camera.fy == 530.0
    assert (setup.depth_camera.fx, setup.depth_camera.cx) == (585.0, 320.0)
    assert -0.03 <= setup.depth_to_color[0, 3] <= -0.01 and setup.depth_to_color[1, 3] == 0.0
    assert f"{SHIPPED} (colour focal 530, t = (+0.0000" in res.output

    run = tmp_path / "run"
    res = cli(["run", SEVEN, "--camera", cam_file, "--max-frames", "30", "--out", run, "--no-map", "-q",
               "--set", "output.plots=false"])
    assert res.exit_code == 0, res.output
    info = json.loads((run / "run.json").read_text())
    assert info["status"] == "finished" and info["tracked"] == 30 and str(cam_file) in info["camera_source"]
    assert info["evaluation"]["ate"]["rmse"] < 0.01  # 2.3 mm over these 30 frames


def test_a_grid_that_is_no_grid_is_one_line(tmp_path):
    res = cli(["calibrate", "depth-to-color", tmp_path, "--focal", "600:500:5"])
    assert res.exit_code == 2 and res.stderr.strip().count("\n") == 0
    assert "--focal '600:500:5' needs lo <= hi" in res.stderr


@pytest.mark.data
@pytest.mark.slow
def test_rolling_shutter_finds_fr1s_readout_from_its_loop_closures(tmp_path):
    """fr1's readout is 17.5 ms (CAMERAS['fr1']); against 0 (no compensation) and 35 ms the
    odometry of fr1/rpy agrees best with its loop closures there (median rotation 1.2 deg vs 4.3
    at 0), with no ground truth used."""
    assert CAMERAS["fr1"].readout == 0.0175
    res = cli(["calibrate", "rolling-shutter", need(RPY200), "--values", "0,0.0175,0.035", "--work", tmp_path])
    assert res.exit_code == 0, res.output
    assert "smallest loop/odometry rotation discrepancy at features.rolling_shutter = 0.0175" in res.output
    at = {v: loop_discrepancies(tmp_path / f"value_{v}") for v in ("0", "0.0175", "0.035")}
    assert all(len(d) >= 10 for d in at.values())  # the runs closed loops to judge by
    med = {v: float(np.median(d[:, 1])) for v, d in at.items()}
    assert med["0.0175"] < 0.5 * med["0"] and med["0.0175"] < med["0.035"]


def test_a_camera_file_varied_per_value_keeps_its_other_keys(tmp_path):
    """--camera-key fx,fy: each value's run reads a copy of the camera file with those keys set."""
    from rgbdslam.calibration.rolling_shutter import camera_variant

    copy = camera_variant(SHIPPED, ["fx", "fy"], 525.0, tmp_path)
    setup, shipped = read_camera_file(copy), read_camera_file(SHIPPED)
    assert (setup.camera.fx, setup.camera.fy) == (525.0, 525.0)
    assert (setup.camera.cx, setup.depth_camera, setup.depth_scale) == (shipped.camera.cx, shipped.depth_camera,
                                                                         shipped.depth_scale)
    res = cli(["calibrate", "rolling-shutter", tmp_path, "--camera-key", "fx", "--values", "500"])
    assert res.exit_code == 2 and "--camera-key needs --set dataset.camera_file=FILE" in res.stderr


@pytest.mark.data
def test_loop_discrepancies_find_keyframes_by_time_stamp_within_one_tracking_segment(tmp_path):
    """odometry.tum has no line for a lost frame: a keyframe's odometry pose is found by its time
    stamp, not by its frame number as a row; an edge to a frame without a line, or across a
    tracking restart (two coordinate frames), is left out. A real fr1/rpy run, its files edited as
    a run that lost frames 50 (a plain frame) and 110 (a keyframe with loop edges) would write."""
    import shutil

    from rgbdslam.posegraph.graph_io import read_graph

    run = tmp_path / "run"
    res = cli(["run", need(RPY200), "--out", run, "--no-map", "-q", "--set", "output.plots=false"])
    assert res.exit_code == 0, res.output
    whole = loop_discrepancies(run)
    g = read_graph(run / "posegraph.g2o")
    ids = [int(x) for x in g.ids]
    edges = [(ids[i], ids[j]) for i, j in zip(g.edges_i, g.edges_j)]
    loops = [e for e in edges if abs(sorted(ids).index(e[0]) - sorted(ids).index(e[1])) != 1]
    assert len(loops) == len(whole) >= 10 and 50 not in ids and any(110 in e for e in loops)

    lost = tmp_path / "lost"
    shutil.copytree(run, lost)
    lines = (run / "odometry.tum").read_text().splitlines()
    rows = [ln for ln in lines if ln.strip() and not ln.startswith("#")]
    assert len(rows) == 200
    drop = {rows[50], rows[110]}
    (lost / "odometry.tum").write_text("\n".join(ln for ln in lines if ln not in drop) + "\n")
    info = json.loads((run / "run.json").read_text())
    info.update(lost_frames=[50, 110], lost=2, tracked=198)
    (lost / "run.json").write_text(json.dumps(info))
    kept = [k for k, e in enumerate(loops) if 110 not in e]
    assert np.array_equal(loop_discrepancies(lost), whole[kept])  # the same poses compared, bit for bit

    split = tmp_path / "split"  # a restart at frame 100: frames 100-199 are tracked in new coordinates
    shutil.copytree(run, split)
    info = json.loads((run / "run.json").read_text())
    info.update(restarts=[100], segments=[{"first": 0, "last": 99, "frames": 100, "map": True},
                                          {"first": 100, "last": 199, "frames": 100, "map": False}])
    (split / "run.json").write_text(json.dumps(info))
    same = [k for k, (i, j) in enumerate(loops) if (i < 100) == (j < 100)]
    assert 0 < len(same) < len(loops)
    assert np.array_equal(loop_discrepancies(split), whole[same])
