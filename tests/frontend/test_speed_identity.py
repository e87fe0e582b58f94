"""Speed-ups of the per-frame chain that must not change a single bit of the poses.

The kernels (blocked Hamming matrix, pair Hamming distances, the 3x3 rigid fit and its stacked
form in the ISLAM loop, row norms, the guided matcher's Hamming cap) are
checked against the expressions they replaced, written out here; the whole chain's poses on fr1/rpy
head200 are held bit for bit by ``tests/test_chain_poses.py``.
"""

from __future__ import annotations


import numpy as np
import pytest

from rgbdslam.frontend.features import descriptor_words
from rgbdslam.frontend.matching import column_argmin, guided_match, hamming_matrix, pair_hamming, pairs_within
from rgbdslam.frontend.registration.islam import gate_threshold, inverse_mean_l1, islam_pair
from rgbdslam.geometry.rigid import fit_rigid, fit_rigid_stacked, residuals, row_norms

def _fit_rigid_before(S, D, weights=None):
    """fit_rigid as it was written before (mean, LAPACK determinant, diag product)."""
    if weights is None:
        p, q = S.mean(axis=0), D.mean(axis=0)
        H = (S - p).T @ (D - q)
    else:
        w = weights / weights.sum()
        p, q = w @ S, w @ D
        H = ((S - p) * w[:, None]).T @ (D - q)
    U, _, Vt = np.linalg.svd(H)
    V, Ut = np.swapaxes(Vt, -1, -2), np.swapaxes(U, -1, -2)
    d = np.sign(np.linalg.det(V @ Ut))
    d = np.where(d == 0, 1.0, d)
    Dg = np.zeros(3)
    Dg[:2], Dg[2] = 1.0, d
    R = (V * Dg[None, :]) @ Ut
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, q - R @ p
    return T


def test_fit_rigid_gives_the_same_bits_as_before_including_reflections():
    rng = np.random.default_rng(3)
    n_reflect = 0
    for k in range(3000):
        n = int(rng.integers(3, 300))
        S = rng.normal(size=(n, 3)) * rng.uniform(0.01, 5.0)
        if k % 3 == 0:
            S[:, 2] = 0.7  # planar: the SVD's sign choice decides the reflection fix
        if k % 5 == 0:
            D = S * np.array([1.0, -1.0, 1.0]) + rng.normal(scale=0.01, size=S.shape)  # mirrored: det(V U^T) < 0
        else:
            D = S + rng.normal(size=3) + rng.normal(scale=0.01, size=S.shape)
        w = rng.uniform(0.1, 2.0, n) if k % 2 else None
        T = fit_rigid(S, D, w)
        assert np.array_equal(T, _fit_rigid_before(S, D, w)), k
        U, _, Vt = np.linalg.svd((S - S.mean(0)).T @ (D - D.mean(0)))
        n_reflect += np.linalg.det(Vt.T @ U.T) < 0
    assert n_reflect > 100  # the negated-column branch ran


