"""Pinhole camera with Brown–Conrady distortion (OpenCV's k1 k2 p1 p2 k3)."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


@dataclass(frozen=True)
class Camera:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int = 640
    height: int = 480
    dist: tuple[float, ...] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))
    name: str = ""
    # rolling shutter: seconds from reading the first row to the last (0 = global shutter or unknown);
    # features.rolling_shutter (None) takes it from here (docs/slam.md "Rolling shutter")
    readout: float = 0.0
    # False: the depth images come from a second camera and were re-projected into this one
    # (datasets.camera_file.CameraSetup.depth_camera), so a key point's depth and its pixel disagree by
    # that calibration's error; the landmark map's pose then fits 3-D points (landmarks.tracking.map_pose)
    depth_registered: bool = True

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0 for d in self.dist)

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixel coordinates (N,2) -> ideal pinhole pixel coordinates (N,2)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion or len(uv) == 0:
            return uv
        out = cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, np.array(self.dist), P=self.K)
        return out.reshape(-1, 2)

    def distort_points(self, uv: np.ndarray) -> np.ndarray:
        """Ideal pinhole pixel coordinates (N,2) -> distorted pixel coordinates (N,2) (the
        inverse of :meth:`undistort_points`)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion or len(uv) == 0:
            return uv
        xy1 = np.column_stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy, np.ones(len(uv))])
        out, _ = cv2.projectPoints(xy1.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, np.array(self.dist))
        return out.reshape(-1, 2)

    def backproject(self, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Ideal pixel coordinates (N,2) and depth (N,) in metres -> camera points (N,3)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        z = np.asarray(z, dtype=np.float64).reshape(-1)
        x = (uv[:, 0] - self.cx) * z / self.fx
        y = (uv[:, 1] - self.cy) * z / self.fy
        return np.stack([x, y, z], axis=1)

    def project(self, P: np.ndarray) -> np.ndarray:
        """Camera points (N,3) -> ideal pixel coordinates (N,2)."""
        P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
        z = P[:, 2]
        return np.stack([self.fx * P[:, 0] / z + self.cx, self.fy * P[:, 1] / z + self.cy], axis=1)


# Known cameras (TUM RGB-D calibration page; Kraft et al. 2016 for the PUT Kinect v1). Rolling-shutter
# readout only where measured (fr1); 0 = not compensated
CAMERAS: dict[str, Camera] = {
    # fr1's rolling shutter readout (17.5 ms): the readout that makes fr1/rpy's odometry agree best with its
    # loop closures, measured without ground truth (`rgbdslam calibrate rolling-shutter`, docs/slam.md)
    "fr1": Camera(517.3, 516.5, 318.6, 255.3, 640, 480, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633), "fr1", 0.0175),
    "fr2": Camera(520.9, 521.0, 325.1, 249.7, 640, 480, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172), "fr2"),
    "fr3": Camera(535.4, 539.2, 320.1, 247.6, 640, 480, (0.0, 0.0, 0.0, 0.0, 0.0), "fr3"),
    "ros_default": Camera(525.0, 525.0, 319.5, 239.5, 640, 480, (0.0, 0.0, 0.0, 0.0, 0.0), "ros_default"),
    "kinect1": Camera(532.77250, 531.85745, 312.23007, 260.11708, 640, 480, (0.16054, -0.24682, 0.00136, 0.00149, 0.0), "kinect1"),
}
