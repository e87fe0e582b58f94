"""Top-down 2-D occupancy map of the fused cloud (the stereo thesis' 2-D map, docs/references.md §6).

1. "Up": from TUM's ``accelerometer.txt`` when present, else from the camera poses (a
   hand-held or robot camera is held roughly upright, so the mean of the cameras' image-down
   axes is close to gravity). The Kinect accelerometer reports the gravity vector in its own
   axes; checked against the fr1 ground truth, ``(ax, ay, -az)`` is "down" in the optical
   camera frame (x right, y down, z forward). Each pose's reading (nearest in time) is rotated
   into the world with that pose and the results are averaged.
2. Floor: Open3D ``segment_plane`` RANSAC (seeded) is run repeatedly on the cloud, removing
   each plane's inliers; among the planes whose normal is within ``floor_max_tilt_deg`` of up,
   the lowest one is the floor (a desk top is horizontal too, but higher); it is refined by a
   least-squares fit to the full-resolution points near it. If no such plane is found the floor is the plane normal to up through the 2nd height percentile.
3. Points are expressed in the floor frame (x, y in the floor plane, z = height above it) and
   binned into cells of ``grid_resolution``: a cell with at least ``obstacle_min_points`` points
   between ``obstacle_min_height`` and ``obstacle_max_height`` is occupied, a cell with floor
   points (|height| < ``floor_band``) only is free, every other cell is unknown.

Output follows ROS map_server: ``map2d.png`` (0 occupied, 254 free, 205 unknown; the first
image row is the largest y), ``map2d.yaml`` (image, resolution, origin [x, y, yaw] of the
lower-left pixel, negate, occupied_thresh, free_thresh, plus ``rgbdslam_world_to_map``, the
4x4 transform from the SLAM world frame into the map frame) and ``map2d_preview.png`` with
the trajectory drawn on the map (start green, end blue).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from rgbdslam.errors import InputError
from rgbdslam.io.atomic import atomic_path, atomic_write_text, interrupts_deferred, make_dirs
from rgbdslam.io.text import read_lines
from rgbdslam.io.numbers import check_magnitude, check_stamps
from rgbdslam.io.trajectory import Trajectory
from rgbdslam.mapping.config import MappingConfig


OCCUPIED, FREE, UNKNOWN = 0, 254, 205
MAX_CELLS = 25_000_000  # a 5000 x 5000 grid: 250 m x 250 m at 5 cm


@dataclass
class Map2D:
    image: np.ndarray  # (H, W) uint8, ROS values, row 0 = largest y
    resolution: float  # metres per cell
    origin: tuple[float, float, float]  # map-frame (x, y, yaw) of the lower-left pixel
    world_to_map: np.ndarray  # 4x4: SLAM world -> map frame (z = height above the floor)
    up_source: str  # "accelerometer" | "camera"
    floor_source: str  # "ransac" | "percentile"

    def cells(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image (row, col) of world points (may lie outside the image)."""
        q = np.asarray(points_world, dtype=np.float64) @ self.world_to_map[:3, :3].T + self.world_to_map[:3, 3]
        col = np.floor((q[:, 0] - self.origin[0]) / self.resolution).astype(int)
        row_up = np.floor((q[:, 1] - self.origin[1]) / self.resolution).astype(int)
        return self.image.shape[0] - 1 - row_up, col


# ----------------------------------------------------------------------------- up direction


