"""End-to-end: the orchestrator and the `run`/`demo` commands on synthetic and real frames."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from rgbdslam.cli import main
from rgbdslam.config import load_config
from rgbdslam.datasets import open_sequence
from rgbdslam.datasets.base import Sequence
from rgbdslam.errors import InputError, TrackingLost
from rgbdslam.evaluation.ate import ate
from rgbdslam.io.trajectory import read_tum
from rgbdslam.pipeline import run_sequence


def _fast_cfg(*extra):
    return load_config(None, ["mapping.enabled=false", "output.plots=false", *extra])


@pytest.fixture(scope="module")
def synth_clean(tmp_path_factory):
    from rgbdslam.datasets.synthetic import generate_sequence

    out = tmp_path_factory.mktemp("synth") / "clean"
    generate_sequence(out, frames=100, motion="xyz", noise=False, seed=3)
    return out


def test_synthetic_noise_free_within_5mm(synth_clean, tmp_path):
    summary = run_sequence(synth_clean, tmp_path / "run", _fast_cfg(), progress=False)
    est = read_tum(tmp_path / "run" / "trajectory.tum")
    gt = open_sequence(synth_clean).groundtruth()
    res = ate(gt, est)
    assert summary["lost"] == 0
    assert res.n_pairs == 100
    assert res.rmse < 0.005


def test_run_is_reproducible(synth_clean, tmp_path):
    cfg = _fast_cfg("dataset.max_frames=40")
    run_sequence(synth_clean, tmp_path / "a", cfg, progress=False)
    run_sequence(synth_clean, tmp_path / "b", cfg, progress=False)
    a = (tmp_path / "a" / "trajectory.tum").read_text()
    b = (tmp_path / "b" / "trajectory.tum").read_text()
    assert a == b


@pytest.mark.data
def test_run_folder_contents(desk9, tmp_path):
    out = tmp_path / "desk"
    res = CliRunner().invoke(main, ["run", str(desk9), "--out", str(out), "--no-map", "-q",
                                    "--set", "registration.mp=3", "--set", "loop.min_votes=17"])
    assert res.exit_code == 0, res.output
    for name in ("trajectory.tum", "odometry.tum", "config.yaml", "run.json", "evaluation.json"):
        assert (out / name).is_file(), name
    run = json.loads((out / "run.json").read_text())
    assert run["frames"] == 9 and run["tracked"] + run["lost"] == 9
    assert run["evaluation"]["ate"]["rmse"] < 0.03
    # the config written next to the outputs loads back and equals the one used (the preset the
    # freiburg1 folder chooses, overrides included)
    assert "preset tum_fr1: TUM layout, camera fr1" in res.output
    used = load_config("tum_fr1", ["registration.mp=3", "loop.min_votes=17"]).to_dict()
    saved = load_config(out / "config.yaml").to_dict()
    assert saved["registration"]["mp"] == 3 and saved["loop"]["min_votes"] == 17
    assert {k: v for k, v in saved.items() if k != "mapping"} == {k: v for k, v in used.items() if k != "mapping"}


@pytest.mark.data
def test_rpy200_accuracy(rpy200, tmp_path):
    """fr1/rpy head200 with the defaults: 0.0177 m ATE RMSE with 31 loops (benchmarks.md). The
    front end alone gives 0.027 m, so the bound fails if loop closure or the pose graph stops
    helping; issue 2 asked for 0.05 m."""
    summary = run_sequence(rpy200, tmp_path / "rpy", _fast_cfg(), progress=False)
    assert summary["evaluation"]["ate"]["rmse"] < 0.022
    assert summary["lost"] == 0 and summary["restarts"] == []
    assert len(summary["loops"]) >= 10
    lc = summary["loop_closure"]  # the counters add up: every accepted loop was verified, ...
    assert lc["n_accepted"] == len(summary["loops"]) and lc["n_sharp"] == summary["sharp_frames"]
    assert lc["n_verified"] == lc["n_candidates"] >= lc["n_accepted"] + lc["n_rejected_geometry"]
    assert lc["n_queries"] >= lc["n_sharp"]  # sharp frames, plus the query_gap floor


class _InterruptingSequence:
    """Wraps a sequence and raises KeyboardInterrupt when frame ``at`` is loaded (a Ctrl-C)."""

    prefetched = Sequence.prefetched  # reads through this wrapper's load, in the reader thread

    def __init__(self, seq, at):
        self._seq, self._at = seq, at

    def __getattr__(self, name):
        return getattr(self._seq, name)

    def __len__(self):
        return len(self._seq)

    def load(self, i):
        if i == self._at:
            raise KeyboardInterrupt
        return self._seq.load(i)


@pytest.mark.parametrize("prefetch", [0, 4])
def test_interrupted_run_keeps_valid_trajectory(synth_clean, tmp_path, monkeypatch, prefetch):
    import rgbdslam.pipeline as pl

    seq = open_sequence(synth_clean)
    wrapped = _InterruptingSequence(seq, at=12)
    monkeypatch.setattr(pl, "open_sequence", lambda *a, **k: wrapped)
    cfg = _fast_cfg()
    cfg.dataset.prefetch = prefetch
    with pytest.raises(KeyboardInterrupt):
        run_sequence(synth_clean, tmp_path / "int", cfg, progress=False)
    traj = read_tum(tmp_path / "int" / "trajectory.tum")
    assert len(traj) == 12 and np.all(np.isfinite(traj.poses))
    assert len(read_tum(tmp_path / "int" / "odometry.tum")) == 12
    run = json.loads((tmp_path / "int" / "run.json").read_text())
    assert run["interrupted"] is True and run["frames"] == 12 and run["tracked"] == 12
    # the 12 poses are the right ones, not merely 12 lines (noise-free: millimetres)
    assert ate(open_sequence(synth_clean).groundtruth(), traj).rmse < 0.005


def test_interrupt_before_any_frame_is_an_interrupt_not_a_tracking_failure(synth_clean, tmp_path, monkeypatch):
    import rgbdslam.pipeline as pl

    monkeypatch.setattr(pl, "open_sequence", lambda *a, **k: _InterruptingSequence(open_sequence(synth_clean), at=0))
    with pytest.raises(KeyboardInterrupt):
        run_sequence(synth_clean, tmp_path / "int", _fast_cfg("dataset.prefetch=0"), progress=False)
    run = json.loads((tmp_path / "int" / "run.json").read_text())
    assert run["interrupted"] is True and run["tracked"] == 0


def test_ctrl_c_on_the_command_line_exits_130_and_says_work_was_saved(synth_clean, tmp_path, monkeypatch):
    import rgbdslam.pipeline as pl

    monkeypatch.setattr(pl, "open_sequence", lambda *a, **k: _InterruptingSequence(open_sequence(synth_clean), at=8))
    res = CliRunner().invoke(main, ["run", str(synth_clean), "--out", str(tmp_path / "run"), "--no-map", "-q"])
    assert isinstance(res.exception, SystemExit) and res.exit_code == 130
    assert "interrupted: finished work was saved" in res.output
    assert len(read_tum(tmp_path / "run" / "trajectory.tum")) == 8


class _CheckingSequence(_InterruptingSequence):
    """Records, when frame ``at`` is loaded, how many poses trajectory.tum holds on disk."""

    def __init__(self, seq, at, path):
        super().__init__(seq, at=-1)
        self._check, self._path, self.seen = at, path, None

    def load(self, i):
        if i == self._check:
            self.seen = len(read_tum(self._path)) if self._path.is_file() else 0
        return self._seq.load(i)


def test_long_runs_write_their_trajectory_every_50_frames(synth_clean, tmp_path, monkeypatch):
    """A run killed hard (no chance to clean up) still leaves the trajectory of the last 50-frame
    block: by the time frame 55 is read, trajectory.tum on disk holds frames 0-49."""
    import rgbdslam.pipeline as pl

    wrapped = _CheckingSequence(open_sequence(synth_clean), 55, tmp_path / "run" / "trajectory.tum")
    monkeypatch.setattr(pl, "open_sequence", lambda *a, **k: wrapped)
    run_sequence(synth_clean, tmp_path / "run", _fast_cfg("dataset.prefetch=0", "dataset.max_frames=60"),
                 progress=False)
    assert pl.FLUSH_EVERY == 50 and wrapped.seen == 50


@pytest.mark.data
def test_corrupt_image_is_skipped_not_fatal(desk9, tmp_path):
    seq_dir = tmp_path / "desk"
    shutil.copytree(desk9, seq_dir)
    victim = sorted((seq_dir / "rgb").glob("*.png"))[4]
    victim.write_bytes(b"not a png")
    summary = run_sequence(seq_dir, tmp_path / "run", _fast_cfg(), progress=False)
    assert summary["skipped"] == 1 and summary["skipped_frames"] == [4]
    assert summary["tracked"] == 8 and summary["lost"] == 0
    stamps = read_tum(tmp_path / "run" / "trajectory.tum").timestamps
    assert len(stamps) == 8 and open_sequence(desk9).timestamps[4] not in stamps


@pytest.mark.data
def test_empty_depth_everywhere_is_a_clear_error(desk9, tmp_path):
    seq_dir = tmp_path / "desk"
    shutil.copytree(desk9, seq_dir)
    for p in (seq_dir / "depth").glob("*.png"):
        cv2.imwrite(str(p), np.zeros((480, 640), np.uint16))
    res = CliRunner().invoke(main, ["run", str(seq_dir), "--out", str(tmp_path / "run"), "--no-map", "-q"])
    assert isinstance(res.exception, SystemExit) and res.exit_code == 3  # TrackingLost, not a crash (1)
    assert "could be tracked" in res.output
    run = json.loads((tmp_path / "run" / "run.json").read_text())  # what happened is still recorded
    assert run["tracked"] == 0 and run["lost"] == 9


def test_missing_sequence_is_one_line(tmp_path):
    res = CliRunner().invoke(main, ["run", str(tmp_path / "nope"), "--out", str(tmp_path / "run")])
    assert isinstance(res.exception, SystemExit) and res.exit_code == 2
    assert "does not exist" in res.output and str(tmp_path / "nope") in res.output
    assert len(res.output.strip().splitlines()) == 1


def test_bad_override_is_one_line(tmp_path):
    """The config is checked before the sequence is opened: no data needed."""
    res = CliRunner().invoke(main, ["run", str(tmp_path), "--set", "registration.nope=1"])
    assert isinstance(res.exception, SystemExit) and res.exit_code == 2
    assert "registration.nope" in res.output
    assert len(res.output.strip().splitlines()) == 1


@pytest.mark.data
def test_evaluation_failure_does_not_fail_a_finished_run(desk9, tmp_path):
    """Ground truth of another time span: the run is written, evaluation is skipped with a warning."""
    seq_dir = tmp_path / "desk"
    shutil.copytree(desk9, seq_dir)
    lines = (seq_dir / "groundtruth.txt").read_text().splitlines()
    shifted = [ln if ln.startswith("#") else " ".join([f"{float(ln.split()[0]) + 1000:.4f}", *ln.split()[1:]])
               for ln in lines if ln.strip()]
    (seq_dir / "groundtruth.txt").write_text("\n".join(shifted) + "\n")
    res = CliRunner().invoke(main, ["run", str(seq_dir), "--out", str(tmp_path / "run"), "--no-map"])
    assert res.exit_code == 0, res.output
    assert "no evaluation" in res.output and "no overlapping timestamps" in res.output
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["tracked"] == 9 and run.get("evaluation") == {}
    assert len(read_tum(tmp_path / "run" / "trajectory.tum")) == 9


@pytest.mark.data
def test_info_and_config_commands(desk9):
    res = CliRunner().invoke(main, ["info", str(desk9)])
    assert res.exit_code == 0, res.output
    assert "fx 517.3" in res.output and "frames      9" in res.output
    res = CliRunner().invoke(main, ["config", "-c", "tum_fr2", "--set", "registration.mp=6"])
    assert res.exit_code == 0, res.output
    import yaml

    d = yaml.safe_load(res.output)
    assert d["dataset"]["camera"] == "fr2" and d["registration"]["mp"] == 6


@pytest.mark.data
def test_run_records_rerun_with_matches_and_trajectories(desk9, tmp_path):
    rrd = tmp_path / "run.rrd"
    res = CliRunner().invoke(main, ["run", str(desk9), "--out", str(tmp_path / "run"), "--no-map", "-q",
                                    "--rerun-save", str(rrd), "--set", "depth_filter.enabled=true"])
    assert res.exit_code == 0, res.output
    from tests.viz.test_rerun_log import entity_paths

    paths = entity_paths(rrd)
    for entity in ("world/camera/image/matches", "world/camera/image/keypoints", "world/trajectory/groundtruth",
                   "world/trajectory/estimate", "world/camera/image/depth_filtered", "loop/sharpness",
                   "loop/threshold", "loop/sharp"):
        assert "/" + entity in paths, entity


@pytest.mark.data
def test_reading_ahead_changes_nothing_but_speed(desk9, tmp_path, monkeypatch):
    """prefetch (a reader thread that also detects the key points) gives bit-identical poses, and
    the tracking thread really uses those detections: it detects nothing itself (detect() is
    deterministic, so only counting its calls shows whether the prefetched ones were ignored)."""
    import threading

    import rgbdslam.frontend.features as features

    calls = []  # the thread of every ORB detection
    detect = features.detect
    monkeypatch.setattr(features, "detect", lambda *a, **k: calls.append(threading.current_thread()) or detect(*a, **k))
    out, on_tracking_thread = {}, {}
    for ahead in (0, 3):
        calls.clear()
        summary = run_sequence(desk9, tmp_path / f"p{ahead}", _fast_cfg(f"dataset.prefetch={ahead}"), progress=False)
        assert summary["tracked"] == 9
        out[ahead] = read_tum(tmp_path / f"p{ahead}" / "trajectory.tum")
        on_tracking_thread[ahead] = sum(t is threading.current_thread() for t in calls)
        assert len(calls) == 9  # one detection per frame, wherever it ran
    assert on_tracking_thread == {0: 9, 3: 0}  # read in the loop: all on this thread; read ahead: none
    assert np.array_equal(out[0].timestamps, out[3].timestamps)
    assert np.array_equal(out[0].poses, out[3].poses)


def test_tracking_loss_is_relocalised(tmp_path):
    """35 black frames while the camera moves on: the front end restarts from a wrong pose, the
    loop closer relocalises the new segment against the map and the pose graph puts it back."""
    from rgbdslam.datasets.synthetic import generate_sequence

    seq = tmp_path / "seq"
    generate_sequence(seq, frames=120, motion="loop", noise=True, seed=0)
    for p in sorted((seq / "rgb").glob("*.png"))[50:85]:
        cv2.imwrite(str(p), np.zeros((480, 640, 3), np.uint8))
    s = run_sequence(seq, tmp_path / "run", _fast_cfg(), progress=False)
    assert s["lost_frames"] == list(range(50, 85)) and s["restarts"] == [85]
    assert s["relocalized"] == 1
    assert s["evaluation"]["ate"]["rmse"] < 0.02
    # the keyframe graph is written as g2o: a vertex per keyframe at its final pose, an odometry
    # edge between consecutive keyframes (the restart's too) and every loop edge
    from rgbdslam.posegraph.graph_io import read_graph

    g = read_graph(tmp_path / "run" / "posegraph.g2o")
    assert g.ids.tolist() == s["keyframes"]
    assert g.n_edges == len(s["keyframes"]) - 1 + len(s["loops"])
    final = read_tum(tmp_path / "run" / "trajectory.tum")
    at = {round(t, 6): P for t, P in zip(final.timestamps, final.poses)}
    kf_poses = np.array([at[round(t, 6)] for t in s["timestamps_keyframes"]])
    assert np.allclose(g.poses, kf_poses, atol=1e-9)
    from rgbdslam.posegraph.graph import info6_g2o_to_gtsam
    from rgbdslam.frontend.odometry import RESTART_INFORMATION

    restart_edge = g.ids[g.edges_j].tolist().index(85)  # carries no more than the restart's weak information
    assert np.all(np.diag(info6_g2o_to_gtsam(g.info[restart_edge])) <= np.diag(RESTART_INFORMATION) * (1 + 1e-9))
    assert s["segments"] == [{"first": 0, "last": 49, "frames": 50, "map": True},
                             {"first": 85, "last": 119, "frames": 35, "map": True}]
    # without loop closure nothing relates the segments: the second one is off by decimetres,
    # so the map leaves it out (the larger first segment is the map)
    s0 = run_sequence(seq, tmp_path / "run0", _fast_cfg("loop.enabled=false"), progress=False)
    assert s0["restarts"] == [85] and s0["evaluation"]["ate"]["rmse"] > 0.1
    assert [g["map"] for g in s0["segments"]] == [True, False]
    from rgbdslam.config import MappingConfig
    from rgbdslam.mapping.fusion import fuse_run

    fused = fuse_run(tmp_path / "run0", MappingConfig(mesh=False, map2d=False), progress=False)
    kf = s0["keyframes"]
    assert any(i >= 85 for i in kf) and fused.frames == [i for i in kf if i < 85]


def test_tracking_segments_hand_worked():
    from rgbdslam.runfolder.folder import tracking_segments

    frames = [*range(0, 10), *range(20, 30), *range(40, 45)]
    # a loop from segment 1 back to segment 0 joins them (20 frames); segment 2 (5 frames) is alone
    assert tracking_segments(frames, [20, 40], [(3, 25), (22, 28)]) == [
        {"first": 0, "last": 9, "frames": 10, "map": True},
        {"first": 20, "last": 29, "frames": 10, "map": True},
        {"first": 40, "last": 44, "frames": 5, "map": False}]
    # no loops: the largest segment is the map, even when it is not the first
    assert [g["map"] for g in tracking_segments([*range(0, 5), *range(10, 30)], [10], [])] == [False, True]
    # a loop within segment 2 links nothing to the others; equal sizes: the earliest wins
    assert [g["map"] for g in tracking_segments([*range(0, 5), *range(10, 15)], [10], [(11, 14)])] == [True, False]
    # segment 2 links to segment 1 only; 1+2 (10 + 5) outweigh segment 0 (10)
    assert [g["map"] for g in tracking_segments(frames, [20, 40], [(21, 42)])] == [False, True, True]
    assert tracking_segments(list(range(7)), [], []) == [{"first": 0, "last": 6, "frames": 7, "map": True}]
    assert tracking_segments([], [5], []) == []


def test_demo_command(tmp_path):
    """README command 1's `rgbdslam demo`, smaller: sequence generated once, run, accuracy table."""
    args = ["demo", "--out", str(tmp_path / "demo"), "--frames", "40", "--set", "mapping.enabled=false"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert "generating a synthetic sequence of 40 frames" in res.output
    assert "odometry.tum" in res.output and "trajectory.tum" in res.output and "rgbdslam view" in res.output
    run = json.loads((tmp_path / "demo" / "run" / "run.json").read_text())
    assert run["tracked"] == 40 and run["evaluation"]["ate"]["rmse"] < 0.02
    again = CliRunner().invoke(main, args)  # the sequence is reused, the result is the same
    assert again.exit_code == 0 and "generating" not in again.output
    rerun = json.loads((tmp_path / "demo" / "run" / "run.json").read_text())
    assert rerun["evaluation"]["ate"]["rmse"] == run["evaluation"]["ate"]["rmse"]


def test_run_with_the_default_mapping_writes_the_map_from_the_filtered_depth(synth_clean, tmp_path):
    """`rgbdslam run` fuses the map by default; with DIF on, fusion reads the filtered keyframe
    depth the run saved. The cloud lies on the synthetic scene: every point is at most a few
    centimetres from the depth the ground truth renders (checked against the first frame)."""
    import open3d as o3d

    from rgbdslam.geometry.se3 import transform_points

    cfg = load_config(None, ["output.plots=false", "dataset.max_frames=30", "depth_filter.enabled=true"])
    s = run_sequence(synth_clean, tmp_path / "run", cfg, progress=False)
    kf_depth = sorted((tmp_path / "run" / "keyframes").glob("depth_*.png"))
    assert len(kf_depth) == len(s["keyframes"]) >= 2
    m = s["map"]
    assert m["frames_fused"] == len(s["keyframes"]) and m["cloud_points"] > 10_000 and m["mesh_triangles"] > 0
    assert json.loads((tmp_path / "run" / "run.json").read_text())["map"]["cloud_points"] == m["cloud_points"]
    cloud = np.asarray(o3d.io.read_point_cloud(m["cloud"]).points)
    assert len(cloud) == m["cloud_points"]
    # points seen by frame 0: their depth in frame 0 (the map is in the run's coordinates, whose
    # frame-0 pose trajectory.tum holds; ATE < 1 mm) matches frame 0's depth image
    seq = open_sequence(synth_clean)
    f0 = seq.load(0)
    pose0 = read_tum(tmp_path / "run" / "trajectory.tum").poses[0]
    assert s["evaluation"]["ate"]["rmse"] < 0.002
    pc = transform_points(np.linalg.inv(pose0), cloud)
    uv = seq.camera.project(pc)
    u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    inside = (pc[:, 2] > 0.1) & (u >= 0) & (u < f0.depth.shape[1]) & (v >= 0) & (v < f0.depth.shape[0])
    z = f0.depth[v[inside], u[inside]]
    front = z > 0
    err = np.abs(pc[inside][front, 2] - z[front])
    assert front.sum() > 5000
    assert np.median(err) < 0.01  # occluded points (behind what frame 0 sees) are the tail


@pytest.mark.data
def test_several_sequences_in_one_run_command(desk9, tmp_path):
    """`rgbdslam run A B C`: each into OUT/<name> (a repeated name gets _2), a failing one is
    reported and skipped, the table on stdout and summary.csv hold each run's own numbers."""
    import csv

    out = tmp_path / "batch"
    res = CliRunner().invoke(main, ["run", str(desk9), str(tmp_path / "missing"), str(desk9), "--out", str(out),
                                    "--no-map", "-q", "--set", "output.plots=false"])
    assert isinstance(res.exception, SystemExit) and res.exit_code == 2
    assert "1 of 3 sequences failed (first: missing)" in res.output
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["status"] for r in rows] == ["ok", rows[1]["status"], "ok"] and "does not exist" in rows[1]["status"]
    assert [Path(r["out"]).name for r in rows] == [desk9.name, "missing", desk9.name + "_2"]
    for r in (rows[0], rows[2]):
        run = json.loads((Path(r["out"]) / "run.json").read_text())
        assert int(r["tracked"]) == run["tracked"] == 9 and int(r["loops"]) == len(run["loops"])
        assert float(r["ate_rmse"]) == pytest.approx(run["evaluation"]["ate"]["rmse"], rel=1e-12)
    table = [ln for ln in res.output.splitlines() if ln.startswith(f"| {desk9.name} | ok | 9 | 9 |")]
    assert len(table) == 2 and (out / "summary.md").read_text().count("| ok |") == 2


