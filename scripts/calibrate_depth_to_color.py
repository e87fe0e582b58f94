"""Estimate how the depth images of an unregistered RGB-D sequence sit in its colour images.

For sequences whose colour and depth come from two cameras with no published calibration
(7-Scenes): a grid search over the colour camera's focal length and the depth-to-colour
translation (x, y) that best puts the depth image's discontinuities (object outlines) onto
edges of the colour image. Score: the mean colour-gradient magnitude (grey, Sobel, blurred) at
the colour pixels where the near side of every depth discontinuity lands, over a sample of
frames. No ground truth is used. Prints the best values and writes a camera file for
``rgbdslam run --camera`` (depth_camera = the sequence's own intrinsics).

    .venv/bin/python scripts/calibrate_depth_to_color.py ../shared/data/7scenes/frames_0000_0299 \\
        --out my_7scenes_camera.yaml
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import yaml

from rgbdslam.datasets import open_sequence
from rgbdslam.geometry.camera import Camera


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
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def gradient(rgb: np.ndarray) -> np.ndarray:
    g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.GaussianBlur(np.hypot(gx, gy), (5, 5), 1.5)


def score(samples, f: float, cx: float, cy: float, tx: float, ty: float, T: np.ndarray | None = None,
          fy: float | None = None) -> float:
    """Mean colour gradient where the depth outlines land: the depth camera's points moved by
    t = (tx, ty, 0) (or by the whole 4x4 depth-to-colour ``T``, rotation included) and projected
    with the colour focal length ``f`` (``fy``: its y focal length, default ``f``)."""
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence")
    ap.add_argument("--frames", type=int, default=15, help="frames sampled evenly over the sequence")
    ap.add_argument("--focal", default="500:600:5", help="colour focal lengths lo:hi:step (pixels)")
    ap.add_argument("--tx", default="-0.06:0.06:0.005", help="depth-to-colour x translation lo:hi:step (m)")
    ap.add_argument("--ty", default="-0.03:0.03:0.005", help="depth-to-colour y translation lo:hi:step (m)")
    ap.add_argument("--out", default=None, help="write a camera file with the best values")
    ap.add_argument("--check", nargs="+", default=[], metavar="CAMERA_FILE",
                    help="also score these camera files (colour intrinsics + depth_to_color, rotation included), "
                         "e.g. a published calibration, on the same frames")
    a = ap.parse_args()

    def rng(text):
        lo, hi, step = (float(x) for x in text.split(":"))
        return np.round(np.arange(lo, hi + step / 2, step), 6)

    seq = open_sequence(a.sequence)
    cam = seq.camera
    idx = np.linspace(0, len(seq) - 1, min(a.frames, len(seq))).round().astype(int)
    samples = []
    for i in idx:
        fr = seq.load(int(i))
        samples.append((edge_points(fr.depth, cam), gradient(fr.rgb)))
    t0 = time.perf_counter()
    results = []
    for f, tx, ty in itertools.product(rng(a.focal), rng(a.tx), rng(a.ty)):
        results.append((score(samples, f, cam.cx, cam.cy, tx, ty), f, tx, ty))
    results.sort(reverse=True)
    base = score(samples, cam.fx, cam.cx, cam.cy, 0.0, 0.0)
    print(f"{len(results)} settings, {len(idx)} frames, {time.perf_counter() - t0:.1f} s")
    print(f"as recorded (colour = depth camera, no offset): score {base:.2f}")
    for s, f, tx, ty in results[:5]:
        print(f"score {s:.2f}: colour focal {f:g}, depth-to-colour t = ({tx:+.3f}, {ty:+.3f}, 0) m")
    for path in a.check:
        from rgbdslam.datasets.camera_file import read_camera_file

        setup = read_camera_file(path)
        c, T = setup.camera, setup.depth_to_color if setup.depth_to_color is not None else np.eye(4)
        print(f"score {score(samples, c.fx, c.cx, c.cy, 0.0, 0.0, T=T, fy=c.fy):.2f}: {path} (colour focal {c.fx:g}, "
              f"t = ({T[0, 3]:+.4f}, {T[1, 3]:+.4f}, {T[2, 3]:+.4f}) m, rotation "
              f"{np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1))):.2f} deg)")
    _, f, tx, ty = results[0]
    if a.out:
        data = {
            "fx": float(f), "fy": float(f), "cx": float(cam.cx), "cy": float(cam.cy), "size": [cam.width, cam.height],
            "depth_scale": 1000,
            "depth_camera": {"fx": float(cam.fx), "fy": float(cam.fy), "cx": float(cam.cx), "cy": float(cam.cy),
                             "size": [cam.width, cam.height]},
            "depth_to_color": [float(tx), float(ty), 0.0],
        }
        head = (f"# written by scripts/calibrate_depth_to_color.py {' '.join(sys.argv[1:])}\n"
                f"# edge-alignment score {results[0][0]:.2f} (as recorded: {base:.2f}); see docs/benchmarks.md\n")
        Path(a.out).write_text(head + yaml.safe_dump(data, sort_keys=False, default_flow_style=None))
        print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
