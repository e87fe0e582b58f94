"""Map fusion and the 2-D map on hand-made scenes with exact geometry, and on real TUM frames."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
import yaml
from scipy.spatial.transform import Rotation

from rgbdslam.config import Config, MappingConfig, save_config
from rgbdslam.datasets import open_sequence
from rgbdslam.geometry.se3 import make_pose
from rgbdslam.io.trajectory import Trajectory, write_tum
from rgbdslam.mapping.fusion import VoxelCloud, fuse, fuse_run, match_frames, select_by_motion
from rgbdslam.mapping.map2d import FREE, OCCUPIED, UNKNOWN, build_map2d, up_from_accelerometer, write_map2d

from tests.conftest import DATA
RPY = DATA / "tum" / "rgbd_dataset_freiburg1_rpy_head200"

W, H, F = 160, 120, 100.0  # a small ideal pinhole camera
PLANE_Z = 1.0


def _pose(yaw_deg: float, t) -> np.ndarray:
    return make_pose(Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix(), t)


POSES = [_pose(0, [0, 0, 0]), _pose(0, [0.10, 0.0, 0.0]), _pose(6, [0.05, 0.05, 0.10])]


def _render_plane(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact depth (metres along the optical axis) and a checkerboard colour of the plane world z = 1."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([(u - W / 2) / F, (v - H / 2) / F, np.ones_like(u)], -1)  # camera z = 1
    d_w = rays @ pose[:3, :3].T
    s = (PLANE_Z - pose[2, 3]) / d_w[..., 2]  # ray parameter = depth, since the ray's camera z is 1
    X = pose[:3, 3] + s[..., None] * d_w
    check = ((np.floor(X[..., 0] / 0.1) + np.floor(X[..., 1] / 0.1)) % 2).astype(np.uint8)
    rgb = np.stack([check * 200 + 30, 80 + 0 * check, 255 - check * 200], -1).astype(np.uint8)
    return s.astype(np.float32), rgb


def _write_tum_folder(root: Path, poses, stamps) -> None:
    """A TUM-layout sequence (rgb.txt, depth.txt, PNGs, camera.yaml) of the rendered plane."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    (root / "camera.yaml").write_text(yaml.safe_dump({"fx": F, "fy": F, "cx": W / 2, "cy": H / 2,
                                                      "width": W, "height": H, "dist": [0.0] * 5}))
    rgb_lines, depth_lines = [], []
    for t, p in zip(stamps, poses):
        depth, rgb = _render_plane(p)
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(root / "depth" / f"{t:.6f}.png"), np.round(depth * 5000).astype(np.uint16))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
    (root / "rgb.txt").write_text("# rgb\n" + "\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("# depth\n" + "\n".join(depth_lines) + "\n")


@pytest.fixture
def plane_run(tmp_path):
    seq_dir, run = tmp_path / "seq", tmp_path / "run"
    stamps = [100.0, 100.5, 101.0]
    _write_tum_folder(seq_dir, POSES, stamps)
    run.mkdir()
    write_tum(Trajectory(stamps, np.array(POSES)), run / "trajectory.tum")
    (run / "run.json").write_text(json.dumps({"sequence": str(seq_dir), "keyframes": [0, 1, 2]}))
    save_config(Config(), run / "config.yaml")  # as every run folder has (else fuse warns)
    return seq_dir, run


def _cfg(**kw) -> MappingConfig:
    base = dict(depth_min=0.1, depth_max=3.0, voxel_size=0.01, cloud_pixel_stride=1, outlier_neighbors=10,
                map2d=False, mesh_min_frames=1)
    base.update(kw)
    return MappingConfig(**base)


# ----------------------------------------------------------------------------- fusion


def test_fused_plane_lies_on_plane_and_outputs_are_valid_ply(plane_run):
    seq_dir, run = plane_run
    res = fuse_run(run, _cfg(), progress=False)
    assert res.frames == [0, 1, 2]
    cloud = o3d.io.read_point_cloud(str(run / "map" / "cloud.ply"))
    pts = np.asarray(cloud.points)
    assert len(pts) == res.n_points > 5000
    # voxel means of exact plane points: on the plane to float precision, and all within a voxel
    assert np.abs(pts[:, 2] - PLANE_Z).max() < 1e-4
    # the union of the three footprints: wider than one frame (0.8 m at 1 m), shifted by the 0.1 m moves
    assert pts[:, 0].max() - pts[:, 0].min() > 0.85
    assert cloud.has_colors() and np.asarray(cloud.colors).max() > 0.5
    mesh = o3d.io.read_triangle_mesh(str(run / "map" / "mesh.ply"))
    assert len(mesh.triangles) == res.n_triangles > 1000
    v = np.asarray(mesh.vertices)
    assert np.abs(v[:, 2] - PLANE_Z).max() < 0.01  # the zero crossing of an exact plane, within a TSDF voxel
    assert res.peak_rss_mb > 0 and res.seconds > 0
    assert not list((run / "map").glob(".*"))  # no temporary files left behind


def test_keyframe_depth_png_replaces_raw_depth(plane_run):
    """run/keyframes/depth_<i>.png (the DIF output) is what fusion uses: a depth of 0 there removes the frame."""
    seq_dir, run = plane_run
    (run / "keyframes").mkdir()
    for i in range(3):  # frames 0 and 1 filtered away entirely, frame 2 kept
        d = np.zeros((H, W), np.uint16) if i < 2 else np.round(_render_plane(POSES[2])[0] * 5000).astype(np.uint16)
        cv2.imwrite(str(run / "keyframes" / f"depth_{i:06d}.png"), d)
    res = fuse_run(run, _cfg(mesh=False, outlier_neighbors=0), progress=False)
    pts = res.cloud_points
    # only frame 2's footprint: its left image edge (ray (-0.8, y, 1) yawed by 6 deg from
    # (0.05, *, 0.1)) meets the plane at x = -0.527; frames 0 and 1 reach x = -0.8 and -0.7
    c, s = np.cos(np.deg2rad(6)), np.sin(np.deg2rad(6))
    x_lo = 0.05 + 0.9 / (0.8 * s + c) * (-0.8 * c + s)
    assert abs(pts[:, 0].min() - x_lo) < 0.011
    assert res.mesh_path is None


def test_fuse_skips_frames_without_pose_and_rejects_no_pose(plane_run):
    seq_dir, run = plane_run
    seq = open_sequence(seq_dir)
    traj = Trajectory([100.0, 101.0], np.array([POSES[0], POSES[2]]))  # frame 1 untracked
    res = fuse(seq, traj, [0, 1, 2], _cfg(mesh=False), run / "m", progress=False)
    assert res.frames == [0, 2]
    from rgbdslam.errors import InputError

    with pytest.raises(InputError, match="has a pose"):
        fuse(seq, Trajectory([5.0], np.eye(4)[None]), [0, 1], _cfg(), run / "m2", progress=False)


def test_mesh_min_frames_counts_frames(plane_run):
    """Voxels seen by fewer than mesh_min_frames frames are left out (clamped to the frames fused)."""
    seq_dir, run = plane_run
    n = [fuse_run(run, _cfg(mesh_min_frames=k, outlier_neighbors=0), progress=False).n_triangles for k in (1, 2, 3, 4)]
    assert n[0] > n[1] > n[2] > 1000  # the overlap of all three footprints is the smallest
    assert n[3] == n[2]  # only 3 frames: 4 is clamped to 3
    # frames 0 and 1 filtered to nothing: no voxel is seen twice -> no mesh, and no stale mesh.ply
    (run / "keyframes").mkdir()
    for i in range(2):
        cv2.imwrite(str(run / "keyframes" / f"depth_{i:06d}.png"), np.zeros((H, W), np.uint16))
    res = fuse_run(run, _cfg(mesh_min_frames=2, outlier_neighbors=0), progress=False)
    assert res.n_triangles == 0 and res.mesh_path is None and not (run / "map" / "mesh.ply").exists()
    assert res.n_points > 1000  # the cloud is still made from frame 2


def test_match_frames_and_motion_selection():
    traj = Trajectory([1.0, 2.0, 3.0], np.tile(np.eye(4), (3, 1, 1)))
    assert match_frames(np.array([0.5, 1.0004, 2.0, 2.5, 3.0]), traj).tolist() == [-1, 0, 1, -1, 2]
    poses = [np.eye(4), make_pose(np.eye(3), [0.03, 0, 0]), make_pose(np.eye(3), [0.051, 0, 0]),
             make_pose(Rotation.from_euler("z", 4, degrees=True).as_matrix(), [0.06, 0, 0]),
             make_pose(Rotation.from_euler("z", 5.5, degrees=True).as_matrix(), [0.06, 0, 0])]
    # 0.051 m from the first; then 4 deg (+0.009 m) is too little; 5.5 deg is enough
    assert select_by_motion(np.array(poses), 0.05, 5.0) == [0, 2, 4]


def test_voxel_cloud_averages_exactly_across_merges():
    vc = VoxelCloud(0.1)
    vc.add(np.array([[0.01, 0.01, 0.01], [0.05, 0.05, 0.05]]), np.array([[0, 0, 0], [100, 100, 100]]))
    vc.merge()
    vc.add(np.array([[0.09, 0.09, 0.09], [0.25, 0.0, 0.0]]), np.array([[200, 200, 200], [7, 8, 9]]))
    pts, cols = vc.result()
    order = np.argsort(pts[:, 0])
    assert np.allclose(pts[order], [[0.05, 0.05, 0.05], [0.25, 0.0, 0.0]])
    assert cols[order].tolist() == [[100, 100, 100], [7, 8, 9]]


# ----------------------------------------------------------------------------- 2-D map


def _box_scene():
    """Floor z = 0 over [0, 4] x [0, 3] (2 cm spacing) and a 0.4 x 0.4 x 1.0 m box at x, y in [1, 1.4]."""
    g = np.arange(0, 4, 0.02)
    X, Y = np.meshgrid(g, np.arange(0, 3, 0.02))
    floor = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    floor = floor[~((floor[:, 0] >= 1.0) & (floor[:, 0] <= 1.4) & (floor[:, 1] >= 1.0) & (floor[:, 1] <= 1.4))]
    s = np.arange(0, 0.4001, 0.02)
    Z = np.arange(0.02, 1.0001, 0.02)
    sides = []
    for a in s:
        for z in Z:
            sides += [[1.0 + a, 1.0, z], [1.0 + a, 1.4, z], [1.0, 1.0 + a, z], [1.4, 1.0 + a, z]]
    top = np.stack(np.meshgrid(1.0 + s, 1.0 + s), -1).reshape(-1, 2)
    box = np.vstack([np.array(sides), np.c_[top, np.ones(len(top))]])
    return np.vstack([floor, box])


def _level_camera(x, y) -> np.ndarray:
    """A camera 1.2 m up looking along world +x, image-down = world -z."""
    R = np.stack([[0, -1, 0], [0, 0, -1], [1, 0, 0]], 1).astype(float)  # columns: cam x, y, z in world
    return make_pose(R, [x, y, 1.2])


def test_map2d_marks_box_occupied_floor_free(tmp_path):
    pts = _box_scene()
    traj = Trajectory([0.0, 1.0], np.array([_level_camera(0.2, 2.5), _level_camera(3.0, 2.5)]))
    cfg = MappingConfig(grid_resolution=0.1)
    grid = build_map2d(pts, traj, cfg)
    assert grid.floor_source == "ransac" and grid.up_source == "camera"
    assert np.allclose(grid.world_to_map[2, :3], [0, 0, 1], atol=1e-3)  # < 0.06 deg
    assert abs(grid.world_to_map[2, 3]) < 2e-3  # the floor is at height 0 (box feet bias the fit a little)
    r, c = grid.cells(np.array([[1.2, 1.2, 0.5], [3.0, 0.5, 0.0], [0.5, 2.0, 0.0], [10.0, 10.0, 0.0]]))
    assert grid.image[r[0], c[0]] == OCCUPIED
    assert grid.image[r[1], c[1]] == FREE
    assert grid.image[r[2], c[2]] == FREE
    assert not (0 <= r[3] < grid.image.shape[0] and 0 <= c[3] < grid.image.shape[1])
    # every cell is one of the three ROS values, and exactly the box's 4x4-5x5 footprint is occupied
    assert set(np.unique(grid.image)) <= {OCCUPIED, FREE, UNKNOWN}
    assert 16 <= (grid.image == OCCUPIED).sum() <= 25

    png = write_map2d(grid, tmp_path, traj)
    meta = yaml.safe_load((tmp_path / "map2d.yaml").read_text())
    assert {"image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh"} <= set(meta)
    assert meta["image"] == "map2d.png" and meta["resolution"] == 0.1 and meta["negate"] == 0
    assert meta["occupied_thresh"] == 0.65 and meta["free_thresh"] == 0.196 and len(meta["origin"]) == 3
    img = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint8 and np.array_equal(img, grid.image)
    # ROS: the origin is the lower-left pixel, so world (1.2, 1.2) lands where map_server would put it
    col = int((1.2 - meta["origin"][0]) / 0.1)
    row = img.shape[0] - 1 - int((1.2 - meta["origin"][1]) / 0.1)
    assert img[row, col] == OCCUPIED
    prev = cv2.imread(str(tmp_path / "map2d_preview.png"))
    assert prev.shape[2] == 3 and (prev[..., 2] > 200).any() and ((prev[..., 2] > 200) & (prev[..., 1] < 60)).any()


def test_map2d_picks_lowest_horizontal_plane_not_the_desk():
    pts = _box_scene()
    g = np.arange(2.0, 3.5, 0.02)
    desk = np.stack(np.meshgrid(g, g[:40]), -1).reshape(-1, 2)  # a big horizontal desk top at 0.75 m
    pts = np.vstack([pts, np.c_[desk, np.full(len(desk), 0.75)]])
    traj = Trajectory([0.0], _level_camera(0.2, 2.5)[None])
    grid = build_map2d(pts, traj, MappingConfig(grid_resolution=0.1))
    assert abs(grid.world_to_map[2, 3]) < 2e-3
    r, c = grid.cells(np.array([[2.5, 2.2, 0.75]]))
    assert grid.image[r[0], c[0]] == OCCUPIED


def test_accelerometer_gravity_convention():
    """Kinect (ax, ay, -az) is image-down in the optical frame: a camera looking along world +x
    with image-down = world -z must give up = +z."""
    pose = _level_camera(0, 0)
    acc = np.array([[0.0, 0.0, 9.81, 0.0], [1.0, 0.0, 9.81, 0.0]])  # gravity along camera +y
    up = up_from_accelerometer(acc, Trajectory([0.5], pose[None]))
    assert np.allclose(up, [0, 0, 1])


# ----------------------------------------------------------------------------- real frames


@pytest.mark.data
@pytest.mark.usefixtures("rpy200")
def test_rpy_groundtruth_fusion_finds_floor_and_desk(tmp_path):
    """20 keyframes of fr1/rpy fused with the ground truth: the floor found by RANSAC is the
    motion-capture floor (z = 0 up to a few cm), and the desk in front of the camera is occupied."""
    seq = open_sequence(RPY)
    gt = seq.groundtruth()
    idx = np.arange(0, 200, 10)
    stamps = seq.timestamps[idx]
    rows = np.searchsorted(gt.timestamps, stamps).clip(0, len(gt) - 1)
    traj = Trajectory(stamps, gt.poses[rows])  # nearest mocap sample (<= 5 ms): good enough here
    cfg = MappingConfig(cloud_pixel_stride=4, voxel_size=0.02, tsdf_voxel=0.02, sdf_trunc=0.06)
    res = fuse(seq, traj, idx, cfg, tmp_path, progress=False)
    assert res.frames == idx.tolist()
    assert res.n_points > 20000 and res.n_triangles > 20000
    grid = res.map2d
    assert grid.up_source == "accelerometer" and grid.floor_source == "ransac"
    assert np.degrees(np.arccos(grid.world_to_map[2, 2])) < 5  # floor normal ~ mocap z
    assert abs(grid.world_to_map[2, 3]) < 0.08  # floor height ~ 0
    assert (grid.image == OCCUPIED).sum() > 50 and (grid.image == FREE).sum() > 50


# ----------------------------------------------------------------------------- bad settings / run.json


def _map_state(run: Path) -> dict[str, bytes]:
    """Every file in run/map (hidden ones too) with its bytes."""
    return {p.name: p.read_bytes() for p in sorted((run / "map").iterdir())}


def _fuse_cli(run: Path, *sets: str):
    from click.testing import CliRunner

    from rgbdslam.cli import main

    args = ["fuse", str(run), "-q"]
    for s in sets:
        args += ["--set", s]
    return CliRunner().invoke(main, args)


def _one_line_error(res) -> str:
    assert isinstance(res.exception, SystemExit) and res.exit_code == 2, (res.exception, res.output)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    return lines[0]


def test_fuse_empty_depth_range_names_the_settings_and_keeps_the_map(plane_run):
    """No depth in [depth_min, depth_max] used to end in "could not write cloud.ply; check that the
    folder is writable" (after an Open3D warning); now one line names the settings, before any write."""
    seq_dir, run = plane_run
    assert _fuse_cli(run, "mapping.map2d=false").exit_code == 0
    before = _map_state(run)
    res = _fuse_cli(run, "mapping.map2d=false", "mapping.depth_min=2", "mapping.depth_max=3")
    assert _one_line_error(res) == (
        "error: the map would be empty: no depth of the 3 frames to fuse lies between mapping.depth_min=2 and "
        "mapping.depth_max=3 m; widen that range (defaults 0.3 and 3.0)")
    assert "Open3D" not in res.output
    assert _map_state(run) == before


@pytest.mark.parametrize("key, value, message", [  # the config's own rules (config.validate_section)
    ("grid_resolution", 0.0, "config key 'mapping.grid_resolution' must be between 0.001 and 100; got 0.0"),
    ("cloud_pixel_stride", 0, "config key 'mapping.cloud_pixel_stride' must be at least 1; got 0"),
    ("outlier_std", 0.0, "config key 'mapping.outlier_std' must be positive; got 0.0"),
    ("tsdf_voxel", 0.0, "config key 'mapping.tsdf_voxel' must be between 0.001 and 10; got 0.0"),
    ("voxel_size", -0.01, "config key 'mapping.voxel_size' must be between 0.001 and 10; got -0.01"),
    ("voxel_size", float("nan"), "config key 'mapping.voxel_size' must be a finite number; got nan"),
    ("mesh_min_frames", 1.5, "config key 'mapping.mesh_min_frames' expects int; got 1.5"),
    ("depth_min", 3.0, "config key 'mapping.depth_min' (3.0) must be smaller than 'mapping.depth_max' (3.0)"),
    ("gravity", "down", "config key 'mapping.gravity' must be one of auto, accelerometer, camera; got 'down'"),
    ("outlier_method", "radius", "config key 'mapping.outlier_method' must be one of statistical, voxel; got 'radius'"),
    ("outlier_radius", 0, "config key 'mapping.outlier_radius' must be between 1 and 3; got 0"),
    ("outlier_radius", 4, "config key 'mapping.outlier_radius' must be between 1 and 3; got 4"),
    ("outlier_min_neighbors", -1, "config key 'mapping.outlier_min_neighbors' must be between 0 and 342; got -1"),
    ("outlier_min_neighbors", 27, "config key 'mapping.outlier_min_neighbors' (27) must be at most the 26 voxels "
                                  "around a point at mapping.outlier_radius=1"),
])
def test_bad_mapping_settings_are_rejected_before_anything_is_written(plane_run, key, value, message):
    """fuse/fuse_run check the settings first (a MappingConfig made in Python skips load_config's
    checks): grid_resolution=0 used to crash in the 2-D map after cloud.ply and mesh.ply were replaced."""
    from rgbdslam.errors import ConfigError

    seq_dir, run = plane_run
    fuse_run(run, _cfg(), progress=False)
    before = _map_state(run)
    with pytest.raises(ConfigError) as e:
        fuse_run(run, _cfg(**{key: value, "map2d": True}), progress=False)
    assert str(e.value) == message
    assert _map_state(run) == before


def test_cli_grid_resolution_zero_is_one_line_and_keeps_the_map(plane_run):
    seq_dir, run = plane_run
    assert _fuse_cli(run, "mapping.map2d=false").exit_code == 0
    before = _map_state(run)
    line = _one_line_error(_fuse_cli(run, "mapping.grid_resolution=0"))
    assert "mapping.grid_resolution" in line  # (load_config or validate_mapping: whichever checks first)
    assert _map_state(run) == before


def test_failure_part_way_leaves_the_earlier_map_whole(plane_run):
    """A fusion that fails after the cloud and mesh are made (here: the 2-D map wants an
    accelerometer the sequence does not have) changes no file: everything is written into a
    temporary folder that replaces the map files only when all are complete."""
    from rgbdslam.errors import InputError

    seq_dir, run = plane_run
    fuse_run(run, _cfg(), progress=False)
    before = _map_state(run)
    with pytest.raises(InputError) as e:
        fuse_run(run, _cfg(voxel_size=0.02, map2d=True, gravity="accelerometer"), progress=False)
    assert str(e.value) == ("mapping.gravity is 'accelerometer' but the sequence has no usable accelerometer.txt; "
                            "set mapping.gravity=auto")
    assert _map_state(run) == before  # no new cloud beside an old mesh, no temporary folder


def test_a_finished_fusion_leaves_no_files_of_an_earlier_one(plane_run):
    seq_dir, run = plane_run
    from rgbdslam.io.manifest import RUN, Manifest

    fuse_run(run, _cfg(), progress=False)
    (run / "map" / "map2d.png").write_bytes(b"from an older fusion")
    Manifest(run).record(["map/map2d.png"], RUN)  # as that fusion listed it (a file it did not list stops fuse)
    res = fuse_run(run, _cfg(mesh=False), progress=False)
    assert sorted(_map_state(run)) == ["cloud.ply"] and res.cloud_path == run / "map" / "cloud.ply"


def test_map2d_refuses_a_huge_grid(monkeypatch):
    from rgbdslam.errors import InputError
    from rgbdslam.mapping import map2d

    monkeypatch.setattr(map2d, "MAX_CELLS", 1000)
    traj = Trajectory([0.0], _level_camera(0.2, 2.5)[None])
    with pytest.raises(InputError) as e:
        build_map2d(_box_scene(), traj, MappingConfig(grid_resolution=0.1))
    assert re.fullmatch(r"the 2-D map would have \d+ x \d+ cells at mapping\.grid_resolution=0\.1 m \(at most 1000 "
                        r"allowed\); raise mapping\.grid_resolution \(e\.g\. [0-9.]+\) or set mapping\.map2d=false",
                        str(e.value)), str(e.value)


FIX = "re-run `rgbdslam run` to rewrite it, or correct the field"


@pytest.mark.parametrize("edit, message", [
    ({"keyframes": ["a"]}, f"'keyframes' must be a list of frame numbers (whole numbers); found 'a'; {FIX}"),
    ({"keyframes": 3}, f"'keyframes' must be a list of frame numbers (whole numbers); found 3; {FIX}"),
    ({"segments": "x"}, "'segments' must be a list of objects with whole numbers 'first' and 'last' (and true/false "
                        f"'map'); got 'x'; {FIX}"),
    ({"sequence": 5}, f"'sequence' must be the path of the sequence folder as a string; got 5; {FIX}"),
])
def test_hand_edited_run_json_is_one_line(plane_run, edit, message):
    seq_dir, run = plane_run
    info = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps({**info, **edit}))
    assert _one_line_error(_fuse_cli(run)) == f"error: {run / 'run.json'}: {message}"
    assert not (run / "map").exists()


