"""Tracking against a fixed saved map (``--localize``; docs/slam.md "Saved maps").

Relocalisation (the loop closer's two-match confirmation) links the session's odometry to the
map. From then on :class:`MapTracker` registers every ``loop.map_track_every``-th frame against
the ``loop.map_track_neighbours`` map keyframes nearest the frame's *predicted* map pose (camera
centres within ``loop.map_track_distance``, viewing directions within
``loop.map_track_angle_deg``, nearest first; distance plus a quarter metre per radian of
viewing angle), with the same pair registration that verifies loops, its matching guided by the
predicted relative pose (``loop.map_track_gate``; when no guided registration agrees, one
unguided registration with the nearest keyframe). A registration is kept
when it passes the loop closer's geometry checks (``loop.min_inliers``, ``loop.max_residual``)
and puts the camera where the prediction does, within ``loop.relocalize_translation`` /
``loop.relocalize_rotation_deg`` plus the drift ratios times the travel since the last anchoring.
Each kept registration is an edge from the (fixed) map keyframe to the frame, which the SLAM
chain attaches to its last keyframe (composed with the odometry since it) unless the frame is a
keyframe anyway (``loop.map_track_keyframe_every``): the pose graph then holds the session to
the map wherever the map sees it, and odometry carries the pose between (frames with no
agreeing neighbour, parts of the scene the map does not cover).

When the map carries a landmark map (made with ``landmarks.enabled``), each tracked frame is also
posed against the map's landmarks (:meth:`MapTracker.landmark_edge`: projection matching at the
predicted map pose, RANSAC and the reprojection refine of the landmark stage); within the same
prediction gates that pose is one more edge, from the nearest map keyframe.

The prediction is the odometry pose mapped by the latest anchoring (the best edge into the map
of the last frame that had one, relocalisation included): between anchorings it drifts as
odometry does. After a tracking loss the new segment relocalises first.
"""

from __future__ import annotations

import numpy as np

from rgbdslam.geometry.se3 import inv, motion_between