@pytest.mark.data
def test_rerun_save_needs_a_single_sequence(desk9, tmp_path):
    res = CliRunner().invoke(main, ["run", str(desk9), str(desk9), "--rerun-save", str(tmp_path / "x.rrd")])
    assert res.exit_code == 2 and "single SEQUENCE" in res.output and not (tmp_path / "x.rrd").exists()


@pytest.mark.data
def test_a_new_run_into_a_run_folder_keeps_the_finished_one(desk9, tmp_path, monkeypatch):
    """Re-running into a folder that holds a finished run and stopping part-way (Ctrl-C) must not
    cost the finished run: it is moved to previous/ before the new run writes anything."""
    import rgbdslam.pipeline as pl

    out = tmp_path / "run"
    run_sequence(desk9, out, _fast_cfg(), progress=False)
    first = (out / "trajectory.tum").read_text()
    assert len(read_tum(out / "trajectory.tum")) == 9
    monkeypatch.setattr(pl, "open_sequence", lambda *a, **k: _InterruptingSequence(open_sequence(desk9), at=3))
    with pytest.raises(KeyboardInterrupt):
        run_sequence(desk9, out, _fast_cfg("dataset.prefetch=0"), progress=False)
    assert (out / "previous" / "trajectory.tum").read_text() == first
    assert json.loads((out / "previous" / "run.json").read_text())["interrupted"] is False
    assert len(read_tum(out / "trajectory.tum")) == 3
    assert json.loads((out / "run.json").read_text())["interrupted"] is True