def test_run_json_keyframe_outside_the_sequence_is_an_error(plane_run):
    """It used to be dropped silently; a frame number the sequence does not have means run.json
    is not of this sequence (as it is now), so the map would not be the run's."""
    seq_dir, run = plane_run
    (run / "run.json").write_text(json.dumps({"sequence": str(seq_dir), "keyframes": [0, 2, 7]}))
    assert _one_line_error(_fuse_cli(run)) == (
        f"error: {run / 'run.json'}: frame 7 is not in the sequence {seq_dir} (frames 0..2); run.json does not "
        f"belong to this sequence as it is now: re-run `rgbdslam run`")


def test_run_json_not_utf8_or_not_an_object(plane_run):
    seq_dir, run = plane_run
    (run / "run.json").write_bytes(b"\xff\xfe{}")
    assert _one_line_error(_fuse_cli(run)) == (
        f"error: run file {run / 'run.json'} is not UTF-8 text (byte 0); give the text file itself, not a binary or "
        f"compressed copy")
    (run / "run.json").write_text("[1, 2]")
    assert _one_line_error(_fuse_cli(run)) == f"error: {run / 'run.json'} must hold a JSON object (the run summary), not list; {FIX}"


def test_a_run_folder_without_config_warns_that_defaults_are_used(plane_run, capsys):
    from rgbdslam.runfolder.read import read_run

    _, run = plane_run
    (run / "config.yaml").unlink(missing_ok=True)
    info, cfg, traj = read_run(run)
    err = capsys.readouterr().err
    assert f"{run / 'config.yaml'} is missing; the default config is used" in " ".join(err.split())
    assert cfg.to_dict() == Config().to_dict() and len(traj) == 3


