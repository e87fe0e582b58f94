"""Descriptor matching between two frames and the geometric pre-filter of the matches.

Only features with valid depth take part (the 3-D registration cannot use the others), which
also makes the brute-force Hamming matcher cheaper. The pre-filter keeps the matches that
agree with one RANSAC model: 'homography' (the thesis), 'fundamental', 'rigid3d' (3-D rigid
RANSAC, seeded) or 'none'.
"""

from __future__ import annotations

import cv2
import numpy as np

from rgbdslam.frontend.config import MatchingConfig
from rgbdslam.frontend.features import FrameFeatures, descriptor_words
from rgbdslam.geometry.ransac import ransac_rigid
from rgbdslam.geometry.se3 import transform_points


def hamming_matrix(words_a: np.ndarray, words_b: np.ndarray, rows: int = 64) -> np.ndarray:
    """All Hamming distances (Na, Nb) as uint16: popcount of XOR, word by word.

    ``rows`` rows of the matrix at a time, into reused buffers: the XOR and popcount of a block stay
    in the cache (~25 % less time than whole-matrix temporaries at 1000 x 1000; the same integers).
    OpenCV's ``cv2.batchDistance`` / ``BFMatcher`` with NORM_HAMMING took longer per direction on
    this machine than this takes for the whole matrix (benchmarks/profile_chain.py, docs/frontend.md)."""
    na, nb, nw = len(words_a), len(words_b), words_a.shape[1]
    d = np.empty((na, nb), np.uint16)
    wb = np.ascontiguousarray(words_b.T)  # (words, Nb): each word a contiguous row
    x = np.empty((min(rows, na), nb), np.uint64)
    c = np.empty(x.shape, np.uint8)
    for s in range(0, na, rows):
        e = min(na, s + rows)
        blk, xb, cb = d[s:e], x[:e - s], c[:e - s]
        for k in range(nw):
            np.bitwise_xor(words_a[s:e, k, None], wb[k], out=xb)
            np.bitwise_count(xb, out=cb)
            if k == 0:
                np.copyto(blk, cb)
            else:
                np.add(blk, cb, out=blk)
    return d


def column_argmin(d: np.ndarray) -> np.ndarray:
    """``d.argmin(axis=0)`` (the first row on ties) of a 2-D integer matrix without its transposed
    copy: the column minima (a row-wise reduction), then the first matching entry of each column in
    row-major order. About 3x faster on the Hamming matrix of two frames."""
    n_cols = d.shape[1]
    idx = np.flatnonzero(d == np.minimum.reduce(d, axis=0))  # ascending: row by row
    cols = idx % n_cols
    _, first = np.unique(cols, return_index=True)  # every column has its minimum somewhere
    out = np.empty(n_cols, np.intp)
    out[cols[first]] = idx[first] // n_cols
    return out


