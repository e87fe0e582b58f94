"""The ``dataset`` config section: which reader, camera and frames a run uses
(each key declared once with its range and description, :mod:`rgbdslam.configspec`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from rgbdslam.configspec import AtMost, Key, Positive, Range


@dataclass
class DatasetConfig:
    # upper bounds: frame counts and indices fit a C int; prefetched frames are held in memory
    kind: Annotated[Literal["auto", "tum", "icl", "put", "synthetic", "7scenes", "rosbag", "kitti", "euroc", "stereo"], Key(
        "reader; auto: by the folder's files")] = "auto"
    # TUM association (semantics of TUM's associate.py)
    max_difference: Annotated[float, Positive(10000.0,
        "seconds: colour and depth images closer in time than this are paired")] = 0.02
    # range: Unix time stamps are ~1.8e9 s (2026)
    offset: Annotated[float, Range(-2e9, 2e9, "seconds added to the depth time stamps before pairing")] = 0.0
    associations: Annotated[str | None, Key("optional existing associations file")] = None
    camera_file: Annotated[str | None, Key(
        "Camera file (YAML: fx fy cx cy size distortion depth_scale, optional depth_camera and depth_to_color; "
        "`--camera FILE`); wins over everything below (docs/formats.md \"Camera file\")")] = None
    camera: Annotated[Literal["auto", "fr1", "fr2", "fr3", "kinect1", "ros_default"], Key(
        "Camera: \"auto\" = camera.yaml in the folder, else what the source says (bag CameraInfo, 7-Scenes/ETH3D "
        "calibration, freiburg1/2/3 in a TUM folder name, kinect1 for PUT), else ros_default with a warning; or the "
        "named model")] = "auto"
    # raw depth units per metre: below 1e-3 a 16-bit depth image would reach past 65 km
    depth_scale: Annotated[float | None, Range(0.001, 1e6,
        "raw units per metre; None = camera file, else source default (TUM 5000, PUT 1000)")] = None
    depth_correction: Annotated[float, Range(0.1, 10.0, "multiply metric depth (off = 1.0)")] = 1.0
    first_frame: Annotated[int, AtMost(10**9, "first frame used, counted from 0 after pairing (--first-frame)")] = 0
    max_frames: Annotated[int | None, Positive(10**9, "use at most this many frames (None = all; --max-frames)")] = None
    stride: Annotated[int, Positive(10**6, "use every n-th frame (--stride)")] = 1
    groundtruth: Annotated[str | None, Key(
        "PUT: ground-truth TUM file (default groundtruth.txt or the one *.tum); bags: a TUM file")] = None
    # ROS bags: topics (None = found automatically when unambiguous; the error lists the candidates)
    rgb_topic: Annotated[str | None, Key("ROS bags: colour image topic (None: found when unambiguous)")] = None
    depth_topic: Annotated[str | None, Key("ROS bags: depth image topic (None: found when unambiguous)")] = None
    camera_info_topic: Annotated[str | None, Key("ROS bags: CameraInfo topic of the colour camera (None: found)")] = None
    prefetch: Annotated[int, AtMost(64, "frames read ahead by a background thread during `run` (0 = read in the loop)")] = 4
    reader_threads: Annotated[int, Positive(64,
        "threads preparing frames ahead at once where the reader allows it (stereo pairs)")] = 2