# ----------------------------------------------------------------------------- reproducibility


def test_canonical_mesh_is_independent_of_vertex_order_and_copies():
    """Marching cubes emits the vertices in a thread-dependent order, a shared vertex once per
    block: any order and any copies give the same arrays, and every triangle keeps its winding."""
    from rgbdslam.mapping.fusion import canonical_mesh

    rng = np.random.default_rng(0)
    v = rng.normal(size=(40, 3))
    c = rng.uniform(size=(40, 3))
    tri = np.array([rng.choice(40, 3, replace=False) for _ in range(60)])

    def mesh(vv, cc, tt):
        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vv), o3d.utility.Vector3iVector(tt))
        m.vertex_colors = o3d.utility.Vector3dVector(cc)
        return m

    a = canonical_mesh(mesh(v, c, tri))
    perm = rng.permutation(40)
    inv = np.argsort(perm)
    # permuted vertices, a copy of every vertex named by the odd triangles, triangles shuffled and rotated
    v2 = np.concatenate([v[perm], v[perm]])
    c2 = np.concatenate([c[perm], c[perm]])
    t2 = inv[tri] + np.where(np.arange(60) % 2, 40, 0)[:, None]
    t2 = np.roll(t2, 1, axis=1)[rng.permutation(60)]
    b = canonical_mesh(mesh(v2, c2, t2))
    for name in ("vertices", "vertex_colors", "triangles"):
        assert np.array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name))), name
    # winding kept: the normal of each output triangle matches one of the input's
    va, ta = np.asarray(a.vertices), np.asarray(a.triangles)
    n_in = {tuple(np.round(np.cross(v[t[1]] - v[t[0]], v[t[2]] - v[t[0]]), 9)) for t in tri}
    n_out = {tuple(np.round(np.cross(va[t[1]] - va[t[0]], va[t[2]] - va[t[0]]), 9)) for t in ta}
    assert n_in == n_out


