"""The landmark map (spec §6): landmarks with descriptors in world coordinates.

Each landmark has a world position with a 3x3 covariance (smoothed by the static Kalman filter
of :mod:`rgbdslam.landmarks.kalman`), a representative ORB descriptor (the one of its first
observation), the frame it was first seen in, the last frame it was seen in, how many times it
was seen, and the keyframe that anchors it (the keyframe that created it; after a pose-graph
correction the landmark moves with that keyframe). Storage is a set of NumPy arrays indexed by
landmark id (ids are never reused; the arrays grow by doubling); culled landmarks leave the
spatial store (:mod:`rgbdslam.landmarks.store`) and are marked dead. A landmark is culled when it
was seen fewer than ``min_seen`` times ``cull_after`` frames after it was made, so a long run keeps
only landmarks that are re-observed: memory stays bounded by the scene, not the run length.
"""

from __future__ import annotations

import numpy as np

from rgbdslam.frontend.features import descriptor_words
from rgbdslam.landmarks.kalman import kalman_update
from rgbdslam.landmarks.store import make_store


class LandmarkMap:
    def __init__(self, store: str = "multi", kalman: bool = True, process_noise: float = 0.001,
                 min_seen: int = 3, cull_after: int = 30, n1: int = 3500, q: float = 5.5):
        self.kalman = kalman
        self.process_noise = process_noise
        self.min_seen = min_seen
        self.cull_after = cull_after
        self._store_args = (store, 3, n1, q)
        self.store = make_store(*self._store_args)
        self.n = 0  # ids handed out
        cap = 1024
        self.pos = np.zeros((cap, 3))
        self.cov = np.zeros((cap, 3, 3))
        self.desc = np.zeros((cap, 32), np.uint8)
        self.first = np.zeros(cap, np.int64)
        self.last = np.zeros(cap, np.int64)
        self.seen = np.zeros(cap, np.int64)
        self.anchor = np.zeros(cap, np.int64)
        self.alive = np.zeros(cap, bool)
        self.n_culled = 0

    # ------------------------------------------------------------------ storage
    def _grow(self, need: int) -> None:
        cap = len(self.pos)
        if need <= cap:
            return
        new = max(need, 2 * cap)
        for name in ("pos", "cov", "desc", "first", "last", "seen", "anchor", "alive"):
            a = getattr(self, name)
            b = np.zeros((new, *a.shape[1:]), a.dtype)
            b[:cap] = a
            setattr(self, name, b)

    @property
    def size(self) -> int:
        return int(self.alive[: self.n].sum())

    def live_ids(self) -> np.ndarray:
        return np.flatnonzero(self.alive[: self.n])

    def words(self, ids: np.ndarray) -> np.ndarray:
        return descriptor_words(self.desc[ids])

    # ------------------------------------------------------------------ updates
    def add(self, pts_world: np.ndarray, cov: np.ndarray, desc: np.ndarray, frame: int, anchor: int) -> np.ndarray:
        """New landmarks; returns their ids."""
        k = len(pts_world)
        ids = np.arange(self.n, self.n + k)
        self._grow(self.n + k)
        self.pos[ids] = pts_world
        self.cov[ids] = cov
        self.desc[ids] = desc
        self.first[ids] = frame
        self.last[ids] = frame
        self.seen[ids] = 1
        self.anchor[ids] = anchor
        self.alive[ids] = True
        self.n += k
        self.store.insert(ids, pts_world, self.seen[ids])
        return ids

    def observe(self, ids: np.ndarray, z_world: np.ndarray | None, R: np.ndarray | None, frame: int,
                count: bool = True) -> None:
        """Re-observations of landmarks ``ids`` at world points ``z_world`` with covariances ``R``
        (``z_world`` None: only counted as seen at ``frame``; ``count`` False: only the positions)."""
        if not len(ids):
            return
        if self.kalman and z_world is not None:
            x, P = kalman_update(self.pos[ids], self.cov[ids], z_world, R, self.process_noise)
            self.pos[ids] = x
            self.cov[ids] = P
        if count:
            self.last[ids] = frame
            self.seen[ids] += 1

    def end_step(self, frame: int) -> None:
        """Cull landmarks seen fewer than ``min_seen`` times ``cull_after`` frames after they were
        made, then let the store rebuild / promote (one store step per frame)."""
        live = self.live_ids()
        bad = live[(self.seen[live] < self.min_seen) & (frame - self.first[live] >= self.cull_after)]
        if len(bad):
            self.alive[bad] = False
            self.store.remove(bad)
            self.n_culled += len(bad)
        self.store.step(self.seen[: self.n] if self.n else None)

    def near(self, center: np.ndarray, radius: float, allowed: np.ndarray | None = None) -> np.ndarray:
        """Live landmark ids within ``radius`` of ``center`` (from the store), ascending; ``allowed``: a
        boolean mask over landmark ids, only those set (applied before the sort: fewer to sort)."""
        ids = self.store.query_ball(np.asarray(center, dtype=np.float64), radius)
        if allowed is not None:
            ids = ids[allowed[ids]]
        if not len(ids):
            return ids
        ids = np.sort(ids)  # ids are in one tree each: sorted is np.unique's answer without its pass
        if (ids[1:] == ids[:-1]).any():
            ids = np.unique(ids)
        return ids[self.alive[ids]]

    def move_with_anchors(self, corrections: dict[int, np.ndarray]) -> int:
        """Apply rigid corrections ``{anchor keyframe: C}`` (C = new_pose · old_pose⁻¹) to the
        landmarks they anchor (positions and covariances); the store is rebuilt. Returns how many moved."""
        live = self.live_ids()
        moved = 0
        for kf, C in corrections.items():
            ids = live[self.anchor[live] == kf]
            if not len(ids):
                continue
            R, t = C[:3, :3], C[:3, 3]
            self.pos[ids] = self.pos[ids] @ R.T + t
            self.cov[ids] = np.einsum("ij,njk,lk->nil", R, self.cov[ids], R)
            moved += len(ids)
        if moved:  # a fresh store at the new positions
            self.store = make_store(*self._store_args)
            self.store.insert(live, self.pos[live], self.seen[live])
            self.store.step(self.seen[: self.n])
        return moved
