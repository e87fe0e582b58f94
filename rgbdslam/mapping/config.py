"""The ``mapping`` config section: cloud, mesh and 2-D map fusion (:mod:`rgbdslam.configspec`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from rgbdslam.configspec import AtMost, C_INT_MAX, Key, Positive, Range


@dataclass
class MappingConfig:
    # upper bounds: Open3D takes C ints; a TSDF block (8^3 voxels) holds ~10 kB before the hash map grows
    enabled: Annotated[bool, Key("fuse the map at the end of a run")] = True
    keyframes_only: Annotated[bool, Key(
        "which frames are fused: run.json keyframes (else frames chosen by motion) or every tracked frame")] = True
    live: Annotated[bool, Key("fuse keyframes while tracking (keyframes_only); false: fuse after the run")] = True
    live_tolerance: Annotated[float, Range(0.0, 10.0,
        "a keyframe whose points moved by less than this many voxels (translation + rotation angle x depth_max) stays "
        "where the live map integrated it; larger: less re-integration, a map further from the final poses")] = 0.25
    live_nice: Annotated[int, Range(0, 19,
        "niceness of the map process (and of the plot process): tracking keeps its speed, the map takes what tracking "
        "leaves; 0: the same priority as tracking (docs/mapping.md \"Fusion while tracking\")")] = 10
    live_lag: Annotated[int, Range(0, 10_000,
        "the newest keyframes wait this many keyframes before they go into the map: their poses still move with every "
        "loop closure; at the end they are integrated once at their final poses")] = 8
    live_backlog: Annotated[int, Range(0, 10_000,
        "a map process more than this many keyframes behind (beyond live_lag) works at tracking's priority until it "
        "has caught up: what is left for after the last frame stays bounded on a busy machine")] = 4
    select_translation: Annotated[float, AtMost(10000.0, "motion-based choice when run.json has no keyframes (m)")] = 0.05
    select_rotation_deg: Annotated[float, AtMost(360.0, "degrees: see select_translation")] = 5.0
    undistort: Annotated[bool, Key("remap colour and depth to the ideal pinhole before fusing")] = True
    depth_min: Annotated[float, AtMost(1000.0, "metres; depth outside [depth_min, depth_max] is ignored")] = 0.3
    depth_max: Annotated[float, Positive(1000.0, "metres: see depth_min")] = 3.0
    # coloured point cloud
    # voxel keys have 21 bits per axis (+-1 km at 1 mm): finer grids are not sane (also tsdf_voxel, grid_resolution)
    voxel_size: Annotated[float, Range(0.001, 10.0, "voxel-grid downsampling of the merged cloud (m)")] = 0.01
    cloud_pixel_stride: Annotated[int, Positive(1024,
        "back-project every n-th pixel (a 1 cm voxel holds several anyway)")] = 2
    outlier_neighbors: Annotated[int, AtMost(1000, "statistical outlier removal (0 = off)")] = 20
    outlier_std: Annotated[float, Positive(1000.0,
        "statistical outlier removal: standard deviations beyond the neighbours' mean distance")] = 2.0
    outlier_method: Annotated[Literal["statistical", "voxel"], Key(
        "the cloud's outlier removal: \"statistical\" (Open3D's, outlier_neighbors / outlier_std) or \"voxel\" (a point is "
        "kept when at least outlier_min_neighbors of the voxels within outlier_radius voxels of its own are occupied: "
        "a few gathers from a dense occupancy grid, ~10x cheaper)")] = "statistical"
    # range: voxel outlier removal makes (2 r + 1)^3 - 1 gathers; r = 3 is already 342 of them
    outlier_min_neighbors: Annotated[int, Range(0, 342,
        "voxel outlier removal: occupied voxels around a kept point (0 = off)")] = 4
    outlier_radius: Annotated[int, Range(1, 3, "voxel outlier removal: the neighbourhood is (2 r + 1)^3 voxels")] = 1
    # TSDF mesh
    mesh: Annotated[bool, Key("Open3D tensor VoxelBlockGrid TSDF + marching cubes")] = True
    tsdf_voxel: Annotated[float, Range(0.001, 10.0, "metres: TSDF voxel size")] = 0.01
    sdf_trunc: Annotated[float, Positive(100.0, "metres: TSDF truncation distance")] = 0.04
    mesh_min_frames: Annotated[int, Positive(10**6, "voxels seen by fewer frames are left out of the mesh")] = 2
    tsdf_initial_blocks: Annotated[int, Positive(50_000, "8^3-voxel blocks preallocated (the hash map grows)")] = 2000
    map2d: Annotated[bool, Key("2-D occupancy map (docs/references.md §6)")] = True
    grid_resolution: Annotated[float, Range(0.001, 100.0, "metres per cell")] = 0.05
    gravity: Annotated[Literal["auto", "accelerometer", "camera"], Key("up direction hint for the floor")] = "auto"
    floor_max_tilt_deg: Annotated[float, Range(0.0, 90.0, "a floor plane's normal is within this of \"up\"")] = 20.0
    floor_distance: Annotated[float, Positive(100.0, "RANSAC inlier distance of the floor plane (m)")] = 0.02
    floor_ransac_iterations: Annotated[int, Positive(100_000, "RANSAC iterations of the floor plane search")] = 500
    floor_band: Annotated[float, Positive(100.0, "|height| below this = floor point (m)")] = 0.05
    obstacle_min_height: Annotated[float, Range(-1000.0, 1000.0,
        "points between these heights above the floor occupy a cell")] = 0.10
    obstacle_max_height: Annotated[float, Range(-1000.0, 1000.0, "metres: see obstacle_min_height")] = 1.80
    obstacle_min_points: Annotated[int, Positive(10**6, "points needed to mark a cell occupied")] = 3
    # Open3D's random seed is a C int
    seed: Annotated[int, AtMost(C_INT_MAX, "seed of the floor RANSAC")] = 0
