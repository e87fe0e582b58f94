"""Landmark map: Kalman filter maths, the two stores agree, RANSAC prefers old landmarks, tracking on real frames."""

from __future__ import annotations

import numpy as np
import pytest

from rgbdslam.landmarks.kalman import kalman_update, observation_covariance
from rgbdslam.landmarks.map import LandmarkMap
from rgbdslam.landmarks.store import MultiTreeStore, SingleTreeStore


def test_kalman_scalar_case_by_hand():
    # P = 4 I, R = 1 I, q = 0: K = 4/5, x = 0 + 0.8 (5 - 0) = 4, P = (1 - 0.8) 4 = 0.8
    x, P = kalman_update(np.zeros((1, 3)), 4 * np.eye(3)[None], np.full((1, 3), 5.0), np.eye(3)[None], 0.0)
    assert np.allclose(x, 4.0)
    assert np.allclose(P, 0.8 * np.eye(3))
    # process noise q adds q^2 before the update: P = 4 + 1 = 5, K = 5/6
    x, P = kalman_update(np.zeros((1, 3)), 4 * np.eye(3)[None], np.full((1, 3), 6.0), np.eye(3)[None], 1.0)
    assert np.allclose(x, 5.0) and np.allclose(P, 5 / 6 * np.eye(3))


def test_kalman_averages_repeated_observations():
    # with q = 0 and equal R, the filter is the running mean, and P shrinks as R / n
    rng = np.random.default_rng(0)
    z = rng.normal(size=(50, 3))
    x, P = z[:1].copy(), np.eye(3)[None] * 0.01
    for k in range(1, 50):
        x, P = kalman_update(x, P, z[k:k + 1], np.eye(3)[None] * 0.01, 0.0)
    assert np.allclose(x[0], z.mean(axis=0))
    assert np.allclose(P[0], np.eye(3) * 0.01 / 50)


def test_observation_covariance_along_the_ray_grows_with_z2():
    P = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 3.0]])
    C = observation_covariance(P, np.eye(3), 500.0, 1.0, 0.0, 0.002)
    assert np.isclose(np.sqrt(C[0, 2, 2]), 0.002) and np.isclose(np.sqrt(C[1, 2, 2]), 0.018)
    assert np.isclose(np.sqrt(C[1, 0, 0]), 3.0 / 500.0)
    R = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])  # rotated into the world
    Cw = observation_covariance(np.array([[1.0, 0, 0.0001]]), R, 500.0, 1.0, 0.0, 0.002)
    ray = R @ np.array([1.0, 0, 0.0001]) / np.linalg.norm([1.0, 0, 0.0001])
    assert np.isclose(ray @ Cw[0] @ ray, (0.002 * 1e-8) ** 2 + 0, atol=1e-9)  # tiny z: tiny ray sigma


@pytest.mark.parametrize("n1,q", [(50, 2.0), (100, 5.5)])
def test_stores_return_the_same_landmarks(n1, q):
    rng = np.random.default_rng(1)
    single, multi = SingleTreeStore(), MultiTreeStore(n1=n1, q=q)
    seen = np.zeros(5000, int)
    nid = 0
    for step in range(30):
        k = int(rng.integers(20, 120))
        ids = np.arange(nid, nid + k)
        pts = rng.uniform(-5, 5, size=(k, 3))
        seen[ids] = rng.integers(1, 5, size=k)
        nid += k
        single.insert(ids, pts)
        multi.insert(ids, pts, seen[ids])
        if step % 4 == 3:  # remove some
            gone = rng.choice(nid, size=30, replace=False)
            gone = gone[~single._dead[gone]] if len(single._dead) > gone.max() else gone
            single.remove(gone)
            multi.remove(gone)
        single.step(seen[:nid])
        multi.step(seen[:nid])
        c = rng.uniform(-4, 4, size=3)
        a = np.sort(single.query_ball(c, 2.0))
        b = np.sort(np.unique(multi.query_ball(c, 2.0)))
        assert np.array_equal(a, b)
    assert len(single) == len(multi)
    assert len(multi.trees()) >= 3  # the logarithmic method grew beyond its first level


def test_multi_store_level_sizes_respect_capacities():
    s = MultiTreeStore(n1=100, q=3.0, base_seen=0)
    for k in range(50):
        s.insert(np.arange(k * 40, (k + 1) * 40), np.random.default_rng(k).normal(size=(40, 3)))
    sizes = s.trees()[1:]
    assert sum(sizes) == 2000
    assert all(n <= s.capacity(k) for k, n in enumerate(sizes))


def test_map_culls_rarely_seen_landmarks_and_moves_with_anchors():
    m = LandmarkMap(store="multi", min_seen=2, cull_after=5)
    ids = m.add(np.eye(3), np.tile(np.eye(3) * 1e-4, (3, 1, 1)), np.zeros((3, 32), np.uint8), frame=0, anchor=0)
    m.observe(ids[:1], np.array([[1.0, 0, 0]]), np.eye(3)[None] * 1e-4, frame=3)
    m.end_step(6)
    assert m.size == 1 and m.alive[ids[0]] and m.n_culled == 2
    C = np.eye(4)
    C[:3, 3] = [0, 0, 1.0]
    assert m.move_with_anchors({0: C}) == 1
    assert np.allclose(m.pos[ids[0]], [1, 0, 1])
    assert np.array_equal(m.near(np.array([1.0, 0, 1]), 0.1), ids[:1])


def test_ransac_samples_old_landmarks_first():
    from rgbdslam.geometry.ransac import ransac_rigid

    rng = np.random.default_rng(0)
    S = rng.uniform(-1, 1, size=(100, 3)) + [0, 0, 2]
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.2, 0.3]
    D = S + T[:3, 3]
    D[30:] += rng.normal(scale=0.5, size=(70, 3))  # the "young" 70 % are wrong
    # uniform sampling with few iterations rarely draws three good pairs; the old 30 % always do
    out = ransac_rigid(S, D, 0.01, 5, np.random.default_rng(3), 3, subset=100, sample_from=30)
    assert out is not None and np.allclose(out[0], T, atol=1e-9) and out[1].sum() == 30
