"""Stereo input: geometry and noise model, readers (KITTI, EuRoC, plain folder), sparse and SGBM
depth against exact synthetic depth, synth --stereo, KITTI poses/metric, bad input, and the
real KITTI 06 sequence end to end."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import DATA, assert_cli_error, cli, need
from rgbdslam.config import load_config
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.stereo import DepthNoise, StereoRig, midpoint_triangulate

KITTI = DATA / "kitti" / "odometry_06_head51"


@pytest.fixture(scope="module")
def stereo_kitti_layout(tmp_path_factory) -> Path:
    """A small synthetic stereo sequence (KITTI layout, 0.12 m baseline, image noise)."""
    from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence

    out = tmp_path_factory.mktemp("stereo") / "kitti_layout"
    generate_stereo_sequence(out, 0.12, "kitti", frames=40, motion="loop", noise=True, seed=3)
    return out


# ------------------------------------------------------------------ geometry


def test_depth_noise_by_hand():
    n = DepthNoise(fx=700.0, baseline=0.5, sigma_disparity=0.5)
    # z^2 sigma_d / (fx B) = 100 * 0.5 / 350
    assert n.sigma(10.0) == pytest.approx(100 * 0.5 / 350)
    assert n.disparity(10.0) == pytest.approx(35.0)
    # with no pixel noise the depth variance of the covariance is sigma(z)^2, along z only
    n0 = DepthNoise(fx=700.0, baseline=0.5, sigma_disparity=0.5, sigma_pixel=0.0)
    C = n0.covariance(np.array([[0.0, 0.0, 10.0]]))[0]
    assert C[2, 2] == pytest.approx(n0.sigma(10.0) ** 2)
    assert np.allclose(C[:2, :2], 0.0)


def test_midpoint_triangulation_exact():
    cam = Camera(500.0, 500.0, 320.0, 240.0, 640, 480)
    rig = StereoRig(cam, 0.2)
    P = np.array([[0.3, -0.2, 2.0], [-1.0, 0.5, 7.5], [0.0, 0.0, 30.0]])
    uv_l = cam.project(P)
    uv_r = cam.project(P - [0.2, 0.0, 0.0])
    assert np.allclose(midpoint_triangulate(rig, uv_l, uv_r), P, atol=1e-9)
    # skew rays (a row mismatch): the midpoint's segment is perpendicular to both rays
    uv_r2 = uv_r + [0.0, 1.0]
    Q = midpoint_triangulate(rig, uv_l, uv_r2)
    a = np.column_stack([(uv_l - [320, 240]) / 500.0, np.ones(3)])
    b = np.column_stack([(uv_r2 - [320, 240]) / 500.0, np.ones(3)])
    s = (Q * a).sum(1) / (a * a).sum(1)  # Q lies halfway: Q = (s a + (o2 + t b)) / 2
    left_end = s[:, None] * a
    right_end = 2 * Q - left_end
    seg = right_end - left_end
    assert np.allclose((seg * a).sum(1), 0, atol=1e-9) and np.allclose((seg * b).sum(1), 0, atol=1e-9)


def test_mahalanobis_refit_recovers_pose_and_beats_least_squares():
    from scipy.spatial.transform import Rotation

    from rgbdslam.geometry.mahalanobis import refine_pose_near_far
    from rgbdslam.geometry.rigid import fit_rigid
    from rgbdslam.geometry.se3 import make_pose

    rng = np.random.default_rng(0)
    noise = DepthNoise(fx=700.0, baseline=0.5, sigma_disparity=0.3)
    X = make_pose(Rotation.from_rotvec([0.01, -0.02, 0.03]).as_matrix(), np.array([0.1, -0.05, 1.2]))
    C = np.column_stack([rng.uniform(-8, 8, 300), rng.uniform(-2, 2, 300), rng.uniform(3, 40, 300)])
    W = C @ X[:3, :3].T + X[:3, 3]
    cov = noise.covariance(C)
    tiny = np.broadcast_to(np.eye(3) * 1e-8, cov.shape)
    start = make_pose(np.eye(3), np.array([0.0, 0.0, 1.0]))
    near = np.zeros(len(C), bool), np.zeros((len(C), 2)), (700.0, 700.0, 600.0, 180.0), 1.0  # every pair near (3-D)

    def fit_3d(X0, C, cov, W, cov_w):
        return refine_pose_near_far(X0, C, cov, W, cov_w, *near)

    refined, H, inl = fit_3d(start, C, cov, W, tiny)
    assert np.allclose(refined, X, atol=1e-6)  # noise-free: exact
    assert inl.all() and np.linalg.matrix_rank(H) == 6
    # stereo noise on the current points (long along the rays): the covariance-weighted fit is
    # closer to the truth than the plain least-squares fit
    Cn = C + np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.standard_normal(C.shape))
    plain = fit_rigid(Cn, W)
    weighted, _, _ = fit_3d(start, Cn, cov, W, tiny)
    err = lambda T: np.linalg.norm(T[:3, 3] - X[:3, 3])  # noqa: E731
    assert err(weighted) < 0.5 * err(plain), (err(weighted), err(plain))


# ------------------------------------------------------------------ depth from the pair


def test_sparse_and_sgbm_depth_against_exact_depth(stereo_kitti_layout):
    from rgbdslam.datasets import open_sequence
    from rgbdslam.datasets.synthetic import Rays, Scene, make_trajectory

    world = make_trajectory("loop", 40)  # the KITTI layout's poses start at the identity: render from the world's
    for method, search, max_bias, max_sigma, min_pixels, max_gross in (("sparse", "orb", 0.1, 0.3, 200, 0.02),
                                                                       ("sparse", "row", 0.1, 0.3, 300, 0.04),
                                                                       ("sgbm", "orb", 0.15, 0.6, 50000, 0.2)):
        seq = open_sequence(stereo_kitti_layout, load_config(None, [f"stereo.depth={method}",
                                                                    f"stereo.sparse_search={search}"]))
        fb = seq.camera.fx * seq.rig.baseline
        frame = seq.load(20)
        assert frame.rgb.ndim == 2 and frame.right.shape == frame.rgb.shape  # grey camera
        true = Scene(3).render(Rays(seq.camera), world[20])[1]
        ok = (frame.depth > 0) & (true > 0)
        e = fb / frame.depth[ok] - fb / true[ok]
        med = np.median(e)
        assert ok.sum() >= min_pixels, method
        assert abs(med) < max_bias, method
        assert 1.4826 * np.median(np.abs(e - med)) < max_sigma, method
        assert np.mean(np.abs(e) > 1.0) < max_gross, (method, search, np.mean(np.abs(e) > 1.0))
        assert frame.depth_noise.sigma(2.0) == pytest.approx(
            4.0 * getattr(seq.stereo_cfg, f"sigma_disparity_{method}") / fb)


def test_match_rows_respects_rows_and_disparity():
    from rgbdslam.config import StereoConfig
    from rgbdslam.stereo.depth import match_rows

    desc = np.random.default_rng(1).integers(0, 256, (4, 32), dtype=np.uint8)
    uv_l = np.array([[100.0, 50.0], [200.0, 80.0], [300.0, 120.0], [50.0, 10.0]])
    # same descriptors on the right: one at a 3-row offset (refused), one at negative disparity (refused)
    uv_r = np.array([[90.0, 50.5], [190.0, 83.0], [310.0, 120.0], [40.0, 10.0]])
    il, ir = match_rows(uv_l, desc, uv_r, desc, StereoConfig(row_tolerance=2.0))
    assert sorted(zip(il.tolist(), ir.tolist())) == [(0, 0), (3, 3)]


# ------------------------------------------------------------------ readers and synth


@pytest.mark.data
def test_kitti_reader_on_real_data():
    from rgbdslam.datasets import open_sequence

    seq = open_sequence(need(KITTI), load_config("kitti"))
    assert type(seq).__name__ == "KittiSequence" and len(seq) == 51
    assert seq.rig.baseline == pytest.approx(0.537, abs=1e-3)
    assert np.allclose(np.diff(seq.timestamps), 0.1)  # no times.txt: 10 Hz
    gt = seq.groundtruth()
    assert len(gt) == 51 and np.linalg.norm(gt.poses[-1][:3, 3]) == pytest.approx(59.86, abs=0.05)
    f = seq.load(0)
    assert f.rgb.shape == (370, 1226) and np.count_nonzero(f.depth) > 200
    # the sequence folder itself opens the same sequence
    assert len(open_sequence(KITTI / "sequences" / "06")) == 51


def test_euroc_layout_matches_kitti_layout(tmp_path):
    """The same synthetic trajectory in both layouts: EuRoC's body frame (T_BS) and rectification
    undone by the reader give the KITTI layout's left-camera poses and baseline."""
    from rgbdslam.datasets import open_sequence
    from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence
    from rgbdslam.geometry.se3 import inv

    for layout in ("kitti", "euroc"):
        generate_stereo_sequence(tmp_path / layout, 0.12, layout, frames=5, motion="circle", seed=0,
                                 width=320, height=240)
    k = open_sequence(tmp_path / "kitti")
    e = open_sequence(tmp_path / "euroc")
    assert type(e).__name__ == "EurocSequence"
    assert e.rig.baseline == pytest.approx(0.12, abs=1e-9)
    gk, ge = k.groundtruth().poses, e.groundtruth().poses
    rel_k = inv(gk[0]) @ gk
    rel_e = inv(ge[0]) @ ge
    assert np.allclose(rel_k, rel_e, atol=1e-9)
    assert np.array_equal(k.load(2).rgb, e.load(2).rgb)  # undistorted rig: rectification is the identity


