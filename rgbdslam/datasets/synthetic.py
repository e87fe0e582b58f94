"""Synthetic RGB-D sequences with exact ground truth, written in the TUM layout.

The scene is a textured box room (floor, four walls, ceiling) with a few boxes standing on
the floor and two slanted panels, every surface a textured rectangle. Frames are rendered
analytically: for every pixel the ray is intersected with every rectangle (NumPy, no pixel
loops), the nearest hit gives the depth (exact up to the 1/5000 m quantisation of the
written PNG) and the colour (bilinear lookup in the surface's procedural texture). Camera
distortion, if the chosen camera has any, is rendered exactly: the rays are those of the
distorted pixel grid.

World frame: z up, the room spans x in [-3, 3], y in [-2.5, 2.5], z in [0, 2.8] metres.
Poses are camera-to-world with the camera's optical frame (x right, y down, z forward).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from rgbdslam.errors import InputError
from rgbdslam.geometry.camera import CAMERAS, Camera
from rgbdslam.geometry.se3 import look_along
from rgbdslam.io.atomic import atomic_write_text, in_final_place, interrupts_deferred, plain_permissions
from rgbdslam.io.images import write_png
from rgbdslam.io.manifest import SEQUENCE, Manifest
from rgbdslam.io.trajectory import Trajectory, write_tum
from rgbdslam.ui import console, frame_progress

MOTIONS = ("xyz", "rpy", "loop", "circle", "static", "figure8", "revisit", "orbit")
FPS = 30.0
EPOCH = 1_600_000_000.0  # time stamp of frame 0 (seconds)
DEPTH_SCALE = 5000.0  # TUM: raw units per metre
TEXEL = 0.005  # texture resolution on the surfaces (metres per texel)
ATLAS_ROWS = 32000  # texels per side of the texture atlas at most (cv2.remap: below 32767)
ROOM = (np.array([-3.0, -2.5, 0.0]), np.array([3.0, 2.5, 2.8]))
EYE_HEIGHT = 1.4
MAX_RANGE = 4.5  # beyond this the simulated sensor gives no depth (noise/dropout on)


# ----------------------------------------------------------------------------- scene


@dataclass
class Surface:
    """A textured rectangle ``origin + a*u + b*v`` for ``0 <= a <= width``, ``0 <= b <= height``."""

    name: str
    origin: np.ndarray
    u: np.ndarray  # unit vector
    v: np.ndarray  # unit vector, orthogonal to u
    width: float
    height: float
    texel: float = TEXEL  # metres per texel of this surface's texture
    bare: bool = False  # a plain, almost untextured surface (a white wall): no key points

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u, self.v)

    def contains(self, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """Distance of world points (N,3) to the plane, and whether they fall inside the rectangle."""
        d = points - self.origin
        a, b = d @ self.u, d @ self.v
        inside = (a >= -tol) & (a <= self.width + tol) & (b >= -tol) & (b <= self.height + tol)
        return np.abs(d @ self.normal), inside


def _rect(name, p0, p1, p2) -> Surface:
    """Rectangle with corner p0 and edges p0->p1, p0->p2."""
    p0, p1, p2 = (np.asarray(p, dtype=np.float64) for p in (p0, p1, p2))
    eu, ev = p1 - p0, p2 - p0
    return Surface(name, p0, eu / np.linalg.norm(eu), ev / np.linalg.norm(ev), float(np.linalg.norm(eu)), float(np.linalg.norm(ev)))


def _box(name, cx, cy, sx, sy, sz, z0=0.0) -> list[Surface]:
    x0, x1, y0, y1 = cx - sx / 2, cx + sx / 2, cy - sy / 2, cy + sy / 2
    z1 = z0 + sz
    return [
        _rect(f"{name}_top", (x0, y0, z1), (x1, y0, z1), (x0, y1, z1)),
        _rect(f"{name}_xmin", (x0, y0, z0), (x0, y1, z0), (x0, y0, z1)),
        _rect(f"{name}_xmax", (x1, y0, z0), (x1, y1, z0), (x1, y0, z1)),
        _rect(f"{name}_ymin", (x0, y0, z0), (x1, y0, z0), (x0, y0, z1)),
        _rect(f"{name}_ymax", (x0, y1, z0), (x1, y1, z0), (x0, y1, z1)),
    ]


# the orbit motion's object: a textured figure on a pedestal in the middle of the room (x, y centre)
ORBIT_CENTRE = np.array([0.0, 0.0, 0.95])  # the point the camera looks at
ORBIT_RADIUS = 0.9  # metres from the camera to the figure's axis (the figure's front 0.6-0.8 m away)
# the orbit's room is a hall (TUM fr3/teddy's): the walls the camera faces lie 6-10 m away
ORBIT_ROOM = (np.array([-3.0, -6.5, 0.0]), np.array([7.5, 6.5, 3.0]))
ORBIT_RANGE = 10.0  # the orbit's sensor gives depth to 10 m (a Kinect's range, as in fr3/teddy)
FRAME_WIDTH = 0.2  # metres: the width of a door or window frame's textured strips
FRAME_TEXEL = 0.015  # their texture is coarser, legible from 6-10 m (~15 mm per pixel at 8 m)
# door (True) and window (False) frames of the orbit's hall: the wall (x or y, at the room's high or low
# end), the position of the opening's left edge along the wall, its bottom, width and height (metres)
ORBIT_OPENINGS = (
    ("x", 1, -4.2, 0.0, 1.0, 2.1), ("x", 1, -1.2, 0.9, 1.6, 1.2), ("x", 1, 2.6, 0.0, 1.0, 2.1),
    ("y", 1, 3.0, 0.9, 1.4, 1.2), ("y", 0, 2.0, 0.0, 1.0, 2.1), ("y", 0, 5.0, 0.9, 1.4, 1.2),
)


def scene_surfaces(motion: str | None = None) -> list[Surface]:
    """The fixed room layout (textures depend on the seed, geometry does not). ``orbit``: a
    hall (:data:`ORBIT_ROOM`) with bare walls, floor and ceiling, no boxes, a few textured door and window
    frames (:data:`ORBIT_OPENINGS`) 6-10 m from the camera, and a textured figure (a pedestal, a body and
    a head, turned 30° about the vertical) in its middle, as TUM fr3/teddy: a near, textured object in
    front of a far, mostly bare room."""
    (x0, y0, z0), (x1, y1, z1) = ORBIT_ROOM if motion == "orbit" else ROOM
    room = [
        _rect("floor", (x0, y0, z0), (x1, y0, z0), (x0, y1, z0)),
        _rect("ceiling", (x0, y0, z1), (x1, y0, z1), (x0, y1, z1)),
        _rect("wall_xmax", (x1, y0, z0), (x1, y1, z0), (x1, y0, z1)),
        _rect("wall_xmin", (x0, y0, z0), (x0, y1, z0), (x0, y0, z1)),
        _rect("wall_ymax", (x0, y1, z0), (x1, y1, z0), (x0, y1, z1)),
        _rect("wall_ymin", (x0, y0, z0), (x1, y0, z0), (x0, y0, z1)),
    ]
    panel_a = _rect("panel_a", (2.0, -2.5, 0.2), (3.0, -1.7, 0.2), (2.0, -2.5, 2.2))
    if motion == "orbit":
        for r in room:
            r.bare = True
        figure = (_box("pedestal", 0.0, 0.0, 0.45, 0.45, 0.55) + _box("body", 0.0, 0.0, 0.42, 0.3, 0.5, 0.55)
                  + _box("head", 0.0, 0.0, 0.26, 0.24, 0.24, 1.05))
        turn = _rot(2, np.radians(30.0))
        for f in figure:
            f.origin, f.u, f.v = turn @ f.origin, turn @ f.u, turn @ f.v
        return room + figure + [panel_a] + _orbit_openings()
    s = room + [panel_a, _rect("panel_b", (-3.0, 1.6, 0.5), (-2.1, 2.5, 0.5), (-3.0, 1.6, 2.4))]
    s += _box("box1", 2.2, 1.2, 0.8, 1.0, 0.9)
    s += _box("box2", 2.3, -1.3, 0.6, 0.6, 1.4)
    s += _box("box3", -2.0, 1.2, 1.0, 0.8, 0.7)
    s += _box("box4", -1.8, -1.9, 0.8, 0.6, 1.1)
    s += _box("box5", 0.5, 2.0, 1.2, 0.5, 0.8)
    s += _box("box6", 0.2, -2.1, 0.6, 0.4, 1.6)
    return s


def _orbit_openings() -> list[Surface]:
    """The textured frames of :data:`ORBIT_OPENINGS`: strips of :data:`FRAME_WIDTH` standing 3 cm
    in front of their (bare) wall: two jambs and a lintel for a door, a sill as well for a window."""
    lo, hi = ORBIT_ROOM
    out = []
    for k, (axis, end, a0, b0, w, h) in enumerate(ORBIT_OPENINGS):
        inward = 0.03 if end == 0 else -0.03
        if axis == "x":  # along y on the wall x = const
            at = lambda a, b, c=(hi if end else lo)[0] + inward: np.array([c, a, b])  # noqa: E731
        else:  # along x on the wall y = const
            at = lambda a, b, c=(hi if end else lo)[1] + inward: np.array([a, c, b])  # noqa: E731
        f = FRAME_WIDTH
        strips = [(a0 - f, b0, f, h + f), (a0 + w, b0, f, h + f), (a0, b0 + h, w, f)]
        if b0 > 0:  # a window: its sill
            strips.append((a0, b0 - f, w, f))
        for j, (sa, sb, sw, sh) in enumerate(strips):
            r = _rect(f"opening{k}_{j}", at(sa, sb), at(sa + sw, sb), at(sa, sb + sh))
            r.texel = FRAME_TEXEL
            out.append(r)
    return out


def bare_texture(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """A plain surface (H, W, 3) uint8: one light colour with a faint, smooth shading (no corners)."""
    base = rng.uniform(150, 220) * np.array([1.0, 0.98, 0.95], np.float32)
    grid = rng.standard_normal((h // 200 + 3, w // 200 + 3)).astype(np.float32)
    shade = cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)[:, :, None] * 4.0
    return np.clip(base + shade, 0, 255).astype(np.uint8)


def make_texture(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """High-contrast, multi-scale, non-repetitive procedural texture (H, W, 3) uint8 RGB."""
    img = np.zeros((h, w, 3), np.float32)
    base = rng.uniform(40, 215, 3).astype(np.float32)
    img[:] = base
    # value noise at several scales, each octave with its own colour direction
    for scale, amp in ((160, 60.0), (48, 45.0), (14, 30.0)):
        grid = rng.standard_normal((h // scale + 3, w // scale + 3)).astype(np.float32)
        up = cv2.resize(grid, (w + 3 * scale, h + 3 * scale), interpolation=cv2.INTER_CUBIC)
        oy, ox = rng.integers(0, scale, 2)
        img += up[oy : oy + h, ox : ox + w, None] * (amp * rng.uniform(-1, 1, 3).astype(np.float32))
    # random shapes at several sizes, in high-contrast colours
    n_shapes = max(20, int(h * w / 700))
    kinds = rng.integers(0, 4, n_shapes)
    sizes = np.exp(rng.uniform(np.log(4), np.log(70), n_shapes))
    centres = rng.uniform(0, 1, (n_shapes, 2)) * (w, h)
    colours = rng.integers(0, 256, (n_shapes, 3))
    for kind, r, (cx, cy), col in zip(kinds, sizes, centres, colours):
        col = tuple(int(c) for c in col)
        c = (int(cx), int(cy))
        if kind == 0:
            cv2.circle(img, c, int(r / 2) + 1, col, -1, cv2.LINE_AA)
        elif kind == 1:
            ang = rng.uniform(0, 180)
            box = cv2.boxPoints(((cx, cy), (r, r * rng.uniform(0.3, 1.0)), ang))
            cv2.fillPoly(img, [box.astype(np.int32)], col, cv2.LINE_AA)
        elif kind == 2:
            pts = (np.array([cx, cy]) + rng.uniform(-r, r, (3, 2))).astype(np.int32)
            cv2.fillPoly(img, [pts], col, cv2.LINE_AA)
        else:
            p2 = (int(cx + rng.uniform(-r, r)), int(cy + rng.uniform(-r, r)))
            cv2.line(img, c, p2, col, int(rng.integers(1, 4)), cv2.LINE_AA)
    # a few random binary patches (marker-like, never repeating)
    for _ in range(max(2, int(h * w / 60000))):
        n, cell = int(rng.integers(4, 8)), int(rng.integers(3, 8))
        bits = rng.integers(0, 2, (n, n)).astype(np.float32) * 255.0
        patch = cv2.resize(bits, (n * cell, n * cell), interpolation=cv2.INTER_NEAREST)
        py, px = rng.integers(0, max(1, h - n * cell)), rng.integers(0, max(1, w - n * cell))
        sub = img[py : py + n * cell, px : px + n * cell]
        sub[:] = patch[: sub.shape[0], : sub.shape[1], None]
    img = cv2.GaussianBlur(img, (0, 0), 0.7)  # limits aliasing when seen from far
    return np.clip(img, 0, 255).astype(np.uint8)


class Scene:
    """Surfaces plus one texture atlas; :meth:`render` ray-casts a frame."""

    def __init__(self, seed: int = 0, surfaces: list[Surface] | None = None) -> None:
        self.surfaces = surfaces if surfaces is not None else scene_surfaces()
        shapes = [(int(np.ceil(s.height / s.texel)) + 2, int(np.ceil(s.width / s.texel)) + 2) for s in self.surfaces]
        # textures stacked in columns of at most ATLAS_ROWS rows (OpenCV's remap takes < 32767 per side)
        self.row_offset = np.zeros(len(shapes), np.int64)
        self.col_offset = np.zeros(len(shapes), np.int64)
        row = col = col_width = 0
        for k, (h, w) in enumerate(shapes):
            if row + h > ATLAS_ROWS and row > 0:
                row, col, col_width = 0, col + col_width, 0
            self.row_offset[k], self.col_offset[k] = row, col
            row += h
            col_width = max(col_width, w)
        rows = max(int(o) + h for o, (h, _) in zip(self.row_offset, shapes))
        cols = max(int(o) + w for o, (_, w) in zip(self.col_offset, shapes))
        if rows >= ATLAS_ROWS or cols >= ATLAS_ROWS:
            raise InputError(f"the scene's textures need a {cols}x{rows} texel atlas; at most {ATLAS_ROWS} per side "
                             f"(fewer or smaller surfaces, or coarser texels)")
        atlas = np.zeros((rows, cols, 3), np.uint8)
        for k, (h, w) in enumerate(shapes):
            sub_rng = np.random.default_rng([seed, k, 104729])
            r0, c0 = self.row_offset[k], self.col_offset[k]
            texture = bare_texture if self.surfaces[k].bare else make_texture
            atlas[r0 : r0 + h, c0 : c0 + w] = texture(h, w, sub_rng)
        self.atlas = atlas
        self._O = np.array([s.origin for s in self.surfaces])
        self._U = np.array([s.u for s in self.surfaces])
        self._V = np.array([s.v for s in self.surfaces])
        self._N = np.array([s.normal for s in self.surfaces])
        self._size = np.array([(s.width, s.height) for s in self.surfaces])
        self._texel = np.array([s.texel for s in self.surfaces])

    def render(self, rays: "Rays", pose: np.ndarray):
        """Ray-cast one frame seen through ``rays`` from ``pose`` (camera-to-world).

        Returns ``rgb`` (H, W, 3) uint8, ``depth`` (H, W) float64 metres along the optical
        axis (0 where nothing is hit) and ``surface`` (H, W) int16 (index into
        :attr:`surfaces`, -1 where nothing is hit).
        """
        R, c = pose[:3, :3], pose[:3, 3]
        # everything in the camera frame; a ray is (x, y, 1), so its parameter is the depth
        Nc, Uc, Vc = self._N @ R, self._U @ R, self._V @ R
        Oc = (self._O - c) @ R
        H, W = rays.x.shape
        best = np.full((H, W), np.inf)
        best_id = np.full((H, W), -1, np.int16)
        map_x = np.zeros((H, W), np.float32)
        map_y = np.zeros((H, W), np.float32)
        for k in range(len(self.surfaces)):
            dist = Nc[k] @ Oc[k]
            if abs(dist) < 1e-9:
                continue  # the camera lies in this plane: seen edge-on
            w, h = self._size[k]
            corners = Oc[k] + np.array([[0, 0], [w, 0], [w, h], [0, h]]) @ np.stack([Uc[k], Vc[k]])
            window = rays.window(corners)
            if window is None:
                continue
            r0, r1, c0, c1 = window
            rx, ry = rays.x[r0:r1, c0:c1], rays.y[r0:r1, c0:c1]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = dist / (Nc[k, 0] * rx + Nc[k, 1] * ry + Nc[k, 2])
            a = t * (Uc[k, 0] * rx + Uc[k, 1] * ry + Uc[k, 2]) - Oc[k] @ Uc[k]
            b = t * (Vc[k, 0] * rx + Vc[k, 1] * ry + Vc[k, 2]) - Oc[k] @ Vc[k]
            sub = best[r0:r1, c0:c1]
            ok = (t > 1e-6) & (t < sub) & (a >= 0) & (a <= w) & (b >= 0) & (b <= h)
            sub[ok] = t[ok]
            best_id[r0:r1, c0:c1][ok] = k
            map_x[r0:r1, c0:c1][ok] = a[ok] / self._texel[k] + 0.5 + self.col_offset[k]
            map_y[r0:r1, c0:c1][ok] = b[ok] / self._texel[k] + 0.5 + self.row_offset[k]
        seen = best_id >= 0
        depth = np.where(seen, best, 0.0)
        rgb = cv2.remap(self.atlas, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        rgb[~seen] = 0
        return rgb, depth, best_id


class Rays:
    """The ray (x, y, 1) of every pixel centre of a camera, distortion included, with the
    per-column / per-row extent of x and y used to limit each surface to its image window."""

    def __init__(self, camera: Camera) -> None:
        u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
        ideal = camera.undistort_points(np.stack([u.ravel(), v.ravel()], axis=1))
        self.x = ((ideal[:, 0] - camera.cx) / camera.fx).reshape(camera.height, camera.width)
        self.y = ((ideal[:, 1] - camera.cy) / camera.fy).reshape(camera.height, camera.width)
        self._col_lo, self._col_hi = self.x.min(axis=0), self.x.max(axis=0)
        self._row_lo, self._row_hi = self.y.min(axis=1), self.y.max(axis=1)
        self.fx, self.fy = camera.fx, camera.fy

    def window(self, corners: np.ndarray, near: float = 1e-3) -> tuple[int, int, int, int] | None:
        """Rows r0:r1 and columns c0:c1 that may see the convex polygon ``corners``
        (camera frame, (4,3)); None if it lies behind the camera or outside the image."""
        poly = _clip_near(corners, near)
        if len(poly) == 0:
            return None
        px, py = poly[:, 0] / poly[:, 2], poly[:, 1] / poly[:, 2]
        cols = np.flatnonzero((self._col_hi >= px.min()) & (self._col_lo <= px.max()))
        rows = np.flatnonzero((self._row_hi >= py.min()) & (self._row_lo <= py.max()))
        if len(cols) == 0 or len(rows) == 0:
            return None
        return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _clip_near(poly: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a polygon (N,3) to the half space z >= near."""
    out = []
    n = len(poly)
    for i in range(n):
        p, q = poly[i], poly[(i + 1) % n]
        if p[2] >= near:
            out.append(p)
        if (p[2] >= near) != (q[2] >= near):
            s = (near - p[2]) / (q[2] - p[2])
            out.append(p + s * (q - p))
    return np.array(out).reshape(-1, 3)


