"""The ``loop`` config section: loop closure and tracking against the map keyframes (:mod:`rgbdslam.configspec`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from rgbdslam.configspec import AtMost, C_INT_MAX, Key, Positive, Range


@dataclass
class LoopConfig:
    """Sharpness-gated loop closure (docs/references.md §4, docs/slam.md)."""

    # upper bounds: every LSH table indexes every keyframe descriptor (memory grows with lsh_tables)
    enabled: Annotated[bool, Key("detect loops and optimise the pose graph")] = True
    sharpness_measure: Annotated[Literal["n_detected", "response"], Key(
        "sharpness gate: measure > factor * median(measure of the previous window frames). \"n_detected\" is the thesis' "
        "count of detected features (FAST corners at ORB's threshold before ORB keeps the best features.n_features: "
        "rgbdslam.frontend.features.count_detections). \"response\" = sum of the ORB responses of the kept key points "
        "(the default before 2026-11-30, docs/slam.md).")] = "n_detected"
    sharpness_factor: Annotated[float, Positive(1000.0,
        "a frame is sharp when its measure exceeds this times the window's median")] = 1.2
    sharpness_window: Annotated[int, Positive(100_000, "frames in the sharpness gate's median")] = 20
    sharpness_min_history: Annotated[int, AtMost(100_000, "frames seen before the gate can open")] = 5
    query_gap: Annotated[int, AtMost(10**6,
        "also search a frame when none of the last query_gap frames was searched (0 = sharp frames only, the thesis' "
        "gate): where every frame is equally sharp the gate never opens and a revisit goes unnoticed (docs/slam.md, "
        "benchmarks.md \"Synthetic variants\")")] = 5
    # candidate search
    index: Annotated[Literal["lsh", "brute"], Key(
        "keyframe descriptor index for the candidate search (lsh or brute force)")] = "lsh"
    lsh_tables: Annotated[int, Positive(64, "hash tables, each keyed on lsh_bits random descriptor bits")] = 8
    # LSH bucket keys hold the table id above lsh_bits key bits in an int64
    lsh_bits: Annotated[int, Range(1, 40, "descriptor bits per LSH key")] = 24
    min_votes: Annotated[int, Positive(10**6, "query descriptors colliding with a keyframe before it is a candidate")] = 20
    skip_recent: Annotated[int, AtMost(10**6,
        "the last this many keyframes of the current segment are no loop candidates")] = 20
    max_candidates: Annotated[int, Positive(100, "keyframes verified per query")] = 3
    seed: Annotated[int, AtMost(C_INT_MAX, "seed of the LSH bit choice")] = 0
    # verification
    min_inliers: Annotated[int, Range(3, 10**9, "inliers a loop's registration needs")] = 40
    max_residual: Annotated[float, Positive(10.0, "metres: largest mean residual of an accepted loop registration")] = 0.02
    max_loops_per_frame: Annotated[int, Positive(100, "loop edges added per query frame")] = 1
    stop_at_first: Annotated[bool, Key("verify candidates in vote order and stop at max_loops_per_frame loops")] = False
    # agreement with the current estimate: |T_loop - T_est| < bound + drift_ratio * travelled
    consistency_translation: Annotated[float, Positive(10000.0,
        "metres: a loop may disagree with the estimate this much (+ drift ratio)")] = 0.3
    consistency_rotation_deg: Annotated[float, Positive(360.0, "degrees: see consistency_translation")] = 15.0
    drift_ratio_translation: Annotated[float, AtMost(100.0,
        "extra metres allowed per metre travelled since the keyframe")] = 0.1
    drift_ratio_rotation: Annotated[float, AtMost(100.0, "extra degrees allowed per degree turned since the keyframe")] = 0.1
    relocalize_confirm: Annotated[int, Positive(100,
        "relocalisation after a tracking loss (no estimate to agree with): a match into an older segment links the "
        "segments only once relocalize_confirm matches (distinct frames or distinct keyframes, within "
        "relocalize_window frames) put the camera at the same place in that segment, within relocalize_translation / "
        "relocalize_rotation_deg; 1 = the first sound match links")] = 2
    relocalize_window: Annotated[int, Positive(100_000, "frames a match waits for its confirmation")] = 15
    relocalize_translation: Annotated[float, Positive(10000.0, "metres: two relocalisation matches agree within this")] = 0.1
    relocalize_rotation_deg: Annotated[float, Positive(360.0, "degrees: see relocalize_translation")] = 5.0
    map_track_every: Annotated[int, AtMost(10**6,
        "tracking against a fixed map (--localize; rgbdslam/session/tracking.py): once relocalised, every "
        "map_track_every-th frame is registered against the map_track_neighbours map keyframes nearest its predicted "
        "map pose; a registration that agrees with the prediction (within relocalize_translation / _rotation_deg plus "
        "the drift ratios times the travel since the last anchoring) is an edge to the map; odometry carries the pose "
        "between. 0 = off (loops only)")] = 1
    map_track_neighbours: Annotated[int, Positive(100, "map keyframes registered per tracked frame")] = 2
    map_track_distance: Annotated[float, Positive(10000.0,
        "metres: largest distance between camera centres of a neighbour")] = 1.0
    map_track_angle_deg: Annotated[float, Positive(180.0,
        "degrees: largest angle between the viewing directions of a neighbour")] = 45.0
    map_track_gate: Annotated[float, AtMost(100.0,
        "metres: matching guided by the prediction (3-D neighbours within this gate, no RANSAC pre-filter; an unguided "
        "registration with the nearest neighbour when no guided one agrees); 0 = unguided only")] = 0.05
    map_track_keyframe_every: Annotated[int, AtMost(10**6,
        "a frame with map edges becomes a keyframe only every map_track_keyframe_every-th anchored frame (or when the "
        "keyframe policy wants one); the other frames' map edges go to the last keyframe, composed with the odometry "
        "since it (its covariance added). 1 = every anchored frame a keyframe; 0 = never forced: map edges always go "
        "to the last keyframe")] = 0