def read_accelerometer(path: str | Path) -> np.ndarray:
    """TUM accelerometer.txt -> (N, 4) array ``timestamp ax ay az``."""
    rows, linenos = [], []
    for lineno, line in enumerate(read_lines(path, "accelerometer file"), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        try:
            vals = [float(x) for x in s.split()]
        except ValueError:
            raise InputError(f"{path}:{lineno}: expected 'timestamp ax ay az'; fix or delete the line") from None
        if len(vals) != 4:
            raise InputError(f"{path}:{lineno}: expected 4 numbers 'timestamp ax ay az'; got {len(vals)}")
        if not np.isfinite(vals).all():
            raise InputError(f"{path}:{lineno}: non-finite value; fix or delete the line")
        rows.append(vals)
        linenos.append(lineno)
    acc = np.array(rows).reshape(-1, 4)
    check_stamps(acc[:, 0], path, linenos)  # all lines at once (line by line was 0.1 s of a run's end)
    check_magnitude(acc[:, 1:], 1e3, path, linenos, "acceleration", "accelerations must be m/s^2")
    return acc


def up_from_accelerometer(acc: np.ndarray, traj: Trajectory) -> np.ndarray | None:
    """World "up" from Kinect accelerometer readings and camera-to-world poses (None if unusable)."""
    if len(acc) == 0 or len(traj) == 0:
        return None
    j = np.clip(np.searchsorted(acc[:, 0], traj.timestamps), 0, len(acc) - 1)
    down_cam = acc[j, 1:] * np.array([1.0, 1.0, -1.0])
    down_cam /= np.maximum(np.linalg.norm(down_cam, axis=1, keepdims=True), 1e-9)
    down_w = np.einsum("nij,nj->ni", traj.poses[:, :3, :3], down_cam).mean(axis=0)
    n = np.linalg.norm(down_w)
    if n < 0.5:  # readings disagree: the pose frames or the accelerometer cannot be trusted
        return None
    return -down_w / n


def up_from_cameras(traj: Trajectory) -> np.ndarray:
    """World "up" as minus the mean image-down (camera +y) axis of the poses."""
    down = traj.poses[:, :3, 1].mean(axis=0) if len(traj) else np.array([0.0, 1.0, 0.0])
    n = np.linalg.norm(down)
    return -down / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])


# ----------------------------------------------------------------------------- floor


def find_floor(points: np.ndarray, up: np.ndarray, cfg: MappingConfig, max_planes: int = 6
               ) -> tuple[np.ndarray, float, str]:
    """Floor plane ``n . p + d = 0`` (n unit, pointing up) of a cloud; returns (n, d, source)."""
    # Open3D imported here, not with the module: a run's process unpickles a Map2D made by its
    # cloud process (rgbdslam.mapping.live) without paying Open3D's import (~1 s) after the last frame
    with interrupts_deferred():  # Ctrl-C during Open3D's start-up leaves its C++ state half made (exit 1
        import open3d as o3d  # and a page of memory statistics at exit): the interrupt waits for the import

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    voxel = max(cfg.grid_resolution, cfg.floor_distance)
    pc = pc.voxel_down_sample(voxel)
    o3d.utility.random.seed(cfg.seed)
    min_inliers = max(30, int(0.01 * len(pc.points)))
    cos_tilt = np.cos(np.deg2rad(cfg.floor_max_tilt_deg))
    candidates = []
    for _ in range(max_planes):
        if len(pc.points) < min_inliers:
            break
        plane, inl = pc.segment_plane(cfg.floor_distance, 3, cfg.floor_ransac_iterations)
        if len(inl) < min_inliers:
            break
        n, d = np.asarray(plane[:3], dtype=np.float64), float(plane[3])
        s = np.linalg.norm(n)
        n, d = n / s, d / s
        if n @ up < 0:
            n, d = -n, -d
        if n @ up >= cos_tilt:
            height = float(np.median(np.asarray(pc.points)[inl] @ n))
            candidates.append((height, len(inl), n, d))
        pc = pc.select_by_index(inl, invert=True)
    if candidates:
        biggest = max(c[1] for c in candidates)
        height, _, n, d = min((c for c in candidates if c[1] >= 0.05 * biggest), key=lambda c: c[0])
        return (*_refine_plane(np.asarray(points, dtype=np.float64), n, d, cfg.floor_distance), "ransac")
    h = np.asarray(points) @ up
    return up.copy(), -float(np.percentile(h, 2)), "percentile"


def _refine_plane(points: np.ndarray, n: np.ndarray, d: float, dist: float) -> tuple[np.ndarray, float]:
    """Least-squares plane (SVD) through the full-resolution points within ``dist`` of ``n . p + d = 0``."""
    near = points[np.abs(points @ n + d) < dist]
    if len(near) < 3:
        return n, d
    c = near.mean(axis=0)
    m = np.linalg.svd(near - c, full_matrices=False)[2][2]
    m = m if m @ n > 0 else -m
    return m, -float(m @ c)


