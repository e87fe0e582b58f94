"""Depth images re-projected into the colour camera (registration of two-sensor RGB-D data).

A Kinect v1 (7-Scenes), a RealSense recording or any rig with separate depth and colour sensors
gives depth in the depth camera's image. The pipeline looks depth up at colour pixels, so each
depth pixel is back-projected with the depth intrinsics, moved by the depth-to-colour extrinsic
and projected into the colour image (distortion included); where several land on one colour
pixel the nearest wins (a z-buffer), and colour pixels no depth pixel lands on stay 0 (no
measurement). Vectorised: the depth rays are computed once, each frame is a few array passes.
"""

from __future__ import annotations

import cv2
import numpy as np

from rgbdslam.geometry.camera import Camera


class DepthRegistration:
    """Re-projects depth images of ``depth_camera`` into ``color_camera``."""

    def __init__(self, depth_camera: Camera, color_camera: Camera, depth_to_color: np.ndarray) -> None:
        self.depth_camera, self.color_camera = depth_camera, color_camera
        self.T = np.asarray(depth_to_color, dtype=np.float64).reshape(4, 4)
        w, h = depth_camera.width, depth_camera.height
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        ideal = depth_camera.undistort_points(np.stack([u.ravel(), v.ravel()], axis=1))
        # the ray (x, y, 1) of every depth pixel
        self._rx = ((ideal[:, 0] - depth_camera.cx) / depth_camera.fx).astype(np.float32)
        self._ry = ((ideal[:, 1] - depth_camera.cy) / depth_camera.fy).astype(np.float32)

    @property
    def is_identity(self) -> bool:
        d, c = self.depth_camera, self.color_camera
        return (np.allclose(self.T, np.eye(4)) and (d.fx, d.fy, d.cx, d.cy, d.width, d.height, d.dist)
                == (c.fx, c.fy, c.cx, c.cy, c.width, c.height, c.dist))

    def __call__(self, depth: np.ndarray) -> np.ndarray:
        """Depth (H_d, W_d) float metres in the depth camera -> (H_c, W_c) float32 metres in colour."""
        z = np.asarray(depth, dtype=np.float32).reshape(-1)
        ok = np.flatnonzero(z > 0)
        z = z[ok]
        x, y = self._rx[ok] * z, self._ry[ok] * z
        R, t = self.T[:3, :3].astype(np.float32), self.T[:3, 3].astype(np.float32)
        # component arithmetic on 1-D float32 arrays (no (N, 3) temporaries, no BLAS threads)
        X = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
        Y = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
        Z = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
        front = Z > 1e-6
        X, Y, Z = X[front], Y[front], Z[front]
        c = self.color_camera
        if c.has_distortion:
            Q = np.stack([X, Y, Z], axis=1).astype(np.float64)
            uv, _ = cv2.projectPoints(Q.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), c.K, np.array(c.dist))
            u, v = uv[:, 0, 0], uv[:, 0, 1]
        else:
            u, v = np.float32(c.fx) * X / Z + np.float32(c.cx), np.float32(c.fy) * Y / Z + np.float32(c.cy)
        col = np.rint(u).astype(np.int32)
        row = np.rint(v).astype(np.int32)
        inside = (col >= 0) & (col < c.width) & (row >= 0) & (row < c.height)
        zc, flat = Z[inside], row[inside] * c.width + col[inside]
        out = np.zeros(c.width * c.height, dtype=np.float32)
        order = np.argsort(-zc)  # far first: the nearest is written last and wins
        out[flat[order]] = zc[order]
        return out.reshape(c.height, c.width)