def test_canonical_order_sorts_by_quantised_position_then_by_every_value():
    """Hand-worked: the extent is 2 (x from 0 to 2), so a step is 2 / (2**21 - 1). Rows 1 and 3
    share the last step of x (both within one step of 2) and are ordered by their exact x; rows
    0 and 4 are equal in position and ordered by colour; row 2 is alone in the first step."""
    from rgbdslam.mapping.fusion import canonical_order

    step = 2 / (2**21 - 1)
    rows = np.array([[1.0, 0.0, 0.0, 0.7],
                     [2.0, 0.0, 0.0, 0.1],
                     [0.0, 0.0, 0.0, 0.5],
                     [2.0 - step / 4, 0.0, 0.0, 0.9],
                     [1.0, 0.0, 0.0, 0.2]])
    assert canonical_order(rows).tolist() == [2, 4, 0, 3, 1]
    rng = np.random.default_rng(1)
    for _ in range(3):  # the order follows the rows, not where they stand
        perm = rng.permutation(5)
        assert np.array_equal(rows[perm][canonical_order(rows[perm])], rows[[2, 4, 0, 3, 1]])
    assert canonical_order(np.zeros((0, 4))).tolist() == []
    assert canonical_order(np.ones((3, 3))).tolist() == [0, 1, 2]  # one point three times: extent 0