def test_hamming_kernels_give_the_same_integers_as_the_broadcast_popcount():
    rng = np.random.default_rng(4)
    for na, nb in [(0, 5), (1, 1), (63, 65), (64, 64), (130, 200), (1000, 997)]:
        a = rng.integers(0, 256, (na, 32), dtype=np.uint8)
        b = rng.integers(0, 256, (nb, 32), dtype=np.uint8)
        b[: min(na, nb) // 2] = ~a[: min(na, nb) // 2]  # distance 256 where they overlap: the uint16 maximum used
        wa, wb = descriptor_words(a), descriptor_words(b)
        ref = np.bitwise_count(wa[:, None, :] ^ wb[None, :, :]).sum(axis=2, dtype=np.int64)
        d = hamming_matrix(wa, wb)
        assert d.dtype == np.uint16 and d.shape == (na, nb) and np.array_equal(d, ref)
        if na and nb:
            ia, ib = rng.integers(0, na, 500), rng.integers(0, nb, 500)
            assert np.array_equal(pair_hamming(wa, wb, ia, ib), ref[ia, ib])
            # 2-D index arrays broadcast (the landmark matcher's (features, k candidates) table)
            nn = rng.integers(0, nb, (na, 6))
            assert np.array_equal(pair_hamming(wa, wb, np.arange(na)[:, None], nn), ref[np.arange(na)[:, None], nn])


def test_column_argmin_is_numpys_argmin_with_its_ties():
    rng = np.random.default_rng(6)
    for shape, hi in [((1, 1), 3), ((2, 7), 2), ((300, 200), 4), ((50, 900), 300), ((900, 880), 257)]:
        d = rng.integers(0, hi, shape).astype(np.uint16)  # few values: many equal minima per column
        assert np.array_equal(column_argmin(d), d.argmin(axis=0))


def test_row_norms_are_numpys_norms():
    rng = np.random.default_rng(5)
    for n in (1, 3, 17, 500):
        r = rng.normal(size=(n, 3)) * 10.0 ** rng.uniform(-4, 2, (n, 1))
        assert np.array_equal(row_norms(r), np.linalg.norm(r, axis=1))


def _islam_pair_before(S, D, keep, max_it, alpha, beta, min_error, min_points):
    """islam_pair as it was written before: S and D compressed apart and fitted by fit_rigid."""
    need = max(3, min_points)
    W, it = 0.0, 0
    for j in range(1, max_it + 1):
        it = j
        T = fit_rigid(S[keep], D[keep])
        th = gate_threshold(alpha, beta, j)
        r = residuals(T, S, D)
        W = inverse_mean_l1(r[keep])
        keep = keep & (np.linalg.norm(r, axis=1) <= th)
        if th < min_error or keep.sum() < need:
            break
    if keep.sum() < need:
        return None
    return keep, W, it


def test_stacked_fit_gives_fit_rigids_bits():
    rng = np.random.default_rng(7)
    for k in range(2000):
        n = int(rng.integers(3, 3000 if k % 50 == 0 else 400))
        S = rng.normal(size=(n, 3)) * rng.uniform(0.01, 5.0) + rng.normal(size=3) * 3.0
        if k % 3 == 0:
            S[:, 2] = 0.7
        sign = np.array([1.0, -1.0, 1.0]) if k % 5 == 0 else 1.0  # mirrored: the reflection branch
        D = S * sign + rng.normal(size=3) + rng.normal(scale=0.01, size=S.shape)
        assert np.array_equal(fit_rigid_stacked(np.concatenate((S, D), axis=1)), fit_rigid(S, D)), k


@pytest.fixture(scope="module")
def rpy_pairs():
    """Depth-valid matched 3-D points of real fr1/rpy frame pairs (1 to 4 frames apart)."""
    from rgbdslam.config import Config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.frontend.features import extract_features
    from rgbdslam.frontend.matching import match_pairs
    from tests.conftest import TUM_RPY200, need

    cfg = Config()
    seq = open_sequence(need(TUM_RPY200))
    feats = [extract_features(seq.load(i), cfg.features, cfg.matching) for i in range(0, 40, 4)]
    out = []
    for a in range(len(feats)):
        for b in range(a + 1, min(len(feats), a + 3)):
            ia, ib = match_pairs(feats[a], feats[b], cfg.matching)
            out.append((feats[a].pts[ia], feats[b].pts[ib]))
    return cfg, out, feats


@pytest.mark.data
def test_islam_loop_on_real_frames_gives_the_same_bits_as_before(rpy_pairs):
    cfg, pairs, _ = rpy_pairs
    rc = cfg.registration
    n_fitted = 0
    for S, D in pairs:
        keep = np.ones(len(S), bool)
        for alpha in (rc.alpha, 0.5 * rc.alpha, 2.0 * rc.alpha):  # different gates: different survivors
            new = islam_pair(S, D, keep, rc.max_iterations, alpha, rc.beta, rc.min_error, rc.min_points)
            old = _islam_pair_before(S, D, keep, rc.max_iterations, alpha, rc.beta, rc.min_error, rc.min_points)
            assert (new is None) == (old is None)
            if new is not None:
                assert np.array_equal(new[0], old[0]) and new[1] == old[1] and new[2] == old[2]
                n_fitted += 1
    assert n_fitted >= 20


def test_pairs_within_the_cap_are_the_capped_pair_distances():
    rng = np.random.default_rng(8)
    for n_words in (1, 2, 4):
        def words():  # all 64 bits of each word random (the top bit too)
            return np.frombuffer(rng.bytes(300 * n_words * 8), np.uint64).reshape(300, n_words)

        wa = words()
        wb = wa[rng.permutation(300)] ^ (words() & words() & words())
        assert (wa >> np.uint64(63)).any() and (wa ^ wb).any()
        i, j = rng.integers(0, 300, 20000), rng.integers(0, 300, 20000)
        full = pair_hamming(wa, wb, i, j)
        for cap in (0, 8 * n_words, 16 * n_words, 64 * n_words):
            k, ham = pairs_within(wa, wb, i, j, cap)
            assert np.array_equal(k, np.flatnonzero(full <= cap)) and np.array_equal(ham, full[full <= cap])
            assert ham.dtype == np.int64 and (0 < len(k) < len(i) or cap in (0, 64 * n_words))


def _guided_match_before(ref, cur, T0, radius, mc):
    """guided_match as it was written before: every candidate pair's full Hamming distance, then the cap."""
    from scipy.spatial import cKDTree

    from rgbdslam.geometry.se3 import transform_points

    def first_per_group(group, dist):  # the smallest distance per group, ties: the first in input order
        order = np.argsort(group * 1024 + dist, kind="stable")
        first = np.r_[True, group[order][1:] != group[order][:-1]]
        mask = np.zeros(len(group), bool)
        mask[order[first]] = True
        return mask

    va = np.flatnonzero(ref.valid)
    pairs = cKDTree(transform_points(T0, ref.pts[va])).sparse_distance_matrix(cur.tree, radius, output_type="ndarray")
    ia, ib = va[pairs["i"].astype(int)], cur.tree_index[pairs["j"].astype(int)]
    ham = pair_hamming(ref.words, cur.words, ia, ib)
    close = ham <= mc.max_hamming
    ia, ib, ham = ia[close], ib[close], ham[close]
    keep = first_per_group(ia, ham) & first_per_group(ib, ham)
    ia, ib = ia[keep], ib[keep]
    order = np.argsort(ia, kind="stable")
    return ia[order], ib[order]


@pytest.mark.data
def test_guided_matching_on_real_frames_gives_the_same_matches_as_before(rpy_pairs):
    from dataclasses import replace

    from rgbdslam.frontend.pairwise import build_pair_registration

    cfg, _, feats = rpy_pairs
    register = build_pair_registration(cfg)
    n_matches = []
    for a in range(len(feats) - 1):
        for b in range(a + 1, min(len(feats), a + 3)):
            res = register(feats[a], feats[b])
            if res is None:
                continue
            for gate in (0.02, 0.05, 0.10):
                for mc in (cfg.matching, replace(cfg.matching, max_hamming=40)):
                    new = guided_match(feats[a], feats[b], res.T, gate, mc)
                    old = _guided_match_before(feats[a], feats[b], res.T, gate, mc)
                    assert all(np.array_equal(x, y) and x.dtype == y.dtype for x, y in zip(new, old))
                    n_matches.append(len(new[0]))
    assert len(n_matches) >= 60 and min(n_matches) > 20


def _depth_edges_before(depth, u, v, radius, jump):
    """depth_edges as it was written before: every window pixel's difference tested in float64."""
    d = np.asarray(depth)
    h, w = d.shape[:2]
    radius = np.broadcast_to(np.asarray(radius, dtype=np.int64), np.shape(u))
    out = np.zeros(len(u), bool)
    for r in np.unique(radius):
        if r <= 0:
            continue
        m = radius == r
        uu_, vv_ = u[m], v[m]
        z = d[vv_, uu_].astype(np.float64)
        k = np.arange(-r, r + 1)
        vv = np.clip(vv_[:, None, None] + k[None, :, None], 0, h - 1)
        uu = np.clip(uu_[:, None, None] + k[None, None, :], 0, w - 1)
        nb = d[vv, uu].reshape(len(uu_), -1).astype(np.float64)
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(nb) | (nb <= 0) | (np.abs(nb - z[:, None]) > jump * z[:, None])
        out[m] = np.isfinite(z) & (z > 0) & bad.any(axis=1)
    return out


@pytest.mark.data
def test_depth_edges_on_real_frames_are_the_pixelwise_test(rpy_pairs):
    """The window's extremes decide as every pixel did (fr1/rpy key points at every pyramid level's radius,
    one radius for all and jumps from 2 % to 50 %; holes and NaN depth pixels included)."""
    from rgbdslam.datasets import open_sequence
    from rgbdslam.frontend.features import depth_edges, edge_radii
    from tests.conftest import TUM_RPY200

    _, _, feats = rpy_pairs
    seq = open_sequence(TUM_RPY200)
    n_flagged = []
    for f in feats:
        depth = seq.load(f.index).depth
        depth = np.where(np.arange(depth.size).reshape(depth.shape) % 997 == 0, np.nan, depth)  # a few NaN pixels
        u = np.clip(np.round(f.uv_raw[:, 0]).astype(int), 0, depth.shape[1] - 1)
        v = np.clip(np.round(f.uv_raw[:, 1]).astype(int), 0, depth.shape[0] - 1)
        for radius in (edge_radii(f, 2), 1, 4):
            for jump in (0.02, 0.15, 0.5):
                new = depth_edges(depth, u, v, radius, jump)
                assert np.array_equal(new, _depth_edges_before(depth, u, v, radius, jump))
                n_flagged.append(new.mean())
    assert 0.0 < min(n_flagged) and max(n_flagged) < 1.0  # both answers occur in every case