@pytest.mark.data
def test_only_the_first_frame_tracked_is_a_tracking_failure(desk9, tmp_path):
    """Frames 1-8 black: frame 0 is the origin and nothing registers after it. That is no
    trajectory (exit 3), not a one-pose 'success'; the five per-frame warnings cap the output."""
    seq_dir = tmp_path / "desk"
    shutil.copytree(desk9, seq_dir)
    for p in sorted((seq_dir / "rgb").glob("*.png"))[1:]:
        cv2.imwrite(str(p), np.zeros((480, 640, 3), np.uint8))
    res = CliRunner().invoke(main, ["run", str(seq_dir), "--out", str(tmp_path / "run"), "--no-map", "-q"])
    assert isinstance(res.exception, SystemExit) and res.exit_code == 3
    assert "no frame after the first (0) of" in res.output
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["tracked"] == 1 and run["lost"] == 8


@pytest.mark.data
def test_unreadable_frames_warn_five_times_then_are_counted(desk9, tmp_path):
    seq_dir = tmp_path / "desk"
    shutil.copytree(desk9, seq_dir)
    for p in sorted((seq_dir / "rgb").glob("*.png"))[1:8]:
        p.write_bytes(b"not a png")
    res = CliRunner().invoke(main, ["run", str(seq_dir), "--out", str(tmp_path / "run"), "--no-map", "-q"])
    assert res.output.count("skipped frame") == 5
    assert "further unreadable frames are skipped silently" in res.output
    assert json.loads((tmp_path / "run" / "run.json").read_text())["skipped_frames"] == list(range(1, 8))


