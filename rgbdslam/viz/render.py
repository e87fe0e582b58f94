"""Off-screen PNG previews of a run's fused map (``rgbdslam fuse --render``): map/cloud.png, map/mesh.png.

Open3D's ``OffscreenRenderer`` needs a GPU context (EGL/Vulkan) that headless machines often
lack (here it fails with "Failed to load vulkan library"), so this renders with NumPy:
points are projected into a virtual pinhole camera and the nearest one per pixel is kept
(z-buffer splatting: every point covers a small square whose side shrinks with depth). The
mesh is drawn as its vertices, shaded by their normals (Lambert, light from the viewer),
which reads as a surface at TSDF resolution; the cloud is drawn in its own colours.

The viewpoint stands ``back`` metres behind the cameras' mean position (away from the
cloud's median point) and ``lift`` metres above it, level with the floor found by the 2-D
map (map/map2d.yaml), looking at the cloud's median point.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import yaml

from rgbdslam.errors import InputError
from rgbdslam.geometry.se3 import inv, look_along
from rgbdslam.io.atomic import atomic_path
from rgbdslam.io.trajectory import read_tum


def up_vector(run_dir: Path, poses: np.ndarray) -> np.ndarray:
    """World "up": the floor normal of map/map2d.yaml, else minus the cameras' mean image-down axis."""
    meta = run_dir / "map" / "map2d.yaml"
    if meta.is_file():
        T = np.array(yaml.safe_load(meta.read_text())["rgbdslam_world_to_map"])
        return T[2, :3]
    d = -poses[:, :3, 1].mean(axis=0)
    return d / np.linalg.norm(d)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera (OpenCV axes: x right, y down, z forward) looking from eye at target."""
    return inv(look_along(eye, target - eye, up))


def default_view(points: np.ndarray, poses: np.ndarray, up: np.ndarray,
                 back: float = 1.0, lift: float = 0.8) -> np.ndarray:
    """Look at the cloud's median point from behind the cameras' mean position, raised by ``lift``."""
    target = np.median(points, axis=0)
    centre = poses[:, :3, 3].mean(axis=0)
    fwd = target - centre
    fwd -= (fwd @ up) * up
    fwd /= max(np.linalg.norm(fwd), 1e-9)
    return look_at(centre - back * fwd + lift * up, target, up)


def splat(points: np.ndarray, colors: np.ndarray, w2c: np.ndarray, width: int, height: int,
          hfov_deg: float = 80.0, size: float = 2.5, background=(255, 255, 255)) -> np.ndarray:
    """Nearest-point image (H, W, 3) uint8 of coloured points seen by the camera ``w2c``."""
    f = 0.5 * width / np.tan(np.deg2rad(hfov_deg) / 2)
    P = points @ w2c[:3, :3].T + w2c[:3, 3]
    ok = P[:, 2] > 0.05
    P, C = P[ok], colors[ok]
    u = f * P[:, 0] / P[:, 2] + width / 2
    v = f * P[:, 1] / P[:, 2] + height / 2
    r = np.clip(np.ceil(size * 1.5 / P[:, 2]).astype(int), 1, 6)  # splat radius shrinks with depth
    us, vs, zs, cs = [], [], [], []
    for rad in np.unique(r):
        sel = r == rad
        for du in range(-rad + 1, rad):
            for dv in range(-rad + 1, rad):
                us.append(np.round(u[sel]).astype(int) + du)
                vs.append(np.round(v[sel]).astype(int) + dv)
                zs.append(P[sel, 2])
                cs.append(C[sel])
    u, v, z, c = (np.concatenate(x) for x in (us, vs, zs, cs))
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    pix, z, c = (v * width + u)[inside], z[inside], c[inside]
    order = np.lexsort((z, pix))  # by pixel, nearest first
    pix, c = pix[order], c[order]
    first = np.r_[True, pix[1:] != pix[:-1]]
    img = np.empty((height * width, 3), np.uint8)
    img[:] = background
    img[pix[first]] = c[first]
    return img.reshape(height, width, 3)


def shade(mesh: o3d.geometry.TriangleMesh, w2c: np.ndarray) -> np.ndarray:
    """Per-vertex grey-blue Lambert shading with the light at the viewer."""
    if not mesh.has_vertex_normals():
        mesh.compute_vertex_normals()
    V = np.asarray(mesh.vertices)
    N = np.asarray(mesh.vertex_normals)
    eye = -w2c[:3, :3].T @ w2c[:3, 3]
    to_eye = eye - V
    to_eye /= np.linalg.norm(to_eye, axis=1, keepdims=True)
    lam = np.abs(np.sum(N * to_eye, axis=1))  # TSDF normals may face either way
    base = np.array([200.0, 205.0, 215.0])
    if mesh.has_vertex_colors():  # tint with the fused colour, keep the shading dominant
        base = 0.5 * base + 0.5 * 255 * np.asarray(mesh.vertex_colors)
    return np.clip(base * (0.25 + 0.75 * lam[:, None]), 0, 255).astype(np.uint8)


def render_run(run_dir: str | Path, out: str | Path | None = None, prefix: str = "", width: int = 640,
               back: float = 1.0, lift: float = 0.8) -> list[Path]:
    """Write ``{prefix}mesh.png`` and ``{prefix}cloud.png`` of RUN_DIR/map into ``out`` (default
    RUN_DIR/map), atomically; returns the written paths."""
    run_dir = Path(run_dir)
    out = Path(out) if out is not None else run_dir / "map"
    if not (run_dir / "trajectory.tum").is_file():
        raise InputError(f"{run_dir} has no trajectory.tum; give the --out folder of `rgbdslam run`")
    mesh_path, cloud_path = run_dir / "map" / "mesh.ply", run_dir / "map" / "cloud.ply"
    if not cloud_path.is_file() and not mesh_path.is_file():
        raise InputError(f"{run_dir / 'map'} holds no cloud.ply or mesh.ply; run `rgbdslam fuse {run_dir}` first")
    if width < 16:
        raise InputError(f"the render width must be at least 16 pixels (got {width})")
    height = width * 3 // 4
    traj = read_tum(run_dir / "trajectory.tum")
    pc = o3d.io.read_point_cloud(str(cloud_path)) if cloud_path.is_file() else None
    mesh = o3d.io.read_triangle_mesh(str(mesh_path)) if mesh_path.is_file() else None
    pts = np.asarray(pc.points) if pc is not None else np.asarray(mesh.vertices)
    w2c = default_view(pts, traj.poses, up_vector(run_dir, traj.poses), back, lift)
    written = []
    if mesh is not None and len(mesh.vertices):
        img = splat(np.asarray(mesh.vertices), shade(mesh, w2c), w2c, width, height, size=2.0)
        written.append(_write_png(out / f"{prefix}mesh.png", img))
    if pc is not None and len(pc.points):
        col = (np.asarray(pc.colors) * 255).astype(np.uint8)
        img = splat(np.asarray(pc.points), col, w2c, width, height, size=2.5)
        written.append(_write_png(out / f"{prefix}cloud.png", img))
    return written


def _write_png(path: Path, rgb: np.ndarray) -> Path:
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9]):
            raise InputError(f"could not write {path}; check that the folder is writable")
    return path
