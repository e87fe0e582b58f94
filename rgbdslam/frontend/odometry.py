"""The front end: features -> per-reference registration -> fused pose (or "lost").

Conventions
-----------
* Poses are camera-to-world 4x4 matrices; the first tracked frame is the world origin.
* A pairwise registration (:class:`rgbdslam.frontend.pairwise.PairRegistration`) returns
  ``T`` that maps **reference-frame points into the current frame**: ``p_cur = T @ p_ref``;
  the current frame's pose chained from the reference is ``P_cur = P_ref @ inv(T)``.
* ``TrackResult.relative = inv(P_prev) @ P_cur`` (prev = the last tracked frame) and
  ``TrackResult.information`` is its 6x6 information in GTSAM's Pose3 tangent order
  (rotation, translation), right perturbation ``relative * Exp(xi)``.

The registration strategy (``registration.method``: ransac, isvd, islam; see
``rgbdslam/frontend/registration/``) is chosen by the factory; a strategy with
``multi_reference`` (ISLAM) is registered against the last ``registration.mp`` tracked frames
and the candidates are fused (:mod:`rgbdslam.frontend.pose_fusion`), the others against the
previous frame only.
"""

from __future__ import annotations

import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from rgbdslam.frame import Frame
from rgbdslam.frontend.config import FeaturesConfig, MatchingConfig, RegistrationConfig
from rgbdslam.frontend.features import Detections, FrameFeatures, extract_features, lift, reshutter, strongest, subset
from rgbdslam.frontend.pairwise import PairRegistration, RegistrationResult, build_pair_registration
from rgbdslam.frontend.pose_fusion import fuse_candidates
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import inv, rotation_angle, scale_motion, transform_points

if TYPE_CHECKING:
    from rgbdslam.config import Config


@dataclass
class TrackResult:
    index: int
    timestamp: float
    pose: np.ndarray | None  # 4x4 camera-to-world, None if lost
    lost: bool
    features: FrameFeatures
    relative: np.ndarray | None  # inv(P_prev_tracked) @ P_cur
    information: np.ndarray | None  # 6x6 information of `relative`
    n_matches: int
    n_inliers: int
    weight: float
    timings: dict[str, float]
    n_candidates: int = 0  # registrations that succeeded
    n_fused: int = 0  # candidates kept by the fusion
    reset: bool = False  # tracking restarted here after too many lost frames (relative is a guess)
    matches: np.ndarray | None = None  # (K, 4) inlier matches to the newest kept reference: u_ref v_ref u_cur v_cur
    # landmarks.n_features: every key point detected (``features`` holds the strongest features.n_features)
    map_features: FrameFeatures | None = None


def _match_segments(ref, res: RegistrationResult, feats: FrameFeatures) -> np.ndarray:
    """Pixel coordinates of a registration's inlier pairs, for inspection (Rerun)."""
    return np.hstack([ref.features.uv[res.pairs[:, 0]], feats.uv[res.pairs[:, 1]]]).astype(np.float32)


@dataclass
class _Ref:
    features: FrameFeatures
    pose: np.ndarray


def _motion(prev: _Ref, last: _Ref) -> tuple[np.ndarray, int, float]:
    """The constant-velocity model between two tracked frames: motion, index gap, time gap."""
    return (inv(prev.pose) @ last.pose, last.features.index - prev.features.index,
            last.features.timestamp - prev.features.timestamp)