def test_synth_stereo_cli_and_kitti_poses(tmp_path):
    from rgbdslam.io.kitti import read_kitti_poses, write_kitti_poses

    res = cli(["synth", tmp_path / "s", "--stereo", "0.12", "-n", "3", "--size", "160", "120"])
    assert res.exit_code == 0, res.output
    P = read_kitti_poses(tmp_path / "s" / "poses" / "00.txt")
    assert len(P) == 3 and np.allclose(P[0], np.eye(4))
    write_kitti_poses(P, tmp_path / "p.txt")
    assert np.allclose(read_kitti_poses(tmp_path / "p.txt"), P, atol=1e-8)
    calib = (tmp_path / "s" / "sequences" / "00" / "calib.txt").read_text().split("\n")
    p1 = [float(x) for x in calib[1].split()[1:]]
    assert -p1[3] / p1[0] == pytest.approx(0.12)
    res = cli(["synth", tmp_path / "d", "--stereo", "0.12", "--camera", "fr1", "-n", "2"])
    assert_cli_error(res, "the KITTI layout holds rectified images, but camera 'fr1' has lens distortion; choose "
                          "--camera ros_default or fr3, or --layout euroc (its reader rectifies)")


# ------------------------------------------------------------------ KITTI metric


def test_kitti_metric_by_hand():
    from rgbdslam.evaluation.kitti import kitti_metric
    from rgbdslam.io.trajectory import Trajectory

    n = 121
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 2, 3] = np.arange(n) * 1.0  # 1 m per frame along z: 120 m
    est = gt.copy()
    est[:, 2, 3] *= 1.02  # 2 % too long everywhere
    ts = np.arange(n) * 0.1
    r = kitti_metric(Trajectory(ts, gt), Trajectory(ts, est))
    assert r.lengths[0] == 100.0 and r.step == 10 and r.note is None
    # as KITTI's devkit, a segment ends at the first frame *beyond* L: 101 m from frames 0 and 10,
    # 2.02 m error over L = 100 m; no 200 m segment fits
    assert r.n_segments == 2
    assert r.t_err_pct == pytest.approx(2.02) and r.r_err_deg_per_m == pytest.approx(0.0)
    assert r.end_drift_pct == pytest.approx(2.0)
    # a short path: shortened segments, said in the note
    s = kitti_metric(Trajectory(ts[:31], gt[:31]), Trajectory(ts[:31], est[:31]))
    assert s.lengths == [5.0, 10.0, 20.0] and s.step == 1 and "shorter than KITTI" in s.note
    # 25 segments of 6 m for L = 5 (2.4 %), 20 of 11 m for 10 (2.2 %), 10 of 21 m for 20 (2.1 %)
    assert s.n_segments == 55 and s.t_err_pct == pytest.approx((25 * 2.4 + 20 * 2.2 + 10 * 2.1) / 55)


