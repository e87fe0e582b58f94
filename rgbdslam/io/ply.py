"""Binary PLY files (point clouds and triangle meshes) written by NumPy in one piece.

Open3D's writer (RPly) prints one "RPly: Failed writing ..." line per element when the disk
fills up and still reports success; this writer makes the whole file in memory and writes it
through :func:`rgbdslam.io.atomic.atomic_path`, so a full disk is one OSError naming the file
and an earlier file at that path stays as it was. The layout is Open3D's (double x y z, double
nx ny nz, uchar red green blue; faces as ``list uchar uint``), so any PLY reader loads it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rgbdslam.io.atomic import atomic_path


def ply_bytes(points: np.ndarray, colors: np.ndarray | None = None, normals: np.ndarray | None = None,
              triangles: np.ndarray | None = None) -> bytes:
    """The binary little-endian PLY of ``points`` (N, 3) with optional ``normals`` (N, 3),
    ``colors`` (N, 3) in [0, 1] (stored as uchar, rounded) and ``triangles`` (M, 3) indices."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    n = len(points)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    header = ["ply", "format binary_little_endian 1.0", "comment Created by rgbdslam", f"element vertex {n}",
              "property double x", "property double y", "property double z"]
    if normals is not None:
        fields += [("nx", "<f8"), ("ny", "<f8"), ("nz", "<f8")]
        header += ["property double nx", "property double ny", "property double nz"]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    vert = np.empty(n, dtype=fields)
    vert["x"], vert["y"], vert["z"] = points.T
    if normals is not None:
        vert["nx"], vert["ny"], vert["nz"] = np.asarray(normals, np.float64).reshape(-1, 3).T
    if colors is not None:
        c = np.clip(np.round(np.asarray(colors, np.float64).reshape(-1, 3) * 255.0), 0, 255).astype(np.uint8)
        vert["red"], vert["green"], vert["blue"] = c.T
    body = [vert.tobytes()]
    if triangles is not None:
        tri = np.asarray(triangles, np.int64).reshape(-1, 3)
        header += [f"element face {len(tri)}", "property list uchar uint vertex_indices"]
        faces = np.empty(len(tri), dtype=[("k", "u1"), ("v", "<u4", (3,))])
        faces["k"] = 3
        faces["v"] = tri
        body.append(faces.tobytes())
    return ("\n".join(header + ["end_header"]) + "\n").encode("ascii") + b"".join(body)


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None,
              normals: np.ndarray | None = None, triangles: np.ndarray | None = None) -> None:
    """Write :func:`ply_bytes` atomically to ``path`` (an OSError names ``path``)."""
    data = ply_bytes(points, colors, normals, triangles)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_cloud_ply(path: str | Path, points: np.ndarray, colors: np.ndarray) -> None:
    """cloud.ply of ``points`` and their uint8 ``colors``: the bytes Open3D's cloud of them gave (its
    colours are uint8 / 255 as float64, rounded back). Here, not beside the fusion: the run process
    of a live map writes it and never imports Open3D (~1 s of CPU after the last frame)."""
    write_ply(path, np.asarray(points, dtype=np.float64), colors.astype(np.float64) * (1 / 255.0))