class Frontend:
    """Tracks frames one by one; keeps the features of the last MP tracked frames as references."""

    def __init__(self, rc: RegistrationConfig, fc: FeaturesConfig, mc: MatchingConfig, camera: Camera,
                 register: PairRegistration, map_features: int = 0):
        self.rc = rc
        self.fc = fc
        # landmarks.n_features: detect this many (the landmark map's), register with fc.n_features of them
        self.fc_detect = detection_features(fc, map_features)
        self._full: FrameFeatures | None = None  # the last frame's every key point (fc_detect), or None
        self.mc = mc
        self.camera = camera
        self.register = register
        self.mp = max(1, rc.mp) if register.strategy.multi_reference else 1
        self.refs: deque[_Ref] = deque(maxlen=self.mp)
        # (motion between the last two tracked frames, their index gap, their time gap in s)
        self._velocity: tuple[np.ndarray, int, float] | None = None
        self._n_lost = 0  # consecutive lost frames
        self._prediction_error = np.inf  # how far the last tracked frame was from its prediction (m)
        self.n_newest_guided = 0  # frames whose newest reference was matched around the prediction
        self.n_fallback = 0  # stereo frames tracked by the fallback (registration.stereo_fallback)
        self._executor = ThreadPoolExecutor(max_workers=rc.threads) if rc.threads > 1 and self.mp > 1 else None

    def close(self) -> None:
        if self._executor is not None:
            self._executor.shutdown()
            self._executor = None

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass

    def _predict(self, index: int) -> np.ndarray:
        last = self.refs[-1]
        if not self.rc.constant_velocity or self._velocity is None:
            return last.pose
        V, gap, _ = self._velocity
        return last.pose @ scale_motion(V, (index - last.features.index) / gap)

    def _time_velocity(self) -> tuple[np.ndarray, float] | None:
        """The constant-velocity model as (motion, seconds it took), for the rolling shutter."""
        if self._velocity is None or not self.rc.constant_velocity:
            return None
        V, _, dt = self._velocity
        return (V, dt) if dt > 0 else None

    def _depth_motion(self, frame: Frame) -> np.ndarray | None:
        """The camera's motion from the colour to the depth image's time (``features.depth_delay``
        = predict): the constant-velocity model scaled to the frame's ``depth_delay``; None when
        there is no delay, no velocity yet, or the compensation is off."""
        if self.fc.depth_delay == "ignore" or not frame.depth_delay or self._velocity is None:
            return None
        V, _, dt = self._velocity
        if not dt > 0:
            return None
        return scale_motion(V, frame.depth_delay / dt)

    def set_depth(self, index: int, depth: np.ndarray) -> None:
        """Replace a kept reference frame's depth (e.g. DIF output) and re-lift its 3-D points."""
        if self._full is not None and self._full.index == index:  # the landmark map's key points too
            lift(self._full, depth, self.camera, self.mc)
        for r in self.refs:
            if r.features.index == index:
                lift(r.features, depth, self.camera, self.mc)
                return

    def track(self, frame: Frame) -> TrackResult:
        rc = self.rc
        t0 = time.perf_counter()
        fc = self.fc_detect
        det = frame.detections
        if fc is not self.fc and isinstance(det, Detections) and det.image is frame.rgb and det.config == self.fc:
            fc = self.fc  # the reader's own key points (sparse stereo: its depth holds only theirs): kept
        feats = extract_features(frame, fc, self.mc, self._depth_motion(frame), self._time_velocity())
        full = self._full = None
        if fc is not self.fc:  # the landmark map's key points; the strongest for the rest
            full, feats = feats, subset(feats, strongest(feats, self.fc))
            self._full = full
        timings = {"features": time.perf_counter() - t0, "matching": 0.0, "registration": 0.0, "fusion": 0.0}
        need = max(3, rc.min_points)
        if not self.refs:
            if feats.n_valid < need:  # no usable origin yet: wait for a frame with features
                return self._lost(frame, feats, timings, 0)
            pose = np.eye(4)
            self.refs.append(_Ref(feats, pose))
            return TrackResult(frame.index, frame.timestamp, pose, False, feats, None, None, 0, 0, 0.0, timings,
                               map_features=full)
        pred = self._predict(frame.index)
        refs = list(reversed(self.refs))  # most recent first
        results = self._register_all(refs, feats, pred)
        t1 = time.perf_counter()
        for res in results:
            if res is not None:
                timings["matching"] += res.timings["matching"]
                timings["registration"] += res.timings["registration"]
        ok = [(r, res) for r, res in zip(refs, results) if res is not None]
        first = results[0]
        n_matches = first.n_matches if first is not None else max((x.n_matches for _, x in ok), default=0)
        if ok:
            # Motion plausibility: a candidate far from the prediction is a false registration.
            gap = frame.index - self.refs[-1].features.index
            dev = [inv(pred) @ r.pose @ inv(res.T) for r, res in ok]
            ok = [o for o, d in zip(ok, dev)
                  if np.linalg.norm(d[:3, 3]) <= rc.max_jump_translation * gap
                  and np.degrees(rotation_angle(d[:3, :3])) <= rc.max_jump_rotation_deg * gap]
        if not ok:
            return self._fallback(frame, feats, timings, pred, n_matches) or self._lost(frame, feats, timings, n_matches)
        cands = np.stack([r.pose @ inv(res.T) for r, res in ok])
        weights = np.array([res.weight for _, res in ok])
        pose, keep, frac = fuse_candidates(cands, weights, rc.fusion, rc.reject_translation, rc.reject_rotation)
        if frac < rc.min_agreement:
            timings["fusion"] = time.perf_counter() - t1
            return self._fallback(frame, feats, timings, pred, n_matches, len(ok)) \
                or self._lost(frame, feats, timings, n_matches, len(ok))
        kept = [res for (_, res), k in zip(ok, keep) if k]
        kept_pairs = [(r, res) for (r, res), k in zip(ok, keep) if k]
        if rc.stereo_reprojection and feats.depth_noise is not None:
            pose = self._stereo_pose(pose, kept_pairs, feats, pred)
        info = sum(res.information for res in kept)
        last = self.refs[-1]
        relative = inv(last.pose) @ pose
        miss = inv(pred) @ pose  # how far the prediction was off: translation + rotation at 2 m
        self._prediction_error = float(np.linalg.norm(miss[:3, 3]) + 2.0 * rotation_angle(miss[:3, :3]))
        self._velocity = (relative, frame.index - last.features.index, frame.timestamp - last.features.timestamp)
        if self.fc.shutter_velocity == "own" and feats.row_R is not None:
            # the rolling shutter undone again with this frame's own motion (centred half a frame
            # back, the prediction's 1.5): what the later frames, the map and loop closure see
            reshutter(feats, frame.depth, self.camera, self.mc, *self._velocity[::2])
            if full is not None and full.row_R is not None:
                reshutter(full, frame.depth, self.camera, self.mc, *self._velocity[::2])
        self._n_lost = 0
        self.refs.append(_Ref(feats, pose))
        timings["fusion"] = time.perf_counter() - t1
        return TrackResult(
            index=frame.index,
            timestamp=frame.timestamp,
            pose=pose,
            lost=False,
            features=feats,
            relative=relative,
            information=info,
            n_matches=n_matches,
            n_inliers=sum(res.n_inliers for res in kept),
            weight=float(sum(res.weight for res in kept)),
            timings=timings,
            n_candidates=len(ok),
            n_fused=len(kept),
            matches=_match_segments(*kept_pairs[0], feats),
            map_features=full,
        )

    def _register_all(self, refs: list[_Ref], feats: FrameFeatures, pred: np.ndarray) -> list:
        """Registrations of ``feats`` against every reference (most recent first).

        With ``registration.guided_gate`` the newest reference is registered first (RANSAC
        pre-filter, constant-velocity T0); the older ones then use the pose it gives as T0
        and a cheap distance gate instead of RANSAC. Otherwise all are independent (and run
        in threads when ``registration.threads > 1``).
        """
        gate = self.rc.guided_gate
        if gate is not None and len(refs) > 1:
            first = self._register_newest_guided(refs[0], feats, pred)
            if first is None:
                first = self.register(refs[0].features, feats, inv(pred) @ refs[0].pose)
            if first is not None:
                P1 = refs[0].pose @ inv(first.T)
                jobs = [(r.features, feats, inv(P1) @ r.pose, gate) for r in refs[1:]]
                return [first] + self._map(jobs)
            return [first] + self._map([(r.features, feats, inv(pred) @ r.pose) for r in refs[1:]])
        return self._map([(r.features, feats, inv(pred) @ r.pose) for r in refs])

    def _register_newest_guided(self, ref: _Ref, feats: FrameFeatures, pred: np.ndarray) -> RegistrationResult | None:
        """The newest reference matched only around the prediction (``registration.predicted_gate``),
        when the last prediction was good; None = use brute force. At 30 Hz this is most frames
        and saves the Hamming matrix and RANSAC; after a jerk or at a low frame rate the previous
        prediction error is large and brute force is used (docs/frontend.md)."""
        rc = self.rc
        pg = rc.predicted_gate
        if pg is None or self._velocity is None or not self._prediction_error < 0.5 * pg:
            return None
        res = self.register(ref.features, feats, inv(pred) @ ref.pose, pg)
        if res is None or res.n_inliers < rc.predicted_min_inliers:
            return None
        self.n_newest_guided += 1
        return res

    def _stereo_pose(self, pose: np.ndarray, kept_pairs: list, feats: FrameFeatures, pred: np.ndarray) -> np.ndarray:
        """``registration.stereo_reprojection`` on a registered stereo frame: far points fix the rotation, near
        points the translation. The rotation is the refit on stereo reprojection residuals against the newest
        kept reference (:meth:`_stereo_refine`: bearings of every matched key point, with or without a
        disparity); the translation is then re-solved with that rotation held, from the kept references'
        registration inlier pairs in 3-D weighted by their stereo covariances (:meth:`_stereo_translation`),
        where a far point's long depth error weighs little and a near point's depth decides. The translation
        step runs only on an accepted rotation refit; the result is dropped (``pose`` kept) when it moves further
        from ``pose`` than the motion limits (``max_jump_*``), as the rotation refit is. Not the tighter candidate
        gates (``reject_*``): where the registration is off (the highway's few near points) the refit has to move
        further (highway seeds 0-4 0.04-0.26 m, with those gates 0.21-0.72 m; docs/stereo_measured.md)."""
        rc = self.rc
        refit = self._stereo_refine(pose, [r for r, _ in kept_pairs[:1]], feats, pred)
        if refit is pose:
            return pose
        out = self._stereo_translation(refit, kept_pairs, feats)
        d = inv(pose) @ out
        if np.linalg.norm(d[:3, 3]) > rc.max_jump_translation or \
                np.degrees(rotation_angle(d[:3, :3])) > rc.max_jump_rotation_deg:
            return pose
        return out

    def _stereo_translation(self, pose: np.ndarray, kept_pairs: list, feats: FrameFeatures) -> np.ndarray:
        """The translation of ``pose`` re-solved with its rotation held (:func:`solve_translation_mahalanobis`,
        Huber at ``noise_refit_huber``) from the inlier pairs of the kept references: current points ``C`` and
        their world partners ``W`` with their covariances from the depth noise model (``DepthNoise.covariance``:
        long along the viewing ray). Kept with at least ``min_points`` pairs agreeing; else ``pose``."""
        from rgbdslam.geometry.mahalanobis import solve_translation_mahalanobis

        rc = self.rc
        W, C, SW, SC = [], [], [], []
        for r, res in kept_pairs:
            if r.features.depth_noise is None:
                continue
            m = res.pairs
            P = r.features.pts[m[:, 0]]
            R = r.pose[:3, :3]
            W.append(transform_points(r.pose, P))
            SW.append(R @ r.features.depth_noise.covariance(P) @ R.T)
            c = feats.pts[m[:, 1]]
            C.append(c)
            SC.append(feats.depth_noise.covariance(c))
        need = max(3, rc.min_points)
        if sum(len(c) for c in C) < need:
            return pose
        C, SC, W, SW = (np.concatenate(x) for x in (C, SC, W, SW))
        out, inl = solve_translation_mahalanobis(pose, C, SC, W, SW, huber=rc.noise_refit_huber)
        return out if inl.sum() >= need else pose

    def _stereo_refine(self, pose: np.ndarray, refs: list, feats: FrameFeatures, pred: np.ndarray) -> np.ndarray:
        """``registration.stereo_reprojection``: the pose refit on stereo reprojection residuals
        (:func:`rgbdslam.geometry.stereo_pose.refine_pose_stereo`). Every key point of each reference in
        ``refs`` that has a stereo depth (any, also beyond ``matching.max_depth``) or none (then its disparity is
        below ``stereo.min_disparity``, but the scene decides where: min_disparity / 2 with a standard deviation of
        :data:`NO_DISPARITY_SIGMA` x min_disparity, i.e. its depth unknown, so it weighs only across its epipolar
        line) is matched by descriptor to every key point of this frame; a match enters when its
        pixel is within :data:`FALLBACK_GATE_PX` of the reference point projected by ``pose`` or by the
        prediction ``pred``. The measurement is the key point's (u, v) and, when it has a stereo depth, its
        disparity ``fx B / z``; pixel noise ``sigma_pixel * scale**octave`` (both key points), disparity noise
        the pair's ``sigma_d``. The refit pose is kept when at least ``min_points`` residuals pass the
        chi-square gate and it stays within the motion limits (``max_jump_*``) of ``pose``."""
        from rgbdslam.frontend.matching import match_descriptors
        from rgbdslam.geometry.stereo_pose import refine_pose_stereo, stereo_projection

        rc, dn = self.rc, feats.depth_noise
        if len(feats.depth_raw) != len(feats.uv) or len(feats.octave) != len(feats.uv):
            return pose
        intr = (dn.fx, dn.fy or dn.fx, dn.cx, dn.cy)
        W, SW, obs, has_d, s_uv = [], [], [], [], []
        for r in refs:
            rf = r.features
            if rf.depth_noise is None or len(rf.depth_raw) != len(rf.uv) or len(rf.octave) != len(rf.uv):
                continue
            ia, ib = match_descriptors(rf.desc, feats.desc, self.mc, rf.words, feats.words)
            if len(ia) < 3:
                continue
            z = rf.depth_raw[ia]
            has = z > 0
            # no disparity: below min_disparity, and where is not known (placed at min_disparity / 2 with an sd
            # of NO_DISPARITY_SIGMA x min_disparity): no weight along its epipolar line, its bearing across it
            rn = rf.depth_noise
            fb = rn.fx * rn.baseline
            d_far = max(0.5 * rn.min_disparity, fb / FAR_AWAY)
            P = self.camera.backproject(rf.uv[ia], np.where(has, z, fb / d_far))
            s_ref = rn.sigma_pixel * rf.pyramid_scale ** rf.octave[ia].astype(np.float64)
            cov = rn.covariance(P, s_ref)
            cov[~has] = rn.covariance(P[~has], s_ref[~has], NO_DISPARITY_SIGMA * rn.min_disparity)
            R = r.pose[:3, :3]
            w = transform_points(r.pose, P)
            uv = feats.uv[ib]
            near_any = np.zeros(len(ia), bool)
            for X in (pose, pred):
                zp, _, _, ahead = stereo_projection(X, w, intr, dn.baseline, jacobians=False)
                near_any |= ahead & (np.linalg.norm(zp[:, :2] - uv, axis=1) <= FALLBACK_GATE_PX)
            zc = feats.depth_raw[ib]
            k = near_any
            W.append(w[k])
            SW.append((R @ cov @ R.T)[k])
            obs.append(np.column_stack([uv, dn.fx * dn.baseline / np.where(zc > 0, zc, 1.0)])[k])
            has_d.append(((zc > 0) & has)[k])  # a reference direction predicts no disparity: (u, v) only
            s_uv.append((dn.sigma_pixel * feats.pyramid_scale ** feats.octave[ib].astype(np.float64))[k])
        need = max(3, rc.min_points)
        if not W or sum(len(w) for w in W) < need:
            return pose
        W, SW, obs, has_d, s_uv = (np.concatenate(x) for x in (W, SW, obs, has_d, s_uv))
        refined, _, inl = refine_pose_stereo(pose, W, SW, obs, has_d, s_uv, dn.sigma_disparity, intr, dn.baseline)
        d = inv(pose) @ refined
        if inl.sum() < need or np.linalg.norm(d[:3, 3]) > rc.max_jump_translation or \
                np.degrees(rotation_angle(d[:3, :3])) > rc.max_jump_rotation_deg:
            return pose
        return refined

    def _fallback(self, frame: Frame, feats: FrameFeatures, timings: dict, pred: np.ndarray, n_matches: int,
                  n_cand: int = 0) -> TrackResult | None:
        """``registration.stereo_fallback``: a stereo frame whose registration failed gets the
        constant-velocity pose ``pred`` with its rotation refit on the bearings of the descriptor
        matches of **every** key point to the newest reference (a rotation needs no depth: far points,
        even those without any disparity, fix it), then, when at least ``min_points`` near pairs agree,
        one refit with near points in 3-D and far points as bearings (:func:`refine_pose_near_far`).
        With ``registration.stereo_reprojection`` that pose is then refit on every reference's stereo reprojection
        residuals (:meth:`_stereo_refine`: the far points' disparities fix the translation the constant velocity
        guessed). Kept only within the motion limits of ``pred``. Its ``information`` is weak on translation
        (σ: a tenth of the step + 0.1 m; rotation σ 0.01 rad). None = not applicable (no velocity
        yet, RGB-D, too few matches)."""
        from rgbdslam.geometry.mahalanobis import refine_pose_near_far

        rc = self.rc
        dn = feats.depth_noise
        if not rc.stereo_fallback or dn is None or self._velocity is None or not self.refs:
            return None
        ref = self.refs[-1]
        pairs = self._bearing_pairs(ref, feats, pred)
        need = max(3, rc.min_points)
        if pairs is None or len(pairs[0]) < need:
            return None
        C, SC, W, SW, far, UV = pairs
        intr = (dn.fx, dn.fy or dn.fx, dn.cx, dn.cy)
        every = np.ones(len(C), bool)
        pose, _, inl = refine_pose_near_far(pred, C, SC, W, SW, every, UV, intr, dn.sigma_pixel,
                                            huber=rc.noise_refit_huber, rotation_only=True)
        if inl.sum() >= need and (inl & ~far).sum() >= need:
            full, _, inl2 = refine_pose_near_far(pose, C[inl], SC[inl], W[inl], SW[inl], far[inl], UV[inl], intr,
                                                 dn.sigma_pixel, huber=rc.noise_refit_huber)
            if inl2.sum() >= need:
                pose = full
        if rc.stereo_reprojection:  # the far points' disparities fix the translation the constant velocity guessed
            pose = self._stereo_refine(pose, list(reversed(self.refs)), feats, pred)
        d = inv(pred) @ pose
        if np.linalg.norm(d[:3, 3]) > rc.max_jump_translation or \
                np.degrees(rotation_angle(d[:3, :3])) > rc.max_jump_rotation_deg or inl.sum() < need:
            return None
        last = self.refs[-1]
        relative = inv(last.pose) @ pose
        s_t = 0.1 * float(np.linalg.norm(relative[:3, 3])) + 0.1
        info = np.diag([1.0 / 0.01 ** 2] * 3 + [1.0 / s_t ** 2] * 3)
        self._prediction_error = np.inf
        self._velocity = (relative, frame.index - last.features.index, frame.timestamp - last.features.timestamp)
        self._n_lost = 0
        self.n_fallback += 1
        self.refs.append(_Ref(feats, pose))
        return TrackResult(frame.index, frame.timestamp, pose, False, feats, relative, info, n_matches,
                           int(inl.sum()), 0.0, timings, n_candidates=n_cand, map_features=self._full)

    def _bearing_pairs(self, ref: _Ref, feats: FrameFeatures, pred: np.ndarray):
        """Descriptor matches of every key point of ``ref`` and ``feats`` (depth or not) whose
        reprojection under ``pred`` is within :data:`FALLBACK_GATE_PX`: (C, SC, W, SW, far, UV).
        A reference point with stereo depth (any, also beyond ``matching.max_depth``) is that 3-D
        point, one without is its viewing ray at :data:`FAR_AWAY` m (a direction: its parallax is
        nil); a pair is near (3-D) when both points are depth-valid, otherwise far (a bearing). None =
        too few matches."""
        from rgbdslam.frontend.matching import match_descriptors
        from rgbdslam.geometry.mahalanobis import bearing_residuals

        rf, dn = ref.features, feats.depth_noise
        if rf.depth_noise is None or len(rf.depth_raw) != len(rf.uv) or len(feats.depth_raw) != len(feats.uv):
            return None
        ia, ib = match_descriptors(rf.desc, feats.desc, self.mc, rf.words, feats.words)
        if len(ia) < 3:
            return None
        z = rf.depth_raw[ia]
        has = z > 0
        P = self.camera.backproject(rf.uv[ia], np.where(has, z, FAR_AWAY))
        cov_p = rf.depth_noise.covariance(np.where(has[:, None], P, [0.0, 0.0, 1.0]))
        cov_p[~has] = 0.0
        R = ref.pose[:3, :3]
        W, SW = transform_points(ref.pose, P), R @ cov_p @ R.T
        UV = feats.uv[ib]
        intr = (dn.fx, dn.fy or dn.fx, dn.cx, dn.cy)
        r, _, _ = bearing_residuals(pred, W, np.zeros_like(SW), UV, intr, dn.sigma_pixel)
        keep = np.linalg.norm(r, axis=1) <= FALLBACK_GATE_PX
        C = np.where(feats.valid[ib][:, None], feats.pts[ib], [0.0, 0.0, 1.0])
        far = ~feats.valid[ib] | ~rf.valid[ia]
        SC = dn.covariance(C)
        return C[keep], SC[keep], W[keep], SW[keep], far[keep], UV[keep]

    def _map(self, jobs: list[tuple]) -> list:
        if self._executor is not None and len(jobs) > 1:
            return list(self._executor.map(lambda a: self.register(*a), jobs))
        return [self.register(*a) for a in jobs]

    def _lost(self, frame: Frame, feats: FrameFeatures, timings: dict, n_matches: int, n_cand: int = 0) -> TrackResult:
        """A lost frame, or a restart once ``registration.max_lost`` frames in a row were lost.

        A restart keeps the last tracked pose for this frame (constant position: after a long
        loss the velocity is unknown), drops the old references and continues from here; its
        ``relative`` carries a weak information (``RESTART_INFORMATION``: σ = π rad and 5 m) so a
        pose graph can bridge it without trusting it; weaker still made iSAM2's linear systems
        indeterminate once a loop closed across the restart.
        """
        self._n_lost += 1
        self._prediction_error = np.inf  # the next prediction spans a gap: match it by brute force
        rc = self.rc
        if self.refs and rc.max_lost > 0 and self._n_lost >= rc.max_lost \
                and feats.n_valid >= max(3, rc.min_points):
            last = self.refs[-1].pose
            self.refs.clear()
            self.refs.append(_Ref(feats, last.copy()))
            self._velocity = None
            self._n_lost = 0
            return TrackResult(frame.index, frame.timestamp, last.copy(), False, feats, np.eye(4), RESTART_INFORMATION,
                               n_matches, 0, 0.0, timings, n_candidates=n_cand, reset=True,
                               map_features=self._full)
        return TrackResult(frame.index, frame.timestamp, None, True, feats, None, None, n_matches, 0, 0.0,
                           timings, n_candidates=n_cand)

    def correct_last(self, pose: np.ndarray) -> None:
        """Replace the last tracked frame's pose (e.g. by the landmark map's pose): the next frame's
        references and constant-velocity prediction continue from it."""
        if not self.refs:
            return
        last = self.refs[-1]
        last.pose = np.array(pose, dtype=np.float64)
        if len(self.refs) > 1:
            prev = self.refs[-2]
            self._velocity = _motion(prev, last)

    def move_references(self, poses: dict[int, np.ndarray]) -> None:
        """New poses ``{frame index: pose}`` for reference frames moved by a stage (``SLAM._move_keyframes``)."""
        for r in self.refs:
            P = poses.get(r.features.index)
            if P is not None:
                r.pose = np.array(P, dtype=np.float64)
        if len(self.refs) > 1 and self._velocity is not None:  # the constant-velocity model follows
            prev, last = self.refs[-2], self.refs[-1]
            self._velocity = _motion(prev, last)

    def predict_pose(self, index: int) -> np.ndarray | None:
        """Constant-velocity prediction of frame ``index``'s pose (for writing lost frames)."""
        return self._predict(index) if self.refs else None


