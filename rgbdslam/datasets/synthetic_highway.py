"""A highway for the synthetic stereo rig (``rgbdslam synth --stereo 0.54 --motion highway``).

A car drives at 25-30 m/s along a gently curving road, filmed at 10 Hz by a KITTI-like pair
(fx = 718 px at 1241 px width, camera 1.65 m above the road): 2.5-3 m between frames. The
scene is what makes such sequences hard for a stereo chain: the near texture is the road
surface and two guard rails (2-20 m) — absent over :data:`BARE` (metres 60-100 of the drive,
frames ~22-36), where only far points are seen — everything else is far — buildings 20-80 m to the
sides and a skyline of large facades 120-200 m away — where a disparity of a few pixels gives
depth errors of metres. Every surface is a textured rectangle of
:class:`rgbdslam.datasets.synthetic.Scene` with its own texel size, about one texel per pixel
at the distance it is first seen from (coarser far away: ray casting samples one point per
pixel, so finer texture there would alias and differ between the two cameras).

World frame: z up, the road starts at the origin heading +x. The path is parametrised by arc
length ``s``; its heading is ``HEADING_AMPLITUDE * sin(2 pi s / CURVE_LENGTH + phase)``
(radius of curvature >= ~380 m), the speed ``27.5 + 2.5 sin(2 pi t / 8 s + phase)`` m/s; the
seed picks the phase, the textures and where the buildings stand. Ground truth is exact.
"""

from __future__ import annotations

import numpy as np

from rgbdslam.datasets.synthetic import Surface
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import look_along, make_pose

FPS = 10.0
SPEED = 27.5  # m/s mean (25-30)
SPEED_SWING = 2.5
SPEED_PERIOD = 8.0  # s
HEADING_AMPLITUDE = 0.25  # rad
CURVE_LENGTH = 600.0  # m per period of the heading
CAMERA_HEIGHT = 1.65  # m above the road (KITTI)
LANE_OFFSET = -1.8  # m: the car drives in the right lane
ROAD_HALF_WIDTH = 8.5  # the road reaches the rails
RAIL_OFFSET = 8.0  # m from the centre line
RAIL_HEIGHT = 0.8
SEGMENT = 20.0  # m: the road and rails are rectangles of this length along the curve
AHEAD = 220.0  # m of scene beyond the last frame's position
KITTI_FX, KITTI_WIDTH = 718.856, 1241
BARE = (60.0, 100.0)  # m of road without road texture or rails: only far points are seen there


def highway_camera(width: int, height: int) -> Camera:
    """The KITTI-like pinhole camera at ``width`` x ``height`` (fx scales with the width: 718.856 px
    at 1241 px), no distortion, principal point at the centre."""
    f = KITTI_FX * width / KITTI_WIDTH
    return Camera(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height, (0.0,) * 5, f"highway_{width}x{height}")


def _phase(seed: int) -> float:
    return float(np.random.default_rng([seed, 4711]).uniform(0.0, 2.0 * np.pi))


def arc_length(t: np.ndarray, seed: int) -> np.ndarray:
    """Distance driven (m) at time ``t`` (s): the integral of the speed profile, 0 at t = 0."""
    ph = _phase(seed)
    w = 2.0 * np.pi / SPEED_PERIOD
    return SPEED * t - SPEED_SWING / w * (np.cos(w * t + ph) - np.cos(ph))


class RoadPath:
    """The road's centre line: position and heading as functions of the arc length."""

    def __init__(self, length: float, seed: int, step: float = 0.05) -> None:
        self.phase = _phase(seed)
        self.s = np.arange(0.0, length + 2 * step, step)
        psi = self.heading(self.s)
        # trapezoidal integration of (cos psi, sin psi)
        dx = np.concatenate([[0.0], np.cumsum(0.5 * (np.cos(psi[1:]) + np.cos(psi[:-1])) * step)])
        dy = np.concatenate([[0.0], np.cumsum(0.5 * (np.sin(psi[1:]) + np.sin(psi[:-1])) * step)])
        self.x, self.y = dx, dy

    def heading(self, s: np.ndarray) -> np.ndarray:
        return HEADING_AMPLITUDE * (np.sin(2.0 * np.pi * np.asarray(s) / CURVE_LENGTH + self.phase) - np.sin(self.phase))

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centre-line points (N, 3) at z = 0 and headings (N,) at arc lengths ``s``."""
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        p = np.stack([np.interp(s, self.s, self.x), np.interp(s, self.s, self.y), np.zeros(len(s))], axis=1)
        return p, self.heading(s)

    def frame(self, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centre point, forward and left unit vectors (world) at arc length ``s``."""
        p, psi = self.at(np.array([s]))
        fwd = np.array([np.cos(psi[0]), np.sin(psi[0]), 0.0])
        return p[0], fwd, np.array([-fwd[1], fwd[0], 0.0])


def highway_path(frames: int, seed: int) -> RoadPath:
    """The road of a ``frames``-frame sequence: long enough for the drive plus :data:`AHEAD` m."""
    return RoadPath(float(arc_length(np.array([max(frames - 1, 1) / FPS]), seed)[0]) + AHEAD, seed)


