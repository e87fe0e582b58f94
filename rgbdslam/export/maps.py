"""The fused map in the formats other tools load, written by Open3D: the cloud as PCD (PCL,
binary), the TSDF mesh as OBJ (vertex colours as ``v x y z r g b``) and as GLB (binary glTF)."""

from __future__ import annotations

from pathlib import Path

from rgbdslam.errors import InputError
from rgbdslam.io.atomic import atomic_path


def _written(ok: bool, path: Path) -> None:
    if not ok:
        raise InputError(f"Open3D could not write {path}; check that the folder is writable and the disk not full")


def write_pcd(run, out: Path) -> list[Path]:
    import open3d as o3d

    pc = o3d.io.read_point_cloud(str(run.map_file("cloud.ply")))
    path = out / "cloud.pcd"
    with atomic_path(path) as tmp:
        _written(o3d.io.write_point_cloud(str(tmp), pc, write_ascii=False, compressed=False), path)
    return [path]


def _mesh(run):
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(run.map_file("mesh.ply")))
    if not mesh.has_vertex_normals():
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