# ------------------------------------------------------------------ bad input


def _kitti_copy(tmp_path: Path, frames: int = 3) -> Path:
    src = need(KITTI) / "sequences" / "06"
    dst = tmp_path / "seq"
    for d in ("image_0", "image_1"):
        (dst / d).mkdir(parents=True)
        for k in range(frames):
            shutil.copy(src / d / f"{k:06d}.png", dst / d / f"{k:06d}.png")
    shutil.copy(src / "calib.txt", dst / "calib.txt")
    return dst


@pytest.mark.data
def test_bad_stereo_input_one_error_line(tmp_path):
    seq = _kitti_copy(tmp_path)
    (seq / "image_1" / "000002.png").unlink()
    assert_cli_error(cli(["info", seq]), f"{seq} has 3 left images (image_0/) and 2 right images (image_1/); a "
                                         f"stereo sequence needs one right image per left image")
    seq = _kitti_copy(tmp_path / "b")
    img = cv2.imread(str(seq / "image_1" / "000000.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(seq / "image_1" / "000000.png"), img[:, :1200])
    assert_cli_error(cli(["info", seq]), f"left image {seq / 'image_0' / '000000.png'} is 1226x370 but right image "
                                         f"{seq / 'image_1' / '000000.png'} is 1200x370; a stereo pair needs two "
                                         f"images of one size and kind")
    seq = _kitti_copy(tmp_path / "c")
    lines = (seq / "calib.txt").read_text().split("\n")
    p1 = lines[1].split()
    p1[4] = "0.0"  # P1 without the -fx*B column
    lines[1] = " ".join(p1)
    (seq / "calib.txt").write_text("\n".join(lines))
    assert_cli_error(cli(["info", seq]), f"{seq / 'calib.txt'} gives no stereo baseline (got -0 m); the calibration "
                                         f"must give the right camera's offset (e.g. KITTI P1 with -fx*B in its 4th "
                                         f"column, or 'baseline:')")
    folder = tmp_path / "plain"
    (folder / "left").mkdir(parents=True)
    (folder / "right").mkdir()
    (folder / "stereo.yaml").write_text("fx: 500\nfy: 500\ncx: 320\ncy: 240\n")
    assert_cli_error(cli(["info", folder]), f"{folder / 'stereo.yaml'} gives no stereo baseline; add 'baseline: "
                                            f"<metres>' (the distance between the two camera centres)")


@pytest.mark.data
def test_unrectified_pair_is_warned(tmp_path):
    seq = _kitti_copy(tmp_path)
    for k in range(3):  # move the right image 6 rows down: no longer rectified
        p = seq / "image_1" / f"{k:06d}.png"
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(p), np.vstack([np.zeros((6, img.shape[1]), np.uint8), img[:-6]]))
    res = cli(["info", seq])
    assert res.exit_code == 0, res.output
    import re

    m = re.search(r"the stereo pair of frame 0 \(image_0/000000.png\) does not look rectified: \d+ matched features "
                  r"differ by a median of ([0-9.]+) pixels in row", res.output)
    assert m and 5.0 <= float(m.group(1)) <= 7.0, res.output
    ok = cli(["info", _kitti_copy(tmp_path / "ok")])
    assert ok.exit_code == 0 and "warning" not in ok.output


# ------------------------------------------------------------------ end to end


@pytest.mark.data
def test_kitti06_end_to_end_accuracy(tmp_path):
    """Real KITTI 06 frames 0-50 with the kitti preset (sparse depth): ATE <= 0.07 m (ORB-SLAM3
    stereo reaches 0.06-0.07 m on these pairs); poses.txt and the KITTI metric are written."""
    from rgbdslam.io.kitti import read_kitti_poses
    from rgbdslam.pipeline import run_sequence

    cfg = load_config("kitti", ["mapping.enabled=false", "output.plots=false"])
    s = run_sequence(need(KITTI), tmp_path / "run", cfg, progress=False)
    assert s["lost"] == 0
    assert s["evaluation"]["ate"]["rmse"] <= 0.07
    k = s["evaluation"]["kitti"]
    assert k["end_drift_pct"] < 2.0 and "shorter than KITTI" in k["note"]
    assert len(read_kitti_poses(tmp_path / "run" / "poses.txt")) == 51


def test_synthetic_stereo_close_to_rgbd(tmp_path, stereo_kitti_layout):
    """The same trajectory as RGB-D and as stereo (0.12 m baseline): stereo ATE <= 1.5x RGB-D's, both
    through the frame-to-frame chain (the landmark map places no frame on sparse stereo depth, and on
    this RGB-D sequence it cuts the ATE from 0.0082 to 0.0034 m: the depth is what is compared here)."""
    from rgbdslam.datasets.synthetic import generate_sequence
    from rgbdslam.pipeline import run_sequence

    generate_sequence(tmp_path / "rgbd", frames=40, motion="loop", noise=True, seed=3)
    cfg = load_config("thesis", ["mapping.enabled=false", "output.plots=false"])
    a = run_sequence(tmp_path / "rgbd", tmp_path / "ra", cfg, progress=False)["evaluation"]["ate"]["rmse"]
    b = run_sequence(stereo_kitti_layout, tmp_path / "rb", cfg, progress=False)["evaluation"]["ate"]["rmse"]
    assert b <= 1.5 * a, (a, b)


def test_stereo_map_uses_dense_map_depth(tmp_path, stereo_kitti_layout):
    """Tracking on sparse depth, the map on SGBM depth (stereo.map_depth): the map is dense — the
    live map (fed with the tracking frames' sparse depth) is left out for such a run and the map is
    fused after it from the re-read SGBM depth."""
    from rgbdslam.pipeline import run_sequence

    cfg = load_config(None, ["output.plots=false", "dataset.max_frames=12", "mapping.mesh=false",
                             "mapping.map2d=false"])
    s = run_sequence(stereo_kitti_layout, tmp_path / "run", cfg, progress=False)
    sparse_points_per_frame = 1000
    assert s["map"]["cloud_points"] > 20 * sparse_points_per_frame, s["map"]


def test_stereo_pairs_are_prepared_in_two_threads_in_order(tmp_path, stereo_kitti_layout):
    """Stereo pairs (parallel_load) are read and matched by up to ``workers`` threads at once, and
    still come in frame order with exactly what ``load`` gives; an RGB-D folder keeps one reader."""
    import threading
    import time

    from rgbdslam.datasets import open_sequence
    from rgbdslam.datasets.synthetic import generate_sequence

    def overlaps(seq, workers):
        active, most, lock = [0], [0], threading.Lock()
        real = seq.load

        def load(i):
            with lock:
                active[0] += 1
                most[0] = max(most[0], active[0])
            time.sleep(0.05)  # long enough that the next read starts meanwhile when a second thread exists
            try:
                return real(i)
            finally:
                with lock:
                    active[0] -= 1

        seq.load = load
        frames = [(i, p.result()) for i, p in seq.prefetched(4, workers=workers)]
        seq.load = real
        return most[0], frames

    stereo = open_sequence(stereo_kitti_layout)
    most, frames = overlaps(stereo, 2)
    assert most == 2
    assert [i for i, _ in frames] == [f.index for _, f in frames] == list(range(len(stereo)))
    for i in (0, 17, 39):
        ref = stereo.load(i)
        assert np.array_equal(frames[i][1].depth, ref.depth) and np.array_equal(frames[i][1].rgb, ref.rgb)
    assert overlaps(stereo, 1)[0] == 1
    # the front end takes the reader's left key points (those that have depth) as they are: no second ORB
    from rgbdslam.frontend.features import with_detections

    f = stereo.load(5)
    det = f.detections
    assert with_detections(f, load_config(None, []).features).detections is det
    generate_sequence(tmp_path / "rgbd", frames=6, motion="loop", seed=3)
    assert overlaps(open_sequence(tmp_path / "rgbd"), 2)[0] == 1


def test_bad_euroc_and_folder_input_one_error_line(tmp_path):
    """EuRoC and plain-folder counterparts of the KITTI checks: counts, sizes, no baseline (T_BS),
    a distortion list of the wrong length — one error line each; a later pair of two sizes is
    skipped with one warning and the run finishes."""
    from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence

    def euroc(name):
        generate_stereo_sequence(tmp_path / name, 0.12, "euroc", frames=3, motion="circle", seed=0, width=160,
                                 height=120)
        return tmp_path / name / "mav0"

    mav = euroc("count")
    csv = mav / "cam1" / "data.csv"
    csv.write_text("".join(csv.read_text().splitlines(keepends=True)[:-1]))
    assert_cli_error(cli(["info", mav.parent]), f"{mav} has 3 left (cam0) and 2 right (cam1) images with 2 common "
                                                f"time stamps; a stereo sequence needs one right image per left "
                                                f"image at the same time")
    mav = euroc("size")
    y = mav / "cam1" / "sensor.yaml"
    y.write_text(y.read_text().replace("resolution: [160, 120]", "resolution: [150, 120]"))
    assert_cli_error(cli(["info", mav.parent]), "cam0 is 160x120 but cam1 is 150x120 (sensor.yaml); a stereo pair "
                                                "needs two images of one size")
    mav = euroc("nobaseline")
    (mav / "cam1" / "sensor.yaml").write_text((mav / "cam0" / "sensor.yaml").read_text())  # cam1 where cam0 is
    assert_cli_error(cli(["info", mav.parent]), f"{mav / 'cam1' / 'sensor.yaml'} gives no stereo baseline (got 0 m); "
                                                f"the calibration must give the right camera's offset (e.g. KITTI P1 "
                                                f"with -fx*B in its 4th column, or 'baseline:')")
    y = mav / "cam1" / "sensor.yaml"
    y.write_text("\n".join(line for line in y.read_text().splitlines() if not line.startswith(("T_BS", "  "))))
    assert_cli_error(cli(["info", mav.parent]), f"{y} has no T_BS (the camera's pose on the rig); without it the "
                                                f"stereo baseline is unknown")
    mav = euroc("dist")
    y = mav / "cam0" / "sensor.yaml"
    y.write_text(y.read_text().replace("distortion_coefficients: [0.0, 0.0, 0.0, 0.0]",
                                       "distortion_coefficients: [0.1, 0.0, 0.0]"))
    assert_cli_error(cli(["info", mav.parent]), f"{y}: distortion_coefficients has 3 values; radial-tangential "
                                                f"takes 4 (k1, k2, p1, p2) or 5 (OpenCV's k1, k2, p1, p2, k3)")

    # plain folder: counts; then a later pair of two sizes during a run
    kitti = tmp_path / "k"
    generate_stereo_sequence(kitti, 0.12, "kitti", frames=20, motion="circle", seed=0, width=320, height=240)
    folder = tmp_path / "plain"
    shutil.copytree(kitti / "sequences" / "00" / "image_0", folder / "left")
    shutil.copytree(kitti / "sequences" / "00" / "image_1", folder / "right")
    (folder / "stereo.yaml").write_text("fx: 262.5\nfy: 262.5\ncx: 159.5\ncy: 119.5\nbaseline: 0.12\n")
    (folder / "right" / "000019.png").rename(tmp_path / "r5.png")
    assert_cli_error(cli(["info", folder]), f"{folder} has 20 left and 19 right images; a stereo sequence needs one "
                                            f"right image per left image")
    img = cv2.imread(str(tmp_path / "r5.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(folder / "right" / "000019.png"), img)
    cv2.imwrite(str(folder / "right" / "000003.png"), img[:, :300])
    res = cli(["run", folder, "--out", tmp_path / "run", "--no-map", "--set", "output.plots=false"])
    assert res.exit_code == 0, res.output
    warned = [line for line in res.output.splitlines() if "000003.png" in line]
    assert len(warned) == 1 and warned[0].startswith("warning: skipped frame 3: left image") and \
        "is 320x240 but right image" in warned[0] and "is 300x240" in warned[0], res.output
    import json

    s = json.loads((tmp_path / "run" / "run.json").read_text())
    assert s["skipped_frames"] == [3] and s["tracked"] == 19


def test_euroc_distortion_k3_round_trip_and_depth(tmp_path):
    """A strongly distorted synthetic EuRoC rig (fr1: k3 = 1.16, ~15 px at the corners) keeps all five
    coefficients in sensor.yaml, the reader rectifies with them, and the sparse disparities of the
    rectified pair agree with the exact depth (as for an undistorted rig)."""
    import yaml

    from rgbdslam.datasets import open_sequence
    from rgbdslam.datasets.synthetic import Rays, Scene, make_trajectory
    from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence
    from rgbdslam.geometry.camera import CAMERAS

    generate_stereo_sequence(tmp_path / "e", 0.12, "euroc", frames=4, motion="loop", noise=True, seed=1,
                             camera="fr1")
    y = yaml.safe_load((tmp_path / "e" / "mav0" / "cam0" / "sensor.yaml").read_text())
    assert y["distortion_coefficients"] == list(CAMERAS["fr1"].dist)
    seq = open_sequence(tmp_path / "e", load_config(None, ["stereo.depth=sparse"]))
    frame = seq.load(3)
    # exact depth of the rectified left camera: render the scene through the reader's pinhole camera,
    # placed at the left camera's world pose turned by the rectifying rotation
    T = make_trajectory("loop", 4)[3]
    rect = np.eye(4)
    rect[:3, :3] = seq.rectifying_rotation.T
    true = Scene(1).render(Rays(seq.camera), T @ rect)[1]
    ok = (frame.depth > 0) & (true > 0)
    fb = seq.camera.fx * seq.rig.baseline
    e = fb / frame.depth[ok] - fb / true[ok]
    assert ok.sum() >= 150
    assert abs(np.median(e)) < 0.15 and np.mean(np.abs(e) > 1.0) < 0.05, (np.median(e), np.mean(np.abs(e) > 1.0))


def test_row_search_finds_a_known_shift_without_right_key_points():
    """sparse_search=row on a textured pair shifted by exactly 37.25 pixels: every accepted left point
    gets disparity 37.25 (sub-pixel from the refinement), the left-most points (partner outside the
    right image) get none; the ORB search agrees where both give depth."""
    from rgbdslam.config import FeaturesConfig, StereoConfig
    from rgbdslam.frontend.features import detect
    from rgbdslam.stereo.depth import sparse_matches

    rng = np.random.default_rng(5)
    big = cv2.GaussianBlur(rng.integers(0, 256, (240, 1400)).astype(np.float32), (0, 0), 2.0)
    big = cv2.normalize(big, None, 0, 255, cv2.NORM_MINMAX)
    # right(x) = left(x + 37.25): resample a 4x finer image with an integer shift of 149 samples
    fine = cv2.resize(big, (big.shape[1] * 4, big.shape[0]), interpolation=cv2.INTER_CUBIC)
    left = np.ascontiguousarray(cv2.resize(fine[:, 400:400 + 2400], (600, 240), interpolation=cv2.INTER_AREA))
    right = np.ascontiguousarray(cv2.resize(fine[:, 400 + 149:400 + 149 + 2400], (600, 240),
                                            interpolation=cv2.INTER_AREA))
    left, right = left.astype(np.uint8), right.astype(np.uint8)
    rig = StereoRig(Camera(500.0, 500.0, 300.0, 120.0, 600, 240, (0.0,) * 5, "t"), 0.1)
    fc = FeaturesConfig(n_features=600)
    det = detect(left, fc)
    out = {}
    for search in ("row", "orb"):
        sc = StereoConfig(sparse_search=search, min_disparity=4.0, max_disparity=96)
        m = sparse_matches(left, right, rig, det.uv_raw, det.desc, sc, fc)
        assert len(m.left_index) > 150, search
        assert np.median(np.abs(m.disparity - 37.25)) < 0.1, search
        assert np.mean(np.abs(m.disparity - 37.25) > 1.0) < 0.02, search
        assert np.allclose(m.points[:, 2], 500.0 * 0.1 / m.disparity)
        assert m.uv[:, 0].min() >= 37 + 5  # no partner (with its patch) left of the right image's border
        out[search] = dict(zip(m.left_index.tolist(), m.disparity))
    both = sorted(set(out["row"]) & set(out["orb"]))
    assert len(both) > 50 and max(abs(out["row"][k] - out["orb"][k]) for k in both) < 0.05


@pytest.mark.data
def test_row_search_cost_table_budget_is_checked_up_front(tmp_path):
    """A row search whose cost table (disparities x rows x cols, float32, per reader thread) would
    pass ROW_SEARCH_BUDGET is refused with one line, on its own and before a run reads a frame; the
    kitti preset's settings fit."""
    from rgbdslam.config import StereoConfig
    from rgbdslam.errors import ConfigError
    from rgbdslam.stereo.depth import ROW_SEARCH_BUDGET, check_row_search, coarse_row_search, row_search_bytes

    big = StereoConfig(sparse_search="row", row_scale=1, max_disparity=1024)
    assert row_search_bytes(big, 1920, 1080) == 4 * 1024 * 1080 * 1920  # min_disparity 0.5: d = 1..1024
    with pytest.raises(ConfigError, match="needs 8100 MB per reader thread for 1920x1080 pairs"):
        check_row_search(big, 1920, 1080)
    with pytest.raises(ConfigError):  # also when called directly (before any allocation)
        coarse_row_search(np.zeros((1080, 1920), np.uint8), np.zeros((1080, 1920), np.uint8), np.zeros((1, 2)), big)
    kitti = load_config("kitti", ["stereo.sparse_search=row"]).stereo
    assert row_search_bytes(kitti, 1226, 370) < ROW_SEARCH_BUDGET
    check_row_search(kitti, 1920, 1080)
    res = cli(["run", need(KITTI), "--config", "kitti", "--out", tmp_path / "run", "--set",
               "stereo.sparse_search=row", "--set", "stereo.row_scale=1", "--set", "stereo.max_disparity=1024"])
    assert_cli_error(res, "stereo.sparse_search=row with stereo.row_scale=1 and stereo.max_disparity=1024 needs "
                          "1767 MB per reader thread for 1226x370 pairs (budget 256 MB); raise stereo.row_scale or "
                          "lower stereo.max_disparity")


def test_row_search_coarse_pixels_are_whole_blocks():
    """Width/height not multiples of row_scale (KITTI's 1226 at 4): coarse pixel (u // s, v // s) is
    the exact mean of the s x s block that holds (u, v), the mapping coarse_row_search reads key points
    by (a resize of the whole image would stretch the blocks: 1226 / 306 = 4.0065 px)."""
    from rgbdslam.stereo.depth import coarse_image

    rng = np.random.default_rng(3)
    for (h, w), s in (((370, 1226), 4), ((101, 203), 8), ((64, 96), 4)):
        img = rng.integers(0, 256, (h, w)).astype(np.uint8)
        c = coarse_image(img, s)
        assert c.shape == (h // s, w // s) and c.dtype == np.float32
        blocks = img[:h // s * s, :w // s * s].astype(np.float64).reshape(h // s, s, w // s, s).mean(axis=(1, 3))
        assert np.abs(c - blocks).max() <= 0.5 + 1e-6  # OpenCV rounds the 8-bit means


def test_subpixel_refinement_has_no_pull_toward_whole_pixels():
    """refine_disparity on a band-limited texture shifted by 20 + k/8 px (k = 0..7; a 8x finer image
    shifted by whole samples and area-averaged, as a camera's pixels integrate): ``zsad_v`` (zero-mean
    SAD, equiangular fit) recovers every fraction with a mean error below 0.02 px; ``centre_parabola``
    (patch minus its centre pixel, parabola) is pulled toward whole pixels by more than 0.05 px."""
    from rgbdslam.stereo.depth import refine_disparity

    rng = np.random.default_rng(11)
    big = cv2.GaussianBlur(rng.integers(0, 256, (200, 400)).astype(np.float32), (0, 0), 1.2)
    fine = cv2.resize(cv2.normalize(big, None, 0, 255, cv2.NORM_MINMAX), (400 * 8, 200),
                      interpolation=cv2.INTER_CUBIC)

    def view(shift8: int) -> np.ndarray:  # 300 columns starting (64 + shift8) / 8 px into the texture
        return cv2.resize(fine[:, 64 + shift8:64 + shift8 + 2400], (300, 200), interpolation=cv2.INTER_AREA)

    left = view(0)
    v, u = (g.ravel() for g in np.meshgrid(np.arange(20, 180, 7), np.arange(60, 280, 7), indexing="ij"))
    worst = {}
    for method in ("zsad_v", "centre_parabola"):
        errors = []
        for k in range(8):
            d = 20.0 + k / 8.0  # right(x) = left(x + d): the point at left column u is at u - d on the right
            right = view(160 + k)
            ur, ok = refine_disparity(left, right, u, v, (u - round(d)).astype(float), 5, 3, method)
            assert ok.mean() > 0.95
            errors.append(np.mean((u - ur)[ok] - d))
        worst[method] = np.max(np.abs(errors))
    assert worst["zsad_v"] < 0.02, worst
    assert worst["centre_parabola"] > 0.05, worst


def test_euroc_ground_truth_with_a_zero_quaternion_names_its_line(tmp_path):
    """A zero (or non-finite) quaternion in EuRoC's ground truth is one error naming the file and
    line, not NaN poses and NaN accuracy numbers."""
    from rgbdslam.datasets.euroc import read_groundtruth_csv
    from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence
    from rgbdslam.errors import InputError

    generate_stereo_sequence(tmp_path / "e", 0.12, "euroc", frames=3, motion="circle", seed=0, width=160, height=120)
    csv = tmp_path / "e" / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    lines = csv.read_text().splitlines()
    stamps, poses = read_groundtruth_csv(csv)
    assert len(poses) == 3 and np.allclose(np.linalg.det(poses[:, :3, :3]), 1.0)
    k = next(i for i, line in enumerate(lines) if line.strip() and not line.startswith("#")) + 1  # 2nd pose
    for bad in ("0,0,0,0", "nan,0,0,1"):
        f = lines[k].split(",")
        lines2 = list(lines)
        lines2[k] = ",".join(f[:4] + bad.split(",") + f[8:])
        csv.write_text("\n".join(lines2) + "\n")
        with pytest.raises(InputError, match=rf"{csv.name}:{k + 1}: "):
            read_groundtruth_csv(csv)
