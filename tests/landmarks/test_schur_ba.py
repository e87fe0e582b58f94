"""The NumPy Schur-complement local BA (``landmarks.ba_solver: schur``) against GTSAM and hand-worked cases."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import gtsam
from rgbdslam.config import LandmarksConfig
from rgbdslam.landmarks.local_ba import LocalBA, StereoFactors, make_problem, schur_problem, solve_problem
from rgbdslam.landmarks.map import LandmarkMap
from rgbdslam.landmarks.schur_ba import SchurBA, se3_exp
from rgbdslam.landmarks.stage import _KeyframeObs
from tests.landmarks.scenes import CAM, pose, scene, seen


def _problem(seed: int = 4, n: int = 400, duplicate: bool = False, outliers: int = 0):
    """Five keyframes seeing noisy landmarks, the last four off by ~2 cm; ``outliers`` observations
    moved by 30 px (the Huber kernel's side); ``duplicate``: keyframe 2 sees its first landmarks twice."""
    rng = np.random.default_rng(seed)
    X = scene(n, 1)
    cfg = LandmarksConfig(ba_window=4, ba_iterations=10, depth_noise_a=0.001, depth_noise_b=0.002, ba_max_move=1.0,
                          ba_max_move_deg=30.0)
    lmap = LandmarkMap(store="single")
    ids = lmap.add(X + rng.normal(scale=0.01, size=X.shape), np.tile(np.eye(3) * 1e-4, (len(X), 1, 1)),
                   np.zeros((len(X), 32), np.uint8), 0, 0)
    kfs, poses = [], {}
    for k in range(5):
        P = pose([0, 0.03 * k, 0.01 * k], [0.08 * k, 0.01 * k, 0])
        _, uv, z = seen(P, X)
        uv = uv + rng.normal(scale=0.5, size=uv.shape)
        z = z + rng.normal(scale=0.002, size=z.shape)
        if outliers:
            uv[rng.choice(len(uv), outliers, replace=False)] += 30.0
        lm = ids
        if duplicate and k == 2:
            lm, uv, z = np.r_[ids, ids[:20]], np.r_[uv, uv[:20] + 0.7], np.r_[z, z[:20] + 0.003]
        kfs.append(_KeyframeObs(k, lm, uv, z))
        poses[k] = P if k == 0 else P @ pose(rng.normal(scale=0.01, size=3), rng.normal(scale=0.02, size=3))
    return cfg, lmap, kfs, poses


def _both(cfg, p):
    g = solve_problem(dataclasses.replace(cfg, ba_solver="gtsam"), StereoFactors(cfg, CAM), p)
    s = solve_problem(dataclasses.replace(cfg, ba_solver="schur"), StereoFactors(cfg, CAM), p)
    return g, s


@pytest.mark.parametrize("kind", ["plain", "outliers_one_iteration", "duplicate", "no_prior", "one_iteration"])
def test_schur_ba_follows_gtsam_levenberg_marquardt(kind):
    """Same poses, landmarks and graph errors as GTSAM's LM on the same problem (to rounding)."""
    cfg, lmap, kfs, poses = _problem(outliers=40 if kind.startswith("outliers") else 0, duplicate=kind == "duplicate")
    if kind == "no_prior":
        cfg = dataclasses.replace(cfg, ba_landmark_prior=False)
    if kind.endswith("one_iteration"):
        cfg = dataclasses.replace(cfg, ba_iterations=1)
    p = make_problem(cfg, lmap, kfs, poses)
    assert p is not None and len(p.fixed) == 1 and len(p.window) == 4
    g, s = _both(cfg, p)
    assert sorted(g.poses) == sorted(s.poses) == [1, 2, 3, 4]
    assert g.error[1] < 0.5 * g.error[0]  # the solve did something
    assert s.error[0] == pytest.approx(g.error[0], rel=1e-12)
    assert s.error[1] == pytest.approx(g.error[1], rel=1e-9)
    for k in g.poses:
        assert np.abs(s.poses[k] - g.poses[k]).max() < 1e-9
    assert np.abs(s.after - g.after).max() < 1e-9


def test_where_gtsam_declares_the_system_indeterminate_schur_goes_on():
    """With 40 observations 30 px off, GTSAM's elimination reports an indeterminate system near the
    held keyframe from the second iteration on (every λ fails, LM stops after one step; the system is
    well posed: a held pose and a prior on every landmark). The Schur solver takes the same first step
    (test above) and goes on to a lower error."""
    cfg, lmap, kfs, poses = _problem(outliers=40)
    cfg = dataclasses.replace(cfg, ba_adaptive_noise=False)  # the outliers' noise as the model says (not rescaled)
    p = make_problem(cfg, lmap, kfs, poses)
    g, s = _both(cfg, p)
    g1, _ = _both(dataclasses.replace(cfg, ba_iterations=1), p)
    assert g.error[1] == g1.error[1]  # GTSAM: one step only
    assert s.error[1] < 0.95 * g.error[1]


def test_schur_ba_error_is_gtsams_graph_error_on_a_hand_worked_observation():
    """One landmark at (0.1, -0.2, 2) seen from the origin, measured at (u, v, z) = (346, 189, 2.1):
    predicted u = 525·0.05 + 319.5 = 345.75, v = 525·(−0.1) + 239.5 = 187, disparity f b / z =
    525·0.08 / 2 = 21 px against the measured 525·0.08 / 2.1 = 20 px. Whitened (σ_px = 1, σ_d =
    f b σ_z / z² with σ_z = 0.001 + 0.002·2.1² = 0.00982 at the measured z → 0.09352 px, binned):
    (−0.25, (20 − 21) / σ_d, −2): the disparity residual is far outside Huber's 1.345."""
    cfg = LandmarksConfig(ba_landmark_prior=False)
    f = StereoFactors(cfg, CAM)
    sd = float(f.binned(f.disparity_sigma(np.array([2.1])))[0])
    assert sd == pytest.approx(525 * 0.08 * 0.00982 / 2.1**2, rel=0.01)
    ba = SchurBA(np.eye(4)[None], np.array([True]), [0], [0], np.array([[346.0, 189.0, 2.1]]), [sd],
                 np.array([[0.1, -0.2, 2.0]]), None, CAM.fx, CAM.fy, CAM.cx, CAM.cy, f.fb, 1.0, 1.345)
    r = np.linalg.norm([-0.25, -1.0 / sd, -2.0])
    hand = 1.345 * (r - 1.345 / 2)  # Huber's linear side
    assert ba.error(ba.poses, ba.X0) == pytest.approx(hand, rel=1e-12)
    graph = gtsam.NonlinearFactorGraph()
    f.add(graph, 0, np.array([0]), np.array([[346.0, 189.0]]), np.array([2.1]))
    values = gtsam.Values()
    values.insert(gtsam.symbol("x", 0), gtsam.Pose3())
    values.insert(gtsam.symbol("l", 0), np.array([0.1, -0.2, 2.0]))
    assert graph.error(values) == pytest.approx(hand, rel=1e-12)


def test_a_landmark_behind_a_camera_costs_what_gtsam_charges():
    """GTSAM's stereo factor returns (2 fx, 2 fx, 2 fx) for a point behind the camera: whitened
    (2 fx / σ, 0, 2 fx / σ), on Huber's linear side."""
    cfg = LandmarksConfig(ba_landmark_prior=False)
    f = StereoFactors(cfg, CAM)
    ba = SchurBA(np.eye(4)[None], np.array([True]), [0], [0], np.array([[300.0, 200.0, 2.0]]), [1.0],
                 np.array([[0.0, 0.0, -1.0]]), None, CAM.fx, CAM.fy, CAM.cx, CAM.cy, f.fb, 1.0, 1.345)
    r = np.sqrt(2) * 2 * CAM.fx
    assert ba.error(ba.poses, ba.X0) == pytest.approx(1.345 * (r - 1.345 / 2), rel=1e-12)


def test_se3_exp_is_gtsams_expmap():
    rng = np.random.default_rng(0)
    xi = np.r_[rng.normal(scale=0.5, size=(20, 6)), rng.normal(scale=1e-7, size=(3, 6)), np.zeros((1, 6))]
    T = se3_exp(xi)
    for v, M in zip(xi, T):
        assert np.abs(M - gtsam.Pose3.Expmap(v).matrix()).max() < 1e-13


def test_local_ba_with_either_solver_writes_the_same_map():
    cfg, lmap, kfs, poses = _problem(seed=7, n=200)
    lmap2 = LandmarkMap(store="single")
    lmap2.add(lmap.pos[:200], lmap.cov[:200], lmap.desc[:200], 0, 0)
    out_g = LocalBA(dataclasses.replace(cfg, ba_solver="gtsam"), CAM).run(lmap, kfs, poses)
    out_s = LocalBA(dataclasses.replace(cfg, ba_solver="schur"), CAM).run(lmap2, kfs, poses)
    assert sorted(out_g) == sorted(out_s) == [1, 2, 3, 4]
    assert max(np.abs(out_g[k] - out_s[k]).max() for k in out_g) < 1e-9
    assert np.abs(lmap.pos[:200] - lmap2.pos[:200]).max() < 1e-9


def test_schur_problem_keeps_every_observation():
    cfg, lmap, kfs, poses = _problem(duplicate=True)
    p = make_problem(cfg, lmap, kfs, poses)
    ba, kfs_order = schur_problem(cfg, StereoFactors(cfg, CAM), p)
    assert len(ba.op) == sum(len(o[1]) for o in p.obs) and not ba.unique_cells
    assert sorted(kfs_order) == sorted(p.poses) and ba.K == 4
