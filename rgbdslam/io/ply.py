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


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
              "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
              "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}
MAX_PLY_HEADER = 64 * 1024  # bytes: a header longer than this is no map file


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """A binary little-endian PLY (as :func:`ply_bytes` and Open3D write them) read by NumPy:
    ``{"points": (N, 3) float64, "normals"?: (N, 3), "colors"?: (N, 3) float64 in [0, 1],
    "triangles"?: (M, 3) int64}``. A file cut short, with bytes beyond its elements or a header
    this reader does not take is a ValueError saying what (never a partial mesh, never a
    library's own lines)."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n", 0, MAX_PLY_HEADER)
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError("it is not a PLY file (no 'ply' ... 'end_header' header)")
    elements: list[tuple[str, int, list]] = []
    for line in data[:end].decode("ascii", "replace").splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and words[1:] != ["binary_little_endian", "1.0"]:
            raise ValueError(f"its format is {' '.join(words[1:])}, not binary_little_endian 1.0")
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in _PLY_TYPES:
            elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
        elif (words[0] == "property" and elements and len(words) == 5 and words[1] == "list"
              and words[2] in _PLY_TYPES and words[3] in _PLY_TYPES):
            elements[-1][2].append((words[4], (_PLY_TYPES[words[2]], _PLY_TYPES[words[3]])))
        elif words[0] != "format":
            raise ValueError(f"its header line {line[:60]!r} is not one this reader takes")
    pos = end + len(b"end_header\n")
    out: dict[str, np.ndarray] = {}
    for name, count, props in elements:
        lists = [p for p in props if isinstance(p[1], tuple)]
        if lists:  # faces: one list of 3 indices each (triangles), nothing else
            if len(props) != 1:
                raise ValueError(f"its element '{name}' mixes a list with other properties")
            count_t, index_t = lists[0][1]
            dtype = np.dtype([("k", count_t), ("v", index_t, (3,))])
        else:
            dtype = np.dtype([(p, t) for p, t in props])
        need = count * dtype.itemsize
        if len(data) - pos < need:
            raise ValueError(f"it is cut short: its element '{name}' needs {need} bytes, {max(len(data) - pos, 0)} "
                             f"are left")
        arr = np.frombuffer(data, dtype, count, pos)
        pos += need
        if lists:
            if count and not np.all(arr["k"] == 3):
                raise ValueError(f"its element '{name}' has lists that are not triangles")
            out["triangles"] = arr["v"].astype(np.int64)
        elif name == "vertex":
            cols = dtype.names or ()
            if not {"x", "y", "z"} <= set(cols):
                raise ValueError("its vertices have no x, y, z")
            out["points"] = np.stack([arr[c].astype(np.float64) for c in ("x", "y", "z")], axis=1)
            if {"nx", "ny", "nz"} <= set(cols):
                out["normals"] = np.stack([arr[c].astype(np.float64) for c in ("nx", "ny", "nz")], axis=1)
            if {"red", "green", "blue"} <= set(cols):
                rgb = np.stack([arr[c] for c in ("red", "green", "blue")], axis=1)
                out["colors"] = rgb.astype(np.float64) / (255.0 if rgb.dtype == np.uint8 else 1.0)
    if pos != len(data):
        raise ValueError(f"it has {len(data) - pos} bytes after its last element")
    if "points" not in out:
        raise ValueError("it has no vertex element")
    n = len(out["points"])
    tri = out.get("triangles")
    if tri is not None and len(tri) and (tri.min() < 0 or tri.max() >= n):
        raise ValueError(f"a triangle names a vertex outside 0..{n - 1}")
    return out
