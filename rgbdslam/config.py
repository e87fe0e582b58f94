"""Typed configuration.

Every algorithm parameter lives here, grouped in one dataclass per stage. Presets are
YAML files inside the package (``rgbdslam/presets/``, read with ``importlib.resources`` so an
installed wheel has them) that override the defaults below; ``--set section.key=value``
overrides a preset. Unknown keys and values of the wrong type are rejected with a
message naming the key.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args, get_origin, get_type_hints

import yaml

from rgbdslam.io.text import read_text
from rgbdslam.errors import ConfigError, cut, shorten
from rgbdslam.io.yamlfile import Refused, StrictLoader, load_yaml


def preset_files() -> dict[str, Any]:
    """Name -> resource of every preset shipped inside the package (``rgbdslam/presets/*.yaml``)."""
    root = importlib.resources.files("rgbdslam") / "presets"
    return {e.name[:-5]: e for e in root.iterdir() if e.name.endswith(".yaml") and e.is_file()}


@dataclass
class DatasetConfig:
    kind: Literal["auto", "tum", "icl", "put", "synthetic", "7scenes", "rosbag", "kitti", "euroc", "stereo"] = "auto"  # reader; auto: by the folder's files
    # TUM association (semantics of TUM's associate.py)
    max_difference: float = 0.02  # seconds: colour and depth images closer in time than this are paired
    offset: float = 0.0  # seconds added to the depth time stamps before pairing
    associations: str | None = None  # optional existing associations file
    # Camera file (YAML: fx fy cx cy size distortion depth_scale, optional depth_camera and
    # depth_to_color; `--camera FILE`); wins over everything below (docs/formats.md "Camera file")
    camera_file: str | None = None
    # Camera: "auto" = camera.yaml in the folder, else what the source says (bag CameraInfo,
    # 7-Scenes/ETH3D calibration, freiburg1/2/3 in a TUM folder name, kinect1 for PUT), else
    # ros_default with a warning; or the named model
    camera: Literal["auto", "fr1", "fr2", "fr3", "kinect1", "ros_default"] = "auto"
    depth_scale: float | None = None  # raw units per metre; None = camera file, else source default (TUM 5000, PUT 1000)
    depth_correction: float = 1.0  # multiply metric depth (off = 1.0)
    first_frame: int = 0  # first frame used, counted from 0 after pairing (--first-frame)
    max_frames: int | None = None  # use at most this many frames (None = all; --max-frames)
    stride: int = 1  # use every n-th frame (--stride)
    groundtruth: str | None = None  # PUT: ground-truth TUM file (default groundtruth.txt or the one *.tum); bags: a TUM file
    # ROS bags: topics (None = found automatically when unambiguous; the error lists the candidates)
    rgb_topic: str | None = None  # ROS bags: colour image topic (None: found when unambiguous)
    depth_topic: str | None = None  # ROS bags: depth image topic (None: found when unambiguous)
    camera_info_topic: str | None = None  # ROS bags: CameraInfo topic of the colour camera (None: found)
    prefetch: int = 4  # frames read ahead by a background thread during `run` (0 = read in the loop)
    reader_threads: int = 2  # threads preparing frames ahead at once where the reader allows it (stereo pairs)


@dataclass
class FeaturesConfig:
    n_features: int = 1000  # ORB key points kept per frame (the strongest)
    scale_factor: float = 1.2  # ORB pyramid scale step between levels
    n_levels: int = 8  # ORB pyramid levels
    fast_threshold: int = 20  # FAST corner threshold of the ORB detector
    edge_threshold: int = 31  # ORB border (pixels) where no key point is detected
    patch_size: int = 31  # ORB descriptor patch size (pixels)
    grid_rows: int = 1  # >1 enables bucketing: features spread over a grid
    grid_cols: int = 1  # columns of the bucketing grid (see grid_rows)
    undistort: bool = True  # undistort key point positions with the camera's distortion before registration
    # colour and depth images taken at different moments (Frame.depth_delay; TUM freiburg1: 0-14 ms):
    # ignore = each key point's depth read at its own pixel; predict = read where its scene point was
    # at the depth time, the camera's motion over the delay from the constant-velocity model
    # (geometry/depth_time.py, docs/slam.md "Colour/depth time offset")
    depth_delay: Literal["ignore", "predict"] = "ignore"
    # rolling shutter: seconds from reading the first image row to the last (0 = global shutter); each
    # key point is moved to the frame's time (the middle row's) with the constant-velocity model
    # (geometry/depth_time.py row_motions, docs/slam.md "Rolling shutter"); None = the camera's own
    # (Camera.readout: fr1 and the 7-Scenes camera file 0.0175 s, measured without ground truth by
    # scripts/calibrate_rolling_shutter.py; others 0)
    rolling_shutter: float | None = None
    # the motion the rolling shutter is undone with: predict = the constant-velocity model (before
    # the frame is registered); own = then again with the frame's own motion once it is tracked
    # (for the later frames, the landmark map and loop closure; no second registration)
    shutter_velocity: Literal["predict", "own"] = "predict"


@dataclass
class MatchingConfig:
    cross_check: bool = True  # keep a match only when each descriptor is the other's nearest neighbour
    ratio: float | None = None  # Lowe ratio test (None = off)
    max_hamming: int = 64  # largest descriptor Hamming distance of a match (bits)
    prefilter: Literal["none", "homography", "fundamental", "rigid3d"] = "rigid3d"  # outlier pre-filter
    prefilter_threshold: float = 0.03  # metres for rigid3d, pixels for 2-D models
    prefilter_iterations: int = 200  # RANSAC iterations of the pre-filter
    min_depth: float = 0.1  # metres: key points with depth outside [min_depth, max_depth] are not used
    max_depth: float = 6.0  # metres: see min_depth
    # key points at depth discontinuities: a key point whose (2r+1)^2 depth neighbourhood has a missing
    # pixel or one differing from its own depth by more than depth_edge_jump * z is flagged
    # (FrameFeatures.edge); r is depth_edge_radius at ORB pyramid level 0, scaled by
    # features.scale_factor**level (a coarse key point's position is good to its level's pixel size);
    # 0 = off. Its depth may be the other surface's (mixed or misregistered pixels along an outline):
    # flagged points help match and choose the inliers, but each registration's pose is fitted without
    # them and the landmark map leaves them out (docs/frontend.md "Scale bias")
    depth_edge_radius: int = 1
    depth_edge_jump: float = 0.05  # relative depth jump that makes a depth edge


@dataclass
class RegistrationConfig:
    method: Literal["ransac", "isvd", "islam"] = "islam"  # frame-to-frame registration
    # RANSAC baseline
    ransac_iterations: int = 200  # iterations of the RANSAC baseline
    ransac_threshold: float = 0.03  # metres: inlier distance of the RANSAC baseline
    # ISVD (docs/references.md §1)
    max_iterations: int = 10  # ISVD: most rounds of fit-and-gate
    e_start: float = 0.32  # halved each round: 0.32 .. 0.01, the last gate is the first below e_min
    e_min: float = 0.02  # ISVD stops once its gate falls below this (m)
    # ISLAM (docs/references.md §2)
    mp: int = 4  # ISLAM: registered against the last mp frames (MP of the thesis)
    alpha: float = 0.2  # ISLAM gate of iteration j: alpha * j**beta (m)
    beta: float = -1.0  # ISLAM gate exponent (negative: the gate shrinks each iteration)
    min_error: float = 0.01  # ISLAM stops once its gate falls below this (m)
    min_points: int = 12  # ISLAM: a reference needs this many surviving pairs
    fusion: Literal["thesis", "chordal"] = "chordal"  # ISLAM's fusion of its references' poses
    reject_translation: float = 0.05  # candidate disagreement gates (m, rad)
    reject_rotation: float = 0.05  # radians: see reject_translation
    min_agreement: float = 0.5  # lost if the agreeing candidates hold less of the total weight
    pregate: float | None = None  # drop pairs this far (m) from the constant-velocity prediction first
    guided_gate: float | None = 0.05  # older ISLAM references: gate (m) around the newest one's pose, no RANSAC
    # newest reference: when the previous frame's constant-velocity prediction was off by less than
    # half this (m; translation + rotation x 2 m), match guided within this gate around the prediction
    # (no brute-force Hamming matrix, no RANSAC); brute force when that keeps fewer than
    # predicted_min_inliers inliers (None = always brute force; docs/frontend.md)
    predicted_gate: float | None = 0.05
    predicted_min_inliers: int = 60  # inliers the guided match needs before falling back to brute force
    joint_refit: bool = False  # after fusion: one weighted SVD fit on the inliers of all kept references
    joint_gate: float = 0.02  # metres, pairs further from the fused pose are left out of the joint refit
    depth_weighting: bool = False  # weight pairs by 1/z^2 in the joint refit
    # after fusion (frames with a depth noise model, i.e. stereo): Gauss-Newton refit on the kept inlier
    # pairs weighted by their covariances (geometry.mahalanobis; docs/stereo.md). Off by default: on a short
    # indoor baseline (synthetic 0.12 m) it costs accuracy (circle 1.5-2.0x RGB-D with it, 0.4-1.1x without);
    # the kitti preset turns it on (far points: ATE 0.29 m without it)
    noise_refit: bool = False
    noise_refit_all: bool = True  # refit on every descriptor match (robust kernel), not only the inliers
    noise_refit_huber: float = 3.0  # Huber threshold of the refit (Mahalanobis distance, sigmas)
    # stereo fallback (below): matched points deeper than this many baselines (ORB-SLAM's ThDepth, 40) are
    # far: bearing-only (reprojection) residuals, their depth unused (docs/stereo.md); 0 = every depth-valid one 3-D
    far_baselines: float = 0.0
    # a stereo frame whose registration fails is not lost: constant-velocity pose, its rotation refit on the
    # bearings of the newest reference's descriptor matches, then a near + far refit if enough pairs agree
    stereo_fallback: bool = False
    threads: int = 1  # threads registering the ISLAM references in parallel
    constant_velocity: bool = True  # predict each pose from the last motion (else from the last pose)
    max_lost: int = 15  # consecutive lost frames before tracking restarts from the last pose (0 = never)
    max_jump_translation: float = 0.15  # m per frame: candidates further from the prediction are rejected
    max_jump_rotation_deg: float = 15.0  # deg per frame, likewise
    seed: int = 0  # seed of RANSAC's random choices


@dataclass
class DepthFilterConfig:
    """DIF, the conditional averaging depth filter (docs/references.md §3, docs/slam.md)."""

    enabled: bool = False  # run DIF on every frame (off by default: no gain measured, docs/slam.md)
    window: int = 2  # K previous filtered frames warped into the current one (0 = spatial only)
    spatial_radius: int = 1  # window half-size of the spatial averaging (0 = temporal only)
    tolerance_a: float = 0.01  # agreement tolerance = a + b * z^2 (metres)
    tolerance_b: float = 0.0035  # see tolerance_a (1/m)
    min_support: int = 3  # agreeing samples (besides the pixel itself) needed to keep a pixel
    min_depth: float = 0.3  # metres: depth outside [min_depth, max_depth] is dropped
    max_depth: float = 5.0  # metres: see min_depth


@dataclass
class KeyframeConfig:
    min_translation: float = 0.10  # metres moved since the last keyframe
    min_rotation_deg: float = 10.0  # degrees turned since the last keyframe
    max_gap: int = 15  # frames: a keyframe at least every max_gap frames


@dataclass
class LoopConfig:
    """Sharpness-gated loop closure (docs/references.md §4, docs/slam.md)."""

    enabled: bool = True  # detect loops and optimise the pose graph
    # sharpness gate: measure > factor * median(measure of the previous window frames).
    # "n_detected" is the thesis' count of detected features (FAST corners at ORB's threshold
    # before ORB keeps the best features.n_features: rgbdslam.frontend.features.count_detections). "response" =
    # sum of the ORB responses of the kept key points (the default before 2026-11-30, docs/slam.md).
    sharpness_measure: Literal["n_detected", "response"] = "n_detected"
    sharpness_factor: float = 1.2  # a frame is sharp when its measure exceeds this times the window's median
    sharpness_window: int = 20  # frames in the sharpness gate's median
    sharpness_min_history: int = 5  # frames seen before the gate can open
    # also search a frame when none of the last query_gap frames was searched (0 = sharp frames
    # only, the thesis' gate): where every frame is equally sharp the gate never opens and a
    # revisit goes unnoticed (docs/slam.md, benchmarks.md "Synthetic variants")
    query_gap: int = 5
    # candidate search
    index: Literal["lsh", "brute"] = "lsh"  # keyframe descriptor index for the candidate search (lsh or brute force)
    lsh_tables: int = 8  # hash tables, each keyed on lsh_bits random descriptor bits
    lsh_bits: int = 24  # descriptor bits per LSH key
    min_votes: int = 20  # query descriptors colliding with a keyframe before it is a candidate
    skip_recent: int = 20  # keyframes
    max_candidates: int = 3  # keyframes verified per query
    seed: int = 0  # seed of the LSH bit choice
    # verification
    min_inliers: int = 40  # inliers a loop's registration needs
    max_residual: float = 0.02  # metres: largest mean residual of an accepted loop registration
    max_loops_per_frame: int = 1  # loop edges added per query frame
    stop_at_first: bool = False  # verify candidates in vote order and stop at max_loops_per_frame loops
    # agreement with the current estimate: |T_loop - T_est| < bound + drift_ratio * travelled
    consistency_translation: float = 0.3  # metres: a loop may disagree with the estimate this much (+ drift ratio)
    consistency_rotation_deg: float = 15.0  # degrees: see consistency_translation
    drift_ratio_translation: float = 0.1  # extra metres allowed per metre travelled since the keyframe
    drift_ratio_rotation: float = 0.1  # extra degrees allowed per degree turned since the keyframe
    # relocalisation after a tracking loss (no estimate to agree with): a match into an older
    # segment links the segments only once relocalize_confirm matches (distinct frames or distinct
    # keyframes, within relocalize_window frames) put the camera at the same place in that segment,
    # within relocalize_translation / relocalize_rotation_deg; 1 = the first sound match links
    relocalize_confirm: int = 2
    relocalize_window: int = 15  # frames a match waits for its confirmation
    relocalize_translation: float = 0.1  # metres: two relocalisation matches agree within this
    relocalize_rotation_deg: float = 5.0  # degrees: see relocalize_translation
    # tracking against a fixed map (--localize; rgbdslam/session/tracking.py): once relocalised,
    # every map_track_every-th frame is registered against the map_track_neighbours map keyframes
    # nearest its predicted map pose; a registration that agrees with the prediction (within
    # relocalize_translation / _rotation_deg plus the drift ratios times the travel since the last
    # anchoring) is an edge to the map; odometry carries the pose between. 0 = off (loops only)
    map_track_every: int = 1
    map_track_neighbours: int = 2  # map keyframes registered per tracked frame
    map_track_distance: float = 1.0  # metres: largest distance between camera centres of a neighbour
    map_track_angle_deg: float = 45.0  # degrees: largest angle between the viewing directions of a neighbour
    # metres: matching guided by the prediction (3-D neighbours within this gate, no RANSAC pre-filter;
    # an unguided registration with the nearest neighbour when no guided one agrees); 0 = unguided only
    map_track_gate: float = 0.05
    # a frame with map edges becomes a keyframe only every map_track_keyframe_every-th anchored frame
    # (or when the keyframe policy wants one); the other frames' map edges go to the last keyframe,
    # composed with the odometry since it (its covariance added). 1 = every anchored frame a keyframe
    map_track_keyframe_every: int = 0  # 0 = never forced: map edges always go to the last keyframe


@dataclass
class BackendConfig:
    """GTSAM pose graph over keyframes (docs/slam.md)."""

    enabled: bool = False  # a graph of odometry edges only; loop.enabled (the default) builds it anyway
    init: Literal["masat", "weighted_masat", "odometry", "spanning_tree", "isam2"] = "masat"  # initial guess
    robust_kernel: Literal["none", "huber", "cauchy"] = "cauchy"  # applied to loop edges
    kernel_width: float = 1.0  # in whitened units (sigmas)
    kernel_chain_scaling: bool = True  # widen each loop's kernel by the odometry drift expected between its ends
    isam2: bool = True  # incremental update whenever a loop edge arrives
    isam2_extra_updates: int = 4  # extra iSAM2 relinearisation steps after each loop
    optimizer: Literal["lm", "gn"] = "lm"  # final batch optimisation
    max_iterations: int = 100  # iterations of the final batch optimisation
    relative_error_tol: float = 1e-6  # the batch optimisation stops when the error changes less than this (relative)
    prior_sigma: float = 1e-4  # first keyframe's prior (rad and metres)


@dataclass
class LandmarksConfig:
    """Map-based tracking: a persistent landmark map (spec section 6, docs/slam.md 'Landmark map')."""

    enabled: bool = False  # track against the persistent landmark map (docs/slam.md, "Landmark map")
    # how the map pose combines with the frame-to-frame registration (registration.method):
    # 'seed' = the registration's pose predicts, the map pose replaces it (kept when the map fails);
    # 'fuse' = the information-weighted mean of both (the registration's per-frame information,
    # the map pose's from its reprojection refine); 'filter' = as fuse, the registration's covariance
    # plus the last output's (carried from frame to frame) as the prediction's
    mode: Literal["seed", "fuse", "filter"] = "fuse"
    search_radius: float = 10.0  # pixels around a landmark's projection
    max_hamming: int = 50  # largest Hamming distance of a landmark-to-feature descriptor match
    max_depth: float = 5.0  # metres: landmarks further from the camera are not searched, features not mapped
    ransac_threshold: float = 0.03  # metres: inlier distance of the map pose RANSAC
    ransac_iterations: int = 100  # minimal samples drawn by the map pose RANSAC
    min_inliers: int = 30  # fewer: the map pose is not used for this frame
    max_correction: float = 0.03  # metres / degrees: a map pose further from the registration's is rejected
    max_correction_deg: float = 2.0  # degrees: see max_correction
    sampling: Literal["old_first", "uniform"] = "old_first"  # RANSAC samples: oldest landmarks first (thesis) or uniform
    # after RANSAC + weighted 3-D refit: 'reprojection' = motion-only Gauss-Newton on pixel and
    # inverse-depth residuals (whitened; Huber), inliers re-gated at chi_gate sigmas; 'rigid' = stop there
    # (no information: the map pose replaces the registration's); 'points' = stop there too, with the
    # information of a 3-D fit (the registration's formula: per-axis sigma from the RMS residual), fused
    refine: Literal["reprojection", "rigid", "points"] = "reprojection"  # after RANSAC: reprojection GN, rigid refit, or 3-D fit fused
    chi_gate: float = 3.0  # sigmas: inliers re-gated after the reprojection refine
    # Gauss-Newton iterations of each reprojection refine pass (a map pose runs two passes, three with
    # adaptive_noise, each from the last one's pose); 3 is ~7 % cheaper (docs/benchmarks.md "Landmark map speed: the top view ...")
    refine_iterations: int = 5
    # the landmark's covariance in the reprojection refine: 'full' = its 3x3 carried through the
    # projection (along the ray into the inverse depth); 'isotropic' = sqrt(trace/3) in every direction
    landmark_cov: Literal["full", "isotropic"] = "full"
    # the map pose's key point and depth noise rescaled per frame by the robust scale of its residuals
    adaptive_noise: bool = True
    fuse_scale: float = 0.4  # fuse/filter modes: the registration's information is multiplied by this (calibrated)
    # fuse/filter: when the two poses' disagreement (its Mahalanobis² median over the last this many frames,
    # / 5.35) is k > 1 times what their informations say, the map pose's covariance grows until it explains
    # the excess (0 = off): the map pose only gets the weight its agreement with the registration supports
    consistency_window: int = 30
    old_fraction: float = 0.5  # old_first: minimal samples drawn from this oldest share of the matches
    # static Kalman filter of the positions; observation noise along the ray a + b z^2 (m), across it
    # z sigma_px / f; process noise per step (m)
    kalman: bool = True  # smooth landmark positions with the static Kalman filter
    depth_noise_a: float = 0.001  # metres: constant term of the depth noise along the ray
    depth_noise_b: float = 0.002  # per metre: z^2 term of the depth noise along the ray
    sigma_px: float = 1.0  # pixels: key point noise across the ray
    process_noise: float = 0.0002  # metres per step: Kalman process noise of a landmark position
    min_seen: int = 3  # landmarks seen fewer times cull_after frames after they were made are culled
    cull_after: int = 30  # frames after its creation a rarely seen landmark is culled (see min_seen)
    store: Literal["single", "multi"] = "multi"  # landmark store: one k-d tree or the logarithmic method
    store_n1: int = 3500  # multi-tree store: size of the smallest tree
    store_q: float = 5.5  # multi-tree store: size ratio of consecutive trees
    new_min_distance: float = 5.0  # pixels: a keyframe feature this close to a projected landmark makes no new one
    old_age: int = 100  # frames: a matched landmark first seen this long ago counts as "old" (run.json)
    revisit_max_correction: float = 0.1  # metres: a re-measured loop edge further from the registration's is kept as it was
    revisit_max_correction_deg: float = 5.0  # degrees: see revisit_max_correction
    # frames: a landmark not seen for longer is "stale" (an earlier visit of the place; the map is not
    # corrected between visits, so it carries other drift than the landmarks made since) and is left out
    # of the frame's map pose (0 = never); with stale_check it joins when its own pose agrees with the
    # current landmarks' within the chi-square gate stale_gate (6 dof) of their joint covariance
    stale_after: int = 30
    stale_check: bool = True  # stale landmarks join the map pose when they agree (see stale_after)
    stale_gate: float = 12.59  # chi-square (6 dof, 95 %) of the stale-only against the current map pose
    # a loop edge i -> j is not added when frame j's map pose rests on at least this many landmarks that
    # existed at frame i (first seen at or before it): the map already ties the two (0 = every loop edge)
    map_loop_landmarks: int = 30
    # a loop edge i -> j re-measured against the landmarks first seen within loop_window frames of keyframe
    # i: projected with the edge's pose (kf_pose[i] T_ij) and matched within loop_search_radius px, the pose
    # of j against them (RANSAC + reprojection refine) gives T_ij = kf_pose[i]^-1 P_j and its information
    # (pixels, not the registration's 3-D points: far sharper at Kinect depth noise); kept as it was when
    # fewer than loop_min_inliers agree or the pose is further than revisit_max_correction from the edge's
    loop_refine: bool = True
    loop_refine_scaled: bool = True  # the re-measured edge's information divided by the map pose's consistency scale
    # fewer inliers: the edge stays the registration's (the older end's landmarks only at the image border:
    # measured 11-48 mm off the truth with 46-126 inliers, 1-3 mm with 140-840)
    loop_min_inliers: int = 100
    loop_window: int = 30  # frames around the loop's older keyframe whose landmarks re-measure the edge
    loop_search_radius: float = 20.0  # pixels around a landmark's projection with the loop edge's pose
    # windowed local bundle adjustment on every new keyframe (GTSAM, stereo-style factors)
    local_ba: bool = False  # windowed local bundle adjustment on every new keyframe
    ba_window: int = 5  # keyframes optimised; older keyframes seeing their landmarks are held fixed
    ba_iterations: int = 5  # Levenberg-Marquardt iterations of one local BA
    # the local BA's solver: 'schur' = NumPy Levenberg-Marquardt with the landmarks eliminated in closed
    # form (the Schur complement; GTSAM's LM step for step, ~10x faster at this size); 'gtsam' = GTSAM's graph
    ba_solver: Literal["schur", "gtsam"] = "schur"
    ba_max_landmarks: int = 1000  # landmarks in one local BA (those seen by most keyframes)
    ba_baseline: float = 0.08  # virtual stereo baseline (m) turning depth into a disparity
    ba_huber: float = 1.345  # robust kernel width (whitened)
    ba_landmark_prior: bool = True  # each landmark's Kalman position and covariance as a prior in local BA
    # metres added (in quadrature, every direction) to the prior's Kalman sigma: the filter counts every
    # frame's observation as independent, but they share the frames' pose errors
    ba_prior_floor: float = 0.004
    ba_min_observations: int = 30  # a keyframe observing fewer of the optimised landmarks is left out
    ba_max_move: float = 0.05  # metres: a solution moving a keyframe further is dropped (bad convergence)
    ba_max_move_deg: float = 3.0  # degrees: see ba_max_move
    # how the frames between two keyframes follow a local BA's corrections: 'rigid' = with their own
    # (older) keyframe's; 'interpolate' = along the geodesic from their keyframe's correction to the
    # next keyframe's, by frame index (a keyframe the BA did not move: no correction), so the
    # trajectory does not jump where one keyframe's frames end and the next keyframe begins
    ba_frames: Literal["rigid", "interpolate"] = "rigid"
    # ORB key points per frame for the landmark map (0 = features.n_features): frames are detected with
    # this many; the registration, loop closure and the rest keep the strongest features.n_features of
    # them (per pyramid level, ORB's budget), the map matches and makes landmarks from all
    n_features: int = 0
    seed: int = 0  # RANSAC seed of the map pose


@dataclass
class MappingConfig:
    enabled: bool = True  # fuse the map at the end of a run
    # which frames are fused: run.json keyframes (else frames chosen by motion) or every tracked frame
    keyframes_only: bool = True
    live: bool = True  # fuse keyframes while tracking (keyframes_only); false: fuse after the run
    # a keyframe whose points moved by less than this many voxels (translation + rotation angle x
    # depth_max) stays where the live map integrated it; larger: less re-integration, a map further from the final poses
    live_tolerance: float = 0.25
    # niceness of the map process (and of the plot process): tracking keeps its speed, the map takes
    # what tracking leaves; 0: the same priority as tracking (docs/mapping.md "Fusion while tracking")
    live_nice: int = 10
    # the newest keyframes wait this many keyframes before they go into the map: their poses still
    # move with every loop closure; at the end they are integrated once at their final poses
    live_lag: int = 8
    # a map process more than this many keyframes behind (beyond live_lag) works at tracking's priority
    # until it has caught up: what is left for after the last frame stays bounded on a busy machine
    live_backlog: int = 4
    # while the map has nothing else to do, the keyframes waiting within live_lag go into the map early
    # (one that then moves beyond live_tolerance is taken out again and waits): less is left for the end,
    # but the final poses often move the newest keyframes, which are then redone; off: not measured better
    live_early: bool = False
    # while the map has nothing else to do, a waiting keyframe's cloud part (its points reduced to the
    # voxel grid at its newest pose) is made and kept: at the end a waiting keyframe whose final pose is
    # within live_tolerance of it goes into the cloud (and the TSDF) at that pose with no cloud work, so
    # the cloud's outlier removal starts sooner; one that moves further is made again when idle
    live_cloud_ahead: bool = False
    select_translation: float = 0.05  # motion-based choice when run.json has no keyframes (m)
    select_rotation_deg: float = 5.0  # degrees: see select_translation
    undistort: bool = True  # remap colour and depth to the ideal pinhole before fusing
    depth_min: float = 0.3  # metres; depth outside [depth_min, depth_max] is ignored
    depth_max: float = 3.0  # metres: see depth_min
    # coloured point cloud
    voxel_size: float = 0.01  # voxel-grid downsampling of the merged cloud (m)
    cloud_pixel_stride: int = 2  # back-project every n-th pixel (a 1 cm voxel holds several anyway)
    outlier_neighbors: int = 20  # statistical outlier removal (0 = off)
    outlier_std: float = 2.0  # statistical outlier removal: standard deviations beyond the neighbours' mean distance
    # the cloud's outlier removal: "statistical" (Open3D's, outlier_neighbors / outlier_std) or "voxel"
    # (a point is kept when at least outlier_min_neighbors of the voxels within outlier_radius
    # voxels of its own are occupied: a few gathers from a dense occupancy grid, ~10x cheaper)
    outlier_method: Literal["statistical", "voxel"] = "statistical"
    outlier_min_neighbors: int = 4  # voxel outlier removal: occupied voxels around a kept point (0 = off)
    outlier_radius: int = 1  # voxel outlier removal: the neighbourhood is (2 r + 1)^3 voxels
    # TSDF mesh
    mesh: bool = True  # Open3D tensor VoxelBlockGrid TSDF + marching cubes
    tsdf_voxel: float = 0.01  # metres: TSDF voxel size
    sdf_trunc: float = 0.04  # metres: TSDF truncation distance
    mesh_min_frames: int = 2  # voxels seen by fewer frames are left out of the mesh
    tsdf_initial_blocks: int = 2000  # 8^3-voxel blocks preallocated (the hash map grows)
    # 2-D occupancy map (docs/references.md §6)
    map2d: bool = True
    grid_resolution: float = 0.05  # metres per cell
    gravity: Literal["auto", "accelerometer", "camera"] = "auto"  # up direction hint for the floor
    floor_max_tilt_deg: float = 20.0  # a floor plane's normal is within this of "up"
    floor_distance: float = 0.02  # RANSAC inlier distance of the floor plane (m)
    floor_ransac_iterations: int = 500  # RANSAC iterations of the floor plane search
    floor_band: float = 0.05  # |height| below this = floor point (m)
    obstacle_min_height: float = 0.10  # points between these heights above the floor occupy a cell
    obstacle_max_height: float = 1.80  # metres: see obstacle_min_height
    obstacle_min_points: int = 3  # points needed to mark a cell occupied
    seed: int = 0  # seed of the floor RANSAC


@dataclass
class StereoConfig:
    """Depth from a rectified stereo pair (KITTI, EuRoC, stereo folders; docs/stereo.md)."""

    depth: Literal["sparse", "sgbm"] = "sparse"  # tracking: row-matched ORB key points, or OpenCV SGBM
    map_depth: Literal["same", "sparse", "sgbm"] = "sgbm"  # what `fuse` re-reads for the map ("same" = depth)
    # disparity noise (pixels) each method implies: depth sigma = z^2 * sigma / (fx * baseline)
    sigma_disparity_sparse: float = 0.12  # measured: zsad_v refinement, synthetic exact depth and KITTI consistency
    sigma_disparity_sgbm: float = 0.5  # disparity noise (px) of SGBM depth, for the depth noise model
    max_disparity: int = 128  # search range (pixels); SGBM rounds it up to a multiple of 16
    min_disparity: float = 0.5  # smaller disparities (farther than fx * B / this) give no depth
    row_tolerance: float = 2.0  # sparse: |v_left - v_right| allowed for a match (pixels)
    max_hamming: int = 50  # sparse: descriptor distance cap
    ratio: float = 0.9  # sparse: best / second-best Hamming distance along the row band
    # sparse: how a left key point finds its partner in the right image: "orb" = ORB key points of the right
    # image matched along the row by descriptor; "row" = no right ORB: zero-mean SAD along the row on a
    # 1/row_scale image (OpenCV cost volume), unique best (row_ratio), then the sub-pixel refinement
    sparse_search: Literal["orb", "row"] = "orb"
    right_features: int = 2  # sparse orb: ORB budget of the right image, times features.n_features (no grid)
    row_scale: int = 4  # sparse row: the coarse search runs on images reduced by this factor
    row_ratio: float = 0.8  # sparse row: best coarse cost < this x the best one >1 coarse pixel away
    patch_radius: int = 5  # sparse: SAD patch half-size of the sub-pixel refinement
    search_radius: int = 4  # sparse: SAD search +- pixels around the descriptor match
    # sparse: sub-pixel refinement: "zsad_v" = zero-mean SAD + equiangular fit; "centre_parabola" = the
    # method before (patch minus its centre pixel, parabola): biased toward whole pixels (docs/stereo.md)
    subpixel: Literal["zsad_v", "centre_parabola"] = "zsad_v"
    sgbm_block_size: int = 5  # SGBM matching block size (odd, pixels)
    sgbm_uniqueness: int = 10  # SGBM uniqueness ratio (%): the best match must win by this margin
    sgbm_scale: float = 1.0  # SGBM on an image resized by this factor (0.5: ~4x faster, coarser)


@dataclass
class OutputConfig:
    rerun: bool = False  # stream to a spawned Rerun viewer (needs a display)
    rerun_save: str | None = None  # record to this .rrd file
    rerun_image_width: int = 320  # images are logged at this width (aspect kept)
    rerun_log_every: int = 1  # log images every n-th frame (poses/scalars every frame)
    plots: bool = True  # write the evaluation plots into RUN_DIR/plots when the sequence has ground truth


@dataclass
class Config:
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    features: FeaturesConfig = field(default_factory=FeaturesConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    depth_filter: DepthFilterConfig = field(default_factory=DepthFilterConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    landmarks: LandmarksConfig = field(default_factory=LandmarksConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def dump(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


# --------------------------------------------------------------------------- validation


def _check_value(key: str, value: Any, hint: Any) -> Any:
    """Return ``value`` converted to ``hint`` or raise ConfigError naming ``key``."""
    origin = get_origin(hint)
    if origin is Literal:
        allowed = get_args(hint)
        if value not in allowed:
            raise ConfigError(
                f"config key '{key}' must be one of {', '.join(map(str, allowed))}; got {shorten(value)}"
            )
        return value
    if origin in (typing.Union, types.UnionType):
        args = get_args(hint)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _check_value(key, value, a)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(errors[0] if errors else f"config key '{key}' has an invalid value {shorten(value)}")
    if hint is bool:
        if isinstance(value, bool):
            return value
    elif hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif hint is float:
        if isinstance(value, str):  # YAML 1.1 reads "1e-8" (no dot) as a string
            try:
                value = float(value)
            except ValueError:
                pass
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(value):
                raise ConfigError(f"config key '{key}' must be a finite number; got {shorten(value)}")
            return float(value)
    elif hint is str:
        if isinstance(value, str):
            return value
    else:  # pragma: no cover - only the types above are used
        return value
    raise ConfigError(
        f"config key '{key}' expects {getattr(hint, '__name__', hint)}; got {shorten(value)}"
    )


# Ranges. Lower bounds: every number must be >= 0 unless listed in SIGNED; those in POSITIVE must
# be > 0 (integers: >= 1); BOUNDS gives closed intervals [lo, hi]. Upper bounds: every numeric key
# needs one, in BOUNDS or MAXIMA, that its consumer accepts (a C int for OpenCV/GTSAM/Open3D
# arguments and seeds, a memory or time budget for sizes and iteration counts), so that an absurd
# value stops before any work instead of failing in a library after the run. A key without an
# upper bound fails tests/test_config.py (every key of Config is walked with boundary values);
# meanwhile it gets DEFAULT_MAXIMA. ORDERED pairs (a, b) of one section need a < b.
C_INT_MAX = 2**31 - 1
SIGNED = {"registration.beta", "mapping.obstacle_min_height", "mapping.obstacle_max_height", "dataset.offset"}
POSITIVE = {
    "dataset.max_difference", "dataset.max_frames",
    "dataset.stride", "dataset.reader_threads",
    "features.n_features", "features.n_levels", "features.fast_threshold", "features.grid_rows",
    "features.grid_cols",
    "matching.ratio", "matching.prefilter_threshold", "matching.prefilter_iterations", "matching.max_depth",
    "matching.depth_edge_jump",
    "registration.ransac_iterations", "registration.ransac_threshold", "registration.max_iterations",
    "registration.e_start", "registration.e_min", "registration.mp", "registration.alpha",
    "registration.reject_translation", "registration.reject_rotation", "registration.pregate",
    "registration.guided_gate", "registration.predicted_gate", "registration.joint_gate",
    "registration.threads", "registration.noise_refit_huber", "registration.max_jump_translation", "registration.max_jump_rotation_deg",
    "depth_filter.max_depth",
    "keyframes.max_gap",
    "loop.sharpness_factor", "loop.sharpness_window", "loop.lsh_tables", "loop.lsh_bits", "loop.min_votes",
    "loop.max_candidates", "loop.min_inliers", "loop.max_residual", "loop.max_loops_per_frame",
    "loop.consistency_translation", "loop.consistency_rotation_deg",
    "loop.relocalize_confirm", "loop.relocalize_window", "loop.relocalize_translation",
    "loop.relocalize_rotation_deg", "loop.map_track_neighbours", "loop.map_track_distance",
    "loop.map_track_angle_deg",
    "backend.kernel_width", "backend.max_iterations", "backend.relative_error_tol", "backend.prior_sigma",
    "mapping.depth_max", "mapping.voxel_size", "mapping.cloud_pixel_stride", "mapping.outlier_std",
    "mapping.tsdf_voxel", "mapping.sdf_trunc", "mapping.mesh_min_frames", "mapping.tsdf_initial_blocks",
    "mapping.grid_resolution", "mapping.floor_max_tilt_deg", "mapping.floor_distance",
    "mapping.floor_ransac_iterations", "mapping.floor_band", "mapping.obstacle_min_points",
    "output.rerun_image_width", "output.rerun_log_every",
    "stereo.sigma_disparity_sparse", "stereo.sigma_disparity_sgbm", "stereo.max_disparity", "stereo.min_disparity",
    "stereo.row_tolerance", "stereo.right_features", "stereo.row_ratio", "stereo.patch_radius", "stereo.search_radius",
    "stereo.sgbm_block_size",
    "landmarks.search_radius", "landmarks.max_depth", "landmarks.ransac_threshold", "landmarks.ransac_iterations",
    "landmarks.min_seen", "landmarks.store_n1", "landmarks.old_age", "landmarks.ba_window",
    "landmarks.ba_iterations", "landmarks.ba_max_landmarks", "landmarks.ba_baseline", "landmarks.ba_huber", "landmarks.sigma_px",
    "landmarks.chi_gate", "landmarks.refine_iterations", "landmarks.max_correction", "landmarks.max_correction_deg",
    "landmarks.ba_max_move", "landmarks.ba_max_move_deg",
    "landmarks.revisit_max_correction", "landmarks.revisit_max_correction_deg",
    "landmarks.fuse_scale", "landmarks.loop_search_radius",
}
BOUNDS = {
    "features.scale_factor": (1.0 + 1e-6, 4.0), "features.n_levels": (1, 16), "features.patch_size": (2, 255),
    "features.edge_threshold": (1, 255), "matching.ratio": (0.0, 1.0), "matching.max_hamming": (0, 256),
    "registration.min_agreement": (0.0, 1.0), "registration.min_points": (3, 10**9),
    "registration.predicted_min_inliers": (3, 10**9), "loop.min_inliers": (3, 10**9),
    # LSH bucket keys hold the table id above lsh_bits key bits in an int64
    "loop.lsh_bits": (1, 40),
    "mapping.floor_max_tilt_deg": (0.0, 90.0), "mapping.live_tolerance": (0.0, 10.0),
    "mapping.live_nice": (0, 19), "mapping.live_lag": (0, 10000), "mapping.live_backlog": (0, 10000),
    "stereo.ratio": (0.0, 1.0), "stereo.max_hamming": (0, 256), "stereo.sgbm_scale": (0.1, 1.0),
    "stereo.max_disparity": (1, 1024), "stereo.sgbm_block_size": (1, 31),
    # voxel keys have 21 bits per axis (+-1 km at 1 mm): finer grids are not sane
    "mapping.voxel_size": (1e-3, 10.0), "mapping.tsdf_voxel": (1e-3, 10.0), "mapping.grid_resolution": (1e-3, 100.0),
    # raw depth units per metre: below 1e-3 a 16-bit depth image would reach past 65 km
    "dataset.depth_scale": (1e-3, 1e6), "dataset.depth_correction": (0.1, 10.0),
    "dataset.offset": (-2e9, 2e9),  # seconds: Unix time stamps are ~1.8e9 (2026)
    "registration.beta": (-100.0, 100.0),
    "mapping.obstacle_min_height": (-1e3, 1e3), "mapping.obstacle_max_height": (-1e3, 1e3),
    "landmarks.min_inliers": (3, 10**9), "landmarks.old_fraction": (0.0, 1.0),
    "landmarks.store_q": (1.0 + 1e-6, 100.0),
    "landmarks.max_hamming": (0, 256),
    "stereo.row_scale": (1, 16),
    # voxel outlier removal: (2 r + 1)^3 - 1 gathers; r = 3 is already 342 of them
    "mapping.outlier_radius": (1, 3), "mapping.outlier_min_neighbors": (0, 342),
}
# Upper bounds of the keys whose range is not in BOUNDS (closed: the value itself is accepted).
MAXIMA = {
    # dataset: frame counts and indices fit a C int; prefetched frames are held in memory
    "dataset.max_difference": 1e4, "dataset.first_frame": 10**9, "dataset.max_frames": 10**9,
    "dataset.stride": 10**6, "dataset.prefetch": 64, "dataset.reader_threads": 64,
    # features: OpenCV's ORB takes C ints; n_features x n_features Hamming matrices (~1 GB at 10000)
    "features.n_features": 10_000, "features.fast_threshold": 255, "features.grid_rows": 64,
    "features.grid_cols": 64, "features.rolling_shutter": 0.1,
    # matching: RANSAC hypotheses are drawn and scored at once (~3 kB each); cv2 gets 10x as maxIters
    "matching.prefilter_threshold": 1e3, "matching.prefilter_iterations": 20_000,
    "matching.min_depth": 1e3, "matching.max_depth": 1e3,
    "matching.depth_edge_radius": 32, "matching.depth_edge_jump": 10.0,
    "registration.ransac_iterations": 20_000, "registration.ransac_threshold": 10.0,
    "registration.max_iterations": 1000, "registration.e_start": 100.0, "registration.e_min": 100.0,
    "registration.mp": 64, "registration.alpha": 100.0, "registration.min_error": 100.0,
    "registration.reject_translation": 100.0, "registration.reject_rotation": 100.0,
    "registration.pregate": 100.0, "registration.guided_gate": 100.0, "registration.predicted_gate": 100.0,
    "registration.joint_gate": 100.0, "registration.threads": 256, "registration.max_lost": 10**6,
    "registration.max_jump_translation": 1e3, "registration.max_jump_rotation_deg": 360.0,
    "registration.seed": C_INT_MAX,  # cv2.setRNGSeed takes a C int
    # depth filter: each of the window's frames is warped into the current one
    "depth_filter.window": 32, "depth_filter.spatial_radius": 32, "depth_filter.tolerance_a": 10.0,
    "depth_filter.tolerance_b": 10.0, "depth_filter.min_support": 10_000, "depth_filter.min_depth": 1e3,
    "depth_filter.max_depth": 1e3,
    "keyframes.min_translation": 1e4, "keyframes.min_rotation_deg": 360.0, "keyframes.max_gap": 10**6,
    # loop closure: every LSH table indexes every keyframe descriptor (memory grows with lsh_tables)
    "loop.sharpness_factor": 1e3, "loop.sharpness_window": 10**5, "loop.sharpness_min_history": 10**5,
    "loop.query_gap": 10**6, "loop.lsh_tables": 64, "loop.min_votes": 10**6, "loop.skip_recent": 10**6,
    "loop.max_candidates": 100, "loop.seed": C_INT_MAX, "loop.max_residual": 10.0,
    "loop.max_loops_per_frame": 100, "loop.consistency_translation": 1e4, "loop.consistency_rotation_deg": 360.0,
    "loop.drift_ratio_translation": 100.0, "loop.drift_ratio_rotation": 100.0,
    "loop.relocalize_confirm": 100, "loop.relocalize_window": 10**5, "loop.relocalize_translation": 1e4,
    "loop.relocalize_rotation_deg": 360.0, "loop.map_track_every": 10**6, "loop.map_track_keyframe_every": 10**6,
    "loop.map_track_neighbours": 100,
    "loop.map_track_distance": 1e4, "loop.map_track_angle_deg": 180.0, "loop.map_track_gate": 100.0,
    # back end: GTSAM takes C ints for iteration counts
    "backend.kernel_width": 1e6, "backend.isam2_extra_updates": 1000, "backend.max_iterations": 100_000,
    "backend.relative_error_tol": 1.0, "backend.prior_sigma": 1e3,
    # mapping: Open3D takes C ints; a TSDF block (8^3 voxels) holds ~10 kB before the hash map grows
    "mapping.select_translation": 1e4, "mapping.select_rotation_deg": 360.0, "mapping.depth_min": 1e3,
    "mapping.depth_max": 1e3, "mapping.cloud_pixel_stride": 1024, "mapping.outlier_neighbors": 1000,
    "mapping.outlier_std": 1e3, "mapping.sdf_trunc": 100.0, "mapping.mesh_min_frames": 10**6,
    "mapping.tsdf_initial_blocks": 50_000, "mapping.floor_distance": 100.0,
    "mapping.floor_ransac_iterations": 100_000, "mapping.floor_band": 100.0, "mapping.obstacle_min_points": 10**6,
    "mapping.seed": C_INT_MAX,  # Open3D's random seed is a C int
    "output.rerun_image_width": 8192, "output.rerun_log_every": 10**6,
    # stereo: disparities and noise in pixels, ORB budgets of the right image as a multiple of the left's
    "registration.noise_refit_huber": 100.0, "registration.far_baselines": 1e4,
    "stereo.sigma_disparity_sparse": 100.0, "stereo.sigma_disparity_sgbm": 100.0,
    "stereo.min_disparity": 1000.0, "stereo.row_tolerance": 100.0,
    "stereo.right_features": 4, "stereo.patch_radius": 64, "stereo.search_radius": 64,
    "stereo.sgbm_uniqueness": 100, "stereo.row_ratio": 1.0,
    # landmark map: pixels, metres and counts of one frame's search; BA sizes bound its GTSAM problem
    "landmarks.search_radius": 1000.0, "landmarks.max_depth": 1e3, "landmarks.ransac_threshold": 10.0,
    "landmarks.ransac_iterations": 20_000, "landmarks.max_correction": 100.0, "landmarks.max_correction_deg": 360.0,
    "landmarks.chi_gate": 100.0, "landmarks.refine_iterations": 100, "landmarks.fuse_scale": 1e6,
    "landmarks.depth_noise_a": 10.0, "landmarks.depth_noise_b": 10.0,
    "landmarks.sigma_px": 100.0, "landmarks.process_noise": 10.0, "landmarks.min_seen": 10**6,
    "landmarks.cull_after": 10**6, "landmarks.store_n1": 10**7, "landmarks.new_min_distance": 1000.0,
    "landmarks.old_age": 10**9, "landmarks.ba_window": 100, "landmarks.n_features": 10_000, "landmarks.ba_iterations": 1000,
    "landmarks.ba_max_landmarks": 100_000, "landmarks.ba_baseline": 10.0, "landmarks.ba_huber": 100.0,
    "landmarks.ba_min_observations": 10**6, "landmarks.ba_prior_floor": 10.0, "landmarks.ba_max_move": 100.0, "landmarks.ba_max_move_deg": 360.0,
    "landmarks.revisit_max_correction": 100.0,
    "landmarks.revisit_max_correction_deg": 360.0,
    "landmarks.stale_after": 10**9, "landmarks.stale_gate": 1e6, "landmarks.map_loop_landmarks": 10**6,
    "landmarks.consistency_window": 10**6, 
    "landmarks.loop_window": 10**6, "landmarks.loop_min_inliers": 10**6, "landmarks.loop_search_radius": 1000.0,
    "landmarks.seed": C_INT_MAX,
}
DEFAULT_MAXIMA = {int: C_INT_MAX, float: 1e9}  # a key missing from BOUNDS/MAXIMA (a test fails on it)
ORDERED = [("matching.min_depth", "matching.max_depth"), ("depth_filter.min_depth", "depth_filter.max_depth"),
           ("mapping.depth_min", "mapping.depth_max"), ("mapping.obstacle_min_height", "mapping.obstacle_max_height"),
           ("stereo.min_disparity", "stereo.max_disparity")]


def value_range(key: str, kind: type) -> tuple[float, bool, float]:
    """``(lo, lo_open, hi)``: the values ``key`` (of type ``kind``, int or float) accepts are
    ``lo < v`` (``lo_open``) or ``lo <= v``, and ``v <= hi``."""
    lo, hi = BOUNDS.get(key, (None, None))
    if lo is None:
        lo = (1 if kind is int else 0.0) if key in POSITIVE else (-math.inf if key in SIGNED else 0)
    if hi is None:
        hi = MAXIMA.get(key, DEFAULT_MAXIMA[kind])
    return lo, key in POSITIVE and kind is float and key not in BOUNDS, hi


def _bound(x: int | float) -> str:
    """A range bound as written: whole numbers in full (2147483647, not 2.14748e+09)."""
    if isinstance(x, int) or (math.isfinite(x) and x == int(x) and abs(x) < 1e16):
        return str(int(x)) if abs(x) < 1e7 or x != 10 ** round(math.log10(abs(x))) else f"{x:g}"
    return f"{x:g}"


def check_range(key: str, v: int | float) -> None:
    """ConfigError naming ``key`` when ``v`` is outside its range (:func:`value_range`)."""
    lo, lo_open, hi = value_range(key, int if isinstance(v, int) else float)
    if key in BOUNDS:
        if not lo <= v <= hi:
            raise ConfigError(f"config key '{key}' must be between {_bound(lo)} and {_bound(hi)}; got {shorten(v)}")
        return
    if lo_open and not v > lo:
        raise ConfigError(f"config key '{key}' must be positive; got {shorten(v)}")
    if not v >= lo:
        raise ConfigError(f"config key '{key}' must " + (f"be at least {_bound(lo)}" if lo else "not be negative")
                          + f"; got {shorten(v)}")
    if not v <= hi:
        raise ConfigError(f"config key '{key}' must be at most {_bound(hi)}; got {shorten(v)}")


def validate_section(section: str, obj: Any) -> Any:
    """Check one section's values: types (as for YAML input, so a section built in Python is
    held to the same rules) and ranges (:func:`check_range`, ORDERED); ConfigError names the key."""
    hints = get_type_hints(type(obj))
    for f in dataclasses.fields(obj):
        key = f"{section}.{f.name}"
        v = _check_value(key, getattr(obj, f.name), hints[f.name])
        setattr(obj, f.name, v)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        check_range(key, v)
    for a, b in ORDERED:
        if a.split(".")[0] == section:
            va, vb = getattr(obj, a.split(".")[1]), getattr(obj, b.split(".")[1])
            if not va < vb:
                raise ConfigError(f"config key '{a}' ({shorten(va)}) must be smaller than '{b}' ({shorten(vb)})")
    if section == "mapping":
        most = (2 * obj.outlier_radius + 1) ** 3 - 1
        if obj.outlier_min_neighbors > most:
            raise ConfigError(
                f"config key 'mapping.outlier_min_neighbors' ({obj.outlier_min_neighbors}) must be at most the "
                f"{most} voxels around a point at mapping.outlier_radius={obj.outlier_radius}")
    return obj


def validate(cfg: Config) -> Config:
    """Check every section (:func:`validate_section`)."""
    for section in dataclasses.fields(cfg):
        validate_section(section.name, getattr(cfg, section.name))
    lm = cfg.landmarks
    if 0 < lm.n_features < cfg.features.n_features:
        raise ConfigError(
            f"config key 'landmarks.n_features' ({lm.n_features}) must be 0 (off) or at least "
            f"'features.n_features' ({cfg.features.n_features})")
    if lm.n_features > cfg.features.n_features and cfg.features.grid_rows * cfg.features.grid_cols > 1:
        raise ConfigError(
            f"config key 'landmarks.n_features' ({lm.n_features}) cannot be used with a key-point grid "
            f"(features.grid_rows x grid_cols = {cfg.features.grid_rows} x {cfg.features.grid_cols}): the "
            f"registration's strongest subset would not follow the grid; set one of them off")
    return cfg


# keys that earlier versions had: still accepted (run folders keep their config.yaml) and ignored
RETIRED = {
    "loop.sigma_floor",  # loop edges carry their registration's information (one noise floor, in the front end)
    # options that measured no gain, removed with their code (docs/slam.md "Removed options", docs/frontend.md
    # "Scale bias"); an earlier run folder's config.yaml still names them and must load
    "landmarks.anchor_age",
    "landmarks.anchor_edges",
    "landmarks.anchor_info_scale",
    "landmarks.anchor_min_landmarks",
    "landmarks.ba_every",
    "landmarks.ba_handover",
    "landmarks.ba_noise_scale",
    "landmarks.ba_worker",
    "landmarks.consistency_floor",
    "landmarks.drift_sigma",
    "landmarks.global_ba",
    "landmarks.global_ba_frames",
    "landmarks.global_ba_iterations",
    "landmarks.global_ba_odometry",
    "landmarks.graph_information",
    "landmarks.loop_correct",
    "landmarks.match_old_bonus",
    "landmarks.observe",
    "landmarks.ransac_confidence",
    "landmarks.revisit_min_inliers",
    "landmarks.revisit_radius",
    "landmarks.sigma_px_scale",
    "matching.depth_edge_use",
}


def _apply(section_obj: Any, section: str, values: dict[str, Any], source: str) -> None:
    hints = get_type_hints(type(section_obj))
    for k, v in values.items():
        if f"{section}.{k}" in RETIRED:
            continue
        if k not in hints:
            known = ", ".join(hints)
            raise ConfigError(f"unknown config key '{cut(section)}.{cut(k)}' in {source}; known keys: {known}")
        setattr(section_obj, k, _check_value(f"{section}.{k}", v, hints[k]))


def merge(cfg: Config, data: dict[str, Any] | None, source: str = "config") -> Config:
    """Apply a nested mapping (as read from YAML) onto ``cfg`` in place and return it."""
    if not data:
        return cfg
    if not isinstance(data, dict):
        raise ConfigError(f"{source} must be a mapping of sections (dataset:, features:, ...)")
    sections = {f.name for f in dataclasses.fields(Config)}
    for section, values in data.items():
        if section not in sections:
            raise ConfigError(
                f"unknown config section '{cut(section)}' in {source}; known sections: {', '.join(sorted(sections))}"
            )
        if values is None:
            continue
        if not isinstance(values, dict):
            raise ConfigError(f"config section '{section}' in {source} must be a mapping")
        _apply(getattr(cfg, section), section, values, source)
    return cfg


def resolve_preset(name_or_path: str | Path):
    """A path to a YAML file, or the name of a preset shipped in the package (``tum_fr1``);
    returns the file (a Path or an ``importlib.resources`` Traversable)."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    presets = preset_files()
    if str(name_or_path) in presets:
        return presets[str(name_or_path)]
    names = ", ".join(sorted(presets)) or "(none: the package's presets are missing; reinstall rgbdslam)"
    raise ConfigError(f"config file {name_or_path} not found; give a YAML path or one of the presets: {names}")


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """Defaults, then the YAML file (if any), then ``section.key=value`` overrides."""
    cfg = Config()
    if path is not None:
        p = resolve_preset(path)
        data = load_yaml(read_text(p, "config file"), str(p), ConfigError)
        merge(cfg, data, str(p))
    for item in overrides:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise ConfigError(f"override '{cut(item)}' must look like section.key=value")
        key, raw = item.split("=", 1)
        section, name = key.split(".", 1)
        try:
            value = yaml.load(raw, Loader=StrictLoader) if raw != "" else None  # noqa: S506 - a SafeLoader
        except Refused as e:
            raise ConfigError(f"--set {shorten(item)}: the value {e.problem}") from None
        except yaml.YAMLError:
            value = raw
        merge(cfg, {section: {name: value}}, f"--set {cut(item)}")
    return validate(cfg)


# where one run writes its outputs: given on the command line (--rerun-save, --rerun), not part of a
# configuration that is given back to --config to repeat a run (it would overwrite the earlier recording)
RUN_OUTPUT_KEYS = {"output.rerun": False, "output.rerun_save": None}


def save_config(cfg: Config, path: str | Path, outputs: bool = True) -> None:
    """Write ``cfg`` as YAML atomically; ``outputs=False`` leaves the one-run output keys
    (:data:`RUN_OUTPUT_KEYS`) at their defaults, as a run folder's config.yaml does."""
    import copy

    from rgbdslam.io.atomic import atomic_write_text

    if not outputs:
        cfg = copy.deepcopy(cfg)
        for key, default in RUN_OUTPUT_KEYS.items():
            section, name = key.split(".")
            setattr(getattr(cfg, section), name, default)
    atomic_write_text(path, cfg.dump())
