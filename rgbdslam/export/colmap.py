"""COLMAP text model of a run, for Gaussian splatting / NeRF tools that start from COLMAP.

Layout (what 3D Gaussian Splatting and nerfstudio's ``colmap`` loader expect)::

    colmap/images/<frame:06d>.png          the keyframes, undistorted to the pinhole below
    colmap/sparse/0/cameras.txt            one PINHOLE camera: fx fy cx cy
    colmap/sparse/0/images.txt             per keyframe: world-to-camera quaternion (w x y z) and
                                           translation, camera id, image name; then its 2-D points
    colmap/sparse/0/points3D.txt           the map's points with colour and track

The points are the fused cloud subsampled to ``--max-points`` (or the keyframes' depth
back-projected when the run has no map). Each point's track lists the keyframes that see it:
it projects inside the image and the keyframe's depth there agrees with the point's depth
(within ``TRACK_TOLERANCE`` + 2 % of the depth); the 2-D point is that projection, so the
reprojection error column is 0 by construction (the points come from depth, not from
triangulated features).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from rgbdslam.export.run import RunExport, staged_folder
from rgbdslam.geometry.se3 import inv, pose_to_tum
from rgbdslam.io.images import write_png

TRACK_TOLERANCE = 0.03  # metres (+ 2 % of the depth) between a point and the keyframe depth that sees it


def _visible(P_world: np.ndarray, pose: np.ndarray, depth: np.ndarray, cam) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the points a view sees (in the image, depth agrees) and their pixel positions."""
    w2c = inv(pose)
    Pc = P_world @ w2c[:3, :3].T + w2c[:3, 3]
    z = Pc[:, 2]
    front = np.flatnonzero(z > 1e-6)
    u = cam.fx * Pc[front, 0] / z[front] + cam.cx
    v = cam.fy * Pc[front, 1] / z[front] + cam.cy
    h, w = depth.shape
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    front, u, v = front[inside], u[inside], v[inside]
    d = depth[np.round(v).astype(int), np.round(u).astype(int)]
    ok = (d > 0) & (np.abs(d - z[front]) <= TRACK_TOLERANCE + 0.02 * z[front])
    return front[ok], np.stack([u[ok], v[ok]], axis=1)


def write_colmap(run: RunExport, out: Path) -> list[Path]:
    cam = run.camera
    points, colors, _ = run.points()
    n = len(points)
    tracks: list[list[tuple[int, int]]] = [[] for _ in range(n)]
    final = out / "colmap"
    with staged_folder(final) as stage:
        (stage / "images").mkdir()
        (stage / "sparse" / "0").mkdir(parents=True)
        image_lines = [
            "# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
            "#   POINTS2D[] as (X, Y, POINT3D_ID)",
            f"# Number of images: {len(run.keyframes)}; poses are world-to-camera, exported by rgbdslam "
            f"from {run.run_dir / 'trajectory.tum'}",
        ]
        for image_id, view in enumerate(run.views(), 1):
            name = f"{view.index:06d}.png"
            write_png(stage / "images" / name, cv2.cvtColor(view.rgb, cv2.COLOR_RGB2BGR))
            w2c = inv(view.pose)
            t, q = pose_to_tum(w2c)  # x y z w
            t, q = t[0], q[0]
            image_lines.append(f"{image_id} {q[3]:.12f} {q[0]:.12f} {q[1]:.12f} {q[2]:.12f} "
                               f"{t[0]:.12f} {t[1]:.12f} {t[2]:.12f} 1 {name}")
            seen, uv = _visible(points, view.pose, view.depth, cam)
            for k, (pid, (u, v)) in enumerate(zip(seen, uv)):
                tracks[pid].append((image_id, k))
            # COLMAP's pixel centres are at +0.5 (the top-left corner is 0,0); OpenCV's at integers
            image_lines.append(" ".join(f"{u + 0.5:.3f} {v + 0.5:.3f} {pid + 1}" for pid, (u, v) in zip(seen, uv)))
        (stage / "sparse" / "0" / "images.txt").write_text("\n".join(image_lines) + "\n")
        (stage / "sparse" / "0" / "cameras.txt").write_text(
            "# Camera list with one line of data per camera:\n"
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
            "# Number of cameras: 1\n"
            f"1 PINHOLE {cam.width} {cam.height} {cam.fx:.9f} {cam.fy:.9f} {cam.cx + 0.5:.9f} {cam.cy + 0.5:.9f}\n")
        lines = ["# 3D point list with one line of data per point:",
                 "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
                 f"# Number of points: {n}"]
        for pid in range(n):
            p, c = points[pid], colors[pid]
            track = " ".join(f"{i} {k}" for i, k in tracks[pid])
            lines.append(f"{pid + 1} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {c[0]} {c[1]} {c[2]} 0 {track}".rstrip())
        (stage / "sparse" / "0" / "points3D.txt").write_text("\n".join(lines) + "\n")
    return [final / "sparse" / "0" / f for f in ("cameras.txt", "images.txt", "points3D.txt")] + [final / "images"]
