"""A rectified stereo pair's geometry and the depth noise its disparity implies.

After rectification both cameras share the intrinsics ``K`` and differ by a translation of
``baseline`` metres along the left camera's x axis. A point at depth ``z`` has the disparity
``d = fx * baseline / z`` (pixels, ``u_left - u_right``). A disparity error of ``sigma_d``
pixels moves the depth by (first order) ``sigma_z = z^2 * sigma_d / (fx * baseline)``: stereo
depth noise grows with the square of the distance, like a Kinect's, but with a constant set
by the rig, not the sensor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgbdslam.geometry.camera import Camera


@dataclass(frozen=True)
class DepthNoise:
    """Depth noise of a stereo depth map: disparity noise ``sigma_disparity`` (pixels) through
    ``z = fx * baseline / d``. Attached to every stereo frame as ``Frame.depth_noise``; RGB-D
    frames have None. Use :meth:`sigma` for the per-point depth standard deviation (metres) and
    :meth:`covariance` for the full 3x3 covariance of back-projected points (elongated along
    the viewing ray): what registration weights and a landmark filter need."""

    fx: float
    baseline: float  # metres
    sigma_disparity: float  # pixels
    fy: float = 0.0  # 0 = fx
    cx: float = 0.0
    cy: float = 0.0
    sigma_pixel: float = 0.5  # key-point position noise along u and v (pixels), for covariance()
    min_disparity: float = 0.0  # smaller disparities give no depth: a key point without one is at least fx B / this away

    def sigma(self, z: np.ndarray) -> np.ndarray:
        """Depth standard deviation (metres) of depth(s) ``z`` (metres)."""
        z = np.asarray(z, dtype=np.float64)
        return z * z * self.sigma_disparity / (self.fx * self.baseline)

    def disparity(self, z: np.ndarray) -> np.ndarray:
        """Disparity (pixels) of depth(s) ``z``."""
        return self.fx * self.baseline / np.asarray(z, dtype=np.float64)

    def covariance(self, P: np.ndarray, sigma_pixel: np.ndarray | None = None,
                   sigma_disparity: float | None = None) -> np.ndarray:
        """Covariances (N, 3, 3) of camera points ``P`` (N, 3) triangulated from the pair:
        ``J diag(s_u^2, s_v^2, s_d^2) J^T`` with J the Jacobian of (X, Y, Z) w.r.t. (u, v, d).
        ``sigma_pixel`` (scalar or (N,), e.g. per ORB octave) and ``sigma_disparity`` replace the
        model's own values when given."""
        P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
        s_uv = np.broadcast_to(np.asarray(self.sigma_pixel if sigma_pixel is None else sigma_pixel, np.float64),
                               (len(P),))
        s_d = self.sigma_disparity if sigma_disparity is None else sigma_disparity
        fy = self.fy or self.fx
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        d = self.fx * self.baseline / z
        # X = (u - cx) B / d, Y = (v - cy) B fx / (fy d), Z = fx B / d
        J = np.zeros((len(P), 3, 3))
        J[:, 0, 0] = self.baseline / d
        J[:, 1, 1] = self.baseline * self.fx / (fy * d)
        J[:, 0, 2] = -x / d
        J[:, 1, 2] = -y / d
        J[:, 2, 2] = -z / d
        S = np.zeros((len(P), 3, 3))
        S[:, 0, 0] = S[:, 1, 1] = s_uv ** 2
        S[:, 2, 2] = s_d ** 2
        return J @ S @ J.transpose(0, 2, 1)


@dataclass(frozen=True)
class StereoRig:
    """A rectified pair: the left camera (pinhole, no distortion) and the baseline (metres)."""

    camera: Camera
    baseline: float

    def depth_from_disparity(self, disparity: np.ndarray) -> np.ndarray:
        """Metric depth of disparities (pixels); 0 where the disparity is not positive."""
        d = np.asarray(disparity, dtype=np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.float32(self.camera.fx * self.baseline) / d
        return np.where(d > 0, z, 0.0).astype(np.float32)

    def noise(self, sigma_disparity: float, min_disparity: float = 0.0) -> DepthNoise:
        c = self.camera
        return DepthNoise(c.fx, self.baseline, sigma_disparity, c.fy, c.cx, c.cy, min_disparity=min_disparity)


def midpoint_triangulate(rig: StereoRig, uv_left: np.ndarray, uv_right: np.ndarray) -> np.ndarray:
    """3-D points (N, 3, left camera frame) from matched pixels of a rectified pair: the midpoint
    of the shortest segment between the two viewing rays (spec section 6). For an exactly
    rectified match (same row) this is the textbook ``z = fx B / (u_l - u_r)``; a row mismatch
    is split between the rays instead of ignored."""
    c = rig.camera
    uv_left = np.asarray(uv_left, dtype=np.float64).reshape(-1, 2)
    uv_right = np.asarray(uv_right, dtype=np.float64).reshape(-1, 2)
    ray = lambda uv: np.stack([(uv[:, 0] - c.cx) / c.fx, (uv[:, 1] - c.cy) / c.fy, np.ones(len(uv))], 1)  # noqa: E731
    a, b = ray(uv_left), ray(uv_right)
    o2 = np.array([rig.baseline, 0.0, 0.0])  # right camera centre in the left frame
    # minimise |s a - (o2 + t b)|: [a.a  -a.b; a.b  -b.b] [s t] = [a.o2  b.o2]
    aa, bb, ab = (a * a).sum(1), (b * b).sum(1), (a * b).sum(1)
    ao, bo = a @ o2, b @ o2
    den = aa * bb - ab * ab
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (ao * bb - ab * bo) / den
        t = (ab * ao - aa * bo) / den
    return 0.5 * (s[:, None] * a + (o2 + t[:, None] * b))
