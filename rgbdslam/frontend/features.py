"""ORB key points and descriptors, lifted to 3-D camera points with the depth image.

Key points are detected on the (distorted) colour image. Their pixel coordinates are
undistorted with the camera's Brown–Conrady model before back-projection, while the depth is
sampled at the rounded *distorted* location, because TUM/PUT depth images are registered to
the distorted colour image.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from rgbdslam.frame import Frame
from rgbdslam.frontend.config import FeaturesConfig, MatchingConfig
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.depth_time import depth_at_colour_time, row_motions, shutter_corrected_pixels

if TYPE_CHECKING:
    from scipy.spatial import cKDTree


@dataclass
class FrameFeatures:
    """Features of one frame, computed once and cached by the front end."""

    index: int
    timestamp: float
    uv: np.ndarray  # (N, 2) undistorted pixel coordinates
    desc: np.ndarray  # (N, 32) uint8 ORB descriptors
    pts: np.ndarray  # (N, 3) camera-frame points, NaN where depth is invalid
    valid: np.ndarray  # (N,) bool, has valid depth
    n_detected: int  # corners detected before ORB keeps the best n_features (sharpness gate)
    uv_raw: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (N, 2) distorted pixels
    response: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))  # (N,) ORB response
    octave: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int8))  # (N,) ORB pyramid level (scale^octave px)
    depth_noise: Any = None  # the frame's DepthNoise (stereo) or None: covariance of pts
    # pose of the camera when the depth image was taken, in the camera at the colour time (4x4,
    # X_colour = depth_motion @ X_depth), or None (taken together): :func:`lift` reads each key
    # point's depth where its scene point was at the depth time (geometry/depth_time.py)
    depth_motion: np.ndarray | None = None
    # rolling shutter (features.rolling_shutter): each key point's row pose in the camera at the
    # frame's time, rotation (N,3,3) and translation (N,3), and its pixel as observed (N,2, ideal);
    # ``uv`` then holds the pixels at the frame's time and :func:`lift` moves the points likewise
    row_R: np.ndarray | None = None
    row_t: np.ndarray | None = None
    uv_observed: np.ndarray | None = None
    readout: float = 0.0  # the readout (s) the rolling shutter was undone with
    pyramid_scale: float = 1.0  # features.scale_factor: a key point of octave k has pixels pyramid_scale**k wide
    # (N,) bool: the key point sits at a depth discontinuity (matching.depth_edge_radius; all False when off)
    edge: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    # (N,) the depth read at each key point before the [min_depth, max_depth] limits (0 = none): a stereo
    # frame's far points, used as bearings (registration.stereo_fallback, docs/stereo.md)
    depth_raw: np.ndarray = field(default_factory=lambda: np.zeros(0))
    _tree: cKDTree | None = field(default=None, repr=False)
    _tree_index: np.ndarray | None = field(default=None, repr=False)

    @property
    def tree(self) -> cKDTree:
        """k-d tree of the depth-valid 3-D points (built once; reset by :func:`lift`)."""
        if self._tree is None:
            from scipy.spatial import cKDTree  # here: SciPy's import is not on the way to the first frame

            self._tree_index = np.flatnonzero(self.valid)
            self._tree = cKDTree(self.pts[self._tree_index])
        return self._tree

    def with_points(self, pts: np.ndarray) -> FrameFeatures:
        """A copy with the camera-frame points ``pts`` (N, 3) instead (the other arrays shared); its
        k-d tree is built anew from them."""
        pts = np.asarray(pts, dtype=np.float64)
        if pts.shape != self.pts.shape:
            raise ValueError(f"with_points needs {self.pts.shape} points, got {pts.shape}")
        return replace(self, pts=pts, _tree=None, _tree_index=None)

    @property
    def tree_index(self) -> np.ndarray:
        """Feature index of each point in :attr:`tree`."""
        self.tree  # noqa: B018 - builds the tree and its index
        return self._tree_index

    @property
    def words(self) -> np.ndarray:
        """Descriptors as (N, 4) uint64 words (a view, no copy) for popcount matching."""
        return descriptor_words(self.desc)

    @property
    def map_valid(self) -> np.ndarray:
        """(N,) bool: depth-valid and not at a depth edge (:attr:`edge`): the features the landmark
        map matches and makes landmarks from."""
        return map_valid(self)

    @property
    def n_valid(self) -> int:
        return int(np.count_nonzero(self.valid))


def map_valid(feats) -> np.ndarray:
    """``feats.valid`` without the key points flagged at depth edges (``feats.edge``, when it has one
    flag per feature): the features the landmark map matches and makes landmarks from."""
    edge = getattr(feats, "edge", None)
    return feats.valid & ~edge if edge is not None and len(edge) == len(feats.valid) else feats.valid


def descriptor_words(desc: np.ndarray) -> np.ndarray:
    """ORB descriptors (N, 32) uint8 viewed as four 64-bit words (N, 4) for popcount matching."""
    return np.ascontiguousarray(desc, dtype=np.uint8).view(np.uint64).reshape(-1, 4)


_CACHE = threading.local()  # detectors per thread: an OpenCV detector object is not shared between threads


def _cache(name: str) -> dict:
    d = getattr(_CACHE, name, None)
    if d is None:
        d = {}
        setattr(_CACHE, name, d)
    return d


def count_detections(gray: np.ndarray, fc: FeaturesConfig) -> int:
    """Corners ORB's detector finds in ``gray`` before it keeps the best ``n_features``.

    FAST (with non-maximum suppression) at ORB's ``fast_threshold`` on the full-resolution
    image, inside ORB's ``edge_threshold`` border. ORB's own count is not exposed by OpenCV and
    is capped by its retention; this one is not capped, so it falls when the image is blurred
    (the loop-closure sharpness gate, docs/references.md §4). About 0.3 ms at 640x480; its rank
    correlation with the count over the whole 8-level pyramid is 0.98 on fr1/rpy.
    """
    cache = _cache("fast")
    fast = cache.get(fc.fast_threshold)
    if fast is None:
        fast = cv2.FastFeatureDetector_create(threshold=fc.fast_threshold, nonmaxSuppression=True)
        cache[fc.fast_threshold] = fast
    b = fc.edge_threshold
    h, w = gray.shape[:2]
    if h <= 2 * b or w <= 2 * b:
        return 0
    return len(fast.detect(np.ascontiguousarray(gray[b:h - b, b:w - b])))


def _orb(fc: FeaturesConfig, n_features: int) -> cv2.ORB:
    key = (n_features, fc.scale_factor, fc.n_levels, fc.edge_threshold, fc.patch_size, fc.fast_threshold)
    cache = _cache("orb")
    orb = cache.get(key)
    if orb is None:
        orb = cv2.ORB_create(
            nfeatures=n_features,
            scaleFactor=fc.scale_factor,
            nlevels=fc.n_levels,
            edgeThreshold=fc.edge_threshold,
            patchSize=fc.patch_size,
            fastThreshold=fc.fast_threshold,
        )
        cache[key] = orb
    return orb


def _bucket(uv: np.ndarray, response: np.ndarray, fc: FeaturesConfig, shape: tuple[int, int]) -> np.ndarray:
    """Indices of the strongest key points per grid cell (at most n_features / cells each)."""
    rows, cols = fc.grid_rows, fc.grid_cols
    h, w = shape
    cell = (np.minimum((uv[:, 1] * rows / h).astype(int), rows - 1) * cols
            + np.minimum((uv[:, 0] * cols / w).astype(int), cols - 1))
    per_cell = max(1, fc.n_features // (rows * cols))
    order = np.lexsort((-response, cell))  # by cell, strongest first
    sorted_cell = cell[order]
    first = np.searchsorted(sorted_cell, sorted_cell, side="left")
    rank = np.arange(len(order)) - first
    return np.sort(order[rank < per_cell])


@dataclass(frozen=True, eq=False)
class Detections:
    """What the colour image alone gives: ORB key points (distorted pixels), descriptors,
    responses, and the uncapped detection count. Made by :func:`detect` for one features config."""

    uv_raw: np.ndarray
    desc: np.ndarray
    response: np.ndarray
    n_detected: int
    config: FeaturesConfig
    image: np.ndarray = field(repr=False, compare=False)  # the image they were found in (identity is checked)
    octave: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int8))  # pyramid level of each key point


def detect(rgb: np.ndarray, fc: FeaturesConfig, count: bool = True) -> Detections:
    """ORB (with optional grid bucketing) and the detection count on a colour or grey image
    (``count=False``: no count, ``n_detected`` -1, for images only matched against, e.g. a stereo
    pair's right image).

    Needs no depth, pose or earlier frame, so it can run ahead in the frame reader's thread
    (OpenCV releases the GIL): see :func:`with_detections`."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb
    uv_raw, desc, response, octave = orb_features(gray, fc)
    return Detections(uv_raw, desc, response, count_detections(gray, fc) if count else -1, fc, rgb, octave)


def orb_features(gray: np.ndarray, fc: FeaturesConfig, attributes: bool = True
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """ORB key points (N, 2), descriptors (N, 32), responses (N,) and pyramid levels (N,) of a grey image
    (``attributes=False``: responses and levels left empty, for images only matched against: reading them
    is a Python attribute access per key point, ~0.5 ms per 4000).

    With grid bucketing ORB finds twice the budget, the strongest per cell are kept, and only
    those get descriptors (``detect`` then ``compute``: the same descriptors as
    ``detectAndCompute`` on all of them, ~20 % less time on KITTI-sized images)."""
    bucketing = fc.grid_rows * fc.grid_cols > 1
    orb = _orb(fc, fc.n_features * 2 if bucketing else fc.n_features)
    if bucketing:
        kps = orb.detect(gray, None)
        if kps:
            uv = cv2.KeyPoint_convert(kps).astype(np.float64)  # C++: ~50x faster than a list of k.pt
            keep = _bucket(uv, np.array([k.response for k in kps], dtype=np.float32), fc, gray.shape[:2])
            kps = [kps[i] for i in keep]
        kps, desc = orb.compute(gray, kps) if kps else ((), None)
    else:
        kps, desc = orb.detectAndCompute(gray, None)
    if desc is None or len(kps) == 0:
        return np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros(0, np.float32), np.zeros(0, np.int8)
    uv_raw = cv2.KeyPoint_convert(kps).astype(np.float64).reshape(-1, 2)
    if not attributes:
        return uv_raw, np.ascontiguousarray(desc), np.zeros(0, np.float32), np.zeros(0, np.int8)
    response = np.array([k.response for k in kps], dtype=np.float32)
    octave = np.array([k.octave for k in kps], dtype=np.int8)
    return uv_raw, np.ascontiguousarray(desc), response, octave


def orb_level_budget(n_features: int, scale_factor: float, n_levels: int) -> np.ndarray:
    """Key points per pyramid level ORB keeps for ``n_features`` in all (OpenCV's allocation: a
    geometric series by 1 / ``scale_factor``, rounded; the top level gets the rest)."""
    factor = 1.0 / scale_factor
    per = n_features * (1 - factor) / (1 - factor ** n_levels)
    out = np.zeros(n_levels, np.int64)
    for level in range(n_levels - 1):
        out[level] = int(np.floor(per + 0.5))
        per *= factor
    out[-1] = max(n_features - int(out[:-1].sum()), 0)
    return out


def strongest(features: FrameFeatures, fc: FeaturesConfig) -> np.ndarray:
    """Indices (ascending) of the key points of ``features`` ORB would have kept with
    ``fc.n_features`` (detected with more): per pyramid level the strongest by response, as many as
    :func:`orb_level_budget` gives the level. ORB's own choice differs a little (it pre-selects by
    FAST score before the Harris response), so this is the same budget, not the same set."""
    budget = orb_level_budget(fc.n_features, fc.scale_factor, fc.n_levels)
    keep = []
    for level, n in enumerate(budget):
        idx = np.flatnonzero(features.octave == level)
        if len(idx) > n:
            idx = idx[np.argsort(-features.response[idx], kind="stable")[:n]]
        keep.append(idx)
    return np.sort(np.concatenate(keep)) if keep else np.zeros(0, np.int64)


def subset(features: FrameFeatures, idx: np.ndarray) -> FrameFeatures:
    """The key points ``idx`` of ``features`` as a frame's features of their own (arrays copied)."""
    def take(a):
        return a if a is None or len(a) != len(features.uv) else a[idx]

    return replace(features, uv=features.uv[idx], desc=features.desc[idx], pts=features.pts[idx],
                   valid=features.valid[idx], uv_raw=take(features.uv_raw), response=take(features.response),
                   octave=take(features.octave), row_R=take(features.row_R), row_t=take(features.row_t),
                   uv_observed=take(features.uv_observed), edge=take(features.edge), depth_raw=take(features.depth_raw),
                   _tree=None, _tree_index=None)


def with_detections(frame: Frame, fc: FeaturesConfig) -> Frame:
    """``frame`` with its :class:`Detections` attached (``Sequence.prefetched(then=...)``); kept
    when the reader already made them in this image with this config (sparse stereo does)."""
    det = frame.detections
    if not (isinstance(det, Detections) and det.image is frame.rgb and det.config == fc):
        frame.detections = detect(frame.rgb, fc)
    return frame


def extract_features(frame: Frame, fc: FeaturesConfig, mc: MatchingConfig,
                     depth_motion: np.ndarray | None = None,
                     velocity: tuple[np.ndarray, float] | None = None) -> FrameFeatures:
    """ORB on the colour image of ``frame`` (``features`` section), lifted to 3-D with its depth
    (within the ``matching`` section's depth range); ``depth_motion``: the camera's motion from the
    colour to the depth image's time (see :class:`FrameFeatures`), None = taken together;
    ``velocity`` ``(V, dt)``: the camera's constant-velocity motion V over dt seconds, with which a
    rolling shutter (``features.rolling_shutter``, None = the camera's ``readout``; > 0 s) is
    undone: every key point is moved to where it would be seen at the frame's time (its row's time
    taken from the readout; the pixel of a point without depth turned by the row's rotation alone).

    Uses ``frame.detections`` when they were made ahead in this frame's image with the same
    features config."""
    det = frame.detections
    if not isinstance(det, Detections) or det.image is not frame.rgb or det.config != fc:
        det = detect(frame.rgb, fc)
    camera = frame.camera
    uv = camera.undistort_points(det.uv_raw) if fc.undistort else det.uv_raw.copy()
    feats = FrameFeatures(
        index=frame.index,
        timestamp=frame.timestamp,
        uv=uv,
        desc=det.desc,
        pts=np.full((len(uv), 3), np.nan),
        valid=np.zeros(len(uv), bool),
        n_detected=det.n_detected,
        uv_raw=det.uv_raw,
        response=det.response,
        octave=det.octave,
        pyramid_scale=fc.scale_factor,
        depth_noise=frame.depth_noise,
        depth_motion=depth_motion,
    )
    readout = camera.readout if fc.rolling_shutter is None else fc.rolling_shutter
    if readout > 0 and velocity is not None and velocity[1] > 0 and len(uv):
        feats.row_R, feats.row_t = row_motions(det.uv_raw[:, 1], camera.height, readout, *velocity)
        feats.readout = readout
        feats.uv_observed = uv
        feats.uv = shutter_corrected_pixels(uv, camera, feats.row_R)
    lift(feats, frame.depth, camera, mc)
    return feats


def lift(features: FrameFeatures, depth: np.ndarray, camera: Camera, mc: MatchingConfig) -> None:
    """(Re)compute ``features.pts`` / ``features.valid`` from a metric depth image, in place.

    Depth is read at the rounded distorted key-point location; points outside
    ``[matching.min_depth, matching.max_depth]`` or without depth are invalid (NaN). With
    ``features.depth_motion`` the depth is read where the key point's scene point was when the
    depth image was taken, and brought to the colour time
    (:func:`rgbdslam.geometry.depth_time.depth_at_colour_time`).
    """
    n = len(features.uv)
    raw = features.uv_raw if len(features.uv_raw) == n else features.uv
    h, w = depth.shape[:2]
    u = np.clip(np.rint(raw[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(raw[:, 1]).astype(int), 0, h - 1)
    z = depth[v, u].astype(np.float64) if n else np.zeros(0)
    if features.depth_motion is not None and n:
        z = _depth_at_colour_time(features, depth, camera, z)
    valid = np.isfinite(z) & (z >= mc.min_depth) & (z <= mc.max_depth)
    features.depth_raw = np.where(np.isfinite(z) & (z > 0), z, 0.0)
    features.edge = np.zeros(n, bool)
    if mc.depth_edge_radius > 0 and n:
        features.edge = depth_edges(depth, u, v, edge_radii(features, mc.depth_edge_radius), mc.depth_edge_jump) & valid
    pts = np.full((n, 3), np.nan)
    if valid.any() and features.row_R is not None:  # rolling shutter: each point from its row's pose
        X = camera.backproject(features.uv_observed[valid], z[valid])
        pts[valid] = np.einsum("nij,nj->ni", features.row_R[valid], X) + features.row_t[valid]
        features.uv[valid] = camera.project(pts[valid])  # with the row's translation: the pixel at the frame's time
    elif valid.any():
        pts[valid] = camera.backproject(features.uv[valid], z[valid])
    features.pts = pts
    features.valid = valid
    features._tree = None
    features._tree_index = None


def depth_edges(depth: np.ndarray, u: np.ndarray, v: np.ndarray, radius, jump: float) -> np.ndarray:
    """(N,) bool: pixel (u, v) lies at a depth discontinuity — some pixel of its (2r+1)² window
    (``radius`` r, one for all or (N,) one per pixel; clipped at the image border) has no depth
    (0 or not finite) or differs from the pixel's own depth z by more than ``jump`` · z. A depth read
    there may belong to the other surface: a depth image registered a few pixels off the colour image,
    a late depth image under motion, the mixed pixels along an outline, or a key point found in a
    coarse pyramid level, whose position is only good to a few pixels. A pixel without depth itself
    is not flagged."""
    d = np.asarray(depth)
    h, w = d.shape[:2]
    flat = d.reshape(-1)
    radius = np.broadcast_to(np.asarray(radius, dtype=np.int64), np.shape(u))
    out = np.zeros(len(u), bool)
    for r in np.unique(radius):  # one window size at a time (a pyramid level each)
        if r <= 0:
            continue
        m = radius == r
        uu_, vv_ = u[m], v[m]
        z = flat.take(vv_ * w + uu_).astype(np.float64)
        k = np.arange(-r, r + 1)
        rows = np.clip(vv_[:, None] + k, 0, h - 1) * w
        cols = np.clip(uu_[:, None] + k, 0, w - 1)
        nb = flat.take((rows[:, :, None] + cols[:, None, :]).reshape(len(uu_), -1))  # the windows, row by row
        with np.errstate(invalid="ignore"):
            hole = (~np.isfinite(nb) | (nb <= 0)).any(axis=1)
            # |nb - z| > jump·z for some pixel ⟺ for the window's largest or smallest depth: the difference
            # rounds monotonically in nb, so the extremes' differences are the extremes of the differences
            # (the same float64 numbers the pixel-wise test compares; a NaN is a hole already)
            jz = jump * z
            far = (nb.max(axis=1).astype(np.float64) - z > jz) | (z - nb.min(axis=1).astype(np.float64) > jz)
        out[m] = np.isfinite(z) & (z > 0) & (hole | far)
    return out


def edge_radii(features: FrameFeatures, radius: int) -> np.ndarray:
    """Window radius of each key point's depth-edge test: ``radius`` pixels at pyramid level 0,
    scaled with the level's pixel size (``pyramid_scale ** octave``)."""
    n = len(features.uv)
    if len(features.octave) != n:
        return np.full(n, radius, np.int64)
    return np.ceil(radius * features.pyramid_scale ** features.octave.astype(np.float64) - 1e-9).astype(np.int64)


def reshutter(features: FrameFeatures, depth: np.ndarray, camera: Camera, mc: MatchingConfig,
              V: np.ndarray, dt: float) -> None:
    """Undo the rolling shutter of ``features`` (made with a readout) again with another motion
    ``V`` over ``dt`` seconds, in place: the row poses, the pixels and the 3-D points."""
    if features.row_R is None or not dt > 0:
        return
    readout = features.readout
    features.row_R, features.row_t = row_motions(features.uv_raw[:, 1], camera.height, readout, V, dt)
    features.uv = shutter_corrected_pixels(features.uv_observed, camera, features.row_R)
    lift(features, depth, camera, mc)


def _depth_at_colour_time(features: FrameFeatures, depth: np.ndarray, camera: Camera, z: np.ndarray) -> np.ndarray:
    """The key points' depths at the colour time; the first guess is the depth at the key point
    itself, else the median of those (a point off a surface edge reads its neighbour's)."""
    good = np.isfinite(z) & (z > 0)
    if not good.any():
        return z
    z0 = np.where(good, z, np.median(z[good]))
    uv = features.uv if features.uv_observed is None else features.uv_observed
    return depth_at_colour_time(uv, depth, camera, features.depth_motion, z0)
