"""DIF — the conditional averaging depth filter (docs/references.md §3, docs/slam.md).

Runs after registration, once the current frame's camera-to-world pose is known:

* **range**: measurements outside ``[min_depth, max_depth]`` become 0 (no measurement);
* **temporal**: each of the last K *filtered* depth maps is warped into the current frame
  with the relative pose. The warp is done on the current pixel grid (backward warping
  with ``cv2.remap``, nearest neighbour): the current pixel's 3-D point is projected into
  the old frame, the old depth there is read, and converted back to a depth on the current
  pixel's ray (intersection of the ray with the fronto-parallel plane, in the old camera,
  at the old measured depth). Occluded or disoccluded pixels read a different surface and
  so disagree with the current measurement; they are not averaged;
* **spatial**: the current frame's neighbours in a (2r+1)² window;
* a sample **agrees** when ``|z_sample - z| <= a + b z²`` (Kinect axial noise grows with
  z²); the output is the mean of the pixel's own value and its agreeing samples;
* a pixel with fewer than ``min_support`` agreeing samples (besides itself) is
  invalidated: isolated outliers and "flying pixels" on depth edges have no support
  (capped by the samples the frame can have: the first frame of a temporal-only filter is
  kept as measured);
* zero stays zero: the filter never invents depth where the sensor gave none.

Everything is vectorised over the image (float32, OpenCV kernels for the warp).
"""

from __future__ import annotations

from collections import deque

import cv2
import numpy as np

from rgbdslam.errors import ConfigError
from rgbdslam.frontend.config import DepthFilterConfig
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import inv


