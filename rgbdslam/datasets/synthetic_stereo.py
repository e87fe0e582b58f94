"""Synthetic stereo sequences with exact ground truth (``rgbdslam synth --stereo BASELINE``).

The scene, textures and trajectory are those of :mod:`rgbdslam.datasets.synthetic` for the
same seed and motion (so an RGB-D run of ``rgbdslam synth`` with the same options follows the
very same trajectory); a second camera ``BASELINE`` metres to the right of the first (along
its x axis, same orientation and intrinsics) renders the right image. Images are written
grey (as KITTI's and EuRoC's cameras), in one of two layouts:

* ``kitti``: ``sequences/00/image_0`` (left), ``image_1`` (right), ``calib.txt`` (P0, P1 with
  ``P1[0,3] = -fx * B``), ``times.txt``, and ``poses/00.txt`` (left camera-to-world). The
  pair is rectified, so the camera must have no distortion.
* ``euroc``: ``mav0/cam0``, ``mav0/cam1`` (``data/<ns>.png``, ``data.csv``, ``sensor.yaml``
  with intrinsics, distortion and ``T_BS``), ``mav0/state_groundtruth_estimate0/data.csv``
  (body pose). The body frame is not the camera: ``T_BS`` of cam0 is a fixed rotation and
  offset like a real EuRoC rig, so readers must apply it. With a distorted camera (fr1, fr2,
  kinect1) the images are rendered distorted, and the reader's rectification is tested too.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import yaml

from rgbdslam.datasets.synthetic import (
    EPOCH,
    FPS,
    Rays,
    Scene,
    _check_output,
    _replace_folder,
    blur_note,
    exposure_frames,
    make_trajectory,
    motion_parameters,
    partial_folder,
    record_streaks,
    render_exposure,
    resolve_blur,
    scaled_camera,
    trajectory_at,
    validate_parameters,
)
from rgbdslam.datasets import synthetic_highway as hw
from rgbdslam.errors import InputError
from rgbdslam.geometry.se3 import inv, make_pose, pose_to_tum
from rgbdslam.io.atomic import atomic_write_text, in_final_place
from rgbdslam.io.images import write_png
from rgbdslam.io.kitti import format_kitti_calib, format_kitti_poses
from rgbdslam.ui import console, frame_progress

LAYOUTS = ("kitti", "euroc")
STEREO_MOTIONS = ("highway",)  # motions of the stereo generator only (datasets/synthetic_highway.py)
GENERATED = ("sequences", "poses", "mav0", "synthetic.yaml")
# body (IMU) to cam0 of the synthetic EuRoC rig: camera z forward = body x, camera x = -body y
T_BS_CAM0 = make_pose(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), np.array([0.02, -0.06, 0.01]))


def right_offset(baseline: float) -> np.ndarray:
    """Left-camera-to-right-camera placement: the right camera's pose is ``left @ right_offset``."""
    return make_pose(np.eye(3), np.array([baseline, 0.0, 0.0]))


def _grey(rgb: np.ndarray, noise: bool, rng: np.random.Generator) -> np.ndarray:
    """The grey image of a rendered colour image, with the RGB-D rendering's image noise (``--noise``):
    sigma 2 grey levels on each colour channel, rounded to 8 bits, then converted to grey, exactly as the
    RGB-D front end sees a noisy ``rgbdslam synth`` image (sigma ~1.3 on grey). Before, the noise was
    added after the conversion (sigma 2 on grey): the stereo images were 1.5x noisier than the RGB-D
    images they are compared with."""
    if noise:
        rgb = np.clip(rgb + rng.normal(0.0, 2.0, rgb.shape), 0, 255).astype(np.uint8)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def _write_png(path: Path, img: np.ndarray) -> None:
    write_png(path, img, compression=1)


