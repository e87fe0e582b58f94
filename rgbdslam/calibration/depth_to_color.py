"""Where the depth images of an unregistered RGB-D sequence sit in its colour images.

For sequences whose colour and depth come from two cameras with no published calibration
(7-Scenes): a grid search over the colour camera's focal length and the depth-to-colour
translation (x, y) that best puts the depth image's discontinuities (object outlines) onto edges
of the colour image. Score: the mean colour-gradient magnitude (grey, Sobel, blurred) at the
colour pixels where the near side of every depth discontinuity lands, over frames sampled evenly
over the sequence. No ground truth is used. :func:`write_camera_file` writes the best setting as a
camera file for ``rgbdslam run --camera`` (its ``depth_camera`` is the sequence's own intrinsics).

On 7-Scenes frames 0-299 (15 frames, the default grid) the best colour focal length is 530 px
(525 next), the camera file shipped as ``rgbdslam/cameras/7scenes.yaml``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np
import yaml

from rgbdslam.datasets import open_sequence
from rgbdslam.datasets.base import Sequence
from rgbdslam.datasets.tum import RgbdFileSequence
from rgbdslam.errors import InputError
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import rotation_angle
from rgbdslam.io.atomic import atomic_write_text

def grid(text: str, what: str) -> np.ndarray:
    """The values ``lo, lo + step, ..., hi`` of ``"lo:hi:step"``; an InputError naming ``what`` otherwise."""
    try:
        lo, hi, step = (float(x) for x in text.split(":"))
    except ValueError:
        raise InputError(f"{what} '{text}' is not lo:hi:step (three numbers, e.g. 500:600:5)") from None
    if not (np.isfinite([lo, hi, step]).all() and step > 0 and hi >= lo and (hi - lo) / step <= 1e4):
        raise InputError(f"{what} '{text}' needs lo <= hi and a step > 0 giving at most 10000 values")
    return np.round(np.arange(lo, hi + step / 2, step), 6)


def edge_points(depth: np.ndarray, cam: Camera, jump: float = 0.05) -> np.ndarray:
    """Camera-frame points (N, 3) of the near side of depth discontinuities (> ``jump`` relative)."""
    d = depth.astype(np.float64)
    pts = []
    for dy, dx in ((0, 1), (1, 0)):
        a = d[: d.shape[0] - dy, : d.shape[1] - dx]
        b = d[dy:, dx:]
        ok = (a > 0) & (b > 0)
        near_a = ok & (b - a > jump * a)  # a is nearer: the outline pixel is a
        near_b = ok & (a - b > jump * b)
        for mask, off in ((near_a, (0, 0)), (near_b, (dy, dx))):
            v, u = np.nonzero(mask)
            v, u = v + off[0], u + off[1]
            z = d[v, u]
            pts.append(np.stack([(u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy, z], axis=1))
    return np.concatenate(pts)


def gradient(rgb: np.ndarray) -> np.ndarray:
    """The blurred colour-gradient magnitude of an RGB (or grey) image."""
    g = (cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb).astype(np.float32)
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.GaussianBlur(np.hypot(gx, gy), (5, 5), 1.5)


def score(samples: list[tuple[np.ndarray, np.ndarray]], f: float, cx: float, cy: float, tx: float = 0.0,
          ty: float = 0.0, T: np.ndarray | None = None, fy: float | None = None) -> float:
    """Mean colour gradient where the depth outlines land: each sample's depth-camera points
    moved by t = (tx, ty, 0) (or by the whole 4x4 depth-to-colour ``T``, rotation included) and
    projected with the colour focal length ``f`` (``fy``: its y focal length, default ``f``)."""
    fy = f if fy is None else fy
    total, n = 0.0, 0
    for P, grad in samples:
        if T is not None:
            P = P @ T[:3, :3].T + T[:3, 3]
            tx = ty = 0.0
        z = P[:, 2]
        u = np.round(f * (P[:, 0] + tx) / z + cx).astype(np.int64)
        v = np.round(fy * (P[:, 1] + ty) / z + cy).astype(np.int64)
        ok = (u >= 0) & (u < grad.shape[1]) & (v >= 0) & (v < grad.shape[0])
        total += float(grad[v[ok], u[ok]].sum())
        n += int(ok.sum())
    return total / max(n, 1)


def open_as_recorded(path, work) -> Sequence:
    """The sequence in ``path`` as its files hold it: when its camera file re-projects depth into
    the colour camera (7-Scenes' shipped camera), it is opened again through a camera file in the
    folder ``work`` that names the depth camera for both images, so the search starts from the
    recording, not from an earlier calibration."""
    from pathlib import Path

    from rgbdslam.datasets.config import DatasetConfig

    seq = open_sequence(path)
    setup = seq.camera_setup
    if setup is None or setup.depth_camera is None:
        return seq
    d = setup.depth_camera
    data = {"fx": d.fx, "fy": d.fy, "cx": d.cx, "cy": d.cy, "size": [d.width, d.height], "distortion": list(d.dist)}
    if isinstance(seq, RgbdFileSequence):
        data["depth_scale"] = seq.depth_scale
    file = Path(work) / "recorded_camera.yaml"
    atomic_write_text(file, yaml.safe_dump({k: (float(v) if isinstance(v, (float, np.floating)) else v)
                                            for k, v in data.items()}, sort_keys=False))
    return open_sequence(path, DatasetConfig(camera_file=str(file)))


def samples_of(seq: Sequence, frames: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(depth outline points, colour gradient) of ``frames`` frames spread evenly over ``seq``."""
    if len(seq) == 0:
        raise InputError(f"{seq.root} has no frames to calibrate with")
    idx = np.linspace(0, len(seq) - 1, min(frames, len(seq))).round().astype(int)
    out = []
    for i in idx:
        fr = seq.load(int(i))
        out.append((edge_points(fr.depth, seq.camera), gradient(fr.rgb)))
    return out


@dataclass
class Setting:
    score: float
    focal: float  # the colour camera's focal length (pixels)
    tx: float  # depth-to-colour translation (m)
    ty: float


def search(samples, cam: Camera, focal: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> list[Setting]:
    """Every (focal, tx, ty) of the grid scored, best first (the principal point stays the sequence's)."""
    out = [Setting(score(samples, f, cam.cx, cam.cy, x, y), float(f), float(x), float(y))
           for f, x, y in itertools.product(focal, tx, ty)]
    out.sort(key=lambda s: (s.score, s.focal, s.tx, s.ty), reverse=True)
    return out


def score_camera_file(samples, path) -> tuple[float, str]:
    """The score of a camera file's colour intrinsics and depth_to_color (rotation included), and a
    line describing the file's values."""
    from rgbdslam.datasets.camera_file import read_camera_file

    setup = read_camera_file(path)
    c = setup.camera
    T = setup.depth_to_color if setup.depth_to_color is not None else np.eye(4)
    s = score(samples, c.fx, c.cx, c.cy, T=T, fy=c.fy)
    return s, (f"colour focal {c.fx:g}, t = ({T[0, 3]:+.4f}, {T[1, 3]:+.4f}, {T[2, 3]:+.4f}) m, "
               f"rotation {np.degrees(rotation_angle(T[:3, :3])):.2f} deg")


def write_camera_file(path, seq: Sequence, best: Setting, recorded: float, command: str) -> None:
    """A camera file (docs/formats.md "Camera file") with the colour focal length and offset of
    ``best``; the depth camera is the sequence's own camera, its depth scale the sequence's."""
    cam = seq.camera
    depth_cam = {"fx": float(cam.fx), "fy": float(cam.fy), "cx": float(cam.cx), "cy": float(cam.cy),
                 "size": [cam.width, cam.height]}
    data = {"fx": best.focal, "fy": best.focal, "cx": float(cam.cx), "cy": float(cam.cy),
            "size": [cam.width, cam.height]}
    if isinstance(seq, RgbdFileSequence):
        data["depth_scale"] = seq.depth_scale
    data.update(depth_camera=depth_cam, depth_to_color=[best.tx, best.ty, 0.0])
    head = (f"# written by `{command}`\n"
            f"# edge-alignment score {best.score:.2f} (as recorded: {recorded:.2f})\n")
    atomic_write_text(path, head + yaml.safe_dump(data, sort_keys=False, default_flow_style=None))
