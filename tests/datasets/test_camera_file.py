"""Camera files (--camera, dataset.camera_file), the one camera order every reader follows, what
`run` says about the camera, and the TUM-like layouts recognised by their own files (ETH3D
SLAM's calibration.txt)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import yaml

from tests.conftest import TUM_DESK9, cli, need
from rgbdslam.config import DatasetConfig
from rgbdslam.datasets import open_sequence
from rgbdslam.datasets.camera_file import read_camera_file
from rgbdslam.errors import InputError


def _write(path, data):
    path.write_text(yaml.safe_dump(data))
    return path


def test_camera_file_keys(tmp_path):
    f = _write(tmp_path / "cam.yaml", {"fx": 600, "fy": 601, "cx": 330.5, "cy": 250.5, "size": [640, 480],
                                       "distortion": [0.1, -0.2, 0, 0, 0], "depth_scale": 1000,
                                       "depth_camera": {"fx": 580, "fy": 580, "cx": 320, "cy": 240},
                                       "depth_to_color": [0.025, 0, 0]})
    s = read_camera_file(f)
    c = s.camera
    assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height, c.dist) == (600, 601, 330.5, 250.5, 640, 480, (0.1, -0.2, 0, 0, 0))
    assert s.depth_scale == 1000 and s.depth_camera.fx == 580 and s.depth_camera.dist == (0.0,) * 5
    assert s.depth_to_color[:3, 3].tolist() == [0.025, 0, 0] and np.array_equal(s.depth_to_color[:3, :3], np.eye(3))
    assert s.source == str(f) and not s.fallback
    # depth from a second camera: the colour camera says its depth is not registered (the landmark map's
    # pose then fits 3-D points, landmarks.tracking.map_pose); a file without depth_camera / depth_to_color does
    assert not c.depth_registered
    assert read_camera_file(_write(tmp_path / "one.yaml", {"fx": 600, "fy": 601, "cx": 330, "cy": 250})).camera.depth_registered
    offset_only = read_camera_file(_write(tmp_path / "off.yaml", {"camera": "fr1", "depth_to_color": [0.02, 0, 0]}))
    assert offset_only.depth_camera is not None and not offset_only.camera.depth_registered
    for bad, msg in [({"fx": 1, "fy": 1, "cx": 1, "cy": 1, "lens": 3}, "unknown key"),
                     ({"fx": 1, "fy": 1, "cx": 1, "cy": 1, "size": [640]}, "size must be"),
                     ({"fx": 1, "fy": 1, "cx": 1, "cy": 1, "depth_scale": -5}, "depth_scale must be a number of raw units per metre from 0.001 to 1e6"),
                     ({"fx": 1, "fy": 1, "cx": 1, "cy": 1, "depth_to_color": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]},
                      "not a rotation"),
                     ({"fx": 1, "fy": 1, "cx": 1}, "missing cy")]:
        with pytest.raises(InputError, match=msg):
            read_camera_file(_write(tmp_path / "bad.yaml", bad))


@pytest.mark.data
def test_camera_order_and_what_run_says(tmp_path):
    """A copy of a freiburg1 folder under another name: ros_default with a warning naming the
    fix; --camera wins over everything; run prints the camera and where it came from."""
    copy = tmp_path / "my_desk"
    shutil.copytree(need(TUM_DESK9), copy)
    res = cli(["info", copy])
    assert "from the default 'ros_default'" in res.stdout and "pass --camera FILE" in res.stdout
    cam = _write(tmp_path / "fr1.yaml", {"camera": "fr1"})
    res = cli(["run", copy, "--camera", cam, "-o", tmp_path / "run", "--no-map", "-q", "--set", "dataset.max_frames=3"])
    assert res.exit_code == 0, res.output
    text = " ".join(res.stderr.split())
    assert f"camera fr1: fx 517.3 fy 516.5 cx 318.6 cy 255.3, 640x480, with distortion (from --camera {cam})" in text
    assert "warning" not in text
    res = cli(["run", copy, "-o", tmp_path / "run2", "--no-map", "-q", "--set", "dataset.max_frames=3"])
    assert "warning: no camera given for this sequence: assuming 'ros_default'" in " ".join(res.stderr.split())
    # a named camera in the config wins over the folder's camera.yaml; --camera over both
    (copy / "camera.yaml").write_text("camera: fr2\n")
    assert open_sequence(copy).camera.name == "fr2"
    assert open_sequence(copy, DatasetConfig(camera="fr3")).camera.name == "fr3"
    assert open_sequence(copy, DatasetConfig(camera="fr3", camera_file=str(cam))).camera.name == "fr1"
    # intrinsics that do not fit the images: one error line, exit 2
    small = _write(tmp_path / "small.yaml", {"fx": 300, "fy": 300, "cx": 160, "cy": 120, "size": [320, 240]})
    res = cli(["run", copy, "--camera", small, "-o", tmp_path / "run3", "--no-map", "-q"])
    assert res.exit_code == 2 and res.stderr.count("\n") == 1, res.output
    assert "is 640x480 but camera 'custom' is 320x240" in res.stderr
    # the camera file's depth scale is used (and dataset.depth_scale wins over it)
    (copy / "camera.yaml").write_text("camera: fr1\ndepth_scale: 1000\n")
    d_file = open_sequence(copy).load(0).depth
    d_tum = open_sequence(TUM_DESK9).load(0).depth
    np.testing.assert_allclose(d_file, d_tum * 5, rtol=1e-6)
    assert np.array_equal(open_sequence(copy, DatasetConfig(depth_scale=5000)).load(0).depth, d_tum)


@pytest.mark.data
def test_eth3d_layout(tmp_path):
    eth = tmp_path / "eth3d_sofa"
    shutil.copytree(need(TUM_DESK9), eth)
    (eth / "calibration.txt").write_text("726.28 726.28 354.65 186.47\n")
    seq = open_sequence(eth)
    c = seq.camera
    assert (c.name, c.fx, c.cy, c.width, c.height) == ("eth3d", 726.28, 186.47, 640, 480)  # size from the images
    assert seq.camera_setup.source == "calibration.txt (ETH3D SLAM)" and seq.depth_scale == 5000
    (eth / "calibration.txt").write_text("726.28 726.28\n")
    with pytest.raises(InputError, match="expected one line 'fx fy cx cy'"):
        open_sequence(eth)
    # ICL-NUIM's layout has a reader of its own: tests/datasets/test_icl.py


@pytest.mark.parametrize("text, words", [
    ("fx: 500\nfy: 500\ncx: 320\ncy: 240\ndistortion: '12345'\n", "distortion must be a list of numbers; got '12345'"),
    ("fx: true\nfy: 500\ncx: 320\ncy: 240\n", "fx must be a number; got True"),
    ("fx: 500\nfy: 500\ncx: 320\ncy: 240\nsize: [640.7, 480]\n", "width must be a whole number; got 640.7"),
    ("fx: 500\nfy: 500\nfx: 501\ncx: 320\ncy: 240\n", ":3: 'fx' is given twice in one section"),
    ("camera: [fr1]\n", "unknown camera ['fr1']"),
    ("fx: 500\nfy: 500\ncx: 0x10\ncy: 240\n", "cx must be a number; got '0x10'"),
    ("fx: 500\nfy: 500\ncx: 320\ncy: 240\nwidth: 0640\nheight: 480\n", None),  # 640, not octal 416
    ("fx: '" + "9" * 100000 + "'\nfy: 500\ncx: 320\ncy: 240\n", "fx must be a number; got '9999"),
    ("fx: 500\nfy: 500\ncx: 320\ncy: 240\ndist: " + str([0.0] * 100000) + "\n", "distortion must have 4 or 5 or 8"),
    ("".join(f"k{i}: 1\n" for i in range(100000)), "unknown key(s) k0, k1, k10, k100, k1000 and 99995 more"),
    ("a: &a [1, 2]\nfx: *a\n", ":2: uses the alias *a"),
])
def test_camera_file_values_are_taken_as_written(tmp_path, text, words):
    """No silent coercion (a string of digits as a list, true as 1, a size truncated, a repeated
    key's last value, YAML 1.1's octal) and every echoed value shortened."""
    p = tmp_path / "cam.yaml"
    p.write_text(text)
    if words is None:
        assert read_camera_file(p).camera.width == 640
        return
    with pytest.raises(InputError) as e:
        read_camera_file(p)
    assert words in str(e.value) and len(str(e.value)) < 400, str(e.value)[:600]
