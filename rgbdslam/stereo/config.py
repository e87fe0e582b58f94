"""The ``stereo`` config section: depth from a rectified pair (:mod:`rgbdslam.configspec`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from rgbdslam.configspec import AtMost, Key, Positive, Range


@dataclass
class StereoConfig:
    """Depth from a rectified stereo pair (KITTI, EuRoC, stereo folders; docs/stereo.md)."""

    # upper bounds: disparities and noise in pixels, ORB budgets of the right image as a multiple of the left's
    depth: Annotated[Literal["sparse", "sgbm"], Key("tracking: row-matched ORB key points, or OpenCV SGBM")] = "sparse"
    map_depth: Annotated[Literal["same", "sparse", "sgbm"], Key(
        "what `fuse` re-reads for the map (\"same\" = depth)")] = "sgbm"
    # disparity noise (pixels) each method implies: depth sigma = z^2 * sigma / (fx * baseline)
    sigma_disparity_sparse: Annotated[float, Positive(100.0,
        "measured: zsad_v refinement, synthetic exact depth and KITTI consistency")] = 0.12
    sigma_disparity_sgbm: Annotated[float, Positive(100.0,
        "disparity noise (px) of SGBM depth, for the depth noise model")] = 0.5
    disparity_offset: Annotated[float, Range(-10.0, 10.0,
        "sparse: added to every measured disparity (px), a rig's calibration offset; measured without ground truth by "
        "`rgbdslam calibrate stereo-offset` (docs/stereo.md)")] = 0.0
    max_disparity: Annotated[int, Range(1, 1024, "search range (pixels); SGBM rounds it up to a multiple of 16")] = 128
    min_disparity: Annotated[float, Positive(1000.0, "smaller disparities (farther than fx * B / this) give no depth")] = 0.5
    row_tolerance: Annotated[float, Positive(100.0, "sparse: |v_left - v_right| allowed for a match (pixels)")] = 2.0
    max_hamming: Annotated[int, Range(0, 256, "sparse: descriptor distance cap")] = 50
    ratio: Annotated[float, Range(0.0, 1.0, "sparse: best / second-best Hamming distance along the row band")] = 0.9
    sparse_search: Annotated[Literal["orb", "row"], Key(
        "sparse: how a left key point finds its partner in the right image: \"orb\" = ORB key points of the right image "
        "matched along the row by descriptor; \"row\" = no right ORB: zero-mean SAD along the row on a 1/row_scale image "
        "(OpenCV cost volume), unique best (row_ratio), then the sub-pixel refinement")] = "orb"
    right_features: Annotated[int, Positive(4,
        "sparse orb: ORB budget of the right image, times features.n_features (no grid)")] = 2
    row_scale: Annotated[int, Range(1, 16, "sparse row: the coarse search runs on images reduced by this factor")] = 4
    row_ratio: Annotated[float, Positive(1.0,
        "sparse row: best coarse cost < this x the best one >1 coarse pixel away")] = 0.8
    patch_radius: Annotated[int, Positive(64, "sparse: SAD patch half-size of the sub-pixel refinement")] = 5
    search_radius: Annotated[int, Positive(64, "sparse: SAD search +- pixels around the descriptor match")] = 4
    subpixel: Annotated[Literal["zsad_v", "centre_parabola"], Key(
        "sparse: sub-pixel refinement: \"zsad_v\" = zero-mean SAD + equiangular fit; \"centre_parabola\" = the method "
        "before (patch minus its centre pixel, parabola): biased toward whole pixels (docs/stereo.md)")] = "zsad_v"
    sgbm_block_size: Annotated[int, Range(1, 31, "SGBM matching block size (odd, pixels)")] = 5
    sgbm_uniqueness: Annotated[int, AtMost(100, "SGBM uniqueness ratio (%): the best match must win by this margin")] = 10
    sgbm_scale: Annotated[float, Range(0.1, 1.0, "SGBM on an image resized by this factor (0.5: ~4x faster, coarser)")] = 1.0