def scaled_camera(name: str, width: int, height: int) -> Camera:
    """A known camera resized to ``width`` x ``height`` (pixel-centre convention)."""
    if name not in CAMERAS:
        raise InputError(f"unknown camera '{name}'; choose one of {', '.join(CAMERAS)}")
    c = CAMERAS[name]
    if (width, height) == (c.width, c.height):
        return c
    if width < 16 or height < 16:
        raise InputError(f"image size {width}x{height} is too small; use at least 16x16")
    sx, sy = width / c.width, height / c.height
    return Camera(c.fx * sx, c.fy * sy, (c.cx + 0.5) * sx - 0.5, (c.cy + 0.5) * sy - 0.5, width, height, c.dist, f"{name}_{width}x{height}")


# ----------------------------------------------------------------------------- motion


def _rot(axis: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i] = R[j, j] = c
    R[i, j], R[j, i] = -s, s
    return R


FIGURE8_PERIOD = 5.0  # seconds per lap of the figure eight (laps rounded so the last frame closes it)
REVISIT_SHARE = 0.15  # share of the frames in each of the two visits of the revisit motion
REVISIT_MIN_FRAMES = 12
DEFAULT_EXPOSURE_MS = {"figure8": 16.0}  # motion blur on by default (other motions: sharp frames)


