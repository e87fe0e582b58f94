"""`rgbdslam fuse --render` (headless PNG previews, rgbdslam.viz.render) and the 2-D map preview's legend."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.conftest import cli
from rgbdslam.geometry.se3 import make_pose
from rgbdslam.io.trajectory import Trajectory
from rgbdslam.mapping.map2d import FREE, OCCUPIED, UNKNOWN, Map2D, render_preview
from rgbdslam.viz.render import look_at, splat
from tests.mapping.test_mapping import plane_run  # noqa: F401 - the fixture: three posed frames of a textured plane

MAP_SETS = ["--set", "mapping.depth_min=0.1", "--set", "mapping.mesh_min_frames=1", "--set", "mapping.map2d=false"]


def test_splat_keeps_the_nearest_point_at_its_pixel():
    w2c = np.eye(4)  # camera at the origin looking along +z
    pts = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [1.0, 0.0, 2.0]])
    cols = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8)
    img = splat(pts, cols, w2c, 64, 48, hfov_deg=90.0, size=0.1)
    assert tuple(img[24, 32]) == (255, 0, 0)  # the nearer of the two on the axis hides the other
    assert not (img == (0, 255, 0)).all(axis=2).any()
    f = 0.5 * 64 / np.tan(np.deg2rad(45))  # 32 px: x = 1 m at 2 m lands 16 px right of the centre
    assert tuple(img[24, int(32 + f * 0.5)]) == (0, 0, 255)
    # look_at puts the target on the optical axis
    T = look_at(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    p = T[:3, :3] @ np.zeros(3) + T[:3, 3]
    assert np.allclose(p[:2], 0) and p[2] > 0


def test_fuse_render_writes_previews_and_a_plain_fuse_removes_them(plane_run):  # noqa: F811
    _, run = plane_run
    res = cli(["fuse", run, "--render", "-q", *MAP_SETS])
    assert res.exit_code == 0, res.output
    for name in ("cloud.png", "mesh.png"):
        img = cv2.imread(str(run / "map" / name))
        assert img.shape == (480, 640, 3)
        drawn = (img != 255).any(axis=2).mean()
        assert drawn > 0.05, (name, drawn)  # the plane fills part of the view
        assert f"rendered {run / 'map' / name}" in res.stderr
    res = cli(["fuse", run, "-q", *MAP_SETS])
    assert res.exit_code == 0
    assert not (run / "map" / "cloud.png").exists() and not (run / "map" / "mesh.png").exists()  # never stale


def test_render_without_a_map_is_one_line(plane_run, tmp_path):  # noqa: F811
    from rgbdslam.errors import InputError
    from rgbdslam.viz.render import render_run

    _, run = plane_run
    with pytest.raises(InputError, match=r"holds no cloud\.ply or mesh\.ply; run `rgbdslam fuse"):
        render_run(run)


def test_map2d_preview_has_a_legend():
    img = np.full((40, 60), UNKNOWN, np.uint8)
    img[10:30, 10:50] = FREE
    img[18:22, 20:40] = OCCUPIED
    grid = Map2D(img, 0.05, (0.0, 0.0, 0.0), np.eye(4), "camera", "ransac")
    traj = Trajectory([0.0, 1.0, 2.0], np.array([make_pose(np.eye(3), [x, 1.0, 0.0]) for x in (0.8, 1.5, 2.2)]))
    out = render_preview(grid, traj, min_size=600)
    k = int(np.ceil(600 / 60))
    assert out.shape[1] == 60 * k and out.shape[0] > 40 * k  # the map, then the legend strip below it
    strip = out[40 * k:]
    colors = {tuple(c) for c in strip.reshape(-1, 3)}
    for c in [(FREE,) * 3, (OCCUPIED,) * 3, (UNKNOWN,) * 3, (0, 0, 255), (0, 160, 0), (255, 0, 0)]:
        assert c in colors, c
    # without a trajectory the legend shows only the cells
    strip = render_preview(grid, None, min_size=600)[40 * k:]
    assert (0, 0, 255) not in {tuple(c) for c in strip.reshape(-1, 3)}
