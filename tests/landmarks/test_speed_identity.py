"""Speed-ups of the landmark stage's tracking that must not change a single bit.

Each kernel is checked against the plain expression it stands for, written out here, on a real
landmark map: fr1/rpy head200's first frames tracked with the landmark map on, then its later frames'
matches to that map (the reprojection residuals and Jacobians at the frame's pose and near it, every
match's and a refine's inlier subset; the candidates of the covisibility local map and of a loop's
older end). The whole chain's
poses are held bit for bit by ``tests/test_chain_poses.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

from rgbdslam.geometry.se3 import inv
from rgbdslam.geometry.whitening import whitening_rows
from rgbdslam.landmarks.tracking import _UPPER, Reprojection, match_to_map, project_candidates
from tests.landmarks.scenes import pose as near


def _reprojection_residuals_before(R, t, X, uv, z, camera, sigma_px, sigma_z, cov_lm, jacobian=True):
    """reprojection_residuals as it was written before (everything from the arguments, per call)."""
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    n = len(X)
    P = X @ R.T + t
    x, y = P[:, 0], P[:, 1]
    a = 1.0 / np.maximum(P[:, 2], 1e-3)
    xa, ya = x * a, y * a
    r0, r1, r2 = uv[:, 0] - (fx * xa + cx), uv[:, 1] - (fy * ya + cy), 1.0 / z - a
    p, q = fx * a, -fx * xa * a
    p2, q2 = fy * a, -fy * ya * a
    s = -a * a
    cov_lm = np.asarray(cov_lm, float)
    if cov_lm.ndim == 3:
        C = cov_lm.reshape(-1, 9) @ (R[:, None, :, None] * R[None, :, None, :]).reshape(9, 9)[_UPPER].T
        c00, c01, c02, c11, c12, c22 = C.T
        u0, u2 = p * c02 + q * c22, p2 * c12 + q2 * c22
        S00 = p * (p * c00 + q * c02) + q * u0
        S01 = p * (p2 * c01 + q2 * c02) + q * u2
        S02 = s * u0
        S11 = p2 * (p2 * c11 + q2 * c12) + q2 * u2
        S12 = s * u2
        S22 = s * s * c22
    else:
        S00 = S11 = (fx * np.broadcast_to(cov_lm, (n,)) * a) ** 2
        S01 = S02 = S12 = S22 = np.zeros(n)
    s_px2 = np.asarray(sigma_px, float) ** 2
    l00, l10, l20, l11, l21, l22 = whitening_rows(S00 + s_px2, S01, S02, S11 + s_px2, S12,
                                              S22 + (sigma_z / (z * z)) ** 2)
    r = np.empty((n, 3))
    r[:, 0] = l00 * r0 + l10 * r1 + l20 * r2
    r[:, 1] = l11 * r1 + l21 * r2
    r[:, 2] = l22 * r2
    if not jacobian:
        return r, None
    J0 = (-xa * ya * fx, (1 + xa * xa) * fx, -ya * fx, p, -xa * p)
    J1 = (-(1 + ya * ya) * fy, xa * ya * fy, xa * fy, p2, -ya * p2)
    J2 = (-ya * a, xa * a, s)
    J = np.empty((n, 3, 6))
    J[:, 0, 0] = l00 * J0[0] + l10 * J1[0] + l20 * J2[0]
    J[:, 0, 1] = l00 * J0[1] + l10 * J1[1] + l20 * J2[1]
    J[:, 0, 2] = l00 * J0[2] + l10 * J1[2]
    J[:, 0, 3] = l00 * J0[3]
    J[:, 0, 4] = l10 * J1[3]
    J[:, 0, 5] = l00 * J0[4] + l10 * J1[4] + l20 * J2[2]
    J[:, 1, 0] = l11 * J1[0] + l21 * J2[0]
    J[:, 1, 1] = l11 * J1[1] + l21 * J2[1]
    J[:, 1, 2] = l11 * J1[2]
    J[:, 1, 3] = 0.0
    J[:, 1, 4] = l11 * J1[3]
    J[:, 1, 5] = l11 * J1[4] + l21 * J2[2]
    J[:, 2, 0] = l22 * J2[0]
    J[:, 2, 1] = l22 * J2[1]
    J[:, 2, 2:5] = 0.0
    J[:, 2, 5] = l22 * J2[2]
    return r, J


def _project_candidates_before(lmap, pose, camera, max_depth, allowed, margin=0.2):
    """The candidates as they were found before: every landmark near the camera projected, the local
    map's mask applied afterwards."""
    c = pose[:3, 3]
    ids = lmap.near(c + pose[:3, 2] * (0.5 * max_depth), 0.5 * max_depth + margin)
    Tcw = inv(pose)
    P = lmap.pos[ids] @ Tcw[:3, :3].T + Tcw[:3, 3]
    z = P[:, 2]
    ok = (z > 0.1) & (z < max_depth)
    ids, P, z = ids[ok], P[ok], z[ok]
    uv = np.stack([camera.fx * P[:, 0] / z + camera.cx, camera.fy * P[:, 1] / z + camera.cy], axis=1)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    ids, uv, z = ids[inside], uv[inside], z[inside]
    keep = allowed[ids]
    return ids[keep], uv[keep], z[keep]


