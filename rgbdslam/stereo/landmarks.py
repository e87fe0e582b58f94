"""What the landmark map (:mod:`rgbdslam.landmarks`) takes from a stereo frame (docs/stereo.md "The landmark map").

An RGB-D camera's depth ends at a few metres and its noise is the Kinect model of ``landmarks.depth_noise_a/b``;
a stereo pair's depth reaches as far as a disparity is measured, and its noise is the pair's own,
``σ_z = z² σ_d / (fx B)`` (:class:`rgbdslam.geometry.stereo.DepthNoise`). So for a stereo frame:

* the map's key points are **every** key point with a stereo depth (``FrameFeatures.depth_raw``), not only
  those inside ``matching.max_depth``: on a road the facades 20-80 m away are what is left to track on when
  the near texture ends. Their depth is weak (metres at 60 m), their bearing is not: the map pose's
  reprojection refine whitens the inverse depth by the pair's noise, so a far point pins the rotation and
  a near one the translation (ORB-SLAM's stereo residual (u, v, u_right) does the same);
* the map's depth limit is the farthest such point (``depth_limit``), the pair's measured range;
* the depth noise along the ray is the pair's (``depth_noise_ab``: a = 0, b = σ_d / (fx B)).
"""

from __future__ import annotations

import numpy as np


def stereo_map_features(feats):
    """``feats`` with a 3-D point and ``valid`` for every key point that has a stereo depth (``depth_raw`` > 0),
    whatever ``matching``'s depth range; ``feats`` itself for an RGB-D frame (no ``depth_noise``)."""
    dn = feats.depth_noise
    z = np.asarray(feats.depth_raw, dtype=np.float64)
    if dn is None or len(z) != len(feats.uv):
        return feats
    has = z > 0
    if not (has & ~feats.valid).any():
        return feats
    fy = dn.fy or dn.fx
    pts = np.array(feats.pts, dtype=np.float64)
    far = has & ~feats.valid
    u, v, zf = feats.uv[far, 0], feats.uv[far, 1], z[far]
    pts[far] = np.stack([(u - dn.cx) * zf / dn.fx, (v - dn.cy) * zf / fy, zf], axis=1)
    out = feats.with_points(pts)
    out.valid = feats.valid | has
    if len(out.edge) == len(has):
        out.edge = out.edge & feats.valid  # the far points were never tested
    return out


def depth_noise_ab(dn) -> tuple[float, float]:
    """The (a, b) of the landmark map's depth noise along the ray, σ = a + b z², for a stereo frame's
    ``DepthNoise``: (0, σ_d / (fx B))."""
    return 0.0, dn.sigma_disparity / (dn.fx * dn.baseline)


def depth_limit(feats, default: float) -> float:
    """The landmark map's depth limit for this frame: the farthest stereo depth of its key points (the pair's
    range), never below ``default`` (``landmarks.max_depth``); ``default`` for an RGB-D frame."""
    z = np.asarray(getattr(feats, "depth_raw", np.zeros(0)), dtype=np.float64)
    if feats.depth_noise is None or not len(z):
        return default
    return max(default, float(z.max()))