def test_canonical_order_equals_a_full_lexsort_on_vertices_that_share_steps():
    """Many rows in few quantisation steps (a coarse grid of positions, colours apart): the same
    order as a lexsort by (quantised position, x, y, z, colour) over every row."""
    from rgbdslam.mapping.fusion import KEY_BITS, canonical_order

    rng = np.random.default_rng(2)
    rows = np.concatenate([rng.integers(0, 4, (500, 3)) * 0.25, rng.uniform(size=(500, 3))], axis=1)
    rows[::7, :3] += rng.uniform(0, 1e-9, (len(rows[::7]), 3))  # a few just off the grid
    lo, steps = rows[:, :3].min(0), (1 << KEY_BITS) - 1
    q = np.minimum(np.floor((rows[:, :3] - lo) * (steps / (rows[:, :3].max(0) - lo).max())), steps - 1)
    want = np.lexsort((*rows.T[::-1], q[:, 2], q[:, 1], q[:, 0]))
    assert np.array_equal(canonical_order(rows), want)


@pytest.mark.data
def test_two_fusions_of_one_run_are_byte_identical(desk9, tmp_path):
    """A real run's map (the default chain, the live map) fused again (twice): cloud, mesh and 2-D map
    are the same bytes. The run hands its map the poses trajectory.tum holds (``as_written``), the ones
    `fuse` reads back; with the in-memory poses the cloud differed by one float32 step on ~2 % of the
    points (frame 0's final pose the identity +- 1e-30)."""
    from click.testing import CliRunner

    from rgbdslam.cli import main

    run = tmp_path / "run"
    res = CliRunner().invoke(main, ["run", str(desk9), "--out", str(run), "-q", "--set", "output.plots=false"])
    assert res.exit_code == 0, res.output
    first = {p.name: p.read_bytes() for p in (run / "map").iterdir()}
    assert {"cloud.ply", "mesh.ply", "map2d.png"} <= set(first)
    for _ in range(2):
        res = CliRunner().invoke(main, ["fuse", str(run), "-q"])
        assert res.exit_code == 0, res.output
        again = {p.name: p.read_bytes() for p in (run / "map").iterdir()}
        assert again.keys() == first.keys()
        assert [n for n in first if first[n] != again[n]] == []


