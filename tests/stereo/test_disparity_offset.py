"""The disparity offset of a stereo rig, fitted without ground truth (rgbdslam/stereo/offset.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from rgbdslam.stereo.offset import StereoObservations, fit_disparity_offset
from tests.conftest import cli

INTR = (700.0, 700.0, 600.0, 180.0)
BASELINE = 0.54


def exact_observations(delta: float, frames: int = 4, n: int = 300) -> list[StereoObservations]:
    """Exact (u, v, d) of ``n`` points 4-150 m ahead seen from a rig driving 2 m per frame with a slight
    turn, every disparity measured ``delta`` px too small; each point keeps its random descriptor."""
    rng = np.random.default_rng(3)
    P = np.column_stack([rng.uniform(-30, 30, n), rng.uniform(-3, 2, n), rng.uniform(12, 150, n)])
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    fx, fy, cx, cy = INTR
    out = []
    for k in range(frames):
        yaw = 0.01 * k
        R = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        Q = (P - [0.1 * k, 0.0, 2.0 * k]) @ R  # R^T (P - t): the camera at t, turned by yaw
        ok = (Q[:, 2] > 3.0)
        u, v = fx * Q[:, 0] / Q[:, 2] + cx, fy * Q[:, 1] / Q[:, 2] + cy
        ok &= (u > 0) & (u < 1240) & (v > 0) & (v < 375)
        d = fx * BASELINE / Q[:, 2] - delta
        out.append(StereoObservations(np.column_stack([u, v])[ok], d[ok], np.zeros(ok.sum()), desc[ok]))
    return out


@pytest.mark.parametrize("delta", [0.0, 0.25, -0.4])
def test_exact_offset_recovered_from_noise_free_points(delta):
    """Noise-free measurements: the joint fit (motions + one offset) returns the offset the disparities
    were given, to 1e-4 px, from PnP first motions that assumed no offset."""
    fit = fit_disparity_offset(exact_observations(delta), INTR, BASELINE, sigma_d=0.1, max_gap=3)
    assert fit is not None and fit.pairs == 6
    assert abs(fit.delta - delta) < 1e-4
    assert fit.inliers == fit.residuals


def test_disparity_offset_setting_adds_to_every_sparse_disparity(tmp_path):
    """stereo.disparity_offset moves every sparse disparity by exactly its value and the points' depth with it."""
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence
    from rgbdslam.frontend.features import detect
    from rgbdslam.stereo.depth import sparse_matches

    generate_stereo_sequence(tmp_path / "s", 0.54, "kitti", frames=2, motion="highway", width=1241, height=376,
                             noise=True, seed=0)
    got = []
    for off in (0.0, 0.25):
        cfg = load_config("kitti", [f"stereo.disparity_offset={off}"])
        seq = open_sequence(tmp_path / "s", cfg)
        left, right = seq.rectified_pair(0)
        det = detect(left, cfg.features)
        got.append(sparse_matches(left, right, seq.rig, det.uv_raw, det.desc, cfg.stereo, cfg.features))
    a, b = got
    common, ia, ib = np.intersect1d(a.left_index, b.left_index, return_indices=True)
    assert len(common) > 100
    np.testing.assert_allclose(b.disparity[ib] - a.disparity[ia], 0.25, atol=1e-9)
    fb = seq.rig.camera.fx * seq.rig.baseline
    np.testing.assert_allclose(b.points[ib, 2], fb / b.disparity[ib], rtol=1e-6)


@pytest.fixture(scope="module")
def highway16(tmp_path_factory):
    from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence

    path = tmp_path_factory.mktemp("offset") / "highway16"
    generate_stereo_sequence(path, 0.54, "kitti", frames=16, motion="highway", width=1241, height=376,
                             noise=True, seed=0)
    return path


class RightShifted:
    """A stereo sequence whose right images are shifted ``px`` pixels to the right (bicubic): every
    disparity becomes ``px`` smaller, as with a principal-point error of the rig."""

    def __init__(self, seq, px: float) -> None:
        self.seq, self.px, self.rig, self.depth_noise = seq, px, seq.rig, seq.depth_noise

    def __len__(self) -> int:
        return len(self.seq)

    def rectified_pair(self, i: int):
        left, right = self.seq.rectified_pair(i)
        M = np.float32([[1, 0, self.px], [0, 1, 0]])
        return left, cv2.warpAffine(right, M, right.shape[1::-1], flags=cv2.INTER_CUBIC,
                                    borderMode=cv2.BORDER_REPLICATE)


EXACT = ["stereo.disparity_offset=0"]  # the generator's rig is exactly calibrated (the kitti preset has KITTI's offset)


@pytest.mark.parametrize("shift, sets, expect", [(0.0, EXACT, 0.0), (0.3, EXACT, 0.3), (-0.3, EXACT, -0.3),
                                                 (0.0, ["stereo.disparity_offset=-0.3"], 0.3),
                                                 (0.0, [], -0.099)])
def test_offset_of_synthetic_highway(highway16, shift, sets, expect):
    """16 frames of the synthetic highway (a perfect rig, image noise): the fitted offset is ~0 (measured
    +0.016 +- 0.015 px); with the right images shifted by +-0.3 px, or every disparity moved by -0.3 px in
    the config, it is recovered (measured 0.319, -0.318, 0.313) within 0.05 px; with the kitti preset's
    offset of KITTI's camera (+0.099 px) the fit undoes it."""
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.stereo.offset import estimate_disparity_offset

    cfg = load_config("kitti", sets)
    seq = open_sequence(highway16, cfg)
    fit = estimate_disparity_offset(RightShifted(seq, shift) if shift else seq, cfg)
    assert fit.pairs >= 40
    assert abs(fit.delta - expect) < 0.05, fit
    assert fit.se < 0.03
    assert fit.significant == (expect != 0.0)


def test_calibrate_stereo_offset_command(highway16):
    """`rgbdslam calibrate stereo-offset` on a rig whose disparities are 0.3 px too small (set in the config)
    prints the setting that undoes it."""
    res = cli(["calibrate", "stereo-offset", highway16, "--frames", "16", "--set", "stereo.disparity_offset=-0.3"])
    assert res.exit_code == 0, res.output
    line = res.output.strip().splitlines()[-1]
    assert line.startswith("--set stereo.disparity_offset=")
    assert abs(float(line.split("=")[1])) < 0.05
