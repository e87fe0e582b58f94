"""The landmark stage of the per-frame chain: track against the map, update it, grow it at keyframes.

``LandmarkTracker`` implements the chain's stage protocol (:class:`rgbdslam.slam.Stage`):
``on_tracked`` takes the registration's pose, which predicts where the landmarks project, and
returns the map pose fused with it (nothing when the map cannot place the frame); the matched
landmarks are then re-observed (static Kalman update). ``on_loops`` re-measures loop edges against
the map and drops those the map already holds. ``on_frame`` makes new landmarks at a keyframe from
its depth-valid features that matched no landmark, and culls.
``on_finish`` moves the landmarks with their anchor keyframes after the pose graph; ``summary``
goes to run.json.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import inv, rotation_angle
from rgbdslam.landmarks.config import LandmarksConfig
from rgbdslam.landmarks.kalman import observation_covariance
from rgbdslam.landmarks.map import LandmarkMap
from rgbdslam.frontend.features import map_valid
from rgbdslam.landmarks.tracking import map_pose, match_to_map


@dataclass
class LandmarkStats:
    frames: int = 0
    map_poses: int = 0  # frames placed by the map
    rejected: int = 0  # map poses too far from the registration's
    ransac: int = 0  # map poses (and loop re-measures) that needed RANSAC: too few inliers at the prediction
    stale_left_out: int = 0  # matches to stale landmarks left out of the map pose (stale_after)
    loops_held: int = 0  # loop edges not added: the map pose already rests on the older frame's landmarks
    stale_joined: int = 0  # frames whose stale matches agreed with the current ones and joined (stale_check)
    loops_refined: int = 0  # loop_refine: loop edges re-measured against the older end's landmarks
    loops_kept: int = 0  # loop_refine: loop edges left as the registration gave them (too few landmarks)
    loop_refine_moves: list[float] = field(default_factory=list)  # how far each re-measured edge moved (m)
    inliers: list[int] = field(default_factory=list)
    matched: int = 0
    matched_old: int = 0  # inliers first seen >= old_age frames earlier


def _close(A: np.ndarray, B: np.ndarray, metres: float, degrees: float) -> bool:
    d = inv(A) @ B
    return bool(np.linalg.norm(d[:3, 3]) <= metres and np.degrees(rotation_angle(d[:3, :3])) <= degrees)


def _disagreement(P1: np.ndarray, H1: np.ndarray, P2: np.ndarray, H2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The disagreement η = Log(P1⁻¹ P2) of two pose estimates with informations H1, H2 (right
    perturbations, (rotation, translation) order) and its covariance C = H1⁻¹ + H2⁻¹."""
    import gtsam

    return gtsam.Pose3.Logmap(gtsam.Pose3(inv(P1) @ P2)), np.linalg.inv(H1) + np.linalg.inv(H2)


def pose_chi2(P1: np.ndarray, H1: np.ndarray, P2: np.ndarray, H2: np.ndarray) -> float:
    """Mahalanobis² of the two pose estimates' disagreement: ηᵀ C⁻¹ η (χ², 6 dof; :func:`_disagreement`)."""
    eta, C = _disagreement(P1, H1, P2, H2)
    return float(eta @ np.linalg.solve(C, eta))


def fuse_poses(P1: np.ndarray, H1: np.ndarray, P2: np.ndarray, H2: np.ndarray) -> np.ndarray:
    """Information-weighted mean of two poses (right perturbations, (rotation, translation) order):
    P1 · Exp((H1 + H2)⁻¹ H2 · Log(P1⁻¹ P2)) — one Gauss–Newton step, exact when the two agree closely."""
    import gtsam

    eta = gtsam.Pose3.Logmap(gtsam.Pose3(inv(P1) @ P2))
    step = np.linalg.solve(H1 + H2, H2 @ eta)
    return P1 @ gtsam.Pose3.Expmap(step).matrix()


def map_features(result):
    """The key points the landmark map works with: every one detected (``landmarks.n_features``) or the frame's."""
    return result.features if result.map_features is None else result.map_features


