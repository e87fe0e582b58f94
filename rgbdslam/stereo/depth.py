"""Depth from a rectified stereo pair: sparse (row-matched key points) or dense (OpenCV SGBM).

Both give a metric depth image of the left camera (float32 metres, 0 = no depth), so every
later stage (registration, loop closure, pose graph, maps, evaluation) runs unchanged, and a
:class:`~rgbdslam.geometry.stereo.DepthNoise` saying how noisy that depth is.

* ``sparse`` (spec section 6): ORB key points of the left image (the very ones the front end
  uses) are matched to ORB key points of the right image found in the same row band
  (``stereo.row_tolerance``) at a positive disparity, by Hamming distance with a ratio test
  and a one-to-one check; each match is refined to sub-pixel disparity by a zero-mean SAD patch
  search along the row with an equiangular fit through the best three costs, and triangulated as the
  midpoint of the two viewing rays. Depth is written at the key point's rounded pixel only.
  With ``stereo.sparse_search = row`` the right image gets no ORB: a coarse SAD search along
  the row (:func:`coarse_row_search`) gives the column the refinement starts from.
* ``sgbm``: OpenCV's semi-global block matching (3-way), optionally on a resized pair.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from rgbdslam.frontend.config import FeaturesConfig
from rgbdslam.errors import ConfigError
from rgbdslam.geometry.stereo import DepthNoise, StereoRig, midpoint_triangulate
from rgbdslam.stereo.config import StereoConfig

if TYPE_CHECKING:
    from rgbdslam.frontend.features import Detections


def to_gray(img: np.ndarray) -> np.ndarray:
    """A grey image (H, W) uint8 from a grey or RGB image."""
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)


@dataclass
class StereoMatches:
    """Sparse stereo matches: left key-point indices, refined disparities and 3-D points."""

    left_index: np.ndarray  # (M,) into the left detections
    disparity: np.ndarray  # (M,) pixels, sub-pixel
    points: np.ndarray  # (M, 3) left camera frame
    uv: np.ndarray  # (M, 2) integer left pixel the disparity refers to


def _band_pairs(v_left: np.ndarray, v_right: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """All (i, j) with |v_left[i] - v_right[j]| <= tol, without the full N x M matrix."""
    order = np.argsort(v_right, kind="stable")
    vs = v_right[order]
    lo = np.searchsorted(vs, v_left - tol, side="left")
    hi = np.searchsorted(vs, v_left + tol, side="right")
    counts = hi - lo
    i = np.repeat(np.arange(len(v_left)), counts)
    starts = np.repeat(lo - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    j = order[np.arange(len(i)) + starts]
    return i, j


def match_rows(uv_l: np.ndarray, desc_l: np.ndarray, uv_r: np.ndarray, desc_r: np.ndarray,
               sc: StereoConfig) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (il, ir) of left/right key points matched along rectified rows: the right
    point lies within ``row_tolerance`` rows and at a disparity in ``[min_disparity,
    max_disparity]``; best Hamming distance per left point, ratio test against the second best
    of the band, distance cap, and each right point used once (its best left point)."""
    if len(uv_l) == 0 or len(uv_r) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    i, j = _band_pairs(uv_l[:, 1], uv_r[:, 1], sc.row_tolerance)
    d = uv_l[i, 0] - uv_r[j, 0]
    ok = (d >= sc.min_disparity) & (d <= sc.max_disparity)
    i, j = i[ok], j[ok]
    if len(i) == 0:
        return i, j
    wl = np.ascontiguousarray(desc_l).view(np.uint64).reshape(-1, 4)
    wr = np.ascontiguousarray(desc_r).view(np.uint64).reshape(-1, 4)
    c = np.bitwise_count(wl[i] ^ wr[j])
    ham = (c[:, 0].astype(np.int64) + c[:, 1]) + (c[:, 2] + c[:, 3])
    # the band pairs come grouped by ascending left point: one segment each, reduced without sorting. Best =
    # smallest distance, among equals the pair listed first; second = the smallest distance left once the
    # best pair is taken out (equal to the best when two candidates tie)
    n = len(i)
    start = np.flatnonzero(np.r_[True, i[1:] != i[:-1]])
    best = np.minimum.reduceat(ham * n + np.arange(n), start) % n
    rest = ham.copy()
    rest[best] = 1 << 20
    second = np.minimum.reduceat(rest, start)
    bi, bj, bh = i[best], j[best], ham[best]
    keep = (bh <= sc.max_hamming) & (bh < sc.ratio * second)
    bi, bj, bh = bi[keep], bj[keep], bh[keep]
    # one left point per right point: its best one
    order = np.lexsort((bh, bj))
    bi, bj = bi[order], bj[order]
    uniq = np.r_[True, bj[1:] != bj[:-1]]
    return bi[uniq], bj[uniq]