def make_trajectory(motion: str, frames: int, phase: float = 0.0) -> np.ndarray:
    """Smooth camera-to-world poses (frames, 4, 4) for a motion in :data:`MOTIONS`.

    ``phase`` moves the start along the path by that fraction of the sequence (0 = the usual
    start; loop/circle: 0.5 starts half a turn further on, on the other side of the room), so
    two sequences of one scene can start at different places (sessions, docs/slam.md).

    xyz: translation along all three axes (±0.3 m, periods 4-6 s), fixed view of wall x=3;
    rpy: rotation about the optical centre (±20° roll/pitch/yaw, periods 4-6 s);
    loop: one full turn on a 0.7 m circle looking outwards, back at the start pose on the
    last frame (the start view is revisited); circle: a 0.4 m circle in the world
    y-z plane around the eye point (0, 0, 1.4) while looking at a fixed point on wall x=3,
    back at the start on the last frame;
    figure8: a figure eight (lemniscate of Gerono, 1.6 m x 0.84 m) around the room's centre,
    the camera turning once round per lap (yaw = lap angle + 0.3 sin 2·angle: 29-115 °/s,
    72 °/s mean) with pitch and roll swaying, at ~1.0 m/s mean (0.66-1.45 m/s); one lap per
    ~5 s (:data:`FIGURE8_PERIOD`; the number of laps is rounded so that the last frame is
    back at the start pose). Rendered with motion blur by default (:data:`DEFAULT_EXPOSURE_MS`);
    revisit: the camera maps place A (the first :data:`REVISIT_SHARE` of the frames: a slow
    pan at A facing wall x=3), turns left by 75° and moves 1 m to place B (facing the corner
    towards wall y=2.5, a view that does not overlap A's), looks around there, comes back, and
    repeats the first visit pose for pose (the last :data:`REVISIT_SHARE` of the frames; 150
    frames: frames 0-21 and 128-149, 128 frames apart); see :func:`revisit_ranges`;
    orbit: a slow hand-held orbit around the textured figure of the orbit scene
    (:func:`scene_surfaces`), as TUM fr3/teddy: the camera swings ±50° about the figure at
    :data:`ORBIT_RADIUS` (period 10 s; 0.3 m/s mean, ~12 mm per frame), bobbing up and down and
    in and out a little, always looking at the figure; most key points lie 0.6-1.1 m away, the
    rest on the hall's door and window frames 6-10 m away (the orbit's depth reaches 10 m);
    static: no motion.
    """
    return trajectory_at(motion, np.arange(frames, dtype=np.float64), frames, phase)