def _sensor_yaml(cam, T_BS: np.ndarray, comment: str) -> str:
    # radial-tangential k1 k2 p1 p2, and k3 (OpenCV's fifth) when the camera has one: fr1's k3 = 1.16
    # moves the image corners by ~15 px, so dropping it would make the reader rectify a different lens
    d = (list(cam.dist) + [0.0] * 5)[:5]
    if d[4] == 0.0:
        d = d[:4]
    return (
        f"# {comment}\nsensor_type: camera\ncomment: {comment}\n"
        f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{', '.join(repr(float(v)) for v in T_BS.ravel())}]\n"
        f"rate_hz: {FPS:g}\nresolution: [{cam.width}, {cam.height}]\ncamera_model: pinhole\n"
        f"intrinsics: [{cam.fx!r}, {cam.fy!r}, {cam.cx!r}, {cam.cy!r}]\n"
        f"distortion_model: radial-tangential\ndistortion_coefficients: [{', '.join(repr(float(v)) for v in d)}]\n"
    )


def generate_stereo_sequence(out_dir: str | Path, baseline: float, layout: str = "kitti", frames: int = 100,
                             motion: str = "loop", width: int = 640, height: int = 480, noise: bool = False,
                             seed: int = 0, camera: str = "ros_default", progress: bool = False,
                             blur: float | None = None) -> dict:
    """Render a stereo sequence into ``out_dir`` in ``layout`` (see the module doc). ``blur``: the
    exposure (ms) of both cameras, as in :func:`rgbdslam.datasets.synthetic.generate_sequence`."""
    highway = motion == "highway"
    validate_parameters(frames, "static" if highway else motion, width, height, noise, 0.0, 0.0, seed, camera, blur=blur)
    if isinstance(baseline, bool) or not isinstance(baseline, (int, float)) or not 0.0 < baseline <= 10.0:
        raise InputError(f"--stereo must be a baseline in metres, above 0 and at most 10 (got {baseline!r})")
    if layout not in LAYOUTS:
        raise InputError(f"unknown stereo layout '{layout}'; choose one of {', '.join(LAYOUTS)}")
    if highway:
        if layout != "kitti" or camera != "ros_default" or blur:
            raise InputError("--motion highway renders its own KITTI-like camera (fx 718 px at 1241 px width) in the "
                             "KITTI layout, without blur; leave out --camera, --layout euroc and --blur "
                             "(e.g. --stereo 0.54 --size 1241 376)")
        cam = hw.highway_camera(width, height)
    else:
        cam = scaled_camera(camera, width, height)
    if layout == "kitti" and cam.has_distortion:
        raise InputError(f"the KITTI layout holds rectified images, but camera '{camera}' has lens distortion; "
                         f"choose --camera ros_default or fr3, or --layout euroc (its reader rectifies)")
    start = time.perf_counter()
    out = Path(out_dir)
    _check_output(out, GENERATED)
    params = dict(frames=int(frames), motion=motion, width=int(width), height=int(height), noise=bool(noise),
                  seed=int(seed), camera=cam.name if highway else camera, stereo_baseline=float(baseline), layout=layout)
    if highway:
        path = hw.highway_path(frames, seed)
        poses = hw.highway_poses(np.arange(frames), seed, path)
        params.update(fps=hw.FPS, distance_m=round(float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()), 3))
    else:
        poses = make_trajectory(motion, frames)
        params.update(motion_parameters(motion, frames, resolve_blur(motion, blur)))
    target, work = partial_folder(out)
    try:
        streaks: list[float] = []
        try:
            (_write_kitti if layout == "kitti" else _write_euroc)(work, cam, poses, float(baseline), noise, seed,
                                                                  progress, params, streaks)
        except OSError as e:  # a full disk: the file in its final place, never our temporary folder
            raise in_final_place(e, work, out) from None
        record_streaks(params, streaks)
        atomic_write_text(work / "synthetic.yaml",
                          yaml.safe_dump({"generator": "rgbdslam synthetic stereo v2", **params}, sort_keys=False))
        _replace_folder(work, target, GENERATED)
    finally:
        if not (work / ".replaced").is_dir() or not any((work / ".replaced").iterdir()):
            shutil.rmtree(work, ignore_errors=True)
    return {"path": str(out), "seconds": time.perf_counter() - start, **params}


