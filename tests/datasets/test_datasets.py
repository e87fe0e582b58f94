"""Sequence readers: TUM on the real 9-frame fr1/desk excerpt, PUT on a converted copy,
association edge cases and error messages on small hand-made folders."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from rgbdslam.config import DatasetConfig
from rgbdslam.datasets import open_sequence
from rgbdslam.datasets.put import PutSequence, convert_tum_to_put
from rgbdslam.datasets.tum import TumSequence, choose_camera
from rgbdslam.errors import InputError
from rgbdslam.evaluation.associate import associate
from rgbdslam.geometry.camera import CAMERAS

from tests.conftest import DATA, REPO

DESK = DATA / "tum" / "rgbd_dataset_freiburg1_desk_9frames"
need_desk = pytest.mark.usefixtures("desk9")  # fails when the excerpt is missing (conftest.need)


# ----------------------------------------------------------------------------- helpers


def make_tum(root: Path, rgb_ts, depth_ts, size=(8, 6), depth_value=5000) -> Path:
    """A tiny TUM folder with constant images; returns root."""
    w, h = size
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines = ["# color images", "# timestamp filename"], ["# depth"]
    for k, t in enumerate(rgb_ts):
        img = np.zeros((h, w, 3), np.uint8)
        img[..., 0] = 10 + k  # blue channel in BGR
        img[..., 2] = 200  # red
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), img)
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    for t in depth_ts:
        cv2.imwrite(str(root / "depth" / f"{t:.6f}.png"), np.full((h, w), depth_value, np.uint16))
        depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (root / "camera.yaml").write_text(f"camera: ros_default\nwidth: {w}\nheight: {h}\n")
    return root


# ----------------------------------------------------------------------------- association


def test_associate_greedy_smallest_difference_first(tmp_path):
    # Two rgb stamps compete for the depth stamp 1.012:
    #   rgb 1.000 - depth 1.012: 0.012      rgb 1.000 - depth 0.985: 0.015
    #   rgb 1.010 - depth 1.012: 0.002      rgb 1.010 - depth 0.985: 0.025 (>= 0.02, no candidate)
    # Greedy over all candidates by difference: (1.010, 1.012) at 0.002 first, then (1.000, 1.012)
    # is blocked and (1.000, 0.985) at 0.015 is taken: both rgb frames are paired.
    # First come, first served (each rgb in turn takes its nearest free depth) would give
    # 1.000 -> 1.012 and leave 1.010 without a partner.
    rgb = np.array([1.000, 1.010])
    depth = np.array([0.985, 1.012])
    ia, ib = associate(rgb, depth, max_difference=0.02)
    assert ia.tolist() == [0, 1] and ib.tolist() == [0, 1]
    # the same through the TUM reader (rgb.txt / depth.txt)
    seq = open_sequence(make_tum(tmp_path / "s", rgb.tolist(), depth.tolist()))
    np.testing.assert_allclose(seq.timestamps, [1.000, 1.010])
    np.testing.assert_allclose(seq.depth_timestamps, [0.985, 1.012])
    # the contest decided by the difference, not by the order of the lists: reversed input,
    # same pairs (indices refer to the given order)
    ia, ib = associate(rgb[::-1], depth[::-1], max_difference=0.02)
    assert sorted(zip(rgb[::-1][ia], depth[::-1][ib])) == [(1.000, 0.985), (1.010, 1.012)]
    # (the general greedy semantics, offset, strict '<' and TUM parity are in test_evaluation.py)


# ----------------------------------------------------------------------------- TUM on real data


@pytest.mark.data
@need_desk
def test_tum_reader_fr1_desk():
    seq = open_sequence(DESK)
    assert isinstance(seq, TumSequence)
    assert len(seq) == 9
    assert seq.camera == CAMERAS["fr1"]
    listed = [float(l.split()[0]) for l in (DESK / "rgb.txt").read_text().splitlines() if l and not l.startswith("#")]
    np.testing.assert_array_equal(seq.timestamps, np.array(listed))
    assert np.all(np.abs(seq.depth_timestamps - seq.timestamps) < 0.02)
    f = seq.load(4)
    assert f.index == 4 and f.timestamp == listed[4]
    assert f.rgb.shape == (480, 640, 3) and f.rgb.dtype == np.uint8
    assert f.depth.shape == (480, 640) and f.depth.dtype == np.float32
    valid = f.depth[f.depth > 0]
    assert valid.size > 0.5 * f.depth.size
    assert 0.4 < np.percentile(valid, 1) and np.percentile(valid, 99) < 3.5
    # colour really converted to RGB: same pixels as cv2's BGR reversed
    bgr = cv2.imread(str(DESK / f.name), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(f.rgb, bgr[..., ::-1])
    # depth is raw / 5000 exactly
    raw = cv2.imread(str(seq.depth_files[4]), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(f.depth, raw / 5000.0, rtol=1e-6)
    gt = seq.groundtruth()
    assert gt is not None and len(gt) > 1000
    assert gt.timestamps[0] < seq.timestamps[0] < gt.timestamps[-1]


@pytest.mark.data
@need_desk
def test_tum_frame_selection_and_depth_options():
    cfg = DatasetConfig(first_frame=1, stride=3, max_frames=2, depth_scale=2500.0, depth_correction=1.1)
    seq = open_sequence(DESK, cfg)
    full = open_sequence(DESK)
    assert len(seq) == 2
    np.testing.assert_array_equal(seq.timestamps, full.timestamps[[1, 4]])
    d_full, d = full.load(4).depth, seq.load(1).depth
    np.testing.assert_allclose(d, d_full * 2.0 * 1.1, rtol=1e-5)
    with pytest.raises(InputError, match="first_frame"):
        open_sequence(DESK, DatasetConfig(first_frame=9))


def test_tum_associations_file_and_offsets(tmp_path):
    root = make_tum(tmp_path / "s", [1.0, 1.1, 1.2], [1.005, 1.112, 1.3])
    seq = open_sequence(root)
    np.testing.assert_allclose(seq.timestamps, [1.0, 1.1])  # 1.2 has no depth within 0.02 s
    np.testing.assert_allclose(seq.depth_timestamps, [1.005, 1.112])
    assert seq.load(1).rgb[0, 0].tolist() == [200, 0, 11]  # RGB order
    np.testing.assert_allclose(seq.load(0).depth, 1.0)
    (root / "assoc.txt").write_text("# rgb depth\n1.2 rgb/1.200000.png 1.3 depth/1.300000.png\n")
    seq = open_sequence(root, DatasetConfig(associations="assoc.txt"))
    np.testing.assert_allclose(seq.timestamps, [1.2])
    assert seq.depth_files[0].name == "1.300000.png"
    (root / "bad_assoc.txt").write_text("1.2 rgb/1.200000.png 1.3\n")
    with pytest.raises(InputError, match=r"bad_assoc.txt:1"):
        open_sequence(root, DatasetConfig(associations="bad_assoc.txt"))


def test_tum_nothing_associates(tmp_path):
    root = make_tum(tmp_path / "s", [1.0, 2.0], [1.5, 2.5])
    with pytest.raises(InputError, match="no colour/depth pair.*max_difference"):
        open_sequence(root)


def test_tum_malformed_line_names_file_and_line(tmp_path):
    root = make_tum(tmp_path / "s", [1.0, 1.1], [1.0, 1.1])
    lines = (root / "rgb.txt").read_text().splitlines()
    lines.insert(3, "1.15")  # 4th line: timestamp without a file name
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"rgb\.txt:4: expected 'timestamp filename'"):
        open_sequence(root)


def test_tum_missing_unreadable_and_wrong_images(tmp_path):
    root = make_tum(tmp_path / "s", [1.0, 1.1, 1.2], [1.0, 1.1, 1.2])
    seq = open_sequence(root)
    (root / "rgb" / "1.000000.png").unlink()
    with pytest.raises(InputError, match=r"1\.000000\.png is missing"):
        seq.load(0)
    (root / "depth" / "1.100000.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match=r"depth image .*1\.100000\.png cannot be decoded"):
        seq.load(1)
    cv2.imwrite(str(root / "depth" / "1.200000.png"), np.zeros((6, 8), np.uint8))
    with pytest.raises(InputError, match="expected 16-bit"):
        seq.load(2)
    cv2.imwrite(str(root / "depth" / "1.200000.png"), np.zeros((6, 9), np.uint16))
    with pytest.raises(InputError, match="9x6 but camera"):
        seq.load(2)
    cv2.imwrite(str(root / "rgb" / "1.200000.png"), np.zeros((6, 8), np.uint8))
    with pytest.raises(InputError, match="1 channel"):
        seq.load(2)


def test_empty_depth_is_allowed(tmp_path):
    root = make_tum(tmp_path / "s", [1.0], [1.0], depth_value=0)
    f = open_sequence(root).load(0)
    assert f.depth.shape == (6, 8) and not f.depth.any()


def test_missing_folder_and_unknown_layout(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        open_sequence(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="not a known sequence layout"):
        open_sequence(tmp_path / "empty")


def test_camera_choice(tmp_path):
    for name, cam in [("rgbd_dataset_freiburg2_xyz", "fr2"), ("rgbd_dataset_freiburg3_office", "fr3"), ("other", "ros_default")]:
        (tmp_path / name).mkdir()
        assert choose_camera(tmp_path / name).name == cam
    assert choose_camera(tmp_path / "other", "kinect1") == CAMERAS["kinect1"]
    d = tmp_path / "rgbd_dataset_freiburg1_custom"
    d.mkdir()
    (d / "camera.yaml").write_text("fx: 500\nfy: 501\ncx: 100.5\ncy: 80.5\nwidth: 200\nheight: 160\n")
    c = choose_camera(d)  # camera.yaml takes precedence over the folder name
    assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height) == (500, 501, 100.5, 80.5, 200, 160)
    (d / "camera.yaml").write_text("camera: nikon\n")
    with pytest.raises(InputError, match="unknown camera 'nikon'"):
        choose_camera(d)
    for bad in ("fx: 0\nfy: 501\ncx: 1\ncy: 1\n", "fx: .nan\nfy: 501\ncx: 1\ncy: 1\n",
                "fx: 500\nfy: -5\ncx: 1\ncy: 1\n", "fx: 500\nfy: 500\ncx: 1\ncy: 1\nwidth: 0\n",
                # finite but absurd (issue 16, class 6)
                "fx: 1.0e+300\nfy: 500\ncx: 1\ncy: 1\n", "fx: 500\nfy: 500\ncx: -1.0e+300\ncy: 1\n",
                "fx: 500\nfy: 500\ncx: 1\ncy: 1\nwidth: 1.0e+300\n",
                "fx: 500\nfy: 500\ncx: 1\ncy: 1\ndist: [1.0e+300, 0, 0, 0, 0]\n"):
        (d / "camera.yaml").write_text(bad)
        with pytest.raises(InputError, match=r"camera.yaml: ((fx|fy|cx|width) must be a finite number (above 0 and at "
                                             r"most 1e\+06|from -1e\+06 to 1e\+06|from 1 to 65535)|distortion "
                                             r"coefficient 1 must be within ±1000); got"):
            choose_camera(d)


def test_a_time_stamp_listed_twice_is_an_error(tmp_path):
    """Association would keep one image of each repeated stamp and silently drop the others."""
    root = make_tum(tmp_path / "seq", [1.0, 1.1, 1.2], [1.0, 1.1, 1.2])
    lines = (root / "rgb.txt").read_text().splitlines()
    lines[-1] = lines[-1].replace("1.200000 ", "1.100000 ", 1)  # rgb/1.200000.png listed at 1.1
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"rgb.txt: 1 time stamp\(s\) are listed more than once \(e.g. 1.100000\)"):
        TumSequence(root)


def test_a_binary_list_file_is_one_clear_error(tmp_path):
    root = make_tum(tmp_path / "seq", [1.0, 1.1], [1.0, 1.1])
    (root / "rgb.txt").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    with pytest.raises(InputError, match=r"list file .*rgb.txt is not UTF-8 text"):
        TumSequence(root)


# ----------------------------------------------------------------------------- PUT


@pytest.mark.data
@need_desk
def test_put_reader_on_converted_fr1_desk(tmp_path):
    dst = convert_tum_to_put(DESK, tmp_path / "put_desk")
    assert (dst / "matched").is_file() and (dst / "initialPosition").is_file()
    put = open_sequence(dst)
    tum = open_sequence(DESK)
    assert isinstance(put, PutSequence) and len(put) == len(tum) == 9
    np.testing.assert_allclose(put.timestamps, tum.timestamps, atol=1e-6)
    np.testing.assert_allclose(put.depth_timestamps, tum.depth_timestamps, atol=1e-6)
    assert put.camera == tum.camera  # camera.yaml written by the converter
    for i in (0, 8):
        a, b = put.load(i), tum.load(i)
        np.testing.assert_array_equal(a.rgb, b.rgb)
        assert np.abs(a.depth - b.depth).max() <= 0.0005 + 1e-6  # 1 mm quantisation, rounded
        np.testing.assert_array_equal(a.depth > 0, b.depth > 0)
    gt_put, gt_tum = put.groundtruth(), tum.groundtruth()
    np.testing.assert_allclose(gt_put.poses, gt_tum.poses, atol=1e-6)
    j = np.argmin(np.abs(gt_tum.timestamps - tum.timestamps[0]))
    np.testing.assert_allclose(put.initial_pose, gt_tum.poses[j], atol=1e-6)
    # without camera.yaml a PUT folder is the Kinect v1; stride/max_frames pick line numbers
    (dst / "camera.yaml").unlink()
    put2 = PutSequence(dst, DatasetConfig(stride=2, max_frames=3))
    assert put2.camera == CAMERAS["kinect1"]
    assert [p.name for p in put2.rgb_files] == ["rgb_00000.png", "rgb_00002.png", "rgb_00004.png"]


def test_put_errors(tmp_path):
    d = tmp_path / "p"
    d.mkdir()
    (d / "matched").write_text("1.0 1.01\n1.1 x\n")
    with pytest.raises(InputError, match=r"matched:2"):
        open_sequence(d)
    (d / "matched").write_text("1.0 1.01\n")
    (d / "initialPosition").write_text("1 2 3\n")
    with pytest.raises(InputError, match="initialPosition must hold 7 numbers"):
        open_sequence(d)
    (d / "initialPosition").unlink()
    seq = open_sequence(d)
    with pytest.raises(InputError, match="rgb_00000.png is missing"):
        seq.load(0)
    assert seq.groundtruth() is None
    with pytest.raises(InputError, match="ground-truth file"):
        PutSequence(d, DatasetConfig(groundtruth="gt.txt")).groundtruth()


@pytest.mark.data
@need_desk
def test_convert_refuses_nonempty_output(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "x").write_text("keep me")
    with pytest.raises(InputError, match="not empty"):
        convert_tum_to_put(DESK, tmp_path / "out", max_frames=2)
    assert (tmp_path / "out" / "x").read_text() == "keep me"
    shutil.rmtree(tmp_path / "out")


@pytest.mark.data
@need_desk
def test_tum_to_put_script(tmp_path):
    import subprocess
    import sys

    script = REPO / "scripts" / "tum_to_put.py"
    ok = subprocess.run([sys.executable, str(script), str(DESK), str(tmp_path / "p"), "--max-frames", "2"],
                        capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert len((tmp_path / "p" / "matched").read_text().splitlines()) == 2
    assert (tmp_path / "p" / "groundtruth.txt").read_bytes() == (DESK / "groundtruth.txt").read_bytes()
    bad = subprocess.run([sys.executable, str(script), str(tmp_path / "nope"), str(tmp_path / "q")],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "does not exist" in bad.stderr


@pytest.mark.parametrize("ahead", [0, 1, 3])
def test_prefetched_frames_are_load_in_order_with_errors_in_place(tmp_path, ahead):
    import threading

    root = make_tum(tmp_path / "s", [1.0, 1.1, 1.2, 1.3, 1.4], [1.0, 1.1, 1.2, 1.3, 1.4])
    (root / "rgb" / "1.200000.png").write_bytes(b"not a png")
    seq = open_sequence(root)
    before = set(threading.enumerate())
    got = []
    for i, pending in seq.prefetched(ahead):
        try:
            f = pending.result()
        except InputError as e:
            got.append((i, "error", str(e)))
            continue
        ref = seq.load(i)
        assert f.index == ref.index == i and f.timestamp == ref.timestamp
        assert np.array_equal(f.rgb, ref.rgb) and np.array_equal(f.depth, ref.depth)
        got.append((i, "ok", ""))
    assert [g[:2] for g in got] == [(0, "ok"), (1, "ok"), (2, "error"), (3, "ok"), (4, "ok")]
    assert "1.200000.png" in got[2][2]  # the error names the file, as load() does
    # a finished iteration has already ended its reader thread
    assert not [t for t in set(threading.enumerate()) - before if t.name.startswith("frame-reader")]


def test_prefetch_stops_reading_when_the_caller_stops(tmp_path):
    import threading
    import time

    root = make_tum(tmp_path / "s", [1.0 + 0.1 * k for k in range(30)], [1.0 + 0.1 * k for k in range(30)])
    seq = open_sequence(root)
    loaded = []
    real_load = seq.load

    def slow_load(i):
        time.sleep(0.01)
        loaded.append(i)
        return real_load(i)

    seq.load = slow_load
    frames = seq.prefetched(2)
    for i, pending in frames:
        pending.result()
        if i == 3:
            break
    frames.close()
    readers = [t for t in threading.enumerate() if t.name.startswith("frame-reader")]
    for t in readers:
        t.join(timeout=5.0)  # the read in progress finishes, then the thread ends
    assert not [t for t in readers if t.is_alive()]
    assert max(loaded) <= 3 + 2 and len(loaded) < 30  # nothing beyond the read-ahead window


@pytest.mark.data
@need_desk
def test_tum_folders_without_lists_are_read_by_file_name(tmp_path):
    """rgb/ and depth/ of time-stamp-named PNGs without rgb.txt/depth.txt: the same sequence."""
    root = tmp_path / "rgbd_dataset_freiburg1_desk_nolists"
    shutil.copytree(DESK, root)
    (root / "rgb.txt").unlink()
    (root / "depth.txt").unlink()
    a, b = open_sequence(DESK), open_sequence(root)
    assert isinstance(b, TumSequence) and b.camera.name == a.camera.name == "fr1"
    assert np.array_equal(a.timestamps, b.timestamps)
    assert [p.name for p in a.rgb_files] == [p.name for p in b.rgb_files]
    assert [p.name for p in a.depth_files] == [p.name for p in b.depth_files]
    # a stray file that is not named by a time stamp: one clear sentence
    cv2.imwrite(str(root / "rgb" / "snapshot.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(InputError, match=r"snapshot\.png is not named by its time stamp.*write rgb\.txt"):
        open_sequence(root)


def test_depth_warning_flags_implausible_depth():
    from rgbdslam.datasets.base import Frame, depth_warning

    def frame(depth):
        return Frame(0, 0.0, np.zeros((4, 5, 3), np.uint8), np.asarray(depth, np.float32), CAMERAS["fr1"], "d.png")

    assert depth_warning(frame(np.full((4, 5), 1.2))) is None  # a desk at 1.2 m
    assert depth_warning(frame(np.full((4, 5), 7.5))) is None  # a far wall: still a camera's range
    far = depth_warning(frame(np.full((4, 5), 24.0)))  # millimetres read with 5000 per metre ... x5
    assert "median of 24.0 m" in far and "depth_scale=1000" in far and "d.png" in far
    near = depth_warning(frame(np.full((4, 5), 0.2)))  # ... or the other way round
    assert "20.0 cm" in near and "depth_scale" in near
    empty = np.zeros((4, 5))
    assert "almost empty" in depth_warning(frame(empty))
    half = np.zeros((4, 5))
    half[:2] = 1.0  # half the pixels valid: the median is over the valid ones
    assert depth_warning(frame(half)) is None


@pytest.mark.data
@need_desk
def test_info_reports_depth_of_the_first_frame():
    from rgbdslam.config import DatasetConfig
    from rgbdslam.datasets import describe_sequence

    text = describe_sequence(DESK)
    assert "depth       frame 0:" in text and "warning" not in text
    wrong = describe_sequence(DESK, DatasetConfig(depth_scale=1.0))  # raw units taken as metres
    assert "warning" in wrong and "depth_scale=1000" in wrong


def test_error_line_numbers_count_newlines_only(tmp_path):
    """A form feed inside a comment is not a line break: the bad line is named as the editor shows it."""
    from rgbdslam.io.trajectory import read_tum

    p = tmp_path / "t.tum"
    p.write_text("# exported\x0cby a tool\r\n1.0 0 0 0 0 0 0 1\r\nnot a pose\r\n")
    with pytest.raises(InputError, match=r"t.tum:3: expected 8 numbers"):
        read_tum(p)


def test_a_new_reader_is_one_class_declared_with_reader(tmp_path):
    """A reader is a Sequence subclass declared with @reader(name, detect): open_sequence then picks
    it for its layout (kind auto) and every stage reads its frames, with no other change."""
    from rgbdslam.datasets import READERS, detect_kind
    from rgbdslam.datasets.base import Frame, Sequence
    from rgbdslam.datasets.registry import reader
    from rgbdslam.pipeline import run_sequence
    from rgbdslam.config import load_config
    from rgbdslam.datasets.synthetic import generate_sequence

    synth = tmp_path / "synth"
    generate_sequence(synth, frames=12, motion="xyz", seed=3, width=320, height=240)
    tum = open_sequence(synth)

    def is_npz_layout(path: Path) -> bool:
        return (path / "frames.npz").is_file()

    @reader("npz_test", is_npz_layout)
    class NpzSequence(Sequence):  # all frames in one .npz: rgb (N,H,W,3), depth (N,H,W) metres, t (N)
        def __init__(self, root, cfg=None):
            self.root, self.name, self.camera = Path(root), "npz", tum.camera
            self._data = np.load(self.root / "frames.npz")

        @property
        def timestamps(self):
            return self._data["t"]

        def groundtruth(self):
            return tum.groundtruth()

        def load(self, i):
            return Frame(i, float(self._data["t"][i]), self._data["rgb"][i], self._data["depth"][i], self.camera)

    try:
        frames = [tum.load(i) for i in range(len(tum))]
        folder = tmp_path / "npz"
        folder.mkdir()
        np.savez(folder / "frames.npz", rgb=np.stack([f.rgb for f in frames]),
                 depth=np.stack([f.depth for f in frames]), t=tum.timestamps)
        assert detect_kind(folder, DatasetConfig()) == "npz_test"
        summary = run_sequence(folder, tmp_path / "run", load_config(None, ["mapping.enabled=false",
                                                                             "output.plots=false"]), progress=False)
        assert summary["tracked"] == 12 and summary["evaluation"]["ate"]["rmse"] < 0.01
    finally:
        READERS.pop("npz_test", None)
