"""Sharpness-gated loop closure (docs/references.md §4, docs/slam.md).

Per tracked frame the pipeline calls ``observe`` (sharpness gate); on sharp frames it calls
``detect``: candidate keyframes come from the descriptor index (LSH by default), the most
recent ``skip_recent`` keyframes are skipped, the best ``max_candidates`` are verified with
the front end's pairwise registration, and a loop is accepted only when it is geometrically
sound (enough inliers, small residual) and agrees with the current (odometry) estimate
within a bound that grows with the distance travelled / angle turned since the keyframe
(the drift the estimate may have accumulated). Accepted loops become ``LoopEdge`` records
for the pose graph, which adds them with a robust kernel.

Tracking loss: when the front end restarts after too many lost frames, the pipeline calls
``new_segment``. The poses of the new segment have no known relation to the older ones, so
the loop closer *relocalises*: every frame (not only sharp ones) queries all keyframes of
earlier segments, recent ones included, and a match to another segment is accepted on its
geometry alone (there is no estimate to agree with). Geometry alone can be fooled (a repeated
texture, a twin desk), and a wrong link misplaces the whole segment, so a match links the
segments only once ``loop.relocalize_confirm`` matches from distinct frames or to distinct
keyframes, within ``loop.relocalize_window`` frames, put the camera at the same place in the
older segment; until then the matches wait and nothing enters the pose graph. The confirmed
link fixes the offset between the two segments' coordinates; later loops to that segment are
checked against it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from rgbdslam.frontend.pairwise import PairRegistration, build_pair_registration
from rgbdslam.geometry.se3 import inv, motion_between
from rgbdslam.loop.config import LoopConfig
from rgbdslam.loop.gate import SharpnessGate
from rgbdslam.loop.index import make_index

if TYPE_CHECKING:
    from rgbdslam.config import Config


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
    segment: int = 0  # tracking segment (a new one starts after each front-end restart)


class LoopCloser:
    """Loop closure from the ``loop`` section; ``register(ref_features, cur_features)`` verifies a
    candidate (the front end's :class:`~rgbdslam.frontend.pairwise.PairRegistration`);
    ``max_hamming`` (``matching.max_hamming``) bounds the brute-force index's matches."""

    def __init__(self, lc: LoopConfig, register: PairRegistration, max_hamming: int = 64):
        self.lc = lc
        self.gate = SharpnessGate(lc.sharpness_factor, lc.sharpness_window, lc.sharpness_min_history)
        self.index = make_index(lc.index, lc.lsh_tables, lc.lsh_bits, lc.seed, max_hamming)
        self.keyframes: list[_Keyframe] = []
        self._by_index: dict[int, _Keyframe] = {}  # frame index -> keyframe (loop edges name frames)
        self._register = register
        self.query_times: list[tuple[int, float]] = []  # (keyframes in the map, seconds) per detect
        self.segment = 0  # the current tracking segment
        self._segment_start = 0  # position in self.keyframes of its first keyframe
        # older segment -> (4x4 map from current-segment to that segment's coordinates, path and turn
        # of the current segment at the link, path and turn of the linked keyframe in its segment)
        self._links: dict[int, tuple[np.ndarray, float, float, float, float]] = {}
        self.relocalizing = False  # the current segment is not linked to any older one yet
        # relocalisation matches waiting for confirmation: (frame index, keyframe, edge, 4x4 map
        # from current-segment to the keyframe's segment's coordinates)
        self._pending: list[tuple[int, _Keyframe, LoopEdge, np.ndarray]] = []
        self._last_query = 0  # frame index of the last search (see due)
        self.searchable: int | None = None  # only the first this many keyframes are candidates (a fixed map)
        self.stats: dict[str, Any] = {
            "n_observed": 0, "n_sharp": 0, "n_queries": 0, "n_candidates": 0, "n_verified": 0,
            "n_accepted": 0, "n_rejected_geometry": 0, "n_rejected_consistency": 0, "n_segments": 1,
            "n_relocalized": 0, "n_relocalize_unconfirmed": 0,
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

    def due(self, index: int) -> bool:
        """True when no frame was searched in the last ``loop.query_gap`` frames (0: never)."""
        gap = self.lc.query_gap
        return gap > 0 and index - self._last_query >= gap

    def observe(self, features) -> bool:
        """Update the sharpness gate with the frame's measure (``features.n_detected`` or the
        sum of its ORB responses, see ``loop.sharpness_measure``); True when the frame is sharp."""
        sharp = self.gate(self.sharpness(features))
        self.stats["n_observed"] += 1
        self.stats["n_sharp"] += int(sharp)
        return sharp

    # -------------------------------------------------------------- map
    def new_segment(self) -> None:
        """The front end restarted after a tracking loss: keyframes added from now on belong to a
        new segment whose poses are unrelated to the earlier ones; relocalise against those."""
        if not self.keyframes:
            return
        self.segment += 1
        self._segment_start = len(self.keyframes)
        self._links = {}
        self._expire(None)
        self.relocalizing = True
        self.stats["n_segments"] = self.segment + 1

    def add_keyframe(self, features, pose: np.ndarray) -> None:
        pose = np.array(pose, dtype=np.float64)
        last = self.keyframes[-1] if self.keyframes else None
        if last is not None and last.segment == self.segment:
            dt, dr = motion_between(last.pose, pose)
            path, turn = last.path + dt, last.turn + dr
        else:  # first keyframe of a segment: distances restart
            path, turn = 0.0, 0.0
        self.index.add(len(self.keyframes), features.desc)
        self.keyframes.append(_Keyframe(int(features.index), features, pose, path, turn, self.segment))
        self._by_index[self.keyframes[-1].index] = self.keyframes[-1]
        self.stats["map_keyframes"] = len(self.keyframes)
        self.stats["map_entries"] = int(self.index.size)

    def add_map_keyframes(self, keyframes: list[tuple], desc: np.ndarray, starts: np.ndarray) -> None:
        """The keyframes of a loaded map (:mod:`rgbdslam.session`): ``(features, pose, path, turn,
        segment)`` each, with their travel and segment as saved; their descriptors are rows
        ``starts[k]:starts[k + 1]`` of ``desc``, indexed in one pass (``index.add_many``)."""
        if len(self.keyframes) != self.index.n_keyframes:
            raise RuntimeError("the descriptor index and the keyframes disagree")
        self.index.add_many(desc, starts)
        for features, pose, path, turn, segment in keyframes:
            kf = _Keyframe(int(features.index), features, np.array(pose, dtype=np.float64), float(path), float(turn),
                           int(segment))
            self.keyframes.append(kf)
            self._by_index[kf.index] = kf

    def begin_session(self, map_only: bool) -> None:
        """The keyframes so far are a loaded map, its segments older ones: the new session is a new
        segment that relocalises against them (as after a tracking loss). ``map_only``: they stay
        the only loop candidates (a fixed map: localisation)."""
        n = len(self.keyframes)
        if n:
            self.segment = max(kf.segment for kf in self.keyframes) + 1
            self._segment_start = n
            self.relocalizing = True
            self.stats.update(n_segments=self.segment + 1, map_keyframes=n, map_entries=int(self.index.size))
        if map_only:
            self.searchable = n

    def keyframe(self, index: int) -> _Keyframe:
        """The keyframe with frame index (or map id) ``index``."""
        return self._by_index[index]

    def register(self, ref_features, features, T0: np.ndarray | None = None, gate: float | None = None):
        """The pair registration that verifies loops (``T0`` and ``gate``: guided matching)."""
        return self._register(ref_features, features, T0, gate) if gate is not None else \
            self._register(ref_features, features)

    def travel(self, pose: np.ndarray) -> tuple[float, float]:
        """(metres, degrees) travelled in the current segment up to ``pose``."""
        return self._travel(pose)

    def _travel(self, pose: np.ndarray) -> tuple[float, float]:
        """(metres, degrees) travelled in the current segment up to ``pose``."""
        last = self.keyframes[-1]
        if last.segment != self.segment:
            return 0.0, 0.0
        dt, dr = motion_between(last.pose, pose)
        return last.path + dt, last.turn + dr

    def _estimate(self, kf: _Keyframe, pose: np.ndarray) -> tuple[np.ndarray, float, float] | None:
        """The current estimate of kf⁻¹·current and the travel (m, deg) it may have drifted over;
        None when ``kf`` is in an older segment not linked to the current one (no estimate)."""
        path, turn = self._travel(pose)
        if kf.segment == self.segment:
            return inv(kf.pose) @ pose, path - kf.path, turn - kf.turn
        link = self._links.get(kf.segment)
        if link is None:
            return None
        to_old, link_path, link_turn, kf_path, kf_turn = link
        # drift since the link on this side, plus the keyframe's distance from the link's keyframe on the other
        return (inv(kf.pose) @ to_old @ pose, abs(path - link_path) + abs(kf.path - kf_path),
                abs(turn - link_turn) + abs(kf.turn - kf_turn))

    # -------------------------------------------------------------- query
    def candidates(self, features) -> list[tuple[int, int]]:
        """[(keyframe position, votes)] of the best non-recent keyframes, most votes first.

        "Recent" means among the last ``skip_recent`` keyframes of the current segment: a
        keyframe before a tracking loss is never recent, the loss is what a loop bridges.
        While relocalising only the older segments' keyframes are candidates."""
        n = len(self.keyframes)
        first = self._segment_start  # position of the current segment's first keyframe
        n_old = first if self.relocalizing else max(first, n - self.lc.skip_recent)
        if self.searchable is not None:
            n_old = min(n_old, self.searchable)
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
        res = self._register(kf.features, features)
        if res is None:
            self.stats["n_rejected_geometry"] += 1
            return None
        residual = float(res.residual_l2)
        if res.n_inliers < lc.min_inliers or not residual <= lc.max_residual:
            self.stats["n_rejected_geometry"] += 1
            return None
        T_ij = inv(res.T)  # res.T maps keyframe points into the current frame
        pose = np.asarray(pose, dtype=np.float64)
        est = self._estimate(kf, pose)
        if est is None:  # relocalisation: nothing to agree with; the geometry checks above decide
            et = er = float("nan")
        else:
            T_est, path, turn = est
            et, er = motion_between(T_est, T_ij)
            if et > lc.consistency_translation + lc.drift_ratio_translation * path or \
                    er > lc.consistency_rotation_deg + lc.drift_ratio_rotation * turn:
                self.stats["n_rejected_consistency"] += 1
                return None
        return LoopEdge(kf.index, int(features.index), T_ij, np.asarray(res.information, dtype=np.float64),
                        int(res.n_inliers), residual, votes, et, er)

    def _expire(self, index: int | None) -> None:
        """Forget waiting relocalisation matches older than the window (all when ``index`` is None)."""
        keep = [] if index is None else [p for p in self._pending if index - p[0] < self.lc.relocalize_window]
        self.stats["n_relocalize_unconfirmed"] += len(self._pending) - len(keep)
        self._pending = keep

    def _confirmed(self, edges: list[LoopEdge], pose: np.ndarray, index: int) -> list[LoopEdge]:
        """The frame's matches into older segments not linked to the current one (while
        relocalising, and also later for a third segment) that enough waiting matches agree
        with (``loop.relocalize_*``); the others wait for confirmation.

        Each match says where the current frame is in the older segment (keyframe pose · T_ij);
        a waiting match from an earlier frame says it through its map between the segments
        (to_old · current pose), which the new segment's odometry carries forward."""
        lc = self.lc
        pose = np.asarray(pose, dtype=np.float64)
        new = []
        for e in edges:
            kf = self._by_index[e.i]
            if kf.segment == self.segment:
                continue
            new.append((index, kf, e, kf.pose @ e.T_ij @ inv(pose)))
        self._pending.extend(new)
        out = []
        for _, kf, e, _ in new:
            here = kf.pose @ e.T_ij  # where this match puts the camera in the older segment
            agree = 0
            for _, kf2, _, to_old2 in self._pending:
                if kf2.segment != kf.segment:
                    continue
                dt, dr = motion_between(here, to_old2 @ pose)
                agree += int(dt <= lc.relocalize_translation and dr <= lc.relocalize_rotation_deg)
            if agree >= lc.relocalize_confirm:
                out.append(e)
        return out

    def _link(self, edges: list[LoopEdge], pose: np.ndarray) -> None:
        """Record the offset to every older segment a new loop reaches for the first time."""
        for e in edges:
            kf = self._by_index[e.i]
            if kf.segment == self.segment or kf.segment in self._links:
                continue
            pose = np.asarray(pose, dtype=np.float64)
            to_old = kf.pose @ e.T_ij @ inv(pose)  # current-segment coordinates -> kf's segment's
            path, turn = self._travel(pose)
            self._links[kf.segment] = (to_old, path, turn, kf.path, kf.turn)
            if self.relocalizing:
                self.relocalizing = False
                self.stats["n_relocalized"] += 1

    def detect(self, features, pose: np.ndarray) -> list[LoopEdge]:
        """Loop edges between earlier keyframes and the current (sharp) frame."""
        t0 = time.perf_counter()
        self.stats["n_queries"] += 1
        self._last_query = int(features.index)
        cands = self.candidates(features)
        t1 = time.perf_counter()
        self.stats["n_candidates"] += len(cands)
        edges: list[LoopEdge] = []
        for k, v in cands:
            e = self.verify(self.keyframes[k], features, pose, v)
            if e is not None:
                edges.append(e)
                # most votes first: stop once enough loops are found (relocalising needs every match)
                if self.lc.stop_at_first and not self.relocalizing and len(edges) >= self.lc.max_loops_per_frame:
                    break
        # a match into an older segment that is not linked yet has only its geometry: it needs
        # confirmation, whether this segment is still relocalising or already linked to another
        self._expire(int(features.index))
        seg = [self._by_index[e.i].segment for e in edges]
        wait = [g != self.segment and g not in self._links for g in seg]
        if any(wait):
            unlinked = [e for e, w in zip(edges, wait) if w]
            edges = [e for e, w in zip(edges, wait) if not w] + self._confirmed(unlinked, pose, int(features.index))
        edges.sort(key=lambda e: -e.n_inliers)
        edges = edges[: self.lc.max_loops_per_frame]
        self.stats["n_accepted"] += len(edges)
        self._link(edges, pose)
        # matches waiting for a segment that is linked now have done their job
        self._pending = [p for p in self._pending if p[1].segment not in self._links]
        t2 = time.perf_counter()
        self._index_time += t1 - t0
        self._total_time += t2 - t0
        q = self.stats["n_queries"]
        self.stats["time_per_query_ms"] = 1e3 * self._total_time / q
        self.stats["index_time_per_query_ms"] = 1e3 * self._index_time / q
        self.query_times.append((len(self.keyframes), t2 - t0))
        return edges


def build_loop_closer(cfg: Config, register: PairRegistration | None = None) -> LoopCloser:
    """The loop closer from the ``loop`` section; candidates are verified with ``register`` (default:
    the pairwise registration of the ``matching`` and ``registration`` sections)."""
    return LoopCloser(cfg.loop, register or build_pair_registration(cfg), cfg.matching.max_hamming)
