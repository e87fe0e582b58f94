"""benchmarks.peers: the ratio maths and the table on hand-made numbers, publishing between markers,
and one real run of rgbdslam on fr1/desk (9 frames) that must give the trajectory ``rgbdslam run`` gives."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks import common, peers
from benchmarks.common import Metrics
from tests.conftest import TUM_DESK9, need


def _m(ate, ms, scale=1.0, rpe=0.002, frames=100, tracked=100):
    return Metrics(ate=ate, scale=scale, rpe=rpe, frames=frames, tracked=tracked, ms=ms)


def _rows():
    R = peers.Row
    return [
        R("A", "rgbdslam default", [_m(0.010, 20.0), _m(0.010, 30.0)]),
        R("A", peers.ORB, [_m(0.004, 10.0), _m(0.006, 14.0)]),  # median ATE 0.005, ms 12
        R("A", peers.OPEN3D, [_m(0.100, 300.0)]),
        R("B", "rgbdslam default", [_m(0.003, 12.0)]),
        R("B", peers.ORB, [_m(0.006, 12.0), _m(0.006, 12.0)]),
        R("C", "rgbdslam default", [_m(0.008, 40.0, frames=50, tracked=47)]),
        R("C", peers.ORB, [_m(0.004, 20.0)]),
        R("D", "rgbdslam default", [_m(0.020, 10.0)]),  # no ORB-SLAM3 row: no ratio
    ]


def test_ratios_and_their_median_and_worst_on_hand_made_numbers():
    rat = peers.ratios(_rows())
    assert set(rat) == {"rgbdslam default"}
    per = rat["rgbdslam default"]
    assert set(per) == {"A", "B", "C"}
    assert per["A"] == pytest.approx((2.0, 12.0 / 25.0))  # 0.010 / 0.005; ORB 12 ms / rgbdslam 25 ms
    assert per["B"] == pytest.approx((0.5, 1.0))
    assert per["C"] == pytest.approx((2.0, 0.5))
    s = peers.summarise(per)
    assert s["ate"][0] == pytest.approx(2.0) and s["ate"][2] == pytest.approx(2.0) and s["ate"][1] in ("A", "C")
    assert s["rate"][0] == pytest.approx(0.5) and s["rate"][1] == "A" and s["rate"][2] == pytest.approx(0.48)
    # a sequence whose ratio is NaN (ORB-SLAM3 failed) is left out, not counted as best or worst
    s = peers.summarise({"A": (float("nan"), 1.0), "B": (3.0, float("nan")), "C": (1.0, 2.0)})
    assert s["ate"] == (2.0, "B", 3.0) and s["rate"] == (1.5, "A", 1.0)


def test_table_cells_on_hand_made_numbers():
    lines = peers.markdown(_rows()).splitlines()
    assert lines[0].startswith("| sequence | method | ATE RMSE (m) | Sim(3) scale |")
    assert lines[2] == "| A | rgbdslam default | 0.0100 | 1.000 | 2.00 | 100/0 | 25.0 | 2.00 | 0.48 |"
    assert lines[3] == "| A | ORB-SLAM3 | 0.0040 / 0.0060 | 1.000 | 2.00 | 100/0 | 12.0 | – | – |"
    assert lines[4] == "| A | Open3D hybrid odometry | 0.1000 | 1.000 | 2.00 | 100/0 | 300.0 | – | – |"
    assert lines[7] == "| C | rgbdslam default | 0.0080 | 1.000 | 2.00 | 47/3 | 40.0 | 2.00 | 0.50 |"
    assert lines[9] == "| D | rgbdslam default | 0.0200 | 1.000 | 2.00 | 100/0 | 10.0 | – | – |"
    summary = [ln for ln in lines if ln.startswith("- **rgbdslam default**")]
    assert summary == ["- **rgbdslam default** over 3 sequences: ATE ÷ ORB-SLAM3 median **2.00**, worst 2.00 (A); "
                       "rate × ORB-SLAM3 median 0.50, worst 0.48 (A)"]
    # real and synthetic sequences together, and each group on its own
    syn = _rows() + [peers.Row("synthetic loop seed 0", "rgbdslam default", [_m(0.001, 10.0)]),
                     peers.Row("synthetic loop seed 0", peers.ORB, [_m(0.004, 5.0)])]
    assert [ln for ln in peers.markdown(syn).splitlines() if ln.lstrip().startswith("- ")] == [
        "- **rgbdslam default** over 4 sequences: ATE ÷ ORB-SLAM3 median **1.25**, worst 2.00 (A); "
        "rate × ORB-SLAM3 median 0.50, worst 0.48 (A)",
        "  - **rgbdslam default** over 3 real sequences: ATE ÷ ORB-SLAM3 median **2.00**, worst 2.00 (A); "
        "rate × ORB-SLAM3 median 0.50, worst 0.48 (A)",
        "  - **rgbdslam default** over 1 synthetic sequences: ATE ÷ ORB-SLAM3 median **0.25**, worst 0.25 "
        "(synthetic loop seed 0); rate × ORB-SLAM3 median 0.50, worst 0.50 (synthetic loop seed 0)"]
    # rows of another run (--open3d-only, joined by --report) go to their sequence's group
    moved = _rows()
    moved.append(moved.pop(2))
    assert peers.markdown(moved) == peers.markdown(_rows())
    # the rows survive the JSON round trip that --report reads
    again = peers.from_json(json.loads(json.dumps(peers.to_json(_rows()))))
    assert peers.markdown(again) == peers.markdown(_rows())


def test_publish_replaces_only_its_own_block(tmp_path):
    doc = tmp_path / "benchmarks.md"
    doc.write_text("# B\n\nintro\n\n<!-- benchmark:peers -->\nold\n<!-- /benchmark:peers -->\n\n## Next\nkept\n")
    common.publish("peers", "| t |", "python -m benchmarks.peers", "machine M", "note", path=doc, write=True)
    assert doc.read_text() == ("# B\n\nintro\n\n<!-- benchmark:peers -->\n```bash\npython -m benchmarks.peers\n```\n\n"
                               "machine M\n\n| t |\n\nnote\n<!-- /benchmark:peers -->\n\n## Next\nkept\n")
    common.publish("other", "| u |", "cmd", "m", path=doc, write=True)  # a new block is appended
    assert doc.read_text().endswith("<!-- benchmark:other -->\n```bash\ncmd\n```\n\nm\n\n| u |\n<!-- /benchmark:other -->\n")
    doc.write_text("<!-- /benchmark:peers -->\n<!-- benchmark:peers -->\n")
    with pytest.raises(ValueError, match="markers of benchmark 'peers'"):
        common.publish("peers", "x", "c", "m", path=doc, write=True)


@pytest.mark.data
@pytest.mark.slow
def test_one_real_run_on_desk9_matches_the_command_line(tmp_path):
    need(TUM_DESK9)
    out = tmp_path / "peers.json"
    assert peers.main(["--sequences", "desk9", "--rounds", "2", "--no-orb", "--no-open3d", "--json", str(out),
                       "--work", str(tmp_path / "work")]) == 0
    data = json.loads(out.read_text())
    assert data["command"].startswith("python -m benchmarks.peers --sequences desk9")
    (row,) = data["rows"]
    assert row["sequence"] == "fr1/desk 9 frames" and row["method"] == "rgbdslam default"
    a, b = row["runs"]
    assert a["ate"] == b["ate"] and a["scale"] == b["scale"]  # rgbdslam is deterministic
    assert a["frames"] == 9 and a["tracked"] == 9 and a["ms"] > 0
    # the same frames through the whole command: the same ATE (its run.json and trajectory.tum)
    summary = common.run_pipeline(TUM_DESK9, tmp_path / "run")
    assert a["ate"] == pytest.approx(summary["evaluation"]["ate"]["rmse"], abs=1e-6)
    assert 0.001 < a["ate"] < 0.01 and np.isfinite(a["rpe"])


@pytest.mark.data
@pytest.mark.slow
def test_orbslam3_peer_on_desk9(tmp_path):
    why = common.orbslam3_missing()
    if why:
        pytest.skip(why)
    from rgbdslam.datasets import open_sequence

    gt = open_sequence(need(TUM_DESK9), common.load_config()).groundtruth()
    m = common.run_orbslam3(TUM_DESK9, "fr1", tmp_path / "orb", gt)
    assert m.frames == 9 and m.tracked >= 3 and 0 < m.ate < 0.05 and m.ms > 0


def test_orb_settings_take_a_synthetic_folders_own_intrinsics(tmp_path):
    if not common.orb_settings("fr3").exists():
        pytest.skip(f"the peer's settings are not here ({common.orb_settings('fr3')})")
    (tmp_path / "camera.yaml").write_text("fx: 525.0\nfy: 526.5\ncx: 319.5\ncy: 239.5\nwidth: 640\nheight: 480\n")
    text = common.orb_settings_for_folder(tmp_path, tmp_path / "s" / "orb.yaml").read_text()
    assert "Camera1.fx: 525.0\nCamera1.fy: 526.5\nCamera1.cx: 319.5\nCamera1.cy: 239.5\n" in text
    assert "RGBD.DepthMapFactor: 5000.0" in text and "535.4" not in text  # the rest is TUM3's


@pytest.mark.data
def test_a_sequence_view_runs_like_its_sequence_and_sees_every_frame(tmp_path):
    """benchmarks.common.sequence_view: what benchmarks hand to run_sequence instead of patching a
    reader. Reading through it gives the run of the folder itself, pose for pose."""
    from rgbdslam.datasets import open_sequence
    from rgbdslam.io.trajectory import read_tum

    need(TUM_DESK9)
    seen = []

    def load(seq, i):
        seen.append(i)
        return seq.load(i)

    view = common.sequence_view(open_sequence(TUM_DESK9, common.load_config()), load)
    a = common.run_pipeline(view, tmp_path / "view")
    b = common.run_pipeline(TUM_DESK9, tmp_path / "folder")
    assert sorted(set(seen)) == list(range(9)) and a["tracked"] == b["tracked"] == 9
    ta, tb = read_tum(tmp_path / "view" / "trajectory.tum"), read_tum(tmp_path / "folder" / "trajectory.tum")
    assert np.array_equal(ta.timestamps, tb.timestamps) and np.array_equal(ta.poses, tb.poses)
    assert a["evaluation"]["ate"]["rmse"] == b["evaluation"]["ate"]["rmse"]


@pytest.mark.data
def test_sevenscenes_as_tum_keeps_poses_and_depth(tmp_path):
    """The peer reads 7-Scenes from a TUM-layout copy: the same poses, depth at 5000 per metre."""
    import shutil

    import cv2

    from rgbdslam.datasets import open_sequence
    from rgbdslam.io.trajectory import read_tum

    src = need(common.SEVENSCENES)
    small = tmp_path / "src"
    small.mkdir()
    shutil.copy(src / "camera-intrinsics.txt", small)
    for i in range(3):
        for part in ("color.jpg", "depth.png", "pose.txt"):
            shutil.copy(src / f"frame-{i:06d}.{part}", small)
    dst = common.sevenscenes_as_tum(small, tmp_path / "tum")
    gt, ref = read_tum(dst / "groundtruth.txt"), open_sequence(small, common.load_config()).groundtruth()
    assert np.allclose(gt.timestamps, [0.0, 1 / 30, 2 / 30], atol=1e-6)
    assert np.allclose(gt.poses[:, :3, 3], ref.poses[:, :3, 3], atol=1e-7)
    # KinectFusion's rotations are orthonormal to ~1e-4 only; the quaternion makes them exactly so
    assert np.allclose(gt.poses[:, :3, :3], ref.poses[:, :3, :3], atol=2e-4)
    mm = cv2.imread(str(small / "frame-000001.depth.png"), cv2.IMREAD_UNCHANGED).astype(np.int64)
    tum = cv2.imread(str(dst / "depth" / "frame-000001.png"), cv2.IMREAD_UNCHANGED).astype(np.int64)
    assert (mm > 0).mean() > 0.5 and np.array_equal(tum, np.where(mm == 65535, 0, np.minimum(mm * 5, 65535)))
    assert open_sequence(dst, common.load_config()).load(2).rgb.shape == (480, 640, 3)


def test_joined_machine_line_of_runs_made_at_the_same_time():
    a = "x86_64, 2 cores, Python 3.11.7, 2026-12-07 03:24 UTC, load average 43.3, 41.0, 28.2 before, 48.4, 45.0, 38.8 after"
    b = "x86_64, 2 cores, Python 3.11.7, 2026-12-07 03:20 UTC, load average 20.0, 1.0, 1.0 before, 30.5, 2.0, 2.0 after"
    assert peers.joined_machine([a, b]) == ("x86_64, 2 cores, Python 3.11.7, 2026-12-07 03:20 UTC (the first of 2 runs "
                                            "at the same time); 1-minute load average 20–48")
    assert peers.joined_machine([a, a]) == a


@pytest.mark.data
@pytest.mark.slow
def test_open3d_odometry_on_desk9():
    """Open3D's hybrid odometry through common (frames read one by one, as the peer table runs it)."""
    m = common.open3d_odometry(need(TUM_DESK9))
    assert m.frames == 9 and m.tracked == 9 and 0 < m.ate < 0.02 and m.ms > 0 and np.isfinite(m.scale)