def render_pairs(cam, poses: np.ndarray, baseline: float, noise: bool, seed: int, progress: bool, params: dict,
                  streaks: list[float]):
    """Grey left and right images of every frame (motion-blurred over the exposure in ``params``;
    the left image's streak length per frame is appended to ``streaks``)."""
    rays = Rays(cam)
    rng = np.random.default_rng([seed, 31337, 2])
    off = right_offset(baseline)
    frames = len(poses)
    exposure = exposure_frames(params.get("motion_blur", {}).get("exposure_ms", 0.0))
    if params["motion"] == "highway":
        path = hw.highway_path(frames, seed)
        scene = Scene(seed, hw.highway_surfaces(float(path.s[-1]), seed, path))
        left_at = lambda u: hw.highway_poses(u, seed, path)  # noqa: E731
    else:
        scene = Scene(seed)
        left_at = lambda u: trajectory_at(params["motion"], u, frames)  # noqa: E731
    right_at = lambda u: left_at(u) @ off  # noqa: E731
    with frame_progress(frames, f"rendering {frames} stereo pairs", enabled=progress) as advance:
        for k in range(frames):
            rgb, _, _, streak = render_exposure(scene, rays, left_at, k, exposure)
            streaks.append(streak)
            left = _grey(rgb, noise, rng)
            right = _grey(render_exposure(scene, rays, right_at, k, exposure)[0], noise, rng)
            yield k, left, right
            advance()


def _write_kitti(out: Path, cam, poses, baseline, noise, seed, progress, params, streaks) -> None:
    seq = out / "sequences" / "00"
    (seq / "image_0").mkdir(parents=True)
    (seq / "image_1").mkdir()
    (out / "poses").mkdir()
    for k, left, right in render_pairs(cam, poses, baseline, noise, seed, progress, params, streaks):
        _write_png(seq / "image_0" / f"{k:06d}.png", left)
        _write_png(seq / "image_1" / f"{k:06d}.png", right)
    P0 = np.hstack([cam.K, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -cam.fx * baseline
    atomic_write_text(seq / "calib.txt", format_kitti_calib(P0, P1))
    fps = params.get("fps", FPS)
    atomic_write_text(seq / "times.txt", "".join(f"{k / fps:.6e}\n" for k in range(len(poses))))
    # KITTI's poses are relative to the first frame (frame 0 = identity)
    atomic_write_text(out / "poses" / "00.txt", format_kitti_poses(inv(poses[0]) @ poses))


def _write_euroc(out: Path, cam, poses, baseline, noise, seed, progress, params, streaks) -> None:
    mav = out / "mav0"
    stamps = (EPOCH * 1e9 + np.round(np.arange(len(poses)) / FPS * 1e9)).astype(np.int64)
    T_BS1 = T_BS_CAM0 @ right_offset(baseline)
    for c, T_BS in (("cam0", T_BS_CAM0), ("cam1", T_BS1)):
        (mav / c / "data").mkdir(parents=True)
        atomic_write_text(mav / c / "sensor.yaml", _sensor_yaml(cam, T_BS, f"synthetic {c}"))
        atomic_write_text(mav / c / "data.csv", "#timestamp [ns],filename\n"
                          + "".join(f"{t},{t}.png\n" for t in stamps))
    for k, left, right in render_pairs(cam, poses, baseline, noise, seed, progress, params, streaks):
        _write_png(mav / "cam0" / "data" / f"{stamps[k]}.png", left)
        _write_png(mav / "cam1" / "data" / f"{stamps[k]}.png", right)
    body = poses @ inv(T_BS_CAM0)  # T_WB = T_WS inv(T_BS)
    t, q = pose_to_tum(body)
    gt = mav / "state_groundtruth_estimate0"
    gt.mkdir()
    header = ("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
              "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], "
              "b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
              "b_a_RS_S_z [m s^-2]\n")
    rows = "".join(f"{s}," + ",".join(repr(float(v)) for v in (*p, r[3], r[0], r[1], r[2])) + ",0" * 9 + "\n"
                   for s, p, r in zip(stamps, t, q))
    atomic_write_text(gt / "data.csv", header + rows)


def synth_stereo_command(out_dir: str | Path, **kwargs) -> dict:
    summary = generate_stereo_sequence(out_dir, progress=True, **kwargs)
    console.print(
        f"wrote {summary['frames']} {summary['motion']} stereo pairs ({summary['width']}x{summary['height']}, "
        f"baseline {summary['stereo_baseline']:g} m, {summary['layout']} layout{blur_note(summary)}) to {summary['path']} in "
        f"{summary['seconds']:.1f} s"
    )
    return summary
