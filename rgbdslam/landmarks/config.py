"""The ``landmarks`` config section: the persistent landmark map (:mod:`rgbdslam.configspec`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from rgbdslam.configspec import AtMost, C_INT_MAX, Key, Positive, Range


@dataclass
class LandmarksConfig:
    """Map-based tracking: a persistent landmark map (spec section 6, docs/landmarks.md)."""

    # upper bounds: pixels, metres and counts of one frame's search
    enabled: Annotated[bool, Key(
        "track every frame against the persistent landmark map (docs/landmarks.md); false = the "
        "frame-to-frame chain alone (the thesis preset)")] = True
    mode: Annotated[Literal["seed", "fuse", "filter"], Key(
        "how the map pose combines with the frame-to-frame registration (registration.method): 'seed' = the "
        "registration's pose predicts, the map pose replaces it (kept when the map fails); 'fuse' = the "
        "information-weighted mean of both (the registration's per-frame information, the map pose's from its "
        "reprojection refine); 'filter' = as fuse, the registration's covariance plus the last output's (carried from "
        "frame to frame) as the prediction's")] = "fuse"
    search_radius: Annotated[float, Positive(1000.0, "pixels around a landmark's projection")] = 10.0
    max_hamming: Annotated[int, Range(0, 256, "largest Hamming distance of a landmark-to-feature descriptor match")] = 50
    max_depth: Annotated[float, Positive(1000.0,
        "metres: landmarks further from the camera are not searched, features not mapped; 10 = matching.max_depth's "
        "Kinect range (far points pin the rotation: docs/landmarks.md \"Far points\")")] = 10.0
    ransac_threshold: Annotated[float, Positive(10.0, "metres: inlier distance of the map pose RANSAC")] = 0.03
    ransac_iterations: Annotated[int, Positive(20_000,
        "minimal samples drawn by the map pose RANSAC (the landmark stage runs it only when the registration's pose has "
        "fewer than min_inliers inliers within ransac_threshold; --localize's map tracking always)")] = 100
    min_inliers: Annotated[int, Range(3, 10**9, "fewer: the map pose is not used for this frame")] = 30
    max_correction: Annotated[float, Positive(100.0,
        "metres / degrees: a map pose further from the registration's is rejected")] = 0.03
    max_correction_deg: Annotated[float, Positive(360.0, "degrees: see max_correction")] = 2.0
    sampling: Annotated[Literal["old_first", "uniform"], Key(
        "RANSAC samples: oldest landmarks first (thesis) or uniform")] = "old_first"
    refine: Annotated[Literal["reprojection", "rigid", "points"], Key(
        "after RANSAC + weighted 3-D refit: 'reprojection' = motion-only Gauss-Newton on pixel and inverse-depth "
        "residuals (whitened; Huber), inliers re-gated at chi_gate sigmas; 'rigid' = stop there (no information: the "
        "map pose replaces the registration's); 'points' = stop there too, with the information of a 3-D fit (the "
        "registration's formula: per-axis sigma from the RMS residual), fused")] = "reprojection"
    chi_gate: Annotated[float, Positive(100.0, "sigmas: inliers re-gated after the reprojection refine")] = 3.0
    refine_iterations: Annotated[int, Positive(100,
        "Gauss-Newton iterations of each reprojection refine pass (a map pose runs two passes, three with "
        "adaptive_noise, each from the last one's pose); 3 is ~7 % cheaper (docs/benchmarks.md \"Landmark map speed: "
        "the top view ...\")")] = 5
    landmark_cov: Annotated[Literal["full", "isotropic"], Key(
        "the landmark's covariance in the reprojection refine: 'full' = its 3x3 carried through the projection (along "
        "the ray into the inverse depth); 'isotropic' = sqrt(trace/3) in every direction")] = "full"
    adaptive_noise: Annotated[bool, Key(
        "the map pose's key point and depth noise rescaled per frame by the robust scale of its residuals")] = True
    fuse_scale: Annotated[float, Positive(1e6,
        "fuse/filter modes: the registration's information is multiplied by this (calibrated)")] = 0.4
    old_fraction: Annotated[float, Range(0.0, 1.0,
        "old_first: minimal samples drawn from this oldest share of the matches")] = 0.5
    # static Kalman filter of the positions; observation noise along the ray a + b z^2 (m), across it
    # z sigma_px / f; process noise per step (m)
    kalman: Annotated[bool, Key("smooth landmark positions with the static Kalman filter")] = True
    depth_noise_a: Annotated[float, AtMost(10.0, "metres: constant term of the depth noise along the ray")] = 0.001
    depth_noise_b: Annotated[float, AtMost(10.0, "per metre: z^2 term of the depth noise along the ray")] = 0.002
    sigma_px: Annotated[float, Positive(100.0, "pixels: key point noise across the ray")] = 1.0
    process_noise: Annotated[float, AtMost(10.0, "metres per step: Kalman process noise of a landmark position")] = 0.0002
    min_seen: Annotated[int, Positive(10**6,
        "landmarks seen fewer times cull_after frames after they were made are culled")] = 3
    cull_after: Annotated[int, AtMost(10**6,
        "frames after its creation a rarely seen landmark is culled (see min_seen)")] = 30
    store: Annotated[Literal["single", "multi"], Key("landmark store: one k-d tree or the logarithmic method")] = "multi"
    store_n1: Annotated[int, Positive(10**7, "multi-tree store: size of the smallest tree")] = 3500
    store_q: Annotated[float, Range(1.0 + 1e-6, 100.0, "multi-tree store: size ratio of consecutive trees")] = 5.5
    new_min_distance: Annotated[float, AtMost(1000.0,
        "pixels: a keyframe feature this close to a projected landmark makes no new one")] = 5.0
    old_age: Annotated[int, Positive(10**9,
        "frames: a matched landmark first seen this long ago counts as \"old\" (run.json)")] = 100
    revisit_max_correction: Annotated[float, Positive(100.0,
        "metres: a re-measured loop edge further from the registration's is kept as it was")] = 0.1
    revisit_max_correction_deg: Annotated[float, Positive(360.0, "degrees: see revisit_max_correction")] = 5.0
    stale_after: Annotated[int, AtMost(10**9,
        "frames: a landmark not seen for longer is \"stale\" (an earlier visit of the place; the map is not corrected "
        "between visits, so it carries other drift than the landmarks made since) and is left out of the frame's map "
        "pose (0 = never); with stale_check it joins when its own pose agrees with the current landmarks' within the "
        "chi-square gate stale_gate (6 dof) of their joint covariance")] = 30
    local_map_shared: Annotated[int, AtMost(10**6,
        "covisibility local map (ORB-SLAM's): a frame is matched only against the landmarks observed by its reference "
        "keyframe (the newest) and by the keyframes sharing at least this many landmarks with it (ORB-SLAM's "
        "covisibility edge threshold; 0 = every landmark the store returns near the camera)")] = 15
    stale_check: Annotated[bool, Key("stale landmarks join the map pose when they agree (see stale_after)")] = True
    stale_gate: Annotated[float, AtMost(1e6,
        "chi-square (6 dof, 95 %) of the stale-only against the current map pose")] = 12.59
    map_loop_landmarks: Annotated[int, AtMost(10**6,
        "a loop edge i -> j is not added when frame j's map pose rests on at least this many landmarks that existed at "
        "frame i (first seen at or before it): the map already ties the two (0 = every loop edge)")] = 30
    loop_refine: Annotated[bool, Key(
        "a loop edge i -> j re-measured against the landmarks first seen within loop_window frames of keyframe i: "
        "projected with the edge's pose (kf_pose[i] T_ij) and matched within loop_search_radius px, the pose of j "
        "against them (a map pose: refitted from the edge's inliers, RANSAC when too few; reprojection refine) gives "
        "T_ij = kf_pose[i]^-1 P_j and its information (pixels, not "
        "the registration's 3-D points: far sharper at Kinect depth noise); kept as it was when fewer than "
        "loop_min_inliers agree or the pose is further than revisit_max_correction from the edge's")] = True
    loop_min_inliers: Annotated[int, AtMost(10**6,
        "fewer inliers: the edge stays the registration's (the older end's landmarks only at the image border: "
        "measured 11-48 mm off the truth with 46-126 inliers, 1-3 mm with 140-840)")] = 100
    loop_window: Annotated[int, AtMost(10**6,
        "frames around the loop's older keyframe whose landmarks re-measure the edge")] = 30
    loop_search_radius: Annotated[float, Positive(1000.0,
        "pixels around a landmark's projection with the loop edge's pose")] = 20.0
    n_features: Annotated[int, AtMost(10_000,
        "ORB key points per frame for the landmark map (0 = features.n_features): frames are detected with this many; "
        "the registration, loop closure and the rest keep the strongest features.n_features of them (per pyramid "
        "level, ORB's budget), the map matches and makes landmarks from all")] = 0
    seed: Annotated[int, AtMost(C_INT_MAX, "RANSAC seed of the map pose")] = 0