def highway_poses(u: np.ndarray, seed: int, path: RoadPath) -> np.ndarray:
    """Left-camera-to-world poses (len(u), 4, 4) at (fractional) frame indices ``u``: in the right
    lane, 1.65 m above the road, looking along the road with a small body sway (pitch ±0.4°,
    roll ±0.3°, periods 1.3 s and 1.9 s)."""
    u = np.atleast_1d(np.asarray(u, dtype=np.float64))
    t = u / FPS
    s = arc_length(t, seed)
    poses = np.empty((len(u), 4, 4))
    ph = path.phase
    for k in range(len(u)):
        c, fwd, left = path.frame(s[k])
        pos = c + LANE_OFFSET * left + np.array([0.0, 0.0, CAMERA_HEIGHT])
        pitch = np.radians(0.4) * np.sin(2 * np.pi * t[k] / 1.3 + ph)
        roll = np.radians(0.3) * np.sin(2 * np.pi * t[k] / 1.9 + 2 * ph)
        P = look_along(pos, fwd + np.array([0.0, 0.0, np.tan(pitch)]))
        c_r, s_r = np.cos(roll), np.sin(roll)
        Rz = np.array([[c_r, -s_r, 0.0], [s_r, c_r, 0.0], [0.0, 0.0, 1.0]])
        poses[k] = make_pose(P[:3, :3] @ Rz, P[:3, 3])
    return poses


def _strip(name: str, path: RoadPath, s0: float, s1: float, offset: float, z0: float, z1: float, texel: float,
           vertical: bool) -> Surface:
    """A rectangle following the road from ``s0`` to ``s1`` (the chord, a little longer so that
    consecutive strips overlap on a curve): flat at height ``z0`` spanning lateral offsets
    ``offset``..``z1`` (``vertical`` False), or standing at lateral ``offset`` from ``z0`` to ``z1``."""
    p, _ = path.at(np.array([s0, s1]))
    chord = p[1] - p[0]
    length = float(np.linalg.norm(chord))
    u = chord / length
    left = np.array([-u[1], u[0], 0.0])
    ext = 0.5  # m of overlap at both ends
    if vertical:
        origin = p[0] - ext * u + offset * left + np.array([0.0, 0.0, z0])
        return Surface(name, origin, u, np.array([0.0, 0.0, 1.0]), length + 2 * ext, z1 - z0, texel)
    origin = p[0] - ext * u + offset * left + np.array([0.0, 0.0, z0])
    return Surface(name, origin, u, left, length + 2 * ext, z1 - offset, texel)


def highway_surfaces(length: float, seed: int, path: RoadPath) -> list[Surface]:
    """The road, the guard rails, buildings at 20-80 m and a far skyline along ``length`` m of road."""
    rng = np.random.default_rng([seed, 90210])
    out: list[Surface] = []
    edges = np.arange(-10.0, length + SEGMENT, SEGMENT)
    for i, (s0, s1) in enumerate(zip(edges[:-1], edges[1:])):
        if BARE[0] <= s0 < BARE[1]:
            continue
        out.append(_strip(f"road_{i}", path, s0, s1, -ROAD_HALF_WIDTH, 0.0, ROAD_HALF_WIDTH, 0.03, False))
        out.append(_strip(f"rail_r{i}", path, s0, s1, -RAIL_OFFSET, 0.0, RAIL_HEIGHT, 0.02, True))
        out.append(_strip(f"rail_l{i}", path, s0, s1, RAIL_OFFSET, 0.0, RAIL_HEIGHT, 0.02, True))
    # buildings: a facade facing the road and one side wall, every ~30 m on either side, 20-80 m
    # from the centre line
    s = -10.0
    k = 0
    while s < length:
        s += rng.uniform(20.0, 40.0)
        for side in (-1.0, 1.0):
            if rng.uniform() < 0.25:
                continue
            c, fwd, left = path.frame(min(s, length))
            dist = rng.uniform(20.0, 80.0)
            w, depth, h = rng.uniform(8.0, 30.0), rng.uniform(8.0, 20.0), rng.uniform(6.0, 25.0)
            texel = float(np.clip(dist / KITTI_FX * 1.5, 0.03, 0.2))
            up = np.array([0.0, 0.0, 1.0])
            front = c + side * dist * left - 0.5 * w * fwd
            out.append(Surface(f"bldg{k}", front, fwd, up, w, h, texel))
            # the side wall nearer the car (the one it drives towards), going away from the road
            out.append(Surface(f"bldg{k}_side", front, side * left, up, depth, h, texel))
            k += 1
    # skyline: tall facades 120-200 m from the centre line, facing the road, every ~60 m
    s = -40.0
    while s < length + 60.0:
        s += rng.uniform(40.0, 80.0)
        for side in (-1.0, 1.0):
            c, fwd, left = path.frame(min(max(s, 0.0), length))
            dist = rng.uniform(120.0, 200.0)
            w, h = rng.uniform(40.0, 90.0), rng.uniform(20.0, 60.0)
            origin = c + side * dist * left - 0.5 * w * fwd
            out.append(Surface(f"sky{k}", origin, fwd, np.array([0.0, 0.0, 1.0]), w, h, float(dist / KITTI_FX * 1.5)))
            k += 1
    return out