def revisit_ranges(frames: int) -> dict:
    """First and last frame (inclusive) of the first visit and of the revisit of the
    ``revisit`` motion: frame ``k`` of the first visit and frame ``k + offset`` of the
    revisit have the same pose."""
    n_visit = max(2, int(round(REVISIT_SHARE * frames)))
    return {"first_visit": [0, n_visit - 1], "revisit": [frames - n_visit, frames - 1],
            "revisit_offset": frames - n_visit}


def _pose_ypr(position, yaw: float, pitch: float, roll: float = 0.0) -> np.ndarray:
    """Camera at ``position`` looking along heading ``yaw`` (about world z, 0 = +x), ``pitch``
    (up positive) and rolled by ``roll`` about its optical axis."""
    fwd = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    P = look_along(np.asarray(position, dtype=np.float64), fwd)
    if roll:
        P[:3, :3] = P[:3, :3] @ _rot(2, roll)
    return P


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _revisit_pose(u: float, frames: int) -> np.ndarray:
    """Pose of the revisit motion at (fractional) frame index ``u``."""
    last = max(frames - 1, 1)
    r = revisit_ranges(frames)
    d = float(r["first_visit"][1])  # the visit lasts u in [0, d]
    pos_a, yaw_a = np.array([0.4, -0.4, EYE_HEIGHT]), 0.0
    pos_b, yaw_b = np.array([-0.3, 0.3, EYE_HEIGHT - 0.05]), np.radians(75.0)
    pitch = np.radians(-10.0)
    u = float(np.clip(u, 0.0, last))
    if u <= d or u >= last - d:  # first visit or revisit: a slow pan away from B and back
        tau = u if u <= d else u - (last - d)
        phi = 0.5 * (1.0 - np.cos(2 * np.pi * tau / d))  # 0 -> 1 -> 0, at rest at both ends
        return _pose_ypr(pos_a + phi * np.array([0.0, -0.12, 0.04]), yaw_a - np.radians(12.0) * phi, pitch)
    w = (u - d) / (last - 2 * d)  # 0..1 away from A
    if w < 0.37:  # A -> B, turning left by 75 degrees
        g = _smoothstep(w / 0.37)
        return _pose_ypr(pos_a + g * (pos_b - pos_a), yaw_a + g * (yaw_b - yaw_a), pitch)
    if w > 0.63:  # B -> A
        g = _smoothstep((w - 0.63) / 0.37)
        return _pose_ypr(pos_b + g * (pos_a - pos_b), yaw_b + g * (yaw_a - yaw_b), pitch)
    a = (w - 0.37) / 0.26  # at B: a sideways step and a look to both sides, at rest at both ends
    s2 = np.sin(np.pi * a) ** 2
    return _pose_ypr(pos_b + 0.15 * s2 * np.array([1.0, 0.0, 0.0]),
                     yaw_b + np.radians(8.0) * np.sin(2 * np.pi * a) * s2, pitch + np.radians(5.0) * s2)


