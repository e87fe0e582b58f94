"""The fused map in the formats other tools load, written by Open3D: the cloud as PCD (PCL,
binary), the TSDF mesh as OBJ (vertex colours as ``v x y z r g b``) and as GLB (binary glTF)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rgbdslam.errors import InputError
from rgbdslam.io.atomic import atomic_path


def _written(ok: bool, path: Path) -> None:
    if not ok:
        raise InputError(f"Open3D could not write {path}; check that the folder is writable and the disk not full")


def write_pcd(run, out: Path) -> list[Path]:
    import open3d as o3d

    ply = run.map_ply("cloud.ply")
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(ply["points"]))
    if "colors" in ply:
        pc.colors = o3d.utility.Vector3dVector(ply["colors"])
    if "normals" in ply:
        pc.normals = o3d.utility.Vector3dVector(ply["normals"])
    path = out / "cloud.pcd"
    with atomic_path(path) as tmp:
        _written(o3d.io.write_point_cloud(str(tmp), pc, write_ascii=False, compressed=False), path)
    return [path]


def _mesh(run):
    """map/mesh.ply as an Open3D mesh (read by NumPy: a damaged file is one line, not RPly's)."""
    import open3d as o3d

    ply = run.map_ply("mesh.ply")
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(ply["points"]),
                                     o3d.utility.Vector3iVector(ply.get("triangles", np.zeros((0, 3), np.int64))))
    if "colors" in ply:
        mesh.vertex_colors = o3d.utility.Vector3dVector(ply["colors"])
    if "normals" in ply:
        mesh.vertex_normals = o3d.utility.Vector3dVector(ply["normals"])
    else:
        mesh.compute_vertex_normals()
    return mesh


def write_obj(run, out: Path) -> list[Path]:
    import open3d as o3d

    path = out / "mesh.obj"
    with atomic_path(path) as tmp:
        _written(o3d.io.write_triangle_mesh(str(tmp), _mesh(run), write_triangle_uvs=False), path)
    return [path]


def write_glb(run, out: Path) -> list[Path]:
    import open3d as o3d

    path = out / "mesh.glb"
    with atomic_path(path) as tmp:
        _written(o3d.io.write_triangle_mesh(str(tmp), _mesh(run)), path)
    return [path]
