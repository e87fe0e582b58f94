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


BEARING_SIGMA = 1e12  # 1/m: the inverse-depth residual of a key point without stereo depth carries no weight


def stereo_map_pose(lmap, feats, match, pred: np.ndarray, cfg, camera, rng, seeded: bool = False):
    """The map pose of a stereo frame from its matches to the landmarks (``match``: every key point, with or
    without a stereo depth). A first pose from the pairs with depth (3-D RANSAC + reprojection refine,
    :func:`rgbdslam.landmarks.tracking.map_pose`) or, with fewer than ``min_inliers`` of them, the prediction
    ``pred``; then the reprojection refine on **every** match, re-gated at ``chi_gate`` σ twice: a key point with
    stereo depth as (u, v, 1/z) whitened by the pair's noise, one without as its pixel (u, v) alone (the
    inverse-depth residual's σ infinite), so the far facades that have no disparity in this frame still
    hold the rotation and, with the near ones, the translation. None with fewer than ``min_inliers`` inliers."""
    from rgbdslam.landmarks.tracking import MapPose, map_pose, refine_reprojection, reprojection_residuals
    from rgbdslam.geometry.rigid import row_norms
    from rgbdslam.geometry.se3 import inv

    need = max(3, cfg.min_inliers)
    if len(match.lm) < need:
        return None
    depth = feats.valid[match.feat]
    T = pred
    if depth.sum() >= need:
        first = map_pose(lmap, feats, match.subset(depth), pred, cfg, camera, rng, seeded)
        if first is not None:
            T = first.pose
    a, b = depth_noise_ab(feats.depth_noise)
    feat, lm = match.feat, match.lm
    uv, X, cov = feats.uv[feat], lmap.pos[lm], lmap.cov[lm]
    z = np.where(depth, feats.pts[feat, 2], 1.0)
    sig = np.where(depth, a + b * z * z, BEARING_SIGMA)
    Tcw = inv(T)
    r, _ = reprojection_residuals(Tcw[:3, :3], Tcw[:3, 3], X, uv, z, camera, cfg.sigma_px, sig, cov, jacobian=False)
    mask = row_norms(r) < cfg.chi_gate
    info = None
    for _ in range(2):
        if mask.sum() < need:
            return None
        T, _, info = refine_reprojection(T, X[mask], uv[mask], z[mask], camera, cfg.sigma_px, sig[mask], cov[mask],
                                         cfg.refine_iterations)
        Tcw = inv(T)
        r, _ = reprojection_residuals(Tcw[:3, :3], Tcw[:3, 3], X, uv, z, camera, cfg.sigma_px, sig, cov,
                                      jacobian=False)
        mask = row_norms(r) < cfg.chi_gate
    if mask.sum() < need:
        return None
    d = depth & mask
    P = feats.pts[feat[d]]
    rms = float(np.sqrt(np.mean(row_norms(X[d] - (P @ T[:3, :3].T + T[:3, 3])) ** 2))) if d.any() else 0.0
    return MapPose(T, feat[mask], lm[mask], len(lm), match.n_candidates, rms, info)


def prediction_limits(information: np.ndarray, metres: float, degrees: float, radius: float,
                      fx: float) -> tuple[float, float, float]:
    """(metres, degrees, pixels): how far a stereo frame's map pose may differ from the registration's, and
    the search radius around the landmarks' projections, each covering three σ of the registration's pose
    from its 6x6 ``information`` ((rotation, translation) order; the largest σ of each block; a far point's
    pixel moves by fx·σ_rot), at least the configured ``metres`` / ``degrees`` / ``radius``. A car's
    registration is decimetres off where the near texture ends (the stereo fallback: σ_rot 0.01 rad, σ_t a
    tenth of the step + 0.1 m), and the map pose is what corrects it."""
    try:
        C = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        return metres, degrees, radius
    s_rot = float(np.sqrt(max(np.linalg.eigvalsh(C[:3, :3]).max(), 0.0)))
    s_t = float(np.sqrt(max(np.linalg.eigvalsh(C[3:, 3:]).max(), 0.0)))
    return max(metres, 3.0 * s_t), max(degrees, float(np.degrees(3.0 * s_rot))), max(radius, 3.0 * fx * s_rot)