def test_cloud_ply_is_the_bytes_open3d_wrote_of_the_points_outlier_removal_keeps(tmp_path):
    """``write_cloud`` (outlier removal by Open3D, then cloud.ply by NumPy, as the run process of a
    live map writes it while its cloud process makes the 2-D map) gives the file Open3D's own
    cloud of the kept points gave before, byte for byte; the outliers are the points far from the rest."""
    import open3d as o3d

    from rgbdslam.mapping.fusion import _write_ply, outlier_keep, write_cloud

    rng = np.random.default_rng(5)
    wall = np.c_[rng.uniform(0, 1, (4000, 2)), rng.normal(0, 0.002, 4000)]  # a plane, 1 m x 1 m
    stray = rng.uniform(2, 3, (12, 3))  # far away, alone
    points = np.vstack([wall, stray])
    colors = rng.integers(0, 256, (len(points), 3), dtype=np.uint8)
    cfg = MappingConfig()
    keep = outlier_keep(points, cfg)
    assert set(range(4000, 4012)).isdisjoint(keep) and len(keep) > 3800
    path, kept, kept_colors = write_cloud(tmp_path, points, colors, cfg)
    np.testing.assert_array_equal(kept, points[keep])
    old = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    old.colors = o3d.utility.Vector3dVector(colors.astype(np.float64) * (1 / 255.0))
    _write_ply(tmp_path / "old.ply", old.select_by_index(keep), mesh=False)
    assert path.read_bytes() == (tmp_path / "old.ply").read_bytes()
    assert outlier_keep(points, MappingConfig(outlier_neighbors=0)) is None


