"""Every number is checked where it is read, in every reader (rgbdslam.io.validate): a camera,
pose or time stamp that is not a number, not finite or absurd is one error line naming the
file, exit 2 — never a segmentation fault, a traceback, a hang or "ATE inf" later.

Each case below is one instance of a class (camera, pose, time stamp; per reader); the
subprocess test runs the real console script, as a crash in OpenCV kills the process."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import REPO, cli

SMALL = dict(frames=3, motion="circle", seed=0, width=160, height=120)


@pytest.fixture(scope="module")
def layouts(tmp_path_factory) -> dict[str, Path]:
    """One small valid sequence per stereo layout and a 7-Scenes folder (3 frames each)."""
    import cv2

    from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence

    root = tmp_path_factory.mktemp("layouts")
    generate_stereo_sequence(root / "euroc", 0.12, "euroc", **SMALL)
    generate_stereo_sequence(root / "kitti", 0.12, "kitti", **SMALL)
    seq = root / "kitti" / "sequences" / "00"
    (root / "kitti" / "poses").mkdir(exist_ok=True)
    (root / "kitti" / "poses" / "00.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 3)
    (seq / "times.txt").write_text("0.0\n0.1\n0.2\n")
    plain = root / "plain"
    shutil.copytree(seq / "image_0", plain / "left")
    shutil.copytree(seq / "image_1", plain / "right")
    (plain / "stereo.yaml").write_text("fx: 131.25\nfy: 131.25\ncx: 79.5\ncy: 59.5\nbaseline: 0.12\nfps: 10\n")
    seven = root / "seven"
    seven.mkdir()
    rng = np.random.default_rng(0)
    for n in range(3):
        cv2.imwrite(str(seven / f"frame-{n:06d}.color.png"), rng.integers(0, 255, (480, 640, 3), np.uint8))
        cv2.imwrite(str(seven / f"frame-{n:06d}.depth.png"), np.full((480, 640), 1500, np.uint16))
        (seven / f"frame-{n:06d}.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    (seven / "camera-intrinsics.txt").write_text("585 0 320\n0 585 240\n0 0 1\n")
    return {"euroc": root / "euroc", "kitti": root / "kitti", "plain": plain, "seven": seven}


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, (path, old)
    path.write_text(text.replace(old, new))


def _one_line(res, *parts: str) -> None:
    assert res.exit_code == 2 and isinstance(res.exception, SystemExit), (res.exception, res.output)
    assert res.stdout == "" and res.stderr.count("\n") == 1 and res.stderr.startswith("error: "), res.output
    for p in parts:
        assert p in res.stderr, (p, res.stderr)


def test_euroc_negative_resolution_is_one_line_not_a_segfault(layouts, tmp_path):
    """The audit's high finding: a negative resolution reached OpenCV's rectification maps and the
    process died with SIGSEGV (exit 139, nothing printed)."""
    mav = shutil.copytree(layouts["euroc"], tmp_path / "e") / "mav0"
    for cam in ("cam0", "cam1"):
        _edit(mav / cam / "sensor.yaml", "resolution: [160, 120]", "resolution: [-160, -120]")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    res = subprocess.run([sys.executable, "-m", "rgbdslam._entry", "info", str(tmp_path / "e")], env=env,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, (res.returncode, res.stderr[-500:])
    assert res.stdout == "" and res.stderr == (f"error: {mav / 'cam0' / 'sensor.yaml'}: width must be a finite "
                                               f"number from 1 to 65535; got -160\n")


# (layout, file relative to the layout, text replaced, replacement, words the one line holds)
CASES = [
    # EuRoC sensor.yaml: sizes, intrinsics, distortion, T_BS; data.csv time stamps
    ("euroc", "mav0/cam0/sensor.yaml", "resolution: [160, 120]", "resolution: [60000, 60000]",
     "larger than 268,435,456 pixels"),
    ("euroc", "mav0/cam0/sensor.yaml", "resolution: [160, 120]", "resolution: [160.5, 120]", "whole number"),
    ("euroc", "mav0/cam0/sensor.yaml", "intrinsics: [131.25", "intrinsics: [.inf", "intrinsics [fu, fv, cu, cv] must be a finite number; got inf"),
    ("euroc", "mav0/cam0/sensor.yaml", "distortion_coefficients: [0.0, 0.0, 0.0, 0.0]",
     "distortion_coefficients: [1.0e+10, 0.0, 0.0, 0.0]", "distortion coefficient 1 must be within ±1000"),
    ("euroc", "mav0/cam0/sensor.yaml", "distortion_coefficients: [0.0, 0.0, 0.0, 0.0]",
     "distortion_coefficients: '12345'", "must be a list of numbers; got '12345'"),
    ("euroc", "mav0/cam0/sensor.yaml", "data: [0.0, 0.0, 1.0,", "data: [0.0, 0.0, 2.0,", "no rotation matrix"),
    ("euroc", "mav0/cam0/data.csv", "1600000000000000000,", "16000000000000000000000000,", "beyond ±1e+12 s"),
    # plain stereo folder: stereo.yaml
    ("plain", "stereo.yaml", "fps: 10", "fps: 0", "fps must be a finite number from 0.001 to 10000; got 0"),
    ("plain", "stereo.yaml", "fps: 10", "fps: .nan", "fps must be a finite number"),
    ("plain", "stereo.yaml", "fy: 131.25", "fy: .inf", "fy must be a finite number"),
    ("plain", "stereo.yaml", "fps: 10", "width: .nan", "width must be a whole number; got nan"),
    ("plain", "stereo.yaml", "fx: 131.25", "fx: true", "fx must be a number; got True"),
    ("plain", "stereo.yaml", "fps: 10", "fps: 1:00", "fps must be a number; got '1:00'"),
    ("plain", "stereo.yaml", "fx: 131.25", "fx: 131.25\nfx: 131.25", "'fx' is given twice"),
    # KITTI: calib.txt, poses, times
    ("kitti", "sequences/00/calib.txt", "P0: 1.312500000000e+02 0.000000000000e+00 7.950000000000e+01 "
                                        "0.000000000000e+00 0.000000000000e+00 1.312500000000e+02",
     "P0: 1.312500000000e+02 0.000000000000e+00 7.950000000000e+01 0.000000000000e+00 0.000000000000e+00 "
     "-1.312500000000e+02", "(P0): fy must be a finite number above 0"),
    ("kitti", "poses/00.txt", "1 0 0 0 0 1 0 0 0 0 1 0\n", "1 0 0 1e200 0 1 0 0 0 0 1 0\n",
     "translation beyond ±1e+09 m"),
    ("kitti", "poses/00.txt", "1 0 0 0 0 1 0 0 0 0 1 0\n", "2 0 0 0 0 1 0 0 0 0 1 0\n", "no rotation matrix"),
    ("kitti", "sequences/00/times.txt", "0.1\n", "0.0\n", "time stamps must increase"),
    # 7-Scenes: intrinsics and poses
    ("seven", "camera-intrinsics.txt", "0 585 240", "0 585 1e200", "cy must be a finite number from -1e+06"),
    ("seven", "frame-000001.pose.txt", "1 0 0 0\n", "1 0 0 1e300\n", "translation beyond"),
]


@pytest.mark.parametrize("layout, rel, old, new, words", CASES, ids=[f"{c[0]}-{i}" for i, c in enumerate(CASES)])
def test_every_reader_checks_its_numbers(layouts, tmp_path, layout, rel, old, new, words):
    root = shutil.copytree(layouts[layout], tmp_path / layout)
    _edit(root / rel, old, new)
    _one_line(cli(["info", root]), str(root / rel), words)  # `info` reads the ground truth too


def test_a_folder_where_a_file_is_expected_is_named(layouts, tmp_path):
    for layout, rel in (("euroc", "mav0/state_groundtruth_estimate0/data.csv"), ("kitti", "sequences/00/times.txt"),
                        ("kitti", "poses/00.txt"), ("seven", "camera-intrinsics.txt")):
        root = shutil.copytree(layouts[layout], tmp_path / f"{layout}{len(rel)}")
        target = root / rel
        if target.exists():
            target.unlink()
        target.mkdir(parents=True)
        _one_line(cli(["info", root]), f"{target} is a folder")


@pytest.mark.parametrize("layout, rel", [("plain", "left/000000.png"), ("kitti", "sequences/00/image_0/000000.png")])
def test_a_damaged_first_image_is_our_line_alone(layouts, tmp_path, layout, rel):
    """libpng printed "libpng error: ..." (straight to the process's stderr) above our line."""
    root = shutil.copytree(layouts[layout], tmp_path / layout)
    img = root / rel
    data = bytearray(img.read_bytes())
    data[60] ^= 0xFF  # a byte of the image data: the chunk's CRC fails
    img.write_bytes(bytes(data))
    env = dict(os.environ, PYTHONPATH=str(REPO))
    res = subprocess.run([sys.executable, "-m", "rgbdslam._entry", "info", str(root)], env=env, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 2 and res.stdout == "", res.stderr
    assert res.stderr.count("\n") == 1 and res.stderr.startswith(f"error: left image {img} cannot be decoded ("), \
        res.stderr