SUBPIXEL = ("zsad_v", "centre_parabola")


def patch_sum(X: np.ndarray) -> np.ndarray:
    """``X.sum(axis=0)`` of a float32 stack, in NumPy's own order of additions for a contiguous axis of that
    length (its pairwise sum: up to 7 terms one after the other; 8-128 terms in eight running sums combined
    as ((0+1)+(2+3))+((4+5)+(6+7)), the rest added one by one), but as whole-array adds: NumPy reduces a
    short inner axis one small loop per element, ~3x slower here. Longer stacks are split as NumPy splits
    them (halves, the first a multiple of 8)."""
    k = len(X)
    if k > 128:
        half = k // 2 - (k // 2) % 8
        return patch_sum(X[:half]) + patch_sum(X[half:])
    if k < 8:
        acc = np.full_like(X[0], -0.0)
        for x in X:
            acc += x
        return acc
    part = X[:8].copy()
    for b in range(8, k - k % 8, 8):
        part += X[b:b + 8]
    acc = ((part[0] + part[1]) + (part[2] + part[3])) + ((part[4] + part[5]) + (part[6] + part[7]))
    for x in X[k - k % 8:]:
        acc += x
    return acc


def refine_disparity(left: np.ndarray, right: np.ndarray, ul: np.ndarray, vl: np.ndarray, ur: np.ndarray,
                     radius: int, search: int, subpixel: str = "zsad_v") -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel right column for integer left pixels (ul, vl) near the right column ``ur``.

    A (2r+1)^2 patch around the left pixel is compared with the patches along the same row of
    the right image at round(ur) + [-search, search], and a fit through the best cost and its two
    neighbours gives the sub-pixel offset. ``subpixel``:

    * ``zsad_v`` (default): zero-mean SAD (each patch minus its own mean: a brightness offset
      between the cameras cancels) and the equiangular ("V") fit ``(c1 - c3) / (2 (max(c1, c3) - c2))``,
      the exact minimum of a SAD cost, which is V-shaped near the match. Measured on synthetic pairs
      with exact disparity (docs/stereo_measured.md): bias +0.005-0.01 px, no pull toward whole pixels, robust
      sigma 0.05-0.06 px.
    * ``centre_parabola`` (the method before, kept for comparison): each patch minus its centre pixel
      and a parabola through the three costs. The centre pixel's own error (noise, sampling) shifts
      the whole patch, and the parabola on a V-shaped cost pulls estimates toward whole pixels
      ("pixel locking"): bias -0.03 px, up to -0.12 px at fractions 0.2-0.3, robust sigma 0.18 px.

    Returns (ur_refined, ok); not ok at the image border or when the best cost is at the end of
    the search."""
    if subpixel not in SUBPIXEL:
        raise ValueError(f"unknown sub-pixel method {subpixel!r}; choose one of {', '.join(SUBPIXEL)}")
    h, w = left.shape
    ul = ul.astype(np.int64)
    vl = vl.astype(np.int64)
    ur0 = np.rint(ur).astype(np.int64)
    r, s = radius, search
    ok = (vl - r >= 0) & (vl + r < h) & (ul - r >= 0) & (ul + r < w) & (ur0 - r - s >= 0) & (ur0 + r + s < w)
    out = np.full(len(ul), np.nan)
    if not ok.any():
        return out, ok
    idx = np.flatnonzero(ok)
    n, m = 2 * r + 1, len(idx)
    dy = np.arange(-r, r + 1)
    # gathers from the flat images: one offset table per patch, added to each point's base index
    base = vl[idx] * w
    L = np.ascontiguousarray(left).ravel()[(base + ul[idx])[:, None, None] + (dy[:, None] * w + dy)[None]]
    L = L.astype(np.float32)  # (M, n, n)
    # one strip of the right row band per point, the 2s+1 shifted patches are views of it
    cols = np.arange(-r - s, r + s + 1)
    strip = np.ascontiguousarray(right).ravel()[(base + ur0[idx])[:, None, None] + (dy[:, None] * w + cols)[None]]
    strip = strip.astype(np.float32)  # (M, n, n + 2s)
    R = np.lib.stride_tricks.sliding_window_view(strip, n, axis=2)  # (M, n, 2s+1, n)
    if subpixel == "zsad_v":
        L -= L.mean(axis=(1, 2), keepdims=True)
        col = np.zeros((m, strip.shape[2] + 1), np.float32)  # running column sums
        np.cumsum(strip.sum(axis=1), axis=1, out=col[:, 1:])
        mean = (col[:, n:] - col[:, :-n]) / np.float32(n * n)  # (M, 2s+1): each shifted patch's mean
        ref = mean[None, :, None, :]
    else:
        L -= L[:, r:r + 1, r:r + 1]
        ref = strip[None, :, r:r + 1, r:r + 2 * s + 1]  # minus each patch's centre value
    # |patch difference| laid out (patch column, point, patch row, offset): the sum over the patch columns is
    # then whole-array adds (patch_sum), bit for bit NumPy's own sum over that axis
    X = np.empty((n, m, n, 2 * s + 1), np.float32)
    np.subtract(R.transpose(3, 0, 1, 2), ref, out=X)
    X -= L.transpose(2, 0, 1)[:, :, :, None]
    np.abs(X, out=X)
    sad = patch_sum(X).sum(axis=1)  # (M, 2s+1)
    offs = np.arange(-s, s + 1)
    best = sad.argmin(axis=1)
    inner = (best > 0) & (best < 2 * s)
    k = np.arange(m)
    b = np.clip(best, 1, 2 * s - 1)
    c1, c2, c3 = (sad[k, b - 1].astype(np.float64), sad[k, b].astype(np.float64), sad[k, b + 1].astype(np.float64))
    den = 2.0 * (np.maximum(c1, c3) - c2) if subpixel == "zsad_v" else 2.0 * (c1 + c3 - 2.0 * c2)
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(den > 0, (c1 - c3) / den, 0.0)
    inner &= np.abs(delta) <= 1.0
    out[idx] = ur0[idx] + offs[best] + delta
    good = np.zeros(len(ul), bool)
    good[idx] = inner
    return out, good


def right_key_points(right: np.ndarray, fc: FeaturesConfig, sc: StereoConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """ORB key points (N, 2) and descriptors of the right image for ``stereo.sparse_search = orb`` (None for
    ``row``, which finds no right key points): ``stereo.right_features`` times the left's budget and no grid,
    so that a left key point's partner is found whatever the right image's own strongest corners are
    (measured on KITTI 06 frame 5: 367 row matches instead of 268 with the left's settings). No responses,
    levels or detection count: the right image is only matched against."""
    if sc.sparse_search != "orb":
        return None
    import dataclasses

    from rgbdslam.frontend.features import orb_features

    uv, desc, _, _ = orb_features(to_gray(right), dataclasses.replace(
        fc, n_features=sc.right_features * fc.n_features, grid_rows=1, grid_cols=1), attributes=False)
    return uv, desc


_RIGHT_POOL: list = []
_RIGHT_POOL_LOCK = threading.Lock()
os.register_at_fork(after_in_child=_RIGHT_POOL.clear)  # a forked child has none of the pool's threads


def detect_pair(left: np.ndarray, right: np.ndarray, fc: FeaturesConfig, sc: StereoConfig
                ) -> tuple[Detections, tuple[np.ndarray, np.ndarray] | None]:
    """The left image's detections (:func:`rgbdslam.frontend.features.detect`) and the right image's key
    points (:func:`right_key_points`) of one pair, found at once in two threads as ORB-SLAM extracts a
    pair's two images (OpenCV's ORB releases the GIL; each thread has its own ORB object). The same
    values as one after the other."""
    from concurrent.futures import ThreadPoolExecutor

    from rgbdslam.frontend.features import detect

    if sc.sparse_search != "orb":
        return detect(left, fc), None
    with _RIGHT_POOL_LOCK:
        if not _RIGHT_POOL:  # shared by a sequence's reader threads; its threads end with the process
            _RIGHT_POOL.append(ThreadPoolExecutor(max_workers=2, thread_name_prefix="right-orb"))
        pool = _RIGHT_POOL[0]
    job = pool.submit(right_key_points, right, fc, sc)
    return detect(left, fc), job.result()


ROW_SEARCH_BUDGET = 256 * 2**20  # bytes of one reader thread's coarse cost table (float32 disparities x rows x cols)


def row_search_bytes(sc: StereoConfig, width: int, height: int) -> int:
    """Bytes of :func:`coarse_row_search`'s cost table for ``width`` x ``height`` images."""
    s = int(sc.row_scale)
    w, h = max(1, width // s), max(1, height // s)
    dmin = max(1, int(np.floor(sc.min_disparity / s)))
    dmax = min(w - 1, int(np.ceil(sc.max_disparity / s)))
    return 4 * max(0, dmax - dmin + 1) * w * h


def check_row_search(sc: StereoConfig, width: int, height: int) -> None:
    """ConfigError when the row search's cost table for ``width`` x ``height`` pairs would exceed
    :data:`ROW_SEARCH_BUDGET` (per reader thread)."""
    need = row_search_bytes(sc, width, height)
    if need > ROW_SEARCH_BUDGET:
        raise ConfigError(f"stereo.sparse_search=row with stereo.row_scale={sc.row_scale} and stereo.max_disparity="
                          f"{sc.max_disparity} needs {need / 2**20:.0f} MB per reader thread for {width}x{height} "
                          f"pairs (budget {ROW_SEARCH_BUDGET // 2**20} MB); raise stereo.row_scale or lower "
                          f"stereo.max_disparity")


def coarse_image(img: np.ndarray, s: int) -> np.ndarray:
    """float32 mean of every whole ``s`` x ``s`` block of a grey image: cropped to whole blocks first,
    so that coarse pixel ``(u // s, v // s)`` is exactly the block holding full-size pixel (u, v)
    (a plain resize of KITTI's 1226 columns to 306 would stretch each coarse pixel to 4.0065)."""
    if s == 1:
        return img.astype(np.float32)
    h, w = img.shape
    size = (max(1, w // s), max(1, h // s))
    return cv2.resize(img[:size[1] * s, :size[0] * s], size, interpolation=cv2.INTER_AREA).astype(np.float32)


def coarse_row_search(left: np.ndarray, right: np.ndarray, uv_l: np.ndarray, sc: StereoConfig
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Left key points' right columns by a search along the row, without right key points.

    Both grey images are reduced by ``row_scale`` (area average) and high-passed (minus their 5x5
    mean: a brightness difference between the cameras cancels); for every coarse disparity of
    ``[min_disparity, max_disparity]`` OpenCV gives the 5x5 SAD of the whole image (``absdiff`` +
    ``boxFilter``), read at the key points. The best disparity must beat every one more than a coarse
    pixel away by ``row_ratio`` (else repetitive texture or no texture: no depth). Returns the key
    point indices and their right columns (full-resolution pixels, +-row_scale/2), to be refined."""
    s = int(sc.row_scale)
    h, w = left.shape
    check_row_search(sc, w, h)
    size = (max(1, w // s), max(1, h // s))
    k = 5

    def high_pass(img: np.ndarray) -> np.ndarray:
        c = coarse_image(img, s)
        return c - cv2.blur(c, (k, k))

    lc, rc = high_pass(left), high_pass(right)
    dmin = max(1, int(np.floor(sc.min_disparity / s)))
    dmax = min(size[0] - 1, int(np.ceil(sc.max_disparity / s)))
    if dmax < dmin or len(uv_l) == 0:
        return np.zeros(0, int), np.zeros(0)
    uc = np.clip((uv_l[:, 0] / s).astype(np.int64), 0, size[0] - 1)
    vc = np.clip((uv_l[:, 1] / s).astype(np.int64), 0, size[1] - 1)
    nd = dmax - dmin + 1
    # vol[n, v, x]: SAD of left (v, x + d) against right (v, x) for d = dmin + n (inf where x + d >= width)
    vol = np.full((nd, size[1], size[0]), np.inf, np.float32)
    for n, d in enumerate(range(dmin, dmax + 1)):
        vol[n, :, :size[0] - d] = cv2.boxFilter(cv2.absdiff(lc[:, d:], rc[:, :-d]), -1, (k, k), normalize=False,
                                                borderType=cv2.BORDER_REPLICATE)
    dn = np.arange(dmin, dmax + 1)
    xr = uc[:, None] - dn[None, :]  # right column of each disparity
    cost = np.where(xr >= 0, vol[np.arange(nd)[None, :], vc[:, None], np.clip(xr, 0, None)], np.inf)  # (M, nd)
    m = np.arange(len(uv_l))
    best = cost.argmin(axis=1)
    b = cost[m, best]
    others = cost.copy()
    for o in (-1, 0, 1):
        others[m, np.clip(best + o, 0, nd - 1)] = np.inf
    ok = np.isfinite(b) & (b < sc.row_ratio * others.min(axis=1))
    # left-right check: seen from the right pixel, the best left partner along the row is this point (+-1 coarse
    # pixel); fails where the left patch is half occluded in the right image
    xb = np.clip(uc - dn[best], 0, None)
    back = vol[:, vc, xb].argmin(axis=0)
    ok &= np.abs(back - best) <= 1
    good = np.flatnonzero(ok)
    return good, uv_l[good, 0] - dn[best[good]] * s


def sparse_matches(left: np.ndarray, right: np.ndarray, rig: StereoRig, uv_l: np.ndarray, desc_l: np.ndarray,
                   sc: StereoConfig, fc: FeaturesConfig, right_kp: tuple | None = None) -> StereoMatches:
    """Row-matched, sub-pixel refined and triangulated left key points (see the module doc); ``right_kp``:
    the right image's :func:`right_key_points` when already found (:func:`detect_pair`)."""
    gl, gr = to_gray(left), to_gray(right)
    if sc.sparse_search == "row":
        il, ur_coarse = coarse_row_search(gl, gr, uv_l, sc)
        search = sc.search_radius + (sc.row_scale + 1) // 2  # the coarse column is good to +-row_scale/2
    else:
        uv_r, desc_r = right_kp if right_kp is not None else right_key_points(gr, fc, sc)
        il, ir = match_rows(uv_l, desc_l, uv_r, desc_r, sc)
        ur_coarse, search = uv_r[ir, 0], sc.search_radius
    u0 = np.rint(uv_l[il, 0])
    v0 = np.rint(uv_l[il, 1])
    # the right match's column, shifted by the left point's rounding, is the search centre
    ur_guess = ur_coarse + (u0 - uv_l[il, 0])
    ur, ok = refine_disparity(gl, gr, u0, v0, ur_guess, sc.patch_radius, search, sc.subpixel)
    ur = ur - sc.disparity_offset  # a rig's disparity offset (calibrate stereo-offset): the right column it implies
    disp = u0 - ur
    ok &= np.isfinite(disp) & (disp >= sc.min_disparity) & (disp <= sc.max_disparity)
    il, u0, v0, ur, disp = il[ok], u0[ok], v0[ok], ur[ok], disp[ok]
    uv = np.stack([u0, v0], axis=1)
    pts = midpoint_triangulate(rig, uv, np.stack([ur, v0], axis=1))
    return StereoMatches(il, disp, pts, uv)


def sparse_depth(left: np.ndarray, right: np.ndarray, rig: StereoRig, uv_l: np.ndarray, desc_l: np.ndarray,
                 sc: StereoConfig, fc: FeaturesConfig, right_kp: tuple | None = None) -> np.ndarray:
    """Depth image (float32 metres) that holds the triangulated depth at the matched left key
    points' rounded pixels and 0 elsewhere."""
    m = sparse_matches(left, right, rig, uv_l, desc_l, sc, fc, right_kp)
    depth = np.zeros(left.shape[:2], np.float32)
    u, v = m.uv[:, 0].astype(int), m.uv[:, 1].astype(int)
    depth[v, u] = m.points[:, 2]
    return depth


_SGBM = threading.local()


def _sgbm(sc: StereoConfig, num: int) -> cv2.StereoSGBM:
    cache = getattr(_SGBM, "cache", None)
    if cache is None:
        cache = _SGBM.cache = {}
    key = (num, sc.sgbm_block_size, sc.sgbm_uniqueness)
    m = cache.get(key)
    if m is None:
        bs = sc.sgbm_block_size
        m = cv2.StereoSGBM_create(minDisparity=0, numDisparities=num, blockSize=bs, P1=8 * bs * bs,
                                  P2=32 * bs * bs, disp12MaxDiff=1, uniquenessRatio=sc.sgbm_uniqueness,
                                  speckleWindowSize=100, speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
        cache[key] = m
    return m


def sgbm_disparity(left: np.ndarray, right: np.ndarray, sc: StereoConfig) -> np.ndarray:
    """Dense disparity (float32 pixels of the full-size image, <= 0 = none) by OpenCV SGBM."""
    gl, gr = to_gray(left), to_gray(right)
    h, w = gl.shape
    scale = float(sc.sgbm_scale)
    if scale < 1.0:
        size = (max(16, int(round(w * scale))), max(16, int(round(h * scale))))
        gl = cv2.resize(gl, size, interpolation=cv2.INTER_AREA)
        gr = cv2.resize(gr, size, interpolation=cv2.INTER_AREA)
    num = max(16, int(np.ceil(sc.max_disparity * scale / 16.0)) * 16)
    raw = _sgbm(sc, num).compute(gl, gr)
    disp = raw.astype(np.float32) / 16.0
    if scale < 1.0:
        disp = cv2.resize(disp, (w, h), interpolation=cv2.INTER_NEAREST) * np.float32(w / gl.shape[1])
    disp[disp < sc.min_disparity] = 0.0
    return disp


def sgbm_depth(left: np.ndarray, right: np.ndarray, rig: StereoRig, sc: StereoConfig) -> np.ndarray:
    """Dense depth image (float32 metres, 0 = none) from SGBM disparities."""
    return rig.depth_from_disparity(sgbm_disparity(left, right, sc))


def depth_noise(rig: StereoRig, sc: StereoConfig, method: str) -> DepthNoise:
    """The depth noise that ``method``'s disparity noise implies for this rig."""
    return rig.noise(sc.sigma_disparity_sparse if method == "sparse" else sc.sigma_disparity_sgbm, sc.min_disparity)


# ------------------------------------------------------------------ rectification check


def row_offsets(left: np.ndarray, right: np.ndarray, fc: FeaturesConfig, max_hamming: int = 40) -> np.ndarray:
    """Row differences v_left - v_right (pixels) of ORB matches between the two images found
    without any row constraint (mutual nearest neighbours, ratio 0.8, Hamming cap): in a
    rectified pair they cluster at 0."""
    from rgbdslam.frontend.features import detect
    from rgbdslam.frontend.features import descriptor_words
    from rgbdslam.frontend.matching import hamming_matrix

    a, b = detect(to_gray(left), fc), detect(to_gray(right), fc)
    if len(a.desc) < 2 or len(b.desc) < 2:
        return np.zeros(0)
    d = hamming_matrix(descriptor_words(a.desc), descriptor_words(b.desc))
    ia = np.arange(len(d))
    ib = d.argmin(axis=1)
    best = d[ia, ib]
    second = np.partition(d, 1, axis=1)[:, 1]
    keep = (best <= max_hamming) & (best < 0.8 * second) & (d.argmin(axis=0)[ib] == ia)
    return a.uv_raw[ia[keep], 1] - b.uv_raw[ib[keep], 1]


def rectification_warning(left: np.ndarray, right: np.ndarray, fc: FeaturesConfig, name: str = "",
                          threshold: float = 1.0) -> str | None:
    """A sentence when the pair does not look rectified: the median absolute row difference of
    unconstrained ORB matches above ``threshold`` pixels (rectified: ~0.2-0.4), else None."""
    dv = row_offsets(left, right, fc)
    if len(dv) < 20:
        return None  # too few matches to say
    med = float(np.median(np.abs(dv)))
    if med <= threshold:
        return None
    where = f"the stereo pair{f' of {name}' if name else ''}"
    return (f"{where} does not look rectified: {len(dv)} matched features differ by a median of {med:.1f} "
            f"pixels in row (offset {float(np.median(dv)):+.1f}); stereo depth assumes rectified images "
            f"(give the calibration's distortion and extrinsics to rectify, or rectify the images first)")


def stereo_warning(frame) -> str | None:
    """The stereo counterpart of ``datasets.base.depth_warning``: an unrectified-looking pair,
    or a pair that gave (almost) no depth."""
    from rgbdslam.frontend.config import FeaturesConfig

    where = f"frame {frame.index}" + (f" ({frame.name})" if frame.name else "")
    warning = rectification_warning(frame.rgb, frame.right, FeaturesConfig(), where)
    if warning:
        return warning
    n = int(np.count_nonzero(frame.depth > 0))
    if n < 20:
        return (f"the stereo pair of {where} gave depth at only {n} pixels; check that left and right are not "
                f"swapped (depth needs the right image to see points further left) and the stereo.* settings")
    return None


def frame_warning(frame) -> str | None:
    """The first frame's sanity check for any source: :func:`stereo_warning` for a stereo frame
    (its depth ranges are the rig's, the pair must be rectified), else the RGB-D depth check
    ``datasets.base.depth_warning``."""
    from rgbdslam.frame import depth_warning

    return stereo_warning(frame) if frame.right is not None else depth_warning(frame)