# information of the relative pose across a restart (GTSAM order: rotation, then translation):
# σ = π rad and 5 m, i.e. "unknown" next to any registration, yet well conditioned
FALLBACK_GATE_PX = 40.0  # pixels: a match further than this from the constant-velocity prediction is wrong
# x stereo.min_disparity: the disparity sd of a key point without one in the reprojection refit (its depth unknown;
# a uniform [0, min_disparity) prior, sd min/sqrt(12), made the translations 2 % too long on the highway's skyline)
NO_DISPARITY_SIGMA = 10.0
FAR_AWAY = 1e5  # metres: a key point without disparity, as a direction (2.8 m of motion: 0.02 px at fx 718)
RESTART_INFORMATION = np.diag([1.0 / np.pi**2] * 3 + [1.0 / 25.0] * 3)


def build_frontend(cfg: Config, camera: Camera, register: PairRegistration | None = None) -> Frontend:
    """The front end from the ``registration``, ``features`` and ``matching`` sections; the pairwise
    registration (strategy ``registration.method``) from :func:`build_pair_registration` unless given."""
    register = register or build_pair_registration(cfg)
    return Frontend(cfg.registration, cfg.features, cfg.matching, camera, register,
                    cfg.landmarks.n_features if cfg.landmarks.enabled else 0)


def detection_features(fc: FeaturesConfig, map_features: int) -> FeaturesConfig:
    """The features config frames are detected with: ``fc`` itself, or with ``map_features`` key
    points when the landmark map asks for more (``landmarks.n_features``)."""
    return replace(fc, n_features=map_features) if map_features > fc.n_features else fc