def trajectory_at(motion: str, u: np.ndarray, frames: int, phase: float = 0.0) -> np.ndarray:
    """Poses (len(u), 4, 4) of a motion of ``frames`` frames at the (fractional) frame indices
    ``u``: :func:`make_trajectory` at ``u = 0, 1, ...``; between frames for motion blur."""
    if motion not in MOTIONS:
        raise InputError(f"unknown motion '{motion}'; choose one of {', '.join(MOTIONS)}")
    if frames < 1:
        raise InputError(f"frames must be at least 1 (got {frames})")
    u = np.atleast_1d(np.asarray(u, dtype=np.float64))
    last = max(frames - 1, 1)
    shift = float(phase) * last
    t = (u + shift) / FPS
    s = (u + shift) / last  # 0..1 over the sequence (+ phase)
    centre = np.array([0.0, 0.0, EYE_HEIGHT])
    ahead = np.array([1.0, 0.0, 0.0])
    poses = np.empty((len(u), 4, 4))
    laps = max(1, int(round(last / FPS / FIGURE8_PERIOD)))
    for k in range(len(u)):
        if motion == "static":
            poses[k] = look_along(centre, ahead)
        elif motion == "xyz":
            w = 2 * np.pi * t[k]
            d = 0.3 * np.array([np.sin(w / 4.0), np.sin(w / 5.0), 0.6 * np.sin(w / 6.0)])
            poses[k] = look_along(centre + d, ahead)
        elif motion == "rpy":
            w = 2 * np.pi * t[k]
            roll, pitch, yaw = np.radians(20.0) * np.array([np.sin(w / 6.0), np.sin(w / 5.0), np.sin(w / 4.0)])
            P = look_along(centre, ahead)
            P[:3, :3] = P[:3, :3] @ _rot(1, yaw) @ _rot(0, pitch) @ _rot(2, roll)
            poses[k] = P
        elif motion == "loop":
            th = 2 * np.pi * s[k]
            radial = np.array([np.cos(th), np.sin(th), 0.0])
            pos = centre + 0.7 * radial + [0.0, 0.0, 0.1 * np.sin(2 * th)]
            P = look_along(pos, radial + [0.0, 0.0, -0.1 + 0.1 * np.cos(2 * th)])
            poses[k] = P
        elif motion == "circle":
            th = 2 * np.pi * s[k]
            pos = centre + 0.4 * np.array([0.0, np.sin(th), np.cos(th)])
            poses[k] = look_along(pos, np.array([3.0, 0.0, 1.2]) - pos)
        elif motion == "figure8":
            th = 2 * np.pi * laps * s[k]
            pos = centre + np.array([0.8 * np.sin(th), 0.42 * np.sin(2 * th), 0.08 * np.sin(3 * th)])
            poses[k] = _pose_ypr(pos, th + 0.3 * np.sin(2 * th), np.radians(-8.0 + 8.0 * np.sin(3 * th)),
                                 np.radians(6.0) * np.sin(2 * th))
        elif motion == "orbit":
            tt = t[k]
            th = np.radians(50.0) * np.sin(2 * np.pi * tt / 10.0) - np.pi  # facing the figure from -x
            r = ORBIT_RADIUS + 0.06 * np.sin(2 * np.pi * tt / 3.7)
            pos = ORBIT_CENTRE + [r * np.cos(th), r * np.sin(th), 0.3 + 0.05 * np.sin(2 * np.pi * tt / 2.9)]
            poses[k] = look_along(pos, ORBIT_CENTRE + [0.0, 0.03 * np.sin(2 * np.pi * tt / 2.3), 0.0] - pos)
        else:  # revisit (no phase: validate_parameters refuses it)
            poses[k] = _revisit_pose(u[k], frames)
    return poses


# ----------------------------------------------------------------------------- motion blur


def render_exposure(scene: "Scene", rays: "Rays", pose_at, k: int, exposure_frames: float,
                    max_step_px: float = 1.5, max_subframes: int = 41):
    """Render frame ``k`` as a camera whose shutter is open for ``exposure_frames`` frame
    intervals centred on the frame's time: the mean of ``n`` ray-cast sub-frames at poses
    ``pose_at(u)`` (``u`` fractional frame indices, a (n, 4, 4) stack) spread evenly over the
    exposure, ``n`` odd and chosen so that the image moves by at most ``max_step_px`` between
    sub-frames (a continuous streak, not ghost copies). The centre sub-frame is the frame's
    pose (the ground truth): depth and surface ids are its, exact. Deterministic (no random
    draw). Returns ``(rgb, depth, surface, streak_px)``; ``streak_px`` is the longest image
    motion over the exposure (0 without blur)."""
    centre = pose_at(np.array([float(k)]))[0]
    rgb, depth, hit = scene.render(rays, centre)
    if exposure_frames <= 0:
        return rgb, depth, hit, 0.0
    ends = pose_at(np.array([k - 0.5 * exposure_frames, k + 0.5 * exposure_frames]))
    streak = _streak_px(rays, depth, centre, ends)
    n = int(min(max_subframes, 2 * int(np.ceil(streak / (2 * max_step_px))) + 1))
    if n < 3:
        return rgb, depth, hit, streak
    us = k + exposure_frames * (np.arange(n) / (n - 1) - 0.5)
    acc = rgb.astype(np.float32)
    for i, P in enumerate(pose_at(us)):
        if i != (n - 1) // 2:  # the centre is rendered already
            acc += scene.render(rays, P)[0]
    return np.clip(np.round(acc / n), 0, 255).astype(np.uint8), depth, hit, streak