def match_descriptors(
    desc_a: np.ndarray,
    desc_b: np.ndarray,
    mc: MatchingConfig,
    words_a: np.ndarray | None = None,
    words_b: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Index arrays (ia, ib) of matched descriptors, sorted by ia.

    Brute-force nearest neighbour in Hamming distance; the full distance matrix comes from
    NumPy popcounts on 64-bit words (measured ~4x faster than cv2.BFMatcher with cross-check
    on this machine, and it serves both directions of the cross-check at once); then
    mutual-nearest-neighbour cross-check and/or Lowe's ratio test, then a Hamming cap.
    """
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    if words_a is None:
        words_a = descriptor_words(desc_a)
    if words_b is None:
        words_b = descriptor_words(desc_b)
    d = hamming_matrix(words_a, words_b)
    ia = np.arange(len(d))
    ib = d.argmin(axis=1)
    dist = d[ia, ib]
    keep = dist <= mc.max_hamming
    if mc.cross_check:
        keep &= column_argmin(d)[ib] == ia
    if mc.ratio is not None:
        second = np.partition(d, 1, axis=1)[:, 1]
        keep &= dist < mc.ratio * second
    return ia[keep], ib[keep]


def prefilter(
    ref: FrameFeatures,
    cur: FrameFeatures,
    ia: np.ndarray,
    ib: np.ndarray,
    mc: MatchingConfig,
    seed: int = 0,
    T0: np.ndarray | None = None,
) -> np.ndarray:
    """Boolean mask over the matches (ia into ref, ib into cur) that pass the geometric model
    (``matching.prefilter``; RANSAC seeded with ``seed``)."""
    n = len(ia)
    if mc.prefilter == "none" or n == 0:
        return np.ones(n, bool)
    if mc.prefilter == "rigid3d":
        rng = np.random.default_rng(seed)
        out = ransac_rigid(ref.pts[ia], cur.pts[ib], mc.prefilter_threshold, mc.prefilter_iterations, rng, T0=T0)
        return np.zeros(n, bool) if out is None else out[1]
    a = ref.uv[ia].astype(np.float32)
    b = cur.uv[ib].astype(np.float32)
    cv2.setRNGSeed(seed)
    if mc.prefilter == "homography":
        if n < 4:
            return np.zeros(n, bool)
        _, mask = cv2.findHomography(a, b, cv2.RANSAC, mc.prefilter_threshold, maxIters=mc.prefilter_iterations * 10)
    else:  # fundamental
        if n < 8:
            return np.zeros(n, bool)
        _, mask = cv2.findFundamentalMat(a, b, cv2.FM_RANSAC, mc.prefilter_threshold, 0.999, mc.prefilter_iterations * 10)
    if mask is None:
        return np.zeros(n, bool)
    return mask.reshape(-1).astype(bool)


def match_pairs(ref: FrameFeatures, cur: FrameFeatures, mc: MatchingConfig) -> tuple[np.ndarray, np.ndarray]:
    """Descriptor matches between the depth-valid features of ``ref`` and ``cur``.

    Returns (ia, ib): indices into ref's and cur's full feature arrays.
    """
    va = np.flatnonzero(ref.valid)
    vb = np.flatnonzero(cur.valid)
    ia, ib = match_descriptors(ref.desc[va], cur.desc[vb], mc, ref.words[va], cur.words[vb])
    return va[ia], vb[ib]


def pair_hamming(words_a: np.ndarray, words_b: np.ndarray, ia: np.ndarray, ib: np.ndarray) -> np.ndarray:
    """Hamming distances (int64) of the pairs ``(words_a[ia[k]], words_b[ib[k]])``: each 64-bit word
    gathered from a contiguous row of the transposed words (1-D takes, ~4x faster than gathering
    (K, 4) rows and summing over the short last axis; the same integers)."""
    A, B = np.ascontiguousarray(words_a.T), np.ascontiguousarray(words_b.T)
    ham = np.bitwise_count(A[0].take(ia) ^ B[0].take(ib)).astype(np.int64)
    for k in range(1, len(A)):
        ham += np.bitwise_count(A[k].take(ia) ^ B[k].take(ib))
    return ham


def pairs_within(words_a: np.ndarray, words_b: np.ndarray, i: np.ndarray, j: np.ndarray,
                 max_hamming: int) -> tuple[np.ndarray, np.ndarray]:
    """``(k, ham)``: the positions ``k`` (ascending) of the candidate pairs ``(words_a[i[k]],
    words_b[j[k]])`` whose Hamming distance is at most ``max_hamming``, and those distances (int64):
    ``k = flatnonzero(pair_hamming(...) <= max_hamming)`` and its distances, the same integers.
    All words but the last are counted for every pair, the last only for the pairs still within
    the cap (a partial count never exceeds the whole): at the 3-D gate's ~19,000 candidates per
    reference and a cap of 64 bits, three words of unrelated descriptors mostly differ in more than
    64 bits already, so the last word is counted for about a third of them (fr1/rpy)."""
    A, B = np.ascontiguousarray(words_a.T), np.ascontiguousarray(words_b.T)
    ham = np.bitwise_count(A[0].take(i) ^ B[0].take(j)).astype(np.int64)
    for w in range(1, len(A) - 1):
        ham += np.bitwise_count(A[w].take(i) ^ B[w].take(j))
    k = np.flatnonzero(ham <= max_hamming)
    ham = ham[k]
    if len(A) > 1:
        ham += np.bitwise_count(A[-1].take(i[k]) ^ B[-1].take(j[k]))
        keep = ham <= max_hamming
        k, ham = k[keep], ham[keep]
    return k, ham


def _first_per_group(group: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Mask of the smallest-``dist`` element of each ``group`` (ties: first in input order)."""
    order = np.argsort(group * 1024 + dist, kind="stable")  # int64 keys, dist < 1024
    g = group[order]
    first = np.ones(len(g), bool)
    first[1:] = g[1:] != g[:-1]
    mask = np.zeros(len(group), bool)
    mask[order[first]] = True
    return mask


def guided_match(ref: FrameFeatures, cur: FrameFeatures, T0: np.ndarray, radius: float, mc: MatchingConfig) -> tuple[np.ndarray, np.ndarray]:
    """Descriptor matching restricted to 3-D neighbours under a trusted prediction ``T0``.

    Each depth-valid ref point is moved into the current frame with ``T0``; only current
    points within ``radius`` metres are candidates. Mutual best Hamming matches among the
    candidates (capped by ``matching.max_hamming``) are returned as (ia, ib), indices into
    the full feature arrays of ref and cur, sorted by ia.
    """
    va = np.flatnonzero(ref.valid)
    vb = np.flatnonzero(cur.valid)
    if len(va) == 0 or len(vb) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    from scipy.spatial import cKDTree  # here: SciPy's import is not on the way to the first frame

    ta = cKDTree(transform_points(T0, ref.pts[va]))
    pairs = ta.sparse_distance_matrix(cur.tree, radius, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    i = pairs["i"].astype(int)
    j = pairs["j"].astype(int)
    tb = cur.tree_index
    # most candidate pairs are unrelated: only those within the Hamming cap go on
    k, ham = pairs_within(ref.words[va], cur.words[tb], i, j, mc.max_hamming)
    ia, ib = va[i[k]], tb[j[k]]
    keep = _first_per_group(ia, ham) & _first_per_group(ib, ham)
    ia, ib = ia[keep], ib[keep]
    order = np.argsort(ia, kind="stable")
    return ia[order], ib[order]
