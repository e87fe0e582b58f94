"""`rgbdslam export`: every format read back by a reader that is not ours (evo, pycolmap, Open3D's
writers checked by hand-parsed headers, nerfstudio's documented keys), poses compared to the run."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import time
import urllib.request
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import assert_cli_error, cli
from rgbdslam.config import Config
from rgbdslam.datasets.synthetic import generate_sequence
from rgbdslam.io.trajectory import read_tum
from rgbdslam.pipeline import run_sequence

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A finished run with map (cloud + mesh) on a 20-frame synthetic sequence with exact ground truth."""
    root = tmp_path_factory.mktemp("export")
    generate_sequence(root / "seq", frames=24, motion="xyz", noise=True, seed=0)
    cfg = Config()
    cfg.mapping.map2d = False
    run_sequence(root / "seq", root / "run", cfg, progress=False)
    return root / "run"


@pytest.fixture(scope="module")
def exported(run_dir) -> Path:
    out = run_dir.parent / "exported"
    res = cli(["export", run_dir, "--format", "all", "--out", out, "--max-points", 5000, "-q"])
    assert res.exit_code == 0, res.output
    return out


def _keyframe_poses(run_dir: Path) -> dict[int, np.ndarray]:
    """Pose of every keyframe from trajectory.tum, matched to the sequence's stamps via run.json."""
    info = json.loads((run_dir / "run.json").read_text())
    traj = read_tum(run_dir / "trajectory.tum")
    stamps = {round(t, 6): k for k, t in enumerate(traj.timestamps)}
    return {i: traj.poses[stamps[round(t, 6)]] for i, t in zip(info["keyframes"], info["timestamps_keyframes"])}


# ----------------------------------------------------------------------------- trajectories

def test_trajectories_read_back_by_evo(run_dir, exported):
    from evo.tools import file_interface

    traj = read_tum(run_dir / "trajectory.tum")
    kitti = file_interface.read_kitti_poses_file(str(exported / "poses.txt"))
    assert np.allclose(np.array(kitti.poses_se3), traj.poses, atol=1e-8)
    times = np.loadtxt(exported / "times.txt")
    assert np.allclose(times, traj.timestamps, atol=1e-6)
    euroc = file_interface.read_euroc_csv_trajectory(str(exported / "trajectory.csv"))
    assert np.allclose(euroc.timestamps, traj.timestamps, atol=1e-6)
    assert np.allclose(np.array(euroc.poses_se3), traj.poses, atol=1e-8)
    tum = file_interface.read_tum_trajectory_file(str(exported / "trajectory.tum"))
    assert np.allclose(np.array(tum.poses_se3), traj.poses, atol=1e-8)


def test_evo_result_zip_agrees_with_the_runs_ate(run_dir, exported):
    from evo.tools import file_interface

    res = file_interface.load_res_file(str(exported / "evo_ape.zip"), load_trajectories=True)
    ours = json.loads((run_dir / "evaluation.json").read_text())["ate"]
    assert res.stats["rmse"] == pytest.approx(ours["rmse"], rel=1e-6)
    assert res.stats["max"] == pytest.approx(ours["max"], rel=1e-6)
    assert len(res.np_arrays["error_array"]) == ours["n_pairs"]
    # evo_res tables it (evo's own command line, as a user would)
    out = subprocess.run([str(Path(sys.executable).parent / "evo_res"), str(exported / "evo_ape.zip")],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-400:]
    assert "rmse" in out.stdout


# ----------------------------------------------------------------------------- COLMAP