@pytest.mark.data
def test_an_output_path_under_a_file_is_one_line(desk9, tmp_path):
    (tmp_path / "afile").write_text("x")
    res = CliRunner().invoke(main, ["run", str(desk9), "--out", str(tmp_path / "afile" / "run"), "-q"])
    assert isinstance(res.exception, SystemExit) and res.exit_code == 2
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and str(tmp_path / "afile") in lines[0]


@pytest.mark.parametrize("frames", ["0", "2147483648"])
def test_demo_with_too_few_or_many_frames_is_one_line_before_any_work(tmp_path, frames):
    res = CliRunner().invoke(main, ["demo", "--out", str(tmp_path / "demo"), "--frames", frames])
    assert isinstance(res.exception, SystemExit) and res.exit_code == 2
    assert res.output.strip() == f"error: --frames must be a whole number from 2 (a trajectory) to 100000 (got {frames})"
    assert not (tmp_path / "demo").exists()


@pytest.mark.data
def test_a_foreign_previous_folder_is_never_deleted(desk9, tmp_path):
    out = tmp_path / "run"
    run_sequence(desk9, out, _fast_cfg(), progress=False)
    (out / "previous").mkdir()
    (out / "previous" / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="previous exists and is not an earlier run of rgbdslam"):
        run_sequence(desk9, out, _fast_cfg(), progress=False)
    assert (out / "previous" / "notes.txt").read_text() == "mine" and (out / "run.json").is_file()
    # an earlier run there (ours) is replaced by the newer one
    (out / "previous" / "notes.txt").unlink()
    (out / "previous").rmdir()
    run_sequence(desk9, out, _fast_cfg(), progress=False)
    run_sequence(desk9, out, _fast_cfg(), progress=False)
    from rgbdslam.runfolder.folder import LOCK_NAME

    assert sorted(p.name for p in (out / "previous").iterdir()) == sorted(
        p.name for p in out.iterdir() if p.name not in ("previous", LOCK_NAME))  # the manifest went along


