"""Options that make the landmark map cheaper per frame (issue 17's speed target): what each one
changes, exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def test_top_view_draws_each_landmark_in_its_colour_where_it_lies():
    """The OpenCV top view: landmarks at known ground positions land on the pixels of the plot's
    metre scale (the vertical axis dropped: the cameras' image-down direction), in viridis of
    log2(times seen) / the largest; the keyframe path is red; no matplotlib is imported."""
    import subprocess
    import sys

    from rgbdslam.landmarks.topview import MARGIN, SIZE, render_top_view, viridis

    # cameras looking along world +z with image-down along world +y: y is up/down, the view is x-z
    P0, P1 = np.eye(4), np.eye(4)
    P1[:3, 3] = [1.0, 0.0, 1.0]
    pos = np.array([[0.0, 0.3, 1.0], [2.0, -5.0, 2.0], [1.0, 0.0, 0.5], [0.5, 0.0, 1.5]])
    seen = np.array([1, 16, 4, 2])
    img = render_top_view(pos, seen, [P0, P1])
    assert img.shape == (SIZE, SIZE, 3)
    left, top, right, bottom = MARGIN
    w, h = SIZE - left - right, SIZE - top - bottom
    # x and z both span 0..2 m (+5 % each side); the plot area is w x h px, square metres
    scale = min(w, h) / 2.2
    for (x, _, z), s in zip(pos, seen):
        col = int(np.floor(left + (x - (1.0 - w / (2 * scale))) * scale))
        row = int(np.floor(top + h - (z - (1.0 - h / (2 * scale))) * scale))
        want = viridis(np.array([np.log2(s) / 4.0]))[0]
        assert np.array_equal(img[row + 1, col + 1], want)  # the dot's lower-right pixel
    # the keyframe path from (0, 0) to (1, 1) m: its midpoint is red
    mid = (int(round(left + (0.5 - (1.0 - w / (2 * scale))) * scale)), int(round(top + h - (0.5 - (1.0 - h / (2 * scale))) * scale)))
    b, g, r = img[mid[1], mid[0]].astype(int)
    assert r > 150 and g < 150 and b < 150
    code = ("import sys, numpy as np; from rgbdslam.landmarks.topview import plot_top_view; "
            f"plot_top_view(sys.argv[1], np.zeros((3, 3)), np.ones(3), [np.eye(4)]); print('matplotlib' in sys.modules)")
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        out = subprocess.run([sys.executable, "-c", code, f"{d}/t.png"], capture_output=True, text=True, check=True)
        assert out.stdout.strip() == "False" and (Path(d) / "t.png").stat().st_size > 5000


def test_top_view_leaves_out_a_non_finite_landmark():
    """A NaN / inf landmark is not drawn and does not break the axes: the image equals the one
    without it."""
    from rgbdslam.landmarks.topview import render_top_view

    P1 = np.eye(4)
    P1[:3, 3] = [1.0, 0.0, 1.0]
    pos = np.array([[0.0, 0.3, 1.0], [1.0, 0.0, 0.5]])
    seen = np.array([1, 4])
    want = render_top_view(pos, seen, [np.eye(4), P1])
    bad = np.vstack([pos, [[np.nan, 0.0, 1.0], [np.inf, 0.0, 0.0]]])
    got = render_top_view(bad, np.append(seen, [2, 8]), [np.eye(4), P1])
    assert np.array_equal(got, want)