def test_colmap_model_read_back_by_pycolmap(run_dir, exported):
    import pycolmap  # pinned in the test extra (an independent COLMAP reader)
    rec = pycolmap.Reconstruction(str(exported / "colmap" / "sparse" / "0"))
    poses = _keyframe_poses(run_dir)
    assert len(rec.images) == len(poses) and len(rec.cameras) == 1
    cam = rec.cameras[1]
    assert cam.model.name == "PINHOLE" and (cam.width, cam.height) == (640, 480)
    # ros_default camera, OpenCV centre 319.5 -> COLMAP's pixel-centre convention 320.0
    assert np.allclose(cam.params, [525.0, 525.0, 320.0, 240.0])
    for image in rec.images.values():
        T = poses[int(Path(image.name).stem)]
        assert np.allclose(image.cam_from_world().inverse().matrix(), T[:3, :], atol=1e-9)
        assert (exported / "colmap" / "images" / image.name).is_file()
    assert 0 < len(rec.points3D) <= 5000
    # every observation is where pycolmap's camera model projects its 3-D point
    n_obs = 0
    for image in list(rec.images.values())[:5]:
        for p2 in image.points2D:
            if not p2.has_point3D():
                continue
            xyz = rec.points3D[p2.point3D_id].xyz
            uv = cam.img_from_cam(image.cam_from_world() * xyz)
            assert np.allclose(uv, p2.xy, atol=2e-3)
            n_obs += 1
    assert n_obs > 100
    tracks = [p.track.length() for p in rec.points3D.values()]
    assert np.median(tracks) >= 2


def test_colmap_points_carry_the_maps_colours(run_dir, exported):
    import open3d as o3d

    pc = o3d.io.read_point_cloud(str(run_dir / "map" / "cloud.ply"))
    P, C = np.asarray(pc.points), (np.asarray(pc.colors) * 255 + 0.5).astype(int)
    rows = [ln.split() for ln in (exported / "colmap/sparse/0/points3D.txt").read_text().splitlines()
            if not ln.startswith("#")]
    xyz = np.array([[float(v) for v in r[1:4]] for r in rows])
    rgb = np.array([[int(v) for v in r[4:7]] for r in rows])
    from scipy.spatial import cKDTree

    # every exported point is one of the map's points, with its colour

    dist, idx = cKDTree(P).query(xyz)
    assert dist.max() < 1e-5
    assert np.abs(C[idx] - rgb).max() <= 1


# ----------------------------------------------------------------------------- nerfstudio