def _streak_px(rays: "Rays", depth: np.ndarray, centre: np.ndarray, ends: np.ndarray) -> float:
    """Longest motion (pixels) between the exposure's start and end poses of the scene points
    seen at the centre pose (a grid of every 4th pixel; pinhole projection)."""
    sub = (slice(None, None, 4), slice(None, None, 4))
    z = depth[sub]
    ok = z > 0
    if not ok.any():
        return 0.0
    P = np.stack([rays.x[sub][ok] * z[ok], rays.y[sub][ok] * z[ok], z[ok]], axis=1)
    world = P @ centre[:3, :3].T + centre[:3, 3]
    uv = []
    for T in ends:
        c = (world - T[:3, 3]) @ T[:3, :3]
        zc = np.maximum(c[:, 2], 1e-3)
        uv.append(np.stack([rays.fx * c[:, 0] / zc, rays.fy * c[:, 1] / zc], axis=1))
    return float(np.linalg.norm(uv[1] - uv[0], axis=1).max())


def exposure_frames(exposure_ms: float) -> float:
    """An exposure time (ms) in frame intervals at :data:`FPS`."""
    return float(exposure_ms) * 1e-3 * FPS


def motion_parameters(motion: str, frames: int, exposure_ms: float) -> dict:
    """What synthetic.yaml records beyond the options: the revisit motion's frame ranges, and the
    motion blur (only when on, so sharp sequences' files stay as they were)."""
    extra: dict = {}
    if motion == "revisit":
        extra.update(revisit_ranges(frames))
    if exposure_ms > 0:
        extra["motion_blur"] = {"exposure_ms": float(exposure_ms), "shutter": "box, centred on the frame's time",
                                "max_subframe_step_px": 1.5}
    return extra


def record_streaks(params: dict, streaks: list[float]) -> None:
    """Add the blur streak lengths (pixels, per frame: longest image motion over the exposure)."""
    if "motion_blur" in params and streaks:
        a = np.asarray(streaks)
        params["motion_blur"].update(streak_px_median=round(float(np.median(a)), 2),
                                     streak_px_p90=round(float(np.percentile(a, 90)), 2),
                                     streak_px_max=round(float(a.max()), 2))


def blur_note(summary: dict) -> str:
    """", motion blur 16 ms (streaks median 17 px)" for a summary with blur, else ""."""
    b = summary.get("motion_blur")
    if not b:
        return ""
    return f", motion blur {b['exposure_ms']:g} ms (streaks median {b.get('streak_px_median', 0):.0f} px)"


def resolve_blur(motion: str, blur) -> float:
    """The exposure (ms) a sequence is rendered with: ``blur`` if given, else the motion's default."""
    return float(DEFAULT_EXPOSURE_MS.get(motion, 0.0) if blur is None else blur)


# ----------------------------------------------------------------------------- sensor effects


