"""nerfstudio / Instant-NGP ``transforms.json`` with the keyframes' images and depth.

Layout::

    nerfstudio/transforms.json     intrinsics at the top (camera_model OPENCV, fl_x fl_y cx cy w h,
                                   k1 k2 p1 p2 = 0: the images are undistorted), one entry per keyframe
    nerfstudio/images/<frame:06d>.png
    nerfstudio/depth/<frame:06d>.png   16-bit depth in millimetres (nerfstudio's default
                                       depth_unit_scale_factor 1e-3), 0 = no depth
    nerfstudio/sparse_pc.ply       the map's points (``ply_file_path``: splatfacto's initial points)

Instant-NGP reads the same file (``depth_path`` and ``integer_depth_scale`` name the depth for it).

``transform_matrix`` is camera-to-world in the OpenGL/Blender convention nerfstudio and
Instant-NGP use (x right, y up, z back): the run's OpenCV-axis pose times diag(1, -1, -1, 1).
The world frame is the run's (its first camera); nerfstudio re-centres and scales the poses
itself (``auto_scale_poses``). Principal points are in nerfstudio's pixel-centre convention
(the centre of the top-left pixel is 0.5, 0.5), i.e. OpenCV's cx + 0.5.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from rgbdslam.export.run import DEPTH_MM, RunExport, staged_folder
from rgbdslam.io.images import write_png
from rgbdslam.io.ply import write_cloud_ply

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def write_nerfstudio(run: RunExport, out: Path) -> list[Path]:
    cam = run.camera
    final = out / "nerfstudio"
    with staged_folder(final) as stage:
        (stage / "images").mkdir()
        (stage / "depth").mkdir()
        frames = []
        for view in run.views():
            name = f"{view.index:06d}.png"
            write_png(stage / "images" / name, cv2.cvtColor(view.rgb, cv2.COLOR_RGB2BGR))
            d = np.clip(np.round(view.depth * DEPTH_MM), 0, 65535).astype(np.uint16)
            write_png(stage / "depth" / name, d)
            frames.append({
                "file_path": f"images/{name}",
                "depth_file_path": f"depth/{name}",
                "depth_path": f"depth/{name}",  # Instant-NGP's key for the same file
                "transform_matrix": (view.pose @ OPENCV_TO_OPENGL).tolist(),
                "timestamp": view.timestamp,
                "frame_index": view.index,
            })
        points, colors, _ = run.points()
        write_cloud_ply(stage / "sparse_pc.ply", points, colors)
        doc = {
            "camera_model": "OPENCV",
            "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx + 0.5, "cy": cam.cy + 0.5,
            "w": cam.width, "h": cam.height,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
            "ply_file_path": "sparse_pc.ply",
            "integer_depth_scale": 1.0 / DEPTH_MM,  # Instant-NGP: metres per depth-PNG unit
            "frames": frames,
        }
        (stage / "transforms.json").write_text(json.dumps(doc, indent=2) + "\n")
    return [final / "transforms.json", final / "images", final / "depth", final / "sparse_pc.ply"]