class MapTracker:
    """Registers frames against the nearest keyframes of the loop closer's fixed map."""

    def __init__(self, loop, cfg, landmarks=None, lm_cfg=None, camera=None):
        self.loop = loop  # rgbdslam.loop.detector.LoopCloser with the map's keyframes first
        self.cfg = cfg  # the loop section
        # the map's landmark map (rgbdslam.landmarks.map.LandmarkMap, None: the map has none), the landmarks
        # config section and the camera: each anchored frame's pose against the saved landmarks is one more edge
        self.landmarks, self.lm_cfg, self.camera = landmarks, lm_cfg, camera
        self.rng = np.random.default_rng(0 if lm_cfg is None else lm_cfg.seed)
        n = loop.searchable if loop.searchable is not None else len(loop.keyframes)
        self.map_kfs = loop.keyframes[:n]
        poses = np.array([kf.pose for kf in self.map_kfs]).reshape(-1, 4, 4)
        self.centres = poses[:, :3, 3]
        self.axes = poses[:, :3, 2]  # viewing directions (camera z in the map)
        self.map_ids = {kf.index for kf in self.map_kfs}
        # a map's segments (pose-graph components) each have their own coordinates: neighbours
        # come from the segment of the last anchoring only
        self.segments = np.array([kf.segment for kf in self.map_kfs], np.int64)
        self.map_segment: int | None = None
        self.to_map: np.ndarray | None = None  # current segment's coordinates -> map, at the last anchoring
        self._segment = None
        self._anchor_travel = (0.0, 0.0)  # (m, deg) of the segment at the last anchoring
        self.stats = {"frames_tried": 0, "frames_anchored": 0, "registrations": 0, "edges": 0,
                      "guided": 0, "unguided": 0,
                      "rejected_geometry": 0, "rejected_prediction": 0, "no_neighbour": 0, "landmark_edges": 0}

    def predicted(self, pose: np.ndarray) -> np.ndarray | None:
        return None if self.to_map is None else self.to_map @ pose

    def neighbours(self, pred: np.ndarray, exclude: set[int], segment: int | None = None) -> list[int]:
        """Positions of the map keyframes nearest ``pred`` (see the module doc), nearest first; only
        those of map segment ``segment`` when given."""
        d = np.linalg.norm(self.centres - pred[:3, 3], axis=1)
        cosang = np.clip(self.axes @ pred[:3, 2], -1.0, 1.0)
        ang = np.arccos(cosang)
        ok = (d <= self.cfg.map_track_distance) & (np.degrees(ang) <= self.cfg.map_track_angle_deg)
        if segment is not None:
            ok &= self.segments == segment
        cand = np.flatnonzero(ok)
        cand = cand[np.argsort(d[cand] + 0.25 * ang[cand], kind="stable")]
        return [int(k) for k in cand if self.map_kfs[k].index not in exclude][: self.cfg.map_track_neighbours]

    def _register(self, kf, features, pred: np.ndarray, gate: float | None, drift_t: float, drift_r: float):
        """A LoopEdge from map keyframe ``kf`` to the frame, or None (geometry or prediction disagree);
        with ``gate`` the matching is guided by the predicted relative pose."""
        from rgbdslam.loop.detector import LoopEdge

        c = self.cfg
        self.stats["registrations"] += 1
        self.stats["guided" if gate is not None else "unguided"] += 1
        T_pred = inv(pred) @ kf.pose  # maps keyframe points into the frame, as predicted
        res = self.loop.register(kf.features, features, T_pred, gate)
        if res is None or res.n_inliers < c.min_inliers or not float(res.residual_l2) <= c.max_residual:
            self.stats["rejected_geometry"] += 1
            return None
        T_ij = inv(res.T)  # res.T maps keyframe points into the current frame
        et, er = motion_between(inv(kf.pose) @ pred, T_ij)
        if et > c.relocalize_translation + drift_t or er > c.relocalize_rotation_deg + drift_r:
            self.stats["rejected_prediction"] += 1
            return None
        return LoopEdge(kf.index, int(features.index), T_ij, np.asarray(res.information, dtype=np.float64),
                        int(res.n_inliers), float(res.residual_l2), 0, et, er)

    def landmark_edge(self, kf, features, pred: np.ndarray, drift_t: float, drift_r: float):
        """A LoopEdge from map keyframe ``kf`` to the frame from the frame's pose against the saved landmark
        map (matched by projection at the predicted map pose, RANSAC + reprojection refine, as the landmark
        stage's map pose), or None (too few inliers, no information, or too far from the prediction)."""
        from rgbdslam.landmarks.tracking import map_pose, match_to_map
        from rgbdslam.loop.detector import LoopEdge

        c, lc = self.lm_cfg, self.cfg
        m = match_to_map(self.landmarks, features, pred, self.camera, c.search_radius, c.max_hamming, c.max_depth)
        if len(m.lm) < c.min_inliers:
            return None
        res = map_pose(self.landmarks, features, m, pred, c, self.camera, self.rng)
        if res is None or res.information is None:
            return None
        et, er = motion_between(pred, res.pose)
        if et > lc.relocalize_translation + drift_t or er > lc.relocalize_rotation_deg + drift_r:
            return None
        T_ij = inv(kf.pose) @ res.pose
        return LoopEdge(kf.index, int(features.index), T_ij, res.information, int(len(res.lm)), res.rms, 0, et, er)

    def _anchor(self, edges: list, pose: np.ndarray) -> None:
        """The best map edge of this frame (most inliers) sets the prediction's offset."""
        best = max(edges, key=lambda e: e.n_inliers)
        kf = self.loop.keyframe(best.i)
        self.to_map = kf.pose @ best.T_ij @ inv(pose)
        self.map_segment = kf.segment
        self._anchor_travel = self.loop.travel(pose)

    def track(self, features, pose: np.ndarray, loops: list) -> list:
        """Edges from map keyframes to this frame (``LoopEdge``), besides the loop closer's ``loops``."""
        lc, c = self.loop, self.cfg
        pose = np.asarray(pose, dtype=np.float64)
        if lc.segment != self._segment:  # a new segment (the session's start, or after a loss)
            self._segment, self.to_map = lc.segment, None
        into_map = [e for e in loops if e.i in self.map_ids]
        if into_map:  # relocalisation or a loop: a fresh anchoring
            self._anchor(into_map, pose)
        if lc.relocalizing or self.to_map is None or c.map_track_every <= 0 or \
                int(features.index) % c.map_track_every:
            return []
        self.stats["frames_tried"] += 1
        pred = self.to_map @ pose
        cand = self.neighbours(pred, {e.i for e in into_map}, self.map_segment)
        if not cand:
            self.stats["no_neighbour"] += 1
            return []
        path, turn = lc.travel(pose)
        drift_t = abs(path - self._anchor_travel[0]) * c.drift_ratio_translation
        drift_r = abs(turn - self._anchor_travel[1]) * c.drift_ratio_rotation
        out = []
        gate = c.map_track_gate if c.map_track_gate > 0 else None
        for k in cand:
            e = self._register(self.map_kfs[k], features, pred, gate, drift_t, drift_r)
            if e is not None:
                out.append(e)
        if not out and gate is not None:  # the prediction may be off by more than the gate: unguided
            e = self._register(self.map_kfs[cand[0]], features, pred, None, drift_t, drift_r)
            if e is not None:
                out.append(e)
        if self.landmarks is not None and self.landmarks.size:
            e = self.landmark_edge(self.map_kfs[cand[0]], features, pred, drift_t, drift_r)
            if e is not None:
                out.append(e)
                self.stats["landmark_edges"] += 1
        if out:
            self.stats["frames_anchored"] += 1
            self.stats["edges"] += len(out)
            self._anchor(out, pose)
        return out
