"""Damaged images are reported by our one warning line only: no libpng/libjpeg/OpenCV output
on the process's stderr (issue 16, class 8; rgbdslam.io.images)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from rgbdslam.io.images import read_image


def _damaged(tmp_path: Path) -> dict[str, Path]:
    img = (np.arange(64 * 48 * 3) % 251).astype(np.uint8).reshape(48, 64, 3)
    ok, png = cv2.imencode(".png", img)
    ok, jpg = cv2.imencode(".jpg", img)
    png, jpg = png.tobytes(), jpg.tobytes()
    crc = bytearray(png)
    crc[len(crc) // 2] ^= 0xFF
    files = {"good.png": png, "truncated.png": png[: len(png) // 2], "crc.png": bytes(crc),
             "truncated.jpg": jpg[: len(jpg) // 2], "empty.png": b"", "good.jpg": jpg}
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    return {n: tmp_path / n for n in files}


def test_damaged_images_are_refused_silently(tmp_path, capfd):
    files = _damaged(tmp_path)
    for name, path in files.items():
        img, why = read_image(path)
        if name.startswith("good"):
            assert img is not None and img.shape == (48, 64, 3) and why is None
        else:
            assert img is None and why, name
    assert read_image(tmp_path)[0] is None  # a folder
    err = capfd.readouterr().err
    assert err == "", err  # the file descriptor 2 itself: libpng writes there, not to sys.stderr


@pytest.mark.data
def test_a_run_over_damaged_images_prints_only_our_warnings(desk9, tmp_path):
    """A real run in a child process (libpng writes to fd 2, which only a subprocess captures):
    a colour image with a bad CRC and a truncated depth image are skipped with our warning."""
    seq = tmp_path / "rgbd_dataset_freiburg1_damaged"
    for sub in ("rgb", "depth"):
        (seq / sub).mkdir(parents=True)
        for f in sorted((desk9 / sub).iterdir()):
            (seq / sub / f.name).symlink_to(f)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        (seq / name).symlink_to(desk9 / name)
    rgb = sorted((seq / "rgb").iterdir())[3]
    data = bytearray(rgb.read_bytes())
    data[len(data) // 2] ^= 0xFF
    rgb.unlink()
    rgb.write_bytes(bytes(data))
    depth = sorted((seq / "depth").iterdir())[5]
    data = depth.read_bytes()
    depth.unlink()
    depth.write_bytes(data[: len(data) // 3])
    env = {**os.environ, "PYTHONWARNINGS": ""}
    res = subprocess.run([sys.executable, "-m", "rgbdslam.cli", "run", str(seq), "--out", str(tmp_path / "out"),
                          "-q", "--no-map", "--set", "output.plots=false"], capture_output=True, text=True,
                         env=env, timeout=300)
    assert res.returncode == 0, res.stderr
    text = res.stdout + res.stderr
    assert "libpng" not in text and "[ERROR" not in text and "Corrupt" not in text, text
    warnings = [ln for ln in text.splitlines() if ln.startswith("warning:")]
    assert len(warnings) == 2, text
    assert rgb.name in warnings[0] and "CRC" in warnings[0]
    assert depth.name in warnings[1] and "truncated" in warnings[1]