def _floor_frame(n: np.ndarray, d: float) -> np.ndarray:
    """4x4 world -> map: x, y in the floor plane, z = height above it."""
    ref = np.array([1.0, 0.0, 0.0])
    e1 = ref - (ref @ n) * n
    if np.linalg.norm(e1) < 0.3:
        ref = np.array([0.0, 1.0, 0.0])
        e1 = ref - (ref @ n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    T = np.eye(4)
    T[:3, :3] = np.stack([e1, e2, n])
    T[:3, 3] = T[:3, :3] @ (d * n)  # the floor point -d n maps to height 0
    return T


# ----------------------------------------------------------------------------- grid


def build_map2d(points: np.ndarray, trajectory: Trajectory, cfg: MappingConfig,
                accelerometer: str | Path | None = None) -> Map2D:
    """Occupancy grid of world ``points`` (N, 3); see the module docstring for the method."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    res = cfg.grid_resolution
    if isinstance(res, bool) or not isinstance(res, (int, float)) or not np.isfinite(res) or res <= 0:
        raise InputError(f"mapping.grid_resolution must be a positive number of metres per cell (e.g. 0.05); "
                         f"got {res!r}")
    if len(points) == 0:
        raise InputError("the fused cloud is empty, so no 2-D map can be made; check depth range (mapping.depth_max)")
    up, up_source = None, "camera"
    if cfg.gravity in ("auto", "accelerometer") and accelerometer is not None:
        up = up_from_accelerometer(read_accelerometer(accelerometer), trajectory)
        up_source = "accelerometer" if up is not None else "camera"
    if cfg.gravity == "accelerometer" and up is None:
        raise InputError(
            "mapping.gravity is 'accelerometer' but the sequence has no usable accelerometer.txt; "
            "set mapping.gravity=auto"
        )
    if up is None:
        up = up_from_cameras(trajectory)
    n, d, floor_source = find_floor(points, up, cfg)
    T = _floor_frame(n, d)
    q = points @ T[:3, :3].T + T[:3, 3]
    h = q[:, 2]
    floor = np.abs(h) < cfg.floor_band
    obst = (h >= cfg.obstacle_min_height) & (h <= cfg.obstacle_max_height)
    keep = floor | obst
    xy = q[keep, :2]
    if len(trajectory):
        xy_all = np.vstack([xy, (trajectory.positions @ T[:3, :3].T + T[:3, 3])[:, :2]])
    else:
        xy_all = xy
    if len(xy_all) == 0:
        raise InputError("no point of the fused cloud lies on or above the floor; the 2-D map would be empty")
    lo = np.floor(xy_all.min(axis=0) / res) * res - 2 * res
    hi = xy_all.max(axis=0) + 2 * res
    w, hgt = (np.ceil((hi - lo) / res).astype(int) + 1)
    if w * hgt > MAX_CELLS:
        raise InputError(
            f"the 2-D map would have {w} x {hgt} cells at mapping.grid_resolution={res:g} m (at most {MAX_CELLS} "
            f"allowed); raise mapping.grid_resolution (e.g. {res * np.sqrt(w * hgt / MAX_CELLS) * 1.01:.3g}) "
            f"or set mapping.map2d=false"
        )
    col = np.floor((q[:, 0] - lo[0]) / res).astype(int)
    row = hgt - 1 - np.floor((q[:, 1] - lo[1]) / res).astype(int)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < hgt)
    flat = row * w + col
    n_obst = np.bincount(flat[obst & inside], minlength=w * hgt)
    n_floor = np.bincount(flat[floor & inside], minlength=w * hgt)
    img = np.full(w * hgt, UNKNOWN, np.uint8)
    img[n_floor > 0] = FREE
    img[n_obst >= cfg.obstacle_min_points] = OCCUPIED
    return Map2D(img.reshape(hgt, w), res, (float(lo[0]), float(lo[1]), 0.0), T, up_source, floor_source)


def _write_png(path: Path, img: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise InputError(f"could not write {path}; check that the folder is writable")


def render_preview(grid: Map2D, trajectory: Trajectory | None, min_size: int = 600) -> np.ndarray:
    """BGR image of the map scaled up (nearest) to at least ``min_size`` px, trajectory in red."""
    k = max(1, int(np.ceil(min_size / max(grid.image.shape))))
    img = cv2.cvtColor(np.repeat(np.repeat(grid.image, k, 0), k, 1), cv2.COLOR_GRAY2BGR)
    if trajectory is not None and len(trajectory):
        q = trajectory.positions @ grid.world_to_map[:3, :3].T + grid.world_to_map[:3, 3]
        x = (q[:, 0] - grid.origin[0]) / grid.resolution * k
        y = img.shape[0] - (q[:, 1] - grid.origin[1]) / grid.resolution * k
        pts = np.round(np.stack([x, y], 1) * 16).astype(np.int32)  # 4 fractional bits
        cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, (0, 0, 255), 2, cv2.LINE_AA, shift=4)
        cv2.circle(img, tuple(int(v) for v in pts[0]), 6 * 16, (0, 160, 0), -1, cv2.LINE_AA, shift=4)
        cv2.circle(img, tuple(int(v) for v in pts[-1]), 6 * 16, (255, 0, 0), -1, cv2.LINE_AA, shift=4)
    bar = int(round(1.0 / grid.resolution * k))  # 1 m scale bar, bottom left
    if bar < img.shape[1] - 20:
        y0 = img.shape[0] - 12
        cv2.line(img, (10, y0), (10 + bar, y0), (0, 0, 0), 3)
        cv2.putText(img, "1 m", (10, y0 - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([img, legend_strip(img.shape[1], trajectory is not None and len(trajectory) > 0)])


# the preview's legend: (label, kind, BGR colour); kinds: a cell swatch, a line, a dot
LEGEND = [("free", "cell", (FREE,) * 3), ("occupied", "cell", (OCCUPIED,) * 3), ("unknown", "cell", (UNKNOWN,) * 3),
          ("camera path", "line", (0, 0, 255)), ("start", "dot", (0, 160, 0)), ("end", "dot", (255, 0, 0))]


def legend_strip(width: int, with_trajectory: bool = True, row: int = 24) -> np.ndarray:
    """A white BGR strip ``width`` pixels wide naming the preview's colours, items wrapped onto
    as many rows as the width needs."""
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.45
    items = [x for x in LEGEND if with_trajectory or x[1] == "cell"]
    sizes = [22 + cv2.getTextSize(label, font, scale, 1)[0][0] + 16 for label, _, _ in items]
    rows, x = 1, 8
    for w in sizes:
        if x + w > width and x > 8:
            rows, x = rows + 1, 8
        x += w
    strip = np.full((rows * row + 6, width, 3), 255, np.uint8)
    x, y = 8, 6
    for (label, kind, color), w in zip(items, sizes):
        if x + w > width and x > 8:
            x, y = 8, y + row
        mid = y + row // 2 - 2
        if kind == "cell":
            cv2.rectangle(strip, (x, mid - 7), (x + 14, mid + 7), color, -1)
            cv2.rectangle(strip, (x, mid - 7), (x + 14, mid + 7), (120, 120, 120), 1)
        elif kind == "line":
            cv2.line(strip, (x, mid), (x + 14, mid), color, 2, cv2.LINE_AA)
        else:
            cv2.circle(strip, (x + 7, mid), 6, color, -1, cv2.LINE_AA)
        cv2.putText(strip, label, (x + 22, mid + 5), font, scale, (0, 0, 0), 1, cv2.LINE_AA)
        x += w
    return strip


def write_map2d(grid: Map2D, out_dir: str | Path, trajectory: Trajectory | None = None) -> Path:
    """Write map2d.png, map2d.yaml and map2d_preview.png into ``out_dir``; returns the PNG's path."""
    out_dir = Path(out_dir)
    make_dirs(out_dir)
    png = out_dir / "map2d.png"
    _write_png(png, grid.image)
    meta = {
        "image": png.name,
        "resolution": float(grid.resolution),
        "origin": [float(v) for v in grid.origin],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
        "mode": "trinary",
        # to 1e-6 (µm, µrad): the floor fit's last digits follow the summation order of the cloud, which
        # differs between the map fused while tracking and `rgbdslam fuse` of the same run (by ~1e-9:
        # rounded to 1e-9 a value could still fall on either side, as on fr1/desk)
        "rgbdslam_world_to_map": [[round(float(v), 6) + 0.0 for v in r] for r in grid.world_to_map],
        "rgbdslam_up_source": grid.up_source,
        "rgbdslam_floor_source": grid.floor_source,
    }
    atomic_write_text(out_dir / "map2d.yaml", yaml.safe_dump(meta, sort_keys=False, default_flow_style=None))
    _write_png(out_dir / "map2d_preview.png", render_preview(grid, trajectory))
    return png