def _voxel_centres(cells, voxel=0.01):
    return (np.asarray(cells, np.float64) + 0.5) * voxel


def test_voxel_filter_drops_an_isolated_point_and_the_corners_of_a_plane():
    """A 10 x 10 plane of voxels: inside points have 8 occupied neighbours, edge points 5, corners 3;
    a point 5 voxels away has none. At 4 neighbours (the default) exactly the corners and the stray go."""
    from rgbdslam.mapping.fusion import outlier_keep, voxel_neighbours

    plane = [(i, j, 7) for i in range(10) for j in range(10)]
    points = _voxel_centres(plane + [(4, 4, 12)])
    counts = voxel_neighbours(points, 0.01)
    grid = counts[:100].reshape(10, 10)
    assert grid[1:-1, 1:-1].min() == grid[1:-1, 1:-1].max() == 8 and counts[100] == 0
    assert grid[0, 1:-1].tolist() == [5] * 8 and [grid[0, 0], grid[0, 9], grid[9, 0], grid[9, 9]] == [3] * 4
    keep = outlier_keep(points, MappingConfig(outlier_method="voxel"))
    assert keep.dtype == np.int64
    assert keep.tolist() == [k for k in range(100) if k not in (0, 9, 90, 99)]
    assert outlier_keep(points, MappingConfig(outlier_method="voxel", outlier_min_neighbors=0)) is None