class LandmarkTracker:
    """The landmark map as a stage of the per-frame chain (the protocol of :class:`rgbdslam.slam.Stage`:
    ``on_tracked``, ``on_loops``, ``on_frame``, ``on_finish``); ``observer``: where :meth:`log` sends the
    map every ``log_every``-th frame (None: nowhere)."""

    name = "landmarks"  # the timing key of its steps (run.json)

    def __init__(self, cfg: LandmarksConfig, camera: Camera, observer=None, log_every: int = 1):
        self.cfg = cfg
        self.camera = camera
        self.observer = observer
        self.log_every = max(1, log_every)
        self.map = LandmarkMap(cfg.store, cfg.kalman, cfg.process_noise, cfg.min_seen, cfg.cull_after,
                               cfg.store_n1, cfg.store_q)
        self.rng = np.random.default_rng(cfg.seed)
        self.stats = LandmarkStats()
        self.kf_pose: dict[int, np.ndarray] = {}  # keyframe poses as the map saw them (anchors)
        self.kf_obs: dict[int, np.ndarray] = {}  # every keyframe's observed landmark ids (the covisibility graph)
        self._seen_by: dict[int, list[int]] = {}  # landmark id -> the keyframes observing it (once per observation)
        self._newest: int | None = None  # the newest keyframe in kf_obs
        self._local: np.ndarray | None = None  # the local map's landmark mask for the newest keyframe (local_map_shared)
        self._last: tuple[int, np.ndarray, np.ndarray] | None = None  # (frame, inlier feats, inlier ids)
        self._last_matches = None  # this frame's descriptor matches to the map (MapMatch)
        self._cov: np.ndarray | None = None  # mode 'filter': 6x6 covariance of the last output pose

    # ---------------------------------------------------------------- the stage protocol
    def on_tracked(self, frame, result, pose: np.ndarray) -> dict[int, np.ndarray]:
        """After the front end: the frame's map pose (fused with the registration's ``pose``) as a
        correction ``{frame: pose}``; empty when the map cannot place the frame or tracking restarted."""
        if result.reset:  # nothing of the last tracked frame may reach this one's keyframe (add_keyframe)
            self._last = self._last_matches = None
            return {}
        info = result.information
        if info is not None and result.n_fused > 1:  # the references share this frame's noise:
            info = info / result.n_fused  # their summed information counts it n_fused times
        mpose = self.track(frame.index, map_features(result), pose, info)
        return {} if mpose is pose else {frame.index: mpose}

    def on_loops(self, frame, result, loops: list) -> list:
        """The loop closer's edges to this frame re-measured against the map (``loop_refine``; not on a
        restart), less those the map already holds (``map_loop_landmarks``)."""
        c = self.cfg
        if loops and c.loop_refine and not result.reset:
            loops = [self.refine_loop(frame.index, map_features(result), e) for e in loops]
        if loops and c.map_loop_landmarks > 0:
            loops = [e for e in loops if not self.holds(frame.index, e.i)]
        return loops

    def on_frame(self, frame, result, pose: np.ndarray, keyframe: bool) -> dict[int, np.ndarray]:
        """The end of the frame's map step at its pose: on a keyframe new landmarks; culling; Rerun.
        No corrections (an empty dict: the map moves no pose here)."""
        feats = map_features(result)
        if keyframe:
            self.add_keyframe(frame.index, feats, pose)
        self.end_frame(frame.index)
        if self.observer is not None and frame.index % self.log_every == 0:
            self.log(self.observer, frame.index, feats)
        return {}

    def on_finish(self, optimised: dict[int, np.ndarray]) -> None:
        """After the final pose graph: the landmarks move with their anchor keyframes (:meth:`finish`)."""
        self.finish(optimised)

    # ---------------------------------------------------------------- the map step
    def _observe(self, feats, idx: np.ndarray, ids: np.ndarray, pose: np.ndarray, frame: int) -> None:
        """Kalman update of landmarks ``ids`` from frame features ``idx`` seen from ``pose`` (counted as seen at ``frame``)."""
        P = feats.pts[idx]
        zw = P @ pose[:3, :3].T + pose[:3, 3]
        R = observation_covariance(P, pose[:3, :3], self.camera.fx, self.cfg.sigma_px, self.cfg.depth_noise_a,
                                   self.cfg.depth_noise_b)
        self.map.observe(ids, zw, R, frame)

    def track(self, index: int, feats, pose: np.ndarray, information: np.ndarray | None = None) -> np.ndarray:
        """The map pose of frame ``index`` given the registration's ``pose`` (returned unchanged if
        the map cannot place the frame); re-observes the matched landmarks."""
        c = self.cfg
        self.stats.frames += 1
        self._last = None
        self._last_matches = None
        if self.map.size == 0:
            return pose
        m = match_to_map(self.map, feats, pose, self.camera, c.search_radius, c.max_hamming, c.max_depth,
                         allowed=self.local_map())
        res, tried = None, False
        if c.stale_after > 0:
            m, res, tried = self._without_stale(index, feats, m, pose)
        self._last_matches = m
        if not tried and len(m.lm) >= c.min_inliers:  # not when the stale check's try on these matches failed
            res = self._estimate(feats, m, pose)
        if res is not None and not _close(pose, res.pose, c.max_correction, c.max_correction_deg):
            self.stats.rejected += 1  # a map pose far from the registration's is a wrong map match
            res = None
        # the registration's pose as a prediction: its information (mode 'filter': its covariance is
        # the last output's plus this step's; the covariances are only needed there)
        filt = c.mode == "filter"
        H_pred = None if information is None else information * c.fuse_scale
        if H_pred is not None and filt and self._cov is not None:
            H_pred = np.linalg.inv(np.linalg.inv(H_pred) + self._cov)
        if res is None or res.information is None or H_pred is None:
            self._cov = np.linalg.inv(H_pred) if filt and res is None and H_pred is not None else None
            return pose if res is None else self._accept(index, feats, res)
        if c.mode in ("fuse", "filter"):
            res.pose = fuse_poses(pose, H_pred, res.pose, res.information)
            self._cov = np.linalg.inv(H_pred + res.information) if filt else None
        return self._accept(index, feats, res)

    def observe(self, index: int, ids: np.ndarray) -> None:
        """Record the landmark ids keyframe ``index`` observes (the covisibility graph, :meth:`local_map`)."""
        for i in self.kf_obs.get(index, np.zeros(0, np.int64)).tolist():  # observed again: replaces the old ids
            self._seen_by[i].remove(index)
        ids = np.array(ids, dtype=np.int64)
        self.kf_obs[index] = ids
        for i in ids.tolist():
            self._seen_by.setdefault(i, []).append(index)
        self._newest = index if self._newest is None else max(self._newest, index)
        self._local = None

    def local_map(self) -> np.ndarray | None:
        """The covisibility local map (``local_map_shared`` > 0; else None: every landmark): a mask over
        landmark ids of those observed by the newest keyframe (the frame's reference) and by every keyframe
        sharing at least ``local_map_shared`` landmarks with it — the edge weights of ORB-SLAM's covisibility
        graph. Computed once per keyframe, from the keyframes observing the reference's landmarks only
        (not every keyframe: a long run has thousands)."""
        c = self.cfg
        if c.local_map_shared <= 0 or not self.kf_obs:
            return None
        if self._local is None or len(self._local) < self.map.n:
            ref = self.kf_obs[self._newest]
            local = np.zeros(self.map.n, bool)
            local[ref] = True
            # shared landmarks per keyframe: each observation of one of the reference's landmarks counts
            kfs = [k for i in np.unique(ref).tolist() for k in self._seen_by.get(i, ())]
            kf, shared = np.unique(np.array(kfs, dtype=np.int64), return_counts=True)
            for k in kf[shared >= c.local_map_shared].tolist():
                local[self.kf_obs[k]] = True
            self._local = local
        return self._local

    def _estimate(self, feats, m, pose: np.ndarray, seeded: bool = False):
        """The map pose from the matches ``m``, predicted by ``pose`` (the registration's, or another
        estimate of the frame's pose); None if it fails. The refine starts from ``pose``'s inliers; RANSAC
        runs only when they are too few (and never with ``seeded``): a map pose further than
        ``max_correction`` from the registration's is rejected anyway, so a hypothesis far from it could
        not be kept, and near it the prediction's inliers are RANSAC's best hypothesis's. A loop re-measure
        (:meth:`refine_loop`, gate ``revisit_max_correction``) takes the same path: a seeded fit with at least
        ``min_inliers`` but fewer than ``loop_min_inliers`` inliers keeps the edge as it was."""
        res = map_pose(self.map, feats, m, pose, self.cfg, self.camera, self.rng, seeded=True)
        if res is None and not seeded:
            self.stats.ransac += 1
            res = map_pose(self.map, feats, m, pose, self.cfg, self.camera, self.rng)
        return res

    def _without_stale(self, index: int, feats, m, pose: np.ndarray):
        """The matches with the *stale* landmarks (not seen for more than ``stale_after`` frames: an
        earlier visit of the place) left out unless they agree with the rest. Between the visits the
        map is not corrected (the pose graph moves the landmarks at the end of the run), so the first
        visit's landmarks and the ones made since carry different drift; one pose fitted to both is a
        compromise that jumps from frame to frame with their mix. With ``stale_check`` the pose from the
        stale matches alone is compared with the pose from the current ones: when it is within the χ²
        gate ``stale_gate`` of their joint covariance the stale landmarks join (the two agree: no drift
        between the visits to speak of); with too few current or stale matches to compare they stay out.
        Returns (matches, the pose from the current matches or None, whether that pose was tried: a
        failed try is not repeated); the candidates of a left-out landmark no longer keep new landmarks
        from being made there."""
        c = self.cfg
        stale = index - self.map.last[m.lm] > c.stale_after
        if not stale.any():
            return m, None, False
        cand_ok = None if m.cand_ids is None else index - self.map.last[m.cand_ids] <= c.stale_after
        cur = m.subset(~stale, cand_ok)
        res_cur = self._estimate(feats, cur, pose) if len(cur.lm) >= c.min_inliers else None
        # the stale matches' own pose, for the comparison only: without a current pose (or its
        # information) there is nothing to compare it with, so it is not estimated; else it starts from
        # the current pose's inliers among them, no RANSAC (when the two agree — the only case that joins —
        # the current pose's 3-D gate holds the stale inliers; when they are further apart than the
        # gate it finds too few and the stale matches stay out, as the χ² gate would have it)
        if c.stale_check and stale.sum() >= c.min_inliers and res_cur is not None and res_cur.information is not None:
            res_old = self._estimate(feats, m.subset(stale), res_cur.pose, seeded=True)
            if res_old is not None and res_old.information is not None:
                chi2 = pose_chi2(res_cur.pose, res_cur.information, res_old.pose, res_old.information)
                if chi2 <= c.stale_gate:
                    self.stats.stale_joined += 1
                    return m, None, False
        self.stats.stale_left_out += int(stale.sum())
        return cur, res_cur, len(cur.lm) >= c.min_inliers

    def _accept(self, index: int, feats, res) -> np.ndarray:
        """The frame is placed by the map: statistics, and its matches re-observe their landmarks."""
        c = self.cfg
        self.stats.map_poses += 1
        self.stats.inliers.append(len(res.lm))
        self.stats.matched += len(res.lm)
        self.stats.matched_old += int((index - self.map.first[res.lm] >= c.old_age).sum())
        self._last = (index, res.feat, res.lm)
        self._observe(feats, res.feat, res.lm, res.pose, index)
        return res.pose

    def holds(self, index: int, older: int) -> bool:
        """Whether frame ``index``'s map pose rests on at least ``map_loop_landmarks`` landmarks that
        already existed at frame ``older`` (first seen at or before it): the map itself ties the two
        frames together — through landmarks Kalman-averaged over many frames, more precisely than a loop
        edge's one registration — so a loop edge ``older`` -> ``index`` would only add that
        registration's error (docs/landmarks.md "What each step does"). Never when ``older`` is not a keyframe of
        this map (a saved map's keyframe, docs/slam.md "Saved maps and sessions"): its landmarks are not
        in this map, and frame numbers of another session say nothing about them."""
        c = self.cfg
        if c.map_loop_landmarks <= 0 or self._last is None or self._last[0] != index or int(older) not in self.kf_pose:
            return False
        held = int((self.map.first[self._last[2]] <= older).sum()) >= c.map_loop_landmarks
        self.stats.loops_held += int(held)
        return held

    def refine_loop(self, index: int, feats, edge):
        """Loop edge ``edge`` (keyframe i -> this frame ``index``) re-measured against the map
        (``loop_refine``): the landmarks first seen within ``loop_window`` frames of i — made and averaged
        from poses next to i, so in i's coordinates — are projected with the edge's pose kf_pose[i] · T_ij,
        matched within ``loop_search_radius`` px, and the frame's pose against them (a map pose: refitted
        from the edge's inliers, RANSAC only when fewer than ``min_inliers`` agree; reprojection refine)
        gives T_ij = kf_pose[i]⁻¹ · P and the refine's information. The edge as it
        was when i is not a keyframe of the map, fewer than ``loop_min_inliers`` agree, or the pose is further
        than ``revisit_max_correction`` / ``_deg`` from the edge's."""
        from dataclasses import replace

        c = self.cfg
        if int(edge.i) not in self.kf_pose or self.map.size == 0:
            return edge
        A = self.kf_pose[int(edge.i)]
        P0 = A @ edge.T_ij
        m = match_to_map(self.map, feats, P0, self.camera, c.loop_search_radius, c.max_hamming, c.max_depth,
                         first_before=int(edge.i) + c.loop_window + 1, first_after=int(edge.i) - c.loop_window)
        res = self._estimate(feats, m, P0) if len(m.lm) >= c.loop_min_inliers else None
        if res is None or res.information is None or len(res.lm) < c.loop_min_inliers or \
                not _close(P0, res.pose, c.revisit_max_correction, c.revisit_max_correction_deg):
            self.stats.loops_kept += 1
            return edge
        self.stats.loops_refined += 1
        self.stats.loop_refine_moves.append(float(np.linalg.norm((inv(P0) @ res.pose)[:3, 3])))
        return replace(edge, T_ij=inv(A) @ res.pose, information=res.information, n_inliers=int(len(res.lm)))

    def end_frame(self, index: int) -> None:
        """The end of frame ``index``'s map step: culling."""
        self.map.end_step(index)

    def add_keyframe(self, index: int, feats, pose: np.ndarray) -> None:
        """New landmarks from the keyframe's unmatched depth-valid features; the keyframe observes its
        tracking inliers and the new landmarks (the covisibility graph, :meth:`observe`)."""
        c = self.cfg
        matched_feat = np.zeros(len(feats.valid), bool)
        lm_ids = np.zeros(0, np.int64)
        if self._last is not None and self._last[0] == index:
            lm_ids = self._last[2]
            matched_feat[self._last[1]] = True
        m = self._last_matches
        if m is not None and len(m.feat):  # every descriptor match (inlier or not) keeps its feature out
            matched_feat[m.feat] = True
        new = np.flatnonzero(map_valid(feats) & ~matched_feat & (np.nan_to_num(feats.pts[:, 2]) < c.max_depth))
        if len(new) and m is not None and m.cand_uv is not None and len(m.cand_uv) and c.new_min_distance > 0:
            # where a landmark already projects, no second one is made (it would compete with the old one)
            from scipy.spatial import cKDTree  # here: SciPy's import is not on the way to the first frame

            d, _ = cKDTree(m.cand_uv).query(feats.uv[new], k=1, distance_upper_bound=c.new_min_distance)
            new = new[~np.isfinite(d)]
        if len(new):
            P = feats.pts[new]
            zw = P @ pose[:3, :3].T + pose[:3, 3]
            R = observation_covariance(P, pose[:3, :3], self.camera.fx, c.sigma_px, c.depth_noise_a, c.depth_noise_b)
            lm_ids = np.concatenate([lm_ids, self.map.add(zw, R, feats.desc[new], index, index)])
        self.kf_pose[index] = pose.copy()
        self.observe(index, lm_ids)
        self._last_matches = None

    def log(self, observer, index: int, feats) -> None:
        """Send the map to a Rerun observer (landmarks by age, this frame's map matches)."""
        ids = self.map.live_ids()
        uv = feats.uv_raw[self._last[1]] if self._last is not None and len(feats.uv_raw) else None
        observer.log_landmarks(index, self.map.pos[ids], index - self.map.first[ids], uv)

    def top_view(self, path, title: str = "landmarks (top view)") -> None:
        """The thesis' 2-D map: landmarks seen from above (x-y of the world), coloured by times seen."""
        from rgbdslam.landmarks.topview import plot_top_view

        ids = self.map.live_ids()
        plot_top_view(path, self.map.pos[ids], self.map.seen[ids], list(self.kf_pose.values()), title)

    def finish(self, optimised: dict[int, np.ndarray] | None) -> int:
        """Move landmarks with their anchor keyframes' pose-graph corrections. Returns how many moved."""
        if not optimised:
            return 0
        corr = {k: optimised[k] @ inv(P) for k, P in self.kf_pose.items() if k in optimised}
        return self.map.move_with_anchors(corr)

    def summary(self) -> dict:
        s = self.stats
        return {
            "size": self.map.size, "made": int(self.map.n), "culled": int(self.map.n_culled),
            "frames": s.frames, "map_poses": s.map_poses, "rejected": s.rejected, "ransac": s.ransac,
            "stale_left_out": s.stale_left_out, "stale_joined": s.stale_joined, "loops_held": s.loops_held,
            "loops_refined": s.loops_refined, "loops_kept": s.loops_kept,
            "loop_refine_median_m": round(float(np.median(s.loop_refine_moves)), 4) if s.loop_refine_moves else 0.0,
            "median_inliers": float(np.median(s.inliers)) if s.inliers else 0.0,
            "old_share": round(s.matched_old / s.matched, 4) if s.matched else 0.0,
            "old_age": self.cfg.old_age, "store": self.cfg.store, "store_trees": self.map.store.trees(),
        }