@pytest.mark.data
def test_failed_runs_never_push_a_finished_run_out_of_previous(desk9, tmp_path):
    """Finished run, then two failing re-runs into the same folder: previous/ still holds the
    finished run (a failed run is replaced, not moved), and no failed run leaves a trajectory."""
    out = tmp_path / "run"
    run_sequence(desk9, out, _fast_cfg(), progress=False)
    good = (out / "trajectory.tum").read_text()
    bad = tmp_path / "bad"
    shutil.copytree(desk9, bad)
    for p in (bad / "depth").glob("*.png"):
        cv2.imwrite(str(p), np.zeros((480, 640), np.uint16))
    for _ in range(2):
        with pytest.raises(TrackingLost):
            run_sequence(bad, out, _fast_cfg(), progress=False)
        assert (out / "previous" / "trajectory.tum").read_text() == good
        assert json.loads((out / "run.json").read_text())["status"] == "failed"
        assert not (out / "trajectory.tum").exists()
    run_sequence(desk9, out, _fast_cfg(), progress=False)  # a finished run replaces the failed one
    assert json.loads((out / "run.json").read_text())["status"] == "finished"
    assert (out / "previous" / "trajectory.tum").read_text() == good


def test_batch_folder_names_never_collide(tmp_path):
    from rgbdslam.batch import _run_dirs

    dirs = _run_dirs([tmp_path / "a" / "seq", tmp_path / "b" / "seq", tmp_path / "c" / "seq_2",
                      tmp_path / "d" / "SEQ"], tmp_path / "out")
    assert [d.name for d in dirs] == ["seq", "seq_2", "seq_2_2", "SEQ_3"]  # seq_2 is taken, case aside