def test_voxel_filter_keeps_a_point_with_exactly_the_threshold_of_neighbours():
    """A line of voxels: its ends have 1 neighbour, the rest 2; a point with k of its 26 neighbour
    voxels occupied (a diagonal one among them) is kept at min_neighbors = k and dropped at k + 1."""
    from rgbdslam.mapping.fusion import InputError, outlier_keep, voxel_keep, voxel_neighbours

    line = _voxel_centres([(i, 0, 0) for i in range(6)])
    assert voxel_keep(line, 0.01, 2).tolist() == [1, 2, 3, 4]
    assert voxel_keep(line, 0.01, 1).tolist() == list(range(6))
    assert voxel_keep(line, 0.01, 3).tolist() == []
    with pytest.raises(InputError, match="voxel outlier removal left no point of the 6 in the cloud"):
        outlier_keep(line, MappingConfig(outlier_method="voxel", outlier_min_neighbors=3))
    around = [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1) if (dx, dy, dz) != (0, 0, 0)]
    for k in (1, 5, 13, 26):
        centre_first = _voxel_centres([(20, 20, 20)] + [(20 + dx, 20 + dy, 20 + dz) for dx, dy, dz in around[-k:]])
        assert 0 in voxel_keep(centre_first, 0.01, k) and 0 not in voxel_keep(centre_first, 0.01, k + 1)
    # radius 2: the 124 voxels of the 5^3 block; a voxel two steps away counts, three steps does not
    trio = _voxel_centres([(0, 0, 0), (2, -2, 2), (3, 0, 0)])
    # (2,-2,2) is within 2 steps of both others in every axis; (0,0,0) and (3,0,0) are 3 apart in x
    assert voxel_neighbours(trio, 0.01, 2).tolist() == [1, 2, 1] and voxel_neighbours(trio, 0.01, 1).tolist() == [0, 0, 0]
    assert voxel_keep(trio, 0.01, 2, radius=2).tolist() == [1]


def test_voxel_filter_slabs_and_the_sorted_fallback_give_the_dense_counts():
    """Clusters and strays over a box of ~10^9 voxels at 1 cm (a long outdoor run): the sorted-key
    search (no buffer fits), many thin slabs and one buffer over all give the same counts, in any
    point order and at any radius; negative coordinates and points on voxel faces included."""
    from rgbdslam.mapping.fusion import voxel_neighbours

    rng = np.random.default_rng(11)
    centres = rng.uniform(-5, 5, (40, 3))
    points = np.vstack([c + rng.normal(0, 0.02, (300, 3)) for c in centres] + [rng.uniform(-5, 5, (200, 3))]
                       + [np.round(rng.uniform(-0.1, 0.1, (50, 3)), 2)])  # exactly on faces
    small = points[:6000] * 0.05  # a box that fits one buffer
    for r in (1, 2):
        ref = voxel_neighbours(points, 0.01, r, max_cells=0)  # sorted keys
        assert ref.max() >= 8 and (ref == 0).sum() >= 150
        assert np.array_equal(voxel_neighbours(points, 0.01, r, max_cells=1001 ** 2 * 8), ref)  # slabs
        perm = rng.permutation(len(points))
        assert np.array_equal(voxel_neighbours(points[perm], 0.01, r, max_cells=1001 ** 2 * 8), ref[perm])
        ref_small = voxel_neighbours(small, 0.01, r, max_cells=0)
        for cells in (10**9, 25**2 * 50, 10**6):  # one buffer, slabs, slabs
            assert np.array_equal(voxel_neighbours(small, 0.01, r, max_cells=cells), ref_small)
