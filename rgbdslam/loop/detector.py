"""Sharpness-gated loop closure (spec section 4, docs/slam.md).

Per tracked frame the pipeline calls ``observe`` (sharpness gate); on sharp frames it calls
``detect``: candidate keyframes come from the descriptor index (LSH by default), the most
recent ``skip_recent`` keyframes are skipped, the best ``max_candidates`` are verified with
the front end's pairwise registration, and a loop is accepted only when it is geometrically
sound (enough inliers, small residual) and agrees with the current (odometry) estimate
within a bound that grows with the distance travelled / angle turned since the keyframe
(the drift the estimate may have accumulated). Accepted loops become ``LoopEdge`` records
for the pose graph, which adds them with a robust kernel.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from rgbdslam.config import Config
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.se3 import inv, rotation_angle
from rgbdslam.loop.gate import SharpnessGate
from rgbdslam.loop.index import make_index


@dataclass
class LoopEdge:
    i: int  # frame index of the older keyframe
    j: int  # frame index of the current frame
    T_ij: np.ndarray  # 4x4 relative pose pose_i^-1 @ pose_j (camera-to-world convention)
    information: np.ndarray  # 6x6 (gtsam Pose3 tangent order: rotation first, then translation)
    n_inliers: int
    residual: float  # RMS residual of the inliers (m)
    votes: int = 0  # index votes of the keyframe
    error_translation: float = 0.0  # disagreement with the odometry estimate (m)
    error_rotation_deg: float = 0.0


@dataclass
class _Keyframe:
    index: int
    features: Any
    pose: np.ndarray
    path: float  # metres travelled (keyframe to keyframe) since the first keyframe
    turn: float  # degrees turned since the first keyframe


def motion_between(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """(translation metres, rotation degrees) of inv(A) @ B."""
    rel = inv(A) @ B
    return float(np.linalg.norm(rel[:3, 3])), float(np.degrees(rotation_angle(rel[:3, :3])))


def fallback_information(pts: np.ndarray, sigma: float) -> np.ndarray:
    """Information (rotation, translation) of a rigid fit of points ``pts`` with isotropic noise."""
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    n = max(len(pts), 1)
    spread = float(np.sqrt(((pts - pts.mean(axis=0)) ** 2).sum(axis=1).mean())) if len(pts) > 1 else 1.0
    s2 = sigma * sigma
    return np.diag([n * spread**2 / s2] * 3 + [n / s2] * 3)


class LoopCloser:
    def __init__(self, cfg: Config, camera: Camera, register=None):
        self.cfg = cfg
        self.lc = cfg.loop
        self.camera = camera
        lc = self.lc
        self.gate = SharpnessGate(lc.sharpness_factor, lc.sharpness_window, lc.sharpness_min_history)
        self.index = make_index(lc.index, lc.lsh_tables, lc.lsh_bits, lc.seed, cfg.matching.max_hamming)
        self.keyframes: list[_Keyframe] = []
        if register is None:
            from rgbdslam.frontend.odometry import register
        self._register = register
        self.query_times: list[tuple[int, float]] = []  # (keyframes in the map, seconds) per detect
        self.stats: dict[str, Any] = {
            "n_observed": 0, "n_sharp": 0, "n_queries": 0, "n_candidates": 0, "n_verified": 0,
            "n_accepted": 0, "n_rejected_geometry": 0, "n_rejected_consistency": 0,
            "time_per_query_ms": 0.0, "index_time_per_query_ms": 0.0, "map_keyframes": 0, "map_entries": 0,
        }
        self._index_time = 0.0
        self._total_time = 0.0

    # -------------------------------------------------------------- gate
    def sharpness(self, features) -> float:
        """The gate's measure of a frame (``loop.sharpness_measure``)."""
        if self.lc.sharpness_measure == "response":
            r = getattr(features, "response", None)
            if r is not None and len(r) == len(features.desc):
                return float(np.sum(r))
        return float(features.n_detected)

    def observe(self, features) -> bool:
        """Update the sharpness gate with the frame's measure (``features.n_detected`` or the
        sum of its ORB responses, see ``loop.sharpness_measure``); True when the frame is sharp."""
        sharp = self.gate(self.sharpness(features))
        self.stats["n_observed"] += 1
        self.stats["n_sharp"] += int(sharp)
        return sharp

    # -------------------------------------------------------------- map
    def add_keyframe(self, features, pose: np.ndarray) -> None:
        pose = np.array(pose, dtype=np.float64)
        if self.keyframes:
            last = self.keyframes[-1]
            dt, dr = motion_between(last.pose, pose)
            path, turn = last.path + dt, last.turn + dr
        else:
            path, turn = 0.0, 0.0
        self.index.add(len(self.keyframes), features.desc)
        self.keyframes.append(_Keyframe(int(features.index), features, pose, path, turn))
        self.stats["map_keyframes"] = len(self.keyframes)
        self.stats["map_entries"] = int(self.index.size)

    def _travel_since(self, kf: _Keyframe, pose: np.ndarray) -> tuple[float, float]:
        last = self.keyframes[-1]
        dt, dr = motion_between(last.pose, pose)
        return last.path + dt - kf.path, last.turn + dr - kf.turn

    # -------------------------------------------------------------- query
    def candidates(self, features) -> list[tuple[int, int]]:
        """[(keyframe position, votes)] of the best non-recent keyframes, most votes first."""
        n_old = len(self.keyframes) - self.lc.skip_recent
        if n_old <= 0 or len(features.desc) == 0:
            return []
        votes = self.index.votes(features.desc)[:n_old]
        ok = np.flatnonzero(votes >= self.lc.min_votes)
        ok = ok[np.argsort(-votes[ok], kind="stable")][: self.lc.max_candidates]
        return [(int(k), int(votes[k])) for k in ok]

    def verify(self, kf: _Keyframe, features, pose: np.ndarray, votes: int = 0) -> LoopEdge | None:
        """Register ``features`` against keyframe ``kf``; a LoopEdge if every check passes."""
        lc = self.lc
        self.stats["n_verified"] += 1
        res = self._register(kf.features, features, self.cfg, None)
        if res is None:
            self.stats["n_rejected_geometry"] += 1
            return None
        residual = float(getattr(res, "residual_l2", getattr(res, "residual", np.inf)))
        if res.n_inliers < lc.min_inliers or not residual <= lc.max_residual:
            self.stats["n_rejected_geometry"] += 1
            return None
        T_ij = inv(res.T)  # res.T maps keyframe points into the current frame
        T_est = inv(kf.pose) @ np.asarray(pose, dtype=np.float64)
        et, er = motion_between(T_est, T_ij)
        path, turn = self._travel_since(kf, pose)
        if et > lc.consistency_translation + lc.drift_ratio_translation * path or \
                er > lc.consistency_rotation_deg + lc.drift_ratio_rotation * turn:
            self.stats["n_rejected_consistency"] += 1
            return None
        info = getattr(res, "information", None)
        if info is None or not np.all(np.isfinite(info)):
            pairs = getattr(res, "pairs", None)
            pts = features.pts[pairs[:, 1]] if pairs is not None else features.pts[features.valid]
            info = fallback_information(pts, max(residual / np.sqrt(3.0), lc.sigma_floor))
        return LoopEdge(kf.index, int(features.index), T_ij, np.asarray(info, dtype=np.float64),
                        int(res.n_inliers), residual, votes, et, er)

    def detect(self, features, pose: np.ndarray) -> list[LoopEdge]:
        """Loop edges between earlier keyframes and the current (sharp) frame."""
        t0 = time.perf_counter()
        self.stats["n_queries"] += 1
        cands = self.candidates(features)
        t1 = time.perf_counter()
        self.stats["n_candidates"] += len(cands)
        edges: list[LoopEdge] = []
        for k, v in cands:
            e = self.verify(self.keyframes[k], features, pose, v)
            if e is not None:
                edges.append(e)
        edges.sort(key=lambda e: -e.n_inliers)
        edges = edges[: self.lc.max_loops_per_frame]
        self.stats["n_accepted"] += len(edges)
        t2 = time.perf_counter()
        self._index_time += t1 - t0
        self._total_time += t2 - t0
        q = self.stats["n_queries"]
        self.stats["time_per_query_ms"] = 1e3 * self._total_time / q
        self.stats["index_time_per_query_ms"] = 1e3 * self._index_time / q
        self.query_times.append((len(self.keyframes), t2 - t0))
        return edges