@pytest.mark.data
def test_mapping_problems_never_cost_the_run(desk9, tmp_path):
    """A mapping setting fusion refuses is reported before tracking starts; a map that turns
    out empty after a finished run is a warning, and the run's outputs stand."""
    res = CliRunner().invoke(main, ["run", str(desk9), "--out", str(tmp_path / "a"), "-q",
                                    "--set", "mapping.voxel_size=0.0005"])
    assert isinstance(res.exception, SystemExit) and res.exit_code == 2
    assert "'mapping.voxel_size' must be between 0.001 and 10" in res.output and not (tmp_path / "a").exists()
    s = run_sequence(desk9, tmp_path / "b", load_config(None, ["output.plots=false", "mapping.depth_min=0.05",
                                                               "mapping.depth_max=0.1"]), progress=False)
    assert s["map"] == {} and s["tracked"] == 9 and len(read_tum(tmp_path / "b" / "trajectory.tum")) == 9
    assert json.loads((tmp_path / "b" / "run.json").read_text())["status"] == "finished"


def test_a_bad_option_is_one_line_too():
    for args, text in ((["run", "--nosuch", "x"], "No such option '--nosuch'"),
                       (["run"], "Missing argument 'SEQUENCE...'"),
                       (["posegraph", "init", "f.g2o", "--method", "magic"], "Invalid value for '--method'")):
        res = CliRunner().invoke(main, args)
        assert isinstance(res.exception, SystemExit) and res.exit_code == 2
        lines = [ln for ln in res.output.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("error: ") and text in lines[0], res.output
        assert lines[0].endswith("--help')")


@pytest.mark.data
def test_the_first_frame_is_tracked_without_importing_scipy(desk9):
    """SciPy's spatial module (0.3-0.7 s to import on the 2-core machine) is imported where it is
    first used, after the first frame: a fresh interpreter opens a TUM sequence with its ground
    truth, builds the SLAM pipeline and tracks frame 0, and SciPy is still not imported."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "import rgbdslam.pipeline, rgbdslam.cli\n"
        "from rgbdslam.config import load_config, resolve_preset\n"
        "from rgbdslam.datasets import open_sequence\n"
        "from rgbdslam.frontend.features import with_detections\n"
        "from rgbdslam.slam import SLAM\n"
        "cfg = load_config(resolve_preset('tum_fr1'))\n"
        f"seq = open_sequence({str(desk9)!r}, cfg)\n"
        "gt = seq.groundtruth()\n"
        "slam = SLAM(cfg, seq.camera)\n"
        "slam.track(with_detections(seq.load(0), cfg.features))\n"
        "assert len(slam.state.records) == 1 and len(gt) > 0\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'scipy'))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