class DepthFilter:
    """Stateful DIF: call it once per registered frame, in order."""

    def __init__(self, cfg: DepthFilterConfig, camera: Camera):
        possible = max(cfg.window, 0) + (2 * max(cfg.spatial_radius, 0) + 1) ** 2 - 1
        if cfg.min_support > possible:
            raise ConfigError(
                f"depth_filter.min_support={cfg.min_support} exceeds the {possible} samples a pixel can have "
                f"(window={cfg.window}, spatial_radius={cfg.spatial_radius}), so every pixel would be removed; "
                f"lower depth_filter.min_support or widen the window")
        self.cfg = cfg
        self.camera = camera
        self.history: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=max(cfg.window, 0) or None)
        if cfg.window <= 0:
            self.history = deque(maxlen=1)
        self._rays_shape: tuple[int, int] | None = None
        self._rays: tuple[np.ndarray, np.ndarray] | None = None  # (H, W) float32 ray x/z, y/z
        self.last_stats: dict[str, float] = {}

    # ---------------------------------------------------------------- helpers
    def _grid_rays(self, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        if self._rays_shape != (h, w):
            c = self.camera
            u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
            self._rays = ((u - np.float32(c.cx)) / np.float32(c.fx), (v - np.float32(c.cy)) / np.float32(c.fy))
            self._rays_shape = (h, w)
        return self._rays

    def tolerance(self, z: np.ndarray) -> np.ndarray:
        """Agreement tolerance a + b z² (metres), capped at z/2 so a zero never agrees."""
        c = self.cfg
        tol = np.float32(c.tolerance_a) + np.float32(c.tolerance_b) * z * z
        return np.minimum(tol, np.float32(0.5) * z)

    def warp(self, depth_old: np.ndarray, T_cur_old: np.ndarray, depth_cur: np.ndarray) -> np.ndarray:
        """Depth of ``depth_old`` (taken at pose P_old) seen along the current pixels' rays.

        ``T_cur_old`` maps old-camera points into the current camera (P_cur⁻¹ · P_old).
        Returns (H, W) float32, 0 where the old frame has no measurement or the point
        projects outside it; only pixels with a current measurement are computed.
        """
        h, w = depth_cur.shape
        rx, ry = self._grid_rays(h, w)
        T = inv(np.asarray(T_cur_old, dtype=np.float64))  # current -> old
        K = self.camera.K
        M = np.hstack([K @ T[:3, :3], (K @ T[:3, 3])[:, None]]).astype(np.float32)
        z = depth_cur
        # old-camera homogeneous pixel (u*d, v*d, d) of the current point z * (x, y, 1) is
        # z * (M[:, :3] @ ray) + M[:, 3]; rows computed with scalar coefficients on contiguous arrays
        au, av, ad = (m[0] * rx + m[1] * ry + m[2] for m in M)
        bu, bv, bz = M[:, 3]
        pd = z * ad + bz
        mapx = cv2.divide(z * au + bu, pd)  # OpenCV returns 0 where pd == 0
        mapy = cv2.divide(z * av + bv, pd)
        sampled = cv2.remap(depth_old.astype(np.float32, copy=False), mapx, mapy, cv2.INTER_NEAREST,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        # Depth s along the current ray whose old-camera depth equals the sample:
        # s * ad + bz = sampled  =>  s = (sampled - bz) / ad.
        out = (sampled - bz) / np.maximum(ad, np.float32(1e-6))
        out[(sampled <= 0) | (pd <= 1e-6) | (out < 0)] = 0.0
        # pixels without a current measurement (z == 0) are ignored by the caller
        return out

    # ---------------------------------------------------------------- the filter
    def filter(self, depth: np.ndarray, pose: np.ndarray,
               previous: list[tuple[np.ndarray, np.ndarray]] | None = None) -> np.ndarray:
        """Stateless DIF of ``depth`` at ``pose`` given ``previous`` [(filtered depth, pose)]."""
        c = self.cfg
        z = np.asarray(depth, dtype=np.float32).copy()
        z[~np.isfinite(z)] = 0.0
        z[(z < c.min_depth) | (z > c.max_depth)] = 0.0
        valid = z > 0
        tol = self.tolerance(z)
        total = z.copy()
        count = valid.astype(np.float32)
        support = np.zeros(z.shape, np.float32)

        ones = np.ones_like(z)

        def accumulate(sample: np.ndarray) -> None:
            # OpenCV kernels (SIMD, no temporaries); z == 0 has tol 0: harmless, masked below
            agree = cv2.compare(cv2.absdiff(sample, z), tol, cv2.CMP_LE)
            cv2.add(total, sample, dst=total, mask=agree)
            cv2.add(support, ones, dst=support, mask=agree)

        # temporal
        if previous:
            pose_cur_inv = inv(np.asarray(pose, dtype=np.float64))
            for d_old, p_old in previous:
                accumulate(self.warp(d_old, pose_cur_inv @ p_old, z))
        # spatial (shifted views of a zero-padded copy)
        r = int(c.spatial_radius)
        if r > 0:
            h, w = z.shape
            pad = cv2.copyMakeBorder(z, r, r, r, r, cv2.BORDER_CONSTANT, value=0.0)
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    if dy == 0 and dx == 0:
                        continue
                    accumulate(pad[r + dy:r + dy + h, r + dx:r + dx + w])
        count += support
        # The support asked for is capped by the samples this frame can have: without history
        # (first frame) and without a spatial window nothing can be verified, so keep the raw depth.
        need = min(c.min_support, (len(previous) if previous else 0) + (2 * max(r, 0) + 1) ** 2 - 1)
        out = np.zeros_like(z)
        keep = valid & (support >= need)
        out[keep] = total[keep] / count[keep]
        self.last_stats = {
            "valid_in": float(np.count_nonzero(valid)),
            "valid_out": float(np.count_nonzero(keep)),
            "mean_support": float(support[valid].mean()) if valid.any() else 0.0,
        }
        return out

    def __call__(self, depth: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """Filtered depth (float32 metres, 0 = invalid) of the current frame whose
        camera-to-world pose is known; remembers (filtered depth, pose) of the last K frames."""
        previous = list(self.history) if self.cfg.window > 0 else None
        out = self.filter(depth, pose, previous)
        if self.cfg.window > 0:
            self.history.append((out, np.array(pose, dtype=np.float64)))
        return out

    def reset(self) -> None:
        self.history.clear()