def kinect_noise(depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Axial noise with sigma = 0.0012 + 0.0019 (z - 0.4)^2 (Nguyen et al. 2012)."""
    sigma = 0.0012 + 0.0019 * (depth - 0.4) ** 2
    return np.where(depth > 0, depth + sigma * rng.standard_normal(depth.shape), 0.0)


def dropout_mask(shape: tuple[int, int], fraction: float, rng: np.random.Generator) -> np.ndarray:
    """Boolean mask of blob-shaped holes covering about ``fraction`` of the image."""
    if fraction <= 0:
        return np.zeros(shape, bool)
    h, w = shape
    low = rng.standard_normal((h // 16 + 2, w // 16 + 2)).astype(np.float32)
    field = cv2.resize(low, (w, h), interpolation=cv2.INTER_CUBIC)
    field += 0.35 * rng.standard_normal(shape).astype(np.float32)  # ragged hole borders
    return field > np.quantile(field, 1.0 - fraction)


# ----------------------------------------------------------------------------- writer


MAX_SIZE = 4096  # pixels per image side
MAX_FRAMES = 100_000  # ~55 min at 30 Hz
MAX_EXPOSURE_MS = 1000.0 / FPS  # the shutter cannot stay open longer than a frame
MAX_DEPTH_DELAY = 1.0 / FPS  # seconds between a frame's colour and depth images, at most a frame
GENERATED = ("rgb", "depth", "rgb.txt", "depth.txt", "groundtruth.txt", "camera.yaml", "synthetic.yaml")


def _is_int(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def validate_parameters(frames, motion, width, height, noise, dropout, drift, seed, camera, phase=0.0,
                        time_offset=0.0, blur=None, depth_delay=0.0) -> None:
    """Check every parameter of :func:`generate_sequence` before anything is written; an
    InputError names the parameter (as the ``synth`` option) and its valid range."""
    if not _is_int(frames) or not 1 <= frames <= MAX_FRAMES:
        raise InputError(f"--frames must be a whole number from 1 to {MAX_FRAMES} (got {frames!r})")
    if motion not in MOTIONS:
        raise InputError(f"unknown motion '{motion}'; choose one of {', '.join(MOTIONS)}")
    if camera not in CAMERAS:
        raise InputError(f"unknown camera '{camera}'; choose one of {', '.join(CAMERAS)}")
    if not (_is_int(width) and _is_int(height) and 16 <= width <= MAX_SIZE and 16 <= height <= MAX_SIZE):
        raise InputError(f"image size {width}x{height} is out of range; --size W H must be whole numbers from 16 "
                         f"to {MAX_SIZE} (e.g. --size 640 480)")
    if not isinstance(noise, (bool, np.bool_)):
        raise InputError(f"noise must be true or false (got {noise!r})")
    if isinstance(dropout, bool) or not isinstance(dropout, (int, float)) or not 0.0 <= dropout < 1.0:
        raise InputError(f"dropout must be in [0, 1) (got {dropout})")
    if isinstance(drift, bool) or not isinstance(drift, (int, float)) or not -0.5 < drift < 0.5:
        raise InputError(f"drift must be a small relative depth error in (-0.5, 0.5) (got {drift})")
    if not _is_int(seed) or seed < 0:
        raise InputError(f"--seed must be a whole number >= 0 (got {seed!r})")
    if isinstance(phase, bool) or not isinstance(phase, (int, float)) or not 0.0 <= phase < 1.0:
        raise InputError(f"--phase must be a fraction in [0, 1) (got {phase!r})")
    if isinstance(time_offset, bool) or not isinstance(time_offset, (int, float)) or not 0.0 <= time_offset <= 1e6:
        raise InputError(f"--time-offset must be seconds from 0 to 1e6 (got {time_offset!r})")
    if isinstance(depth_delay, bool) or not isinstance(depth_delay, (int, float)) \
            or not abs(depth_delay) <= MAX_DEPTH_DELAY:
        raise InputError(f"--depth-delay must be seconds from -{MAX_DEPTH_DELAY:g} to {MAX_DEPTH_DELAY:g} (one frame "
                         f"at {FPS:g} Hz) (got {depth_delay!r})")
    if blur is not None and (isinstance(blur, bool) or not isinstance(blur, (int, float))
                             or not 0.0 <= blur <= MAX_EXPOSURE_MS):
        raise InputError(f"--blur must be an exposure time in milliseconds from 0 (sharp) to {MAX_EXPOSURE_MS:.1f} "
                         f"(one frame at {FPS:g} Hz) (got {blur!r})")
    if motion == "revisit" and frames < REVISIT_MIN_FRAMES:
        raise InputError(f"--motion revisit needs at least {REVISIT_MIN_FRAMES} frames (visit, away, revisit); "
                         f"use --frames 150 or more for a revisit >= 100 frames later (got {frames})")
    if motion == "revisit" and phase:
        raise InputError("--phase moves the start along a periodic path; --motion revisit has a fixed first visit "
                         "and revisit (leave --phase out)")


def partial_folder(out: Path) -> tuple[Path, Path]:
    """``(target, work)``: ``out`` resolved, and a new temporary folder to render into — inside
    ``out`` when it is an existing folder (it may be a mount point: renames must not cross
    devices), else beside it — renamed to ``out`` when complete. One error line if it cannot be made."""
    target = out.resolve()
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        where = target if target.is_dir() else target.parent
        work = Path(tempfile.mkdtemp(prefix=f".{target.name}.partial-", dir=where))
    except OSError as e:
        raise InputError(f"cannot create the sequence folder {out} ({e.strerror or e}); choose a writable "
                         f"place") from None
    return target, work


def _check_output(out: Path, generated: tuple[str, ...] = GENERATED) -> None:
    """``out`` may be new, an empty folder or an earlier synthetic sequence (which is replaced:
    only what its manifest lists as the generator's, docs/outputs.md)."""
    if out.exists() and not out.is_dir():
        raise InputError(f"{out} exists and is not a folder; give a folder for the synthetic sequence")
    ours = f".{out.name}.partial-"  # a temporary folder a killed run of ours left behind
    if out.is_dir() and any(not p.name.startswith(ours) for p in out.iterdir()) and not (out / "synthetic.yaml").is_file():
        raise InputError(f"{out} is not empty and is not a synthetic sequence; give a new or empty folder")
    if out.is_dir():
        Manifest(out).check_way(generated, [SEQUENCE], "move it away or give a new or empty folder (a new "
                                                       "sequence replaces only what the generator wrote)")


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif os.path.lexists(path):
        path.unlink()


def _replace_folder(new: Path, out: Path, generated: tuple[str, ...] = GENERATED) -> None:
    """Put the finished sequence in ``new`` (a temporary folder inside an existing ``out``, else
    beside it) in the place of ``out``.

    A new ``out`` is the renamed ``new``. An existing ``out`` (an earlier synthetic sequence or an
    empty folder) keeps its folder and any file the generator does not write (notes, a demo marker);
    only the generated entries (:data:`GENERATED`) are swapped, by renames that Ctrl-C cannot cut."""
    if not out.exists():
        plain_permissions(new)
        os.replace(new, out)
        Manifest(out).record(generated, SEQUENCE)
        return
    replaced = new / ".replaced"  # removed with ``new`` at the end
    replaced.mkdir()
    moved_out, moved_in = [], []
    want_in = [n for n in generated if os.path.lexists(new / n)]
    try:
        with interrupts_deferred():
            try:
                for name in generated:
                    if os.path.lexists(out / name):
                        os.replace(out / name, replaced / name)
                        moved_out.append(name)
                for name in want_in:
                    os.replace(new / name, out / name)
                    moved_in.append(name)
            except OSError:  # put the earlier sequence back as it was
                for name in moved_in:
                    _remove(out / name)
                for name in moved_out:
                    os.replace(replaced / name, out / name)
                raise
    finally:  # swapped (also when a Ctrl-C held back during the renames is raised now): drop the old copy
        if len(moved_in) == len(want_in):
            shutil.rmtree(new, ignore_errors=True)
            Manifest(out).record(generated, SEQUENCE)


def _write_frame(out: Path, name: str, rendered, noise: bool, dropout: float, drift: float, rng,
                 max_range: float = MAX_RANGE) -> None:
    """Apply the sensor effects to one rendered frame and write its two PNGs (with noise or dropout,
    no depth beyond ``max_range``)."""
    rgb, depth, _ = rendered
    if noise:
        rgb = np.clip(rgb + rng.normal(0.0, 2.0, rgb.shape), 0, 255).astype(np.uint8)
        depth = kinect_noise(depth, rng)
    depth = depth * (1.0 + drift)
    if noise or dropout > 0:
        depth[(depth > max_range) | dropout_mask(depth.shape, dropout, rng)] = 0.0
    raw = np.clip(np.round(depth * DEPTH_SCALE), 0, 65535).astype(np.uint16)
    write_png(out / "rgb" / name, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), compression=1)
    write_png(out / "depth" / name, raw, compression=1)


def generate_sequence(
    out_dir: str | Path,
    frames: int = 100,
    motion: str = "xyz",
    width: int = 640,
    height: int = 480,
    noise: bool = False,
    dropout: float = 0.0,
    drift: float = 0.0,
    seed: int = 0,
    camera: str = "ros_default",
    progress: bool = False,
    phase: float = 0.0,
    time_offset: float = 0.0,
    blur: float | None = None,
    depth_delay: float = 0.0,
) -> dict:
    """Render a synthetic sequence into ``out_dir`` (TUM layout) and return a summary.

    ``noise``: Kinect-like axial depth noise and colour noise (sigma 2 grey levels);
    ``dropout``: fraction of depth pixels lost in blob-shaped holes; with either, depth
    beyond 4.5 m (the orbit: 10 m) is invalid. ``drift``: systematic relative depth error, written depth =
    true depth * (1 + drift) (undo it with ``dataset.depth_correction = 1 / (1 + drift)``).
    All randomness is seeded by ``seed`` (the scene's textures too: one seed, one scene).
    ``phase`` starts the motion further along its path and ``time_offset`` (s) shifts the time
    stamps: two sequences of one seed are two sessions in the same scene. ``blur``: exposure time
    in ms of a box shutter centred on each frame's time (:func:`render_exposure`; the colour image
    is blurred along its motion, the depth stays the frame's exact depth); None = the motion's
    default (:data:`DEFAULT_EXPOSURE_MS`: 16 ms for figure8, sharp otherwise). ``depth_delay``
    (s): each depth image is rendered at the pose that much later than the colour image (the
    ground truth stays at the colour times) and depth.txt carries its later stamp, as TUM's
    freiburg1 Kinect (colour and depth exposed 0-14 ms apart). Written: ``rgb/``,
    ``depth/`` (16-bit, 5000 per metre), ``rgb.txt``, ``depth.txt``, ``groundtruth.txt``,
    ``camera.yaml`` (read by the TUM reader), ``synthetic.yaml`` (these parameters; with blur its
    exposure and streak lengths, with the revisit motion its visits' frame ranges).
    """
    validate_parameters(frames, motion, width, height, noise, dropout, drift, seed, camera, phase, time_offset, blur,
                        depth_delay)
    start = time.perf_counter()
    out = Path(out_dir)
    _check_output(out)
    cam = scaled_camera(camera, width, height)
    poses = make_trajectory(motion, frames, phase)
    params = dict(frames=int(frames), motion=motion, width=int(width), height=int(height), noise=bool(noise),
                  dropout=float(dropout), drift=float(drift), seed=int(seed), camera=camera)
    if phase or time_offset:  # only then: earlier sequences' synthetic.yaml stay as they were
        params.update(phase=float(phase), time_offset=float(time_offset))
    if depth_delay:
        params.update(depth_delay=float(depth_delay))
    params.update(motion_parameters(motion, frames, resolve_blur(motion, blur)))
    # rendered into a temporary sibling folder that replaces ``out`` only when complete: a
    # failure or Ctrl-C part-way leaves an earlier sequence in ``out`` as it was
    target, work = partial_folder(out)
    try:
        try:
            _render_into(work, cam, poses, params, progress)
        except OSError as e:  # a full disk: the file in its final place, never our temporary folder
            raise in_final_place(e, work, out) from None
        _replace_folder(work, target)
    finally:
        if not (work / ".replaced").is_dir() or not any((work / ".replaced").iterdir()):
            shutil.rmtree(work, ignore_errors=True)  # else it holds the earlier sequence a failed swap kept
    seconds = time.perf_counter() - start
    return {"path": str(out), "frames": frames, "seconds": seconds, "camera": cam.name, **params}


def _render_into(out: Path, cam: Camera, poses: np.ndarray, params: dict, progress: bool) -> None:
    """Write the whole sequence into the (new, temporary) folder ``out``."""
    frames, camera, seed = params["frames"], params["camera"], params["seed"]
    noise, dropout, drift = params["noise"], params["dropout"], params["drift"]
    (out / "rgb").mkdir()
    (out / "depth").mkdir()
    atomic_write_text(
        out / "camera.yaml",
        (f"camera: {camera}\n" if cam is CAMERAS[camera] else "")
        + f"fx: {cam.fx!r}\nfy: {cam.fy!r}\ncx: {cam.cx!r}\ncy: {cam.cy!r}\n"
        f"width: {cam.width}\nheight: {cam.height}\ndist: [{', '.join(repr(float(d)) for d in cam.dist)}]\n"
        "rolling_shutter: 0.0\n",  # rendered with a global shutter (a named camera's readout does not apply)
    )
    scene = Scene(seed, scene_surfaces(params["motion"]))
    rays = Rays(cam)
    rng = np.random.default_rng([seed, 31337])
    stamps = EPOCH + params.get("time_offset", 0.0) + np.arange(frames) / FPS
    names = [f"{ts:.6f}.png" for ts in stamps]
    exposure = exposure_frames(params.get("motion_blur", {}).get("exposure_ms", 0.0))
    delay = params.get("depth_delay", 0.0)
    pose_at = lambda u: trajectory_at(params["motion"], u, frames, params.get("phase", 0.0))  # noqa: E731
    max_range = ORBIT_RANGE if params["motion"] == "orbit" else MAX_RANGE
    streaks = []
    with frame_progress(frames, f"rendering {frames} frames", enabled=progress) as advance:
        for k in range(frames):
            *rendered, streak = render_exposure(scene, rays, pose_at, k, exposure)
            if delay:  # the depth image of the pose ``delay`` later
                rendered[1] = scene.render(rays, pose_at(np.array([k + delay * FPS]))[0])[1]
            streaks.append(streak)
            _write_frame(out, names[k], rendered, noise, dropout, drift, rng, max_range)
            advance()
    record_streaks(params, streaks)
    atomic_write_text(out / "synthetic.yaml", yaml.safe_dump({"generator": "rgbdslam synthetic v1", **params}, sort_keys=False))
    header = "# timestamp filename\n"
    atomic_write_text(out / "rgb.txt", "# color images (synthetic)\n" + header + "".join(f"{t:.6f} rgb/{n}\n" for t, n in zip(stamps, names)))
    atomic_write_text(out / "depth.txt", "# depth maps (synthetic)\n" + header + "".join(f"{t + delay:.6f} depth/{n}\n" for t, n in zip(stamps, names)))
    write_tum(Trajectory(stamps, poses), out / "groundtruth.txt")


def synth_command(out_dir: str | Path, **kwargs) -> dict:
    """``rgbdslam synth``: generate with a progress bar and print where and how fast."""
    summary = generate_sequence(out_dir, progress=True, **kwargs)
    console.print(
        f"wrote {summary['frames']} {summary['motion']} frames ({summary['width']}x{summary['height']}, "
        f"camera {summary['camera']}{blur_note(summary)}) to {summary['path']} in {summary['seconds']:.1f} s"
    )
    return summary