def test_nerfstudio_transforms_follow_the_documented_keys(run_dir, exported):
    ns = exported / "nerfstudio"
    doc = json.loads((ns / "transforms.json").read_text())
    # nerfstudio's data conventions page: intrinsics at the top, per frame file_path + transform_matrix
    for key in ("camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "p1", "p2", "frames"):
        assert key in doc, key
    assert doc["camera_model"] in ("OPENCV", "OPENCV_FISHEYE", "PINHOLE")
    assert (doc["w"], doc["h"]) == (640, 480) and doc["fl_x"] == 525.0 and doc["cx"] == 320.0
    assert (ns / doc["ply_file_path"]).is_file()
    poses = _keyframe_poses(run_dir)
    assert len(doc["frames"]) == len(poses)
    seq = Path(json.loads((run_dir / "run.json").read_text())["sequence"])
    stamps_rgb = dict(ln.split()[:2] for ln in (seq / "depth.txt").read_text().splitlines() if not ln.startswith("#"))
    for fr in doc["frames"]:
        T = np.array(fr["transform_matrix"])
        assert T.shape == (4, 4)
        i = int(Path(fr["file_path"]).stem)
        assert np.allclose(T @ OPENCV_TO_OPENGL, poses[i], atol=1e-9)  # OpenGL camera axes
        img = cv2.imread(str(ns / fr["file_path"]), cv2.IMREAD_UNCHANGED)
        assert img.shape == (480, 640, 3)
        depth = cv2.imread(str(ns / fr["depth_file_path"]), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16
        # millimetres: the sequence's own depth (TUM 5000 per metre) within rounding
        key = min(stamps_rgb, key=lambda s: abs(float(s) - fr["timestamp"]))
        raw = cv2.imread(str(seq / stamps_rgb[key]), cv2.IMREAD_UNCHANGED).astype(float) / 5000.0
        ok = raw > 0
        assert np.abs(depth[ok] / 1000.0 - raw[ok]).max() <= 0.0006


# ----------------------------------------------------------------------------- maps

def _pcd_points(path: Path) -> int:
    """PCL's PCD header, parsed here (not by Open3D, which wrote it)."""
    head = path.read_bytes()[:2000].split(b"\nDATA ")[0].decode()
    fields = dict(ln.split(" ", 1) for ln in head.splitlines() if ln and not ln.startswith("#"))
    assert fields["VERSION"].startswith("0.7") and "x y z" in fields["FIELDS"]
    assert int(fields["WIDTH"]) * int(fields["HEIGHT"]) == int(fields["POINTS"])
    return int(fields["POINTS"])


def _glb_counts(path: Path) -> tuple[int, int]:
    """Vertices and triangles of a binary glTF, from its JSON chunk (glTF 2.0 spec)."""
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2 and length == len(data)
    n, kind = struct.unpack_from("<I4s", data, 12)
    assert kind == b"JSON"
    doc = json.loads(data[20:20 + n])
    prim = doc["meshes"][0]["primitives"][0]
    verts = doc["accessors"][prim["attributes"]["POSITION"]]["count"]
    return verts, doc["accessors"][prim["indices"]]["count"] // 3


def test_map_exports_hold_the_whole_map(run_dir, exported):
    import open3d as o3d

    cloud = o3d.io.read_point_cloud(str(run_dir / "map" / "cloud.ply"))
    mesh = o3d.io.read_triangle_mesh(str(run_dir / "map" / "mesh.ply"))
    assert _pcd_points(exported / "cloud.pcd") == len(cloud.points)
    obj = (exported / "mesh.obj").read_text().splitlines()
    assert sum(ln.startswith("v ") for ln in obj) == len(mesh.vertices)
    assert sum(ln.startswith("f ") for ln in obj) == len(mesh.triangles)
    assert len(next(ln for ln in obj if ln.startswith("v ")).split()) == 7  # x y z r g b: colours kept
    v, t = _glb_counts(exported / "mesh.glb")
    assert t == len(mesh.triangles) and v >= len(mesh.vertices)  # glTF may split vertices, never drop triangles


# ----------------------------------------------------------------------------- command line

def test_export_errors_are_one_line(run_dir, tmp_path):
    res = cli(["export", run_dir, "--format", "tum,ply", "--out", tmp_path / "x"])
    assert_cli_error(res, "unknown export format 'ply'; choose from tum, kitti, euroc, evo, colmap, nerfstudio, "
                          "pcd, obj, glb (or all)")
    assert not (tmp_path / "x").exists()
    res = cli(["export", tmp_path, "--format", "tum"])
    assert res.exit_code == 2 and "is not a run folder" in res.stderr


def test_export_without_mesh_stops_before_writing(run_dir, tmp_path):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(run_dir, run, ignore=shutil.ignore_patterns("keyframes"))
    (run / "map" / "mesh.ply").unlink()
    res = cli(["export", run, "--format", "kitti,glb", "-q"])
    assert_cli_error(res, f"{run / 'map' / 'mesh.ply'} is missing; make the map first with `rgbdslam fuse {run}` "
                          f"(mapping.mesh=true)")
    assert not (run / "export").exists()  # the kitti part was not written either


def test_view_web_serves_the_viewer_on_loopback(run_dir):
    """`rgbdslam view --web` on a headless machine: the page answers on loopback, then it stops (bounded)."""
    port = 9400 + (int(time.time()) % 200) * 2
    proc = subprocess.Popen([str(Path(sys.executable).parent / "rgbdslam"), "view", str(run_dir), "--web", "-q",
                             "--web-port", str(port), "--grpc-port", str(port + 1), "--serve-for", "10"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        page = None
        t0 = time.monotonic()
        while time.monotonic() - t0 < 180 and proc.poll() is None:
            try:
                page = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5).read().decode()
                break
            except OSError:
                time.sleep(0.5)
        assert page is not None and "rerun" in page.lower()
        out, err = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.terminate()  # rgbdslam stops the server it started (which also dies with it on Linux)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    assert proc.returncode == 0, err[-500:]
    assert f"http://localhost:{port}/?url=rerun%2Bhttp%3A%2F%2Flocalhost%3A{port + 1}%2Fproxy" in err.replace("\n", "")
    assert "ssh -L" in err
    from rgbdslam.viz.rerun_log import _port_open

    t0 = time.monotonic()  # the server stopped with it: nothing is left listening
    while (_port_open("127.0.0.1", port) or _port_open("127.0.0.1", port + 1)) and time.monotonic() - t0 < 30:
        time.sleep(0.5)
    assert not _port_open("127.0.0.1", port) and not _port_open("127.0.0.1", port + 1)


def test_run_evaluation_json_names_files_like_evaluate_json(run_dir, tmp_path):
    """The run's evaluation.json and `rgbdslam evaluate GT RUN_DIR/trajectory.tum --json` agree:
    same keys, same file names, same numbers; the run's plots carry the names --help gives."""
    run_eval = json.loads((run_dir / "evaluation.json").read_text())
    gt = Path(json.loads((run_dir / "run.json").read_text())["sequence"]) / "groundtruth.txt"
    res = cli(["evaluate", gt, run_dir / "trajectory.tum", "--json", tmp_path / "e.json",
               "--plot-dir", tmp_path / "plots"])
    assert res.exit_code == 0, res.output
    cmd_eval = json.loads((tmp_path / "e.json").read_text())
    assert run_eval.keys() == cmd_eval.keys()
    assert run_eval["ground_truth"] == cmd_eval["ground_truth"] == str(gt)
    assert run_eval["estimate"] == cmd_eval["estimate"] == str(run_dir / "trajectory.tum")
    assert run_eval["ate"]["rmse"] == pytest.approx(cmd_eval["ate"]["rmse"], rel=1e-6)  # file: 9 decimals
    assert [Path(p).name for p in run_eval["plots"]] == [Path(p).name for p in cmd_eval["plots"]]
    assert all(Path(p).is_file() for p in run_eval["plots"] + cmd_eval["plots"])


def test_an_interrupted_export_keeps_the_earlier_one(run_dir, tmp_path, monkeypatch):
    from rgbdslam.export import export_run
    from rgbdslam.export.run import RunExport

    out = tmp_path / "out"
    export_run(run_dir, ["colmap"], out, max_points=500, progress=False)
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    views = RunExport.views

    def interrupted(self):
        for k, v in enumerate(views(self)):
            if k == 2:
                raise KeyboardInterrupt
            yield v

    monkeypatch.setattr(RunExport, "views", interrupted)
    with pytest.raises(KeyboardInterrupt):
        export_run(run_dir, ["colmap"], out, max_points=900, progress=False)
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before  # the earlier model, whole; no temporary folder left beside it
    assert sorted(p.name for p in out.iterdir()) == [".rgbdslam-manifest.json", ".rgbdslam.lock", "colmap"]


def test_a_new_run_moves_the_earlier_export_with_the_earlier_run(tmp_path):
    """An export belongs to its run: a new run into the folder moves it to previous/ with the rest."""
    from rgbdslam.runfolder.folder import make_way_for_run
    from rgbdslam.io.manifest import EXPORT, RUN, Manifest

    (tmp_path / "run.json").write_text(json.dumps({"status": "finished"}))
    (tmp_path / "export").mkdir()
    (tmp_path / "export" / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    Manifest(tmp_path).record(["run.json"], RUN)
    Manifest(tmp_path).record(["export"], EXPORT)
    assert make_way_for_run(tmp_path)
    assert not (tmp_path / "export").exists()
    assert (tmp_path / "previous" / "export" / "poses.txt").is_file()
    assert Manifest(tmp_path / "previous").entries == {"run.json": RUN, "export": EXPORT, "export/poses.txt": EXPORT}