@pytest.fixture(scope="module")
def rpy_map():
    """The landmark stage after fr1/rpy head200's frames 0-29, and frames 30-35 with their poses."""
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.landmarks.stage import map_features
    from rgbdslam.slam import SLAM
    from tests.conftest import TUM_RPY200, need

    cfg = load_config(None, ["mapping.enabled=false", "landmarks.enabled=true"])
    seq = open_sequence(need(TUM_RPY200), cfg.dataset)
    slam = SLAM(cfg, seq.camera)
    for i in range(30):
        slam.track(seq[i])
    tracker = slam.landmarks
    later = []
    for i in range(30, 36):
        result = slam.frontend.track(seq[i])  # the front end only: the map stays as it was after frame 29
        later.append((map_features(result), result.pose))
    return cfg.landmarks, seq.camera, tracker, later


@pytest.mark.data
def test_candidates_of_the_local_map_are_the_ones_found_before(rpy_map):
    c, camera, tracker, later = rpy_map
    allowed = tracker.local_map()
    assert allowed is not None and 0 < allowed.sum() < tracker.map.n  # the mask leaves landmarks out
    for feats, pose in later:
        new = project_candidates(tracker.map, pose, camera, c.max_depth, allowed=allowed)
        old = _project_candidates_before(tracker.map, pose, camera, c.max_depth, allowed)
        assert len(new[0]) > 100
        assert all(np.array_equal(x, y) and x.dtype == y.dtype for x, y in zip(new, old))
        # a loop's older end (landmarks.loop_refine): the first-sighting window, a mask before the projection too
        m = match_to_map(tracker.map, feats, pose, camera, c.loop_search_radius, c.max_hamming, c.max_depth,
                         first_before=21, first_after=5)
        f = tracker.map.first[: tracker.map.n]
        ids, uv, _ = _project_candidates_before(tracker.map, pose, camera, c.max_depth, (f < 21) & (f >= 5))
        every = _project_candidates_before(tracker.map, pose, camera, c.max_depth, np.ones(len(f), bool))[0]
        assert 0 < len(ids) < len(every)  # the window leaves landmarks out
        assert np.array_equal(m.cand_ids, ids) and np.array_equal(m.cand_uv, uv)


@pytest.mark.data
def test_prepared_reprojection_gives_the_plain_expressions_bits_on_real_matches(rpy_map):
    c, camera, tracker, later = rpy_map
    lmap = tracker.map
    rng = np.random.default_rng(4)
    n_points = []
    for feats, pose in later:
        m = match_to_map(lmap, feats, pose, camera, c.search_radius, c.max_hamming, c.max_depth,
                         allowed=tracker.local_map())
        X, uv, z = lmap.pos[m.lm], feats.uv[m.feat], feats.pts[m.feat, 2]
        n_points.append(len(X))
        sig = c.depth_noise_a + c.depth_noise_b * z * z
        by_octave = 1.2 ** feats.octave[m.feat].astype(float)
        inliers = rng.random(len(X)) < 0.7
        for cov in (lmap.cov[m.lm], np.sqrt(np.trace(lmap.cov[m.lm], axis1=1, axis2=2) / 3)):  # full, isotropic
            for spx in (1.0, by_octave):
                full = Reprojection(X, uv, z, camera, spx, sig, cov)
                part = full.subset(inliers)
                spx_in = spx if np.ndim(spx) == 0 else spx[inliers]
                for k in range(3):  # the frame's pose and two poses near it (a refine's steps)
                    Tcw = inv(pose @ near(rng.normal(scale=0.01, size=3), rng.normal(scale=0.01, size=3))) if k else inv(pose)
                    R, t = Tcw[:3, :3], Tcw[:3, 3]
                    for jac in (True, False):
                        for a, b in ((full(R, t, jac), _reprojection_residuals_before(R, t, X, uv, z, camera, spx,
                                                                                      sig, cov, jac)),
                                     (part(R, t, jac), _reprojection_residuals_before(
                                         R, t, X[inliers], uv[inliers], z[inliers], camera, spx_in, sig[inliers],
                                         cov[inliers], jac))):
                            assert np.array_equal(a[0], b[0])
                            assert (a[1] is None and b[1] is None) or np.array_equal(a[1], b[1])
    assert min(n_points) > 50
