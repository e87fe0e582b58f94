"""The front end's config sections: ``features``, ``matching``, ``registration``, ``depth_filter`` and
``keyframes`` (each key declared once with its range and description, :mod:`rgbdslam.configspec`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from rgbdslam.configspec import AtMost, C_INT_MAX, Key, Positive, Range


@dataclass
class FeaturesConfig:
    # upper bounds: OpenCV's ORB takes C ints; n_features x n_features Hamming matrices (~1 GB at 10000)
    n_features: Annotated[int, Positive(10_000, "ORB key points kept per frame (the strongest)")] = 1000
    scale_factor: Annotated[float, Range(1.0 + 1e-6, 4.0, "ORB pyramid scale step between levels")] = 1.2
    n_levels: Annotated[int, Range(1, 16, "ORB pyramid levels")] = 8
    fast_threshold: Annotated[int, Positive(255, "FAST corner threshold of the ORB detector")] = 20
    edge_threshold: Annotated[int, Range(1, 255, "ORB border (pixels) where no key point is detected")] = 31
    patch_size: Annotated[int, Range(2, 255, "ORB descriptor patch size (pixels)")] = 31
    grid_rows: Annotated[int, Positive(64, ">1 enables bucketing: features spread over a grid")] = 1
    grid_cols: Annotated[int, Positive(64, "columns of the bucketing grid (see grid_rows)")] = 1
    undistort: Annotated[bool, Key("undistort key point positions with the camera's distortion before registration")] = True
    depth_delay: Annotated[Literal["ignore", "predict"], Key(
        "colour and depth images taken at different moments (Frame.depth_delay; TUM freiburg1: 0-14 ms): ignore = each "
        "key point's depth read at its own pixel; predict = read where its scene point was at the depth time, the "
        "camera's motion over the delay from the constant-velocity model (geometry/depth_time.py, docs/slam.md "
        "\"Colour/depth time offset\")")] = "ignore"
    rolling_shutter: Annotated[float | None, AtMost(0.1,
        "rolling shutter: seconds from reading the first image row to the last (0 = global shutter); each key point is "
        "moved to the frame's time (the middle row's) with the constant-velocity model (geometry/depth_time.py "
        "row_motions, docs/slam.md \"Rolling shutter\"); None = the camera's own (Camera.readout: fr1 and the 7-Scenes "
        "camera file 0.0175 s, measured without ground truth by `rgbdslam calibrate rolling-shutter`; others 0)")] = None
    shutter_velocity: Annotated[Literal["predict", "own"], Key(
        "the motion the rolling shutter is undone with: predict = the constant-velocity model (before the frame is "
        "registered); own = then again with the frame's own motion once it is tracked (for the later frames, the "
        "landmark map and loop closure; no second registration)")] = "predict"


@dataclass
class MatchingConfig:
    # upper bounds: RANSAC hypotheses are drawn and scored at once (~3 kB each); cv2 gets 10x as maxIters
    cross_check: Annotated[bool, Key("keep a match only when each descriptor is the other's nearest neighbour")] = True
    ratio: Annotated[float | None, Range(0.0, 1.0, "Lowe ratio test (None = off)")] = None
    max_hamming: Annotated[int, Range(0, 256, "largest descriptor Hamming distance of a match (bits)")] = 64
    prefilter: Annotated[Literal["none", "homography", "fundamental", "rigid3d"], Key(
        "RANSAC outlier pre-filter of the matches (2-D or 3-D model)")] = "rigid3d"
    prefilter_threshold: Annotated[float, Positive(1000.0, "metres for rigid3d, pixels for 2-D models")] = 0.03
    prefilter_iterations: Annotated[int, Positive(20_000, "RANSAC iterations of the pre-filter")] = 200
    min_depth: Annotated[float, AtMost(1000.0,
        "metres: key points with depth outside [min_depth, max_depth] are not used")] = 0.1
    max_depth: Annotated[float, Positive(1000.0,
        "metres: see min_depth; 10 = a Kinect's range (its depth images end there): the room's far points, 6-10 m "
        "on TUM fr3/teddy, are the ones that separate rotation from sideways translation (docs/landmarks.md)")] = 10.0
    depth_edge_radius: Annotated[int, AtMost(32,
        "key points at depth discontinuities: a key point whose (2r+1)^2 depth neighbourhood has a missing pixel or "
        "one differing from its own depth by more than depth_edge_jump * z is flagged (FrameFeatures.edge); r is "
        "depth_edge_radius at ORB pyramid level 0, scaled by features.scale_factor**level (a coarse key point's "
        "position is good to its level's pixel size); 0 = off. Its depth may be the other surface's (mixed or "
        "misregistered pixels along an outline): flagged points help match and choose the inliers, but each "
        "registration's pose is fitted without them and the landmark map leaves them out (docs/frontend.md \"Scale "
        "bias\")")] = 2
    depth_edge_jump: Annotated[float, Positive(10.0, "relative depth jump that makes a depth edge")] = 0.15


@dataclass
class RegistrationConfig:
    method: Annotated[Literal["ransac", "isvd", "islam"], Key("frame-to-frame registration")] = "islam"
    # RANSAC baseline
    ransac_iterations: Annotated[int, Positive(20_000, "iterations of the RANSAC baseline")] = 200
    ransac_threshold: Annotated[float, Positive(10.0, "metres: inlier distance of the RANSAC baseline")] = 0.03
    # ISVD (docs/references.md §1)
    max_iterations: Annotated[int, Positive(1000, "ISVD: most rounds of fit-and-gate")] = 10
    e_start: Annotated[float, Positive(100.0,
        "halved each round: 0.32 .. 0.01, the last gate is the first below e_min")] = 0.32
    e_min: Annotated[float, Positive(100.0, "ISVD stops once its gate falls below this (m)")] = 0.02
    # ISLAM (docs/references.md §2)
    mp: Annotated[int, Positive(64, "ISLAM: registered against the last mp frames (MP of the thesis)")] = 4
    alpha: Annotated[float, Positive(100.0, "ISLAM gate of iteration j: alpha * j**beta (m)")] = 0.2
    beta: Annotated[float, Range(-100.0, 100.0, "ISLAM gate exponent (negative: the gate shrinks each iteration)")] = -1.0
    min_error: Annotated[float, AtMost(100.0, "ISLAM stops once its gate falls below this (m)")] = 0.01
    min_points: Annotated[int, Range(3, 10**9, "ISLAM: a reference needs this many surviving pairs")] = 12
    fusion: Annotated[Literal["thesis", "chordal"], Key("ISLAM's fusion of its references' poses")] = "chordal"
    reject_translation: Annotated[float, Positive(100.0, "candidate disagreement gates (m, rad)")] = 0.05
    reject_rotation: Annotated[float, Positive(100.0, "radians: see reject_translation")] = 0.05
    min_agreement: Annotated[float, Range(0.0, 1.0, "lost if the agreeing candidates hold less of the total weight")] = 0.5
    guided_gate: Annotated[float | None, Positive(100.0,
        "older ISLAM references: gate (m) around the newest one's pose, no RANSAC")] = 0.05
    predicted_gate: Annotated[float | None, Positive(100.0,
        "newest reference: when the previous frame's constant-velocity prediction was off by less than half this (m; "
        "translation + rotation x 2 m), match guided within this gate around the prediction (no brute-force Hamming "
        "matrix, no RANSAC); brute force when that keeps fewer than predicted_min_inliers inliers (None = always brute "
        "force; docs/frontend.md)")] = 0.05
    predicted_min_inliers: Annotated[int, Range(3, 10**9,
        "inliers the guided match needs before falling back to brute force")] = 60
    noise_refit_huber: Annotated[float, Positive(100.0,
        "Huber threshold of the stereo fits on 3-D pairs weighted by their covariances (Mahalanobis distance, sigmas)")] = 3.0
    stereo_reprojection: Annotated[bool, Key(
        "stereo frames: far points fix the rotation, near points the translation. The fused pose is refit on the stereo "
        "reprojection residuals (u, v, disparity; key points without a disparity as (u, v)) of every key point of the "
        "newest kept reference matched by descriptor, its rotation kept and its translation re-solved from the "
        "registration's inlier pairs in 3-D weighted by their stereo covariances (the fallback's pose: the refit "
        "alone, on all references) "
        "(geometry/stereo_pose.py, geometry/mahalanobis.py; docs/stereo.md)")] = False
    stereo_fallback: Annotated[bool, Key(
        "a stereo frame whose registration fails is not lost: constant-velocity pose, its rotation refit on the "
        "bearings of the newest reference's descriptor matches, then a near + far refit if enough pairs agree")] = False
    threads: Annotated[int, Positive(256, "threads registering the ISLAM references in parallel")] = 1
    constant_velocity: Annotated[bool, Key("predict each pose from the last motion (else from the last pose)")] = True
    max_lost: Annotated[int, AtMost(10**6,
        "consecutive lost frames before tracking restarts from the last pose (0 = never)")] = 15
    max_jump_translation: Annotated[float, Positive(1000.0,
        "m per frame: candidates further from the prediction are rejected")] = 0.15
    max_jump_rotation_deg: Annotated[float, Positive(360.0,
        "degrees per frame: candidates turned further from the prediction are rejected")] = 15.0
    # cv2.setRNGSeed takes a C int
    seed: Annotated[int, AtMost(C_INT_MAX, "seed of RANSAC's random choices")] = 0


@dataclass
class DepthFilterConfig:
    """DIF, the conditional averaging depth filter (docs/references.md §3, docs/slam.md)."""

    # upper bounds: each of the window's frames is warped into the current one
    enabled: Annotated[bool, Key("run DIF on every frame (off by default: no gain measured, docs/slam.md)")] = False
    window: Annotated[int, AtMost(32, "K previous filtered frames warped into the current one (0 = spatial only)")] = 2
    spatial_radius: Annotated[int, AtMost(32, "window half-size of the spatial averaging (0 = temporal only)")] = 1
    tolerance_a: Annotated[float, AtMost(10.0, "agreement tolerance = a + b * z^2 (metres)")] = 0.01
    tolerance_b: Annotated[float, AtMost(10.0, "see tolerance_a (1/m)")] = 0.0035
    min_support: Annotated[int, AtMost(10_000, "agreeing samples (besides the pixel itself) needed to keep a pixel")] = 3
    min_depth: Annotated[float, AtMost(1000.0, "metres: depth outside [min_depth, max_depth] is dropped")] = 0.3
    max_depth: Annotated[float, Positive(1000.0, "metres: see min_depth")] = 5.0


@dataclass
class KeyframeConfig:
    min_translation: Annotated[float, AtMost(10000.0, "metres moved since the last keyframe")] = 0.10
    min_rotation_deg: Annotated[float, AtMost(360.0, "degrees turned since the last keyframe")] = 10.0
    max_gap: Annotated[int, Positive(10**6, "frames: a keyframe at least every max_gap frames")] = 15
