"""The translation scale on a synthetic orbit around a near figure (TUM fr3/teddy's geometry): key
points on the figure's outline shorten every frame-to-frame translation (docs/frontend.md "Scale bias")
when every key point used lies on the figure. The orbit's hall has textured door and window frames
6-10 m away; with ``matching.max_depth`` 6 m they are dropped, and with the depth-edge flags (radius per
pyramid level) left out of each registration's pose fit the Sim(3) scale of the odometry is 1.026 at the
default (radius 2, 15 % jump; 1.051 with the former radius 1 and 5 % jump) and 1.012 at radius 3 with a 5 % jump (1.17 without). With the far frames
in (the default 10 m) the scale is 1.002 even without the flags: far points pin the rotation, so the
outline points can no longer trade translation for it."""

import numpy as np
import pytest

from rgbdslam.config import Config
from rgbdslam.datasets import open_sequence
from rgbdslam.datasets.synthetic import generate_sequence
from rgbdslam.evaluation.ate import umeyama_alignment
from rgbdslam.frontend.odometry import build_frontend


def _odometry_scale(path, cfg) -> float:
    seq = open_sequence(path, cfg)
    frontend = build_frontend(cfg, seq.load(0).camera)
    poses = []
    for i in range(len(seq)):
        res = frontend.track(seq.load(i))
        assert not res.lost
        poses.append(res.pose[:3, 3])
    frontend.close()
    gt = seq.groundtruth().poses[:, :3, 3]
    _, _, s = umeyama_alignment(np.array(poses).T, gt.T, "sim3")
    return s


@pytest.mark.slow
def test_orbit_odometry_scale(tmp_path):
    generate_sequence(tmp_path / "orbit", frames=60, motion="orbit", noise=True, seed=0)
    scales = {}
    for name, radius, jump, max_depth in (("off", 0, 0.15, 6.0), ("default", None, None, 6.0), ("r3", 3, 0.05, 6.0),
                                          ("off, far points", 0, 0.15, None)):
        cfg = Config()
        if radius is not None:  # else the default's own values
            cfg.matching.depth_edge_radius, cfg.matching.depth_edge_jump = radius, jump
        if max_depth is not None:  # only the figure's points (and a few on a panel 2-3 m away)
            cfg.matching.max_depth = max_depth
        scales[name] = _odometry_scale(tmp_path / "orbit", cfg)
    assert scales["off"] > 1.1, scales  # the bias: outline points shorten every translation (1.17)
    assert abs(scales["default"] - 1.0) < 0.035, scales  # the default removes most of it (1.026)
    assert abs(scales["r3"] - 1.0) < 0.015, scales  # 1.012: the outline points are the bias
    assert abs(scales["off, far points"] - 1.0) < 0.005, scales  # 1.002: the far frames hold the scale
