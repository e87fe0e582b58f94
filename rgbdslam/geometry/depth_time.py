"""Depth taken at another moment than the colour image: each key point's depth at the colour time.

An RGB-D camera whose colour and depth images are not exposed together (TUM's freiburg1 Kinect:
the depth image's time stamp is 0–14 ms after the colour one) gives every key point a depth from
a slightly different view: at 50 °/s and 10 ms the depth image is turned by 0.5°, about 4 px at
f = 517, so a key point on an edge reads the depth of the surface beside it. With ``D``, the pose
of the camera at the depth time in the camera at the colour time (``X_colour = D · X_depth``, e.g.
the constant-velocity motion over the delay), the scene point seen at a colour key point is found
in the depth image where it was at the depth time, its depth read there, and the point taken back
to the colour time:

1. a first depth z₀ along the colour ray (the depth image at the key point itself, else the
   median of those), X_c = z₀ · ray(u, v);
2. X_d = D⁻¹ X_c projected into the depth image (registered to the distorted colour image) gives
   the pixel where that point was at the depth time; its depth z_d there puts the point at
   X_d' = X_d · z_d / X_d.z;
3. the key point's depth at the colour time is the z of D · X_d'; with translation in D the
   pixel of step 2 depends on z₀, so steps 2–3 run twice (the second with the first's z).

The colour ray (the key point's sub-pixel position) is kept; only its depth changes. Rotation
alone moves the pixel independently of z₀; translation changes z itself (a camera 5 cm nearer the
wall at the depth time reads 5 cm less, which step 3 adds back).
"""

from __future__ import annotations

import numpy as np

from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import inv, transform_points


def sample_depth(depth: np.ndarray, uv_raw: np.ndarray) -> np.ndarray:
    """Depth (N,) at the rounded pixels ``uv_raw`` (N,2) of the depth image; 0 outside it."""
    h, w = depth.shape[:2]
    if len(uv_raw) == 0:
        return np.zeros(0)
    finite = np.all(np.isfinite(uv_raw), axis=1)
    u = np.rint(np.where(finite, uv_raw[:, 0], -1.0)).astype(np.int64)
    v = np.rint(np.where(finite, uv_raw[:, 1], -1.0)).astype(np.int64)
    inside = finite & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    z = np.zeros(len(uv_raw))
    z[inside] = depth[v[inside], u[inside]]
    z[~np.isfinite(z)] = 0.0
    return z


def depth_at_colour_time(uv: np.ndarray, depth: np.ndarray, camera: Camera, D: np.ndarray,
                         z0: np.ndarray, iterations: int = 2) -> np.ndarray:
    """Depth (N,) along the colour rays of the ideal (undistorted) key points ``uv`` (N,2) at the
    colour image's time, read from a ``depth`` image taken with the camera at pose ``D`` in the
    colour-time camera (4x4, ``X_colour = D · X_depth``); ``z0`` (N,) the first guess (> 0).
    0 where the point falls outside the depth image, has no depth there, or lies behind a camera."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    z = np.asarray(z0, dtype=np.float64).reshape(-1).copy()
    Dinv = inv(np.asarray(D, dtype=np.float64))
    out = np.zeros(len(uv))
    for _ in range(max(1, iterations)):
        Xd = transform_points(Dinv, camera.backproject(uv, z))
        front = Xd[:, 2] > 1e-6
        zd = np.zeros(len(uv))
        if front.any():
            zd[front] = sample_depth(depth, camera.distort_points(camera.project(Xd[front])))
        ok = front & (zd > 0)
        Xd[ok] *= (zd[ok] / Xd[ok, 2])[:, None]
        zc = transform_points(np.asarray(D, dtype=np.float64), Xd)[:, 2]
        ok &= zc > 1e-6
        out = np.where(ok, zc, 0.0)
        z = np.where(ok, zc, z)  # the next pass starts from this answer (translation: the pixel depends on z)
    return out


def row_motions(rows: np.ndarray, height: int, readout: float, V: np.ndarray, dt: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Rolling shutter: the pose of the camera when image row ``rows`` (N,) was read, in the camera
    at the frame's time stamp (taken as the middle row's time), under the constant-velocity motion
    ``V`` (4x4) over ``dt`` seconds, the rows read from top to bottom in ``readout`` seconds. Row v
    is read τ = (v - height/2) / height · readout after the middle row; its pose is V scaled by τ/dt
    on SE(3) (rotation vector and translation). Returns ``(R (N,3,3), t (N,3))``."""
    from scipy.spatial.transform import Rotation

    rows = np.asarray(rows, dtype=np.float64).reshape(-1)
    f = (rows - 0.5 * height) / height * readout / dt
    rv = Rotation.from_matrix(np.asarray(V, dtype=np.float64)[:3, :3]).as_rotvec()
    R = Rotation.from_rotvec(f[:, None] * rv[None, :]).as_matrix().reshape(-1, 3, 3)
    return R, f[:, None] * np.asarray(V, dtype=np.float64)[None, :3, 3]


def shutter_corrected_pixels(uv: np.ndarray, camera: Camera, R: np.ndarray) -> np.ndarray:
    """Ideal pixels (N,2) seen along the rays of ``uv`` (N,2) turned by the row rotations ``R``
    (N,3,3): where the key points would be in an image taken all at once at the reference time
    (rotation alone: a pixel's shift does not depend on its depth)."""
    rays = camera.backproject(uv, np.ones(len(uv)))
    return camera.project(np.einsum("nij,nj->ni", R, rays))
