"""A run with a saved map (docs/slam.md "Saved maps"): localise in it, or extend it.

``--map RUN_DIR`` loads ``RUN_DIR/map.npz`` (checked: version, integrity, camera) before the new run
folder is touched. :meth:`MapSession.attach` puts the map into the SLAM chain:

* the map's keyframes go into the loop closer (features, map-frame poses, the descriptor index is
  rebuilt) as older tracking segments, and the new session starts as a new segment that
  *relocalises* against them with the loop closer's confirmation (``loop.relocalize_confirm``
  agreeing matches) — the mechanism that links segments after a tracking loss;
* the map's keyframes go into the pose graph under ids ``MAP_ID_BASE + position`` (no clash with
  the new sequence's frame numbers), with their odometry and loop edges;
* ``localize``: every map keyframe gets a tight prior (the map stays fixed), only the map's
  keyframes are loop candidates, and the new keyframes are not saved; between relocalisations
  the session's poses follow its odometry (loop edges to the map pull them at each match).
  ``extend`` (no ``--localize``): the map keyframes are free (a prior on the first keeps the
  map's frame), loops may connect old and new keyframes, and the run saves the joined map.

A session that never relocalises stays a separate segment (its own coordinates), as after a
tracking loss; run.json says so.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from rgbdslam import __version__
from rgbdslam.errors import InputError
from rgbdslam.geometry.graph import components
from rgbdslam.io.trajectory import Trajectory
from rgbdslam.session.mapfile import MAP_NAME, MapData, load_map, map_path, save_map

MAP_ID_BASE = 1 << 40  # pose-graph / loop-closer id of map keyframe k: MAP_ID_BASE + k
FIXED_SIGMA = 1e-5  # prior sigma that holds a map keyframe in place in localisation mode


def _spans(frames: list[int]) -> list[list[int]]:
    """Sorted frame numbers as [[first, last], ...] runs of consecutive numbers."""
    out: list[list[int]] = []
    for f in sorted(frames):
        if out and f == out[-1][1] + 1:
            out[-1][1] = f
        else:
            out.append([f, f])
    return out


class MapSession:
    """A saved map loaded for a new run (``localize`` or extend)."""

    def __init__(self, data: MapData, path: Path, localize: bool):
        self.data = data
        self.path = path
        self.localize = localize
        self.session = len(data.sessions)  # this run's session number
        self.load_time_s = 0.0

    # ------------------------------------------------------------------ before the run
    def attach(self, slam) -> None:
        """Put the map's keyframes into ``slam``'s loop closer and pose graph (see module doc)."""
        from rgbdslam.frontend.features import FrameFeatures
        from rgbdslam.loop.detector import LoopEdge

        if slam.loop is None:
            raise InputError("--map needs loop closure (loop.enabled: true): relocalising in a map is loop closure "
                             "against its keyframes")
        a, n = self.data.arrays, self.data.n_keyframes
        lc, graph = slam.loop, slam.graph
        kfs = []
        for k in range(n):
            f = self.data.features(k)
            kid = MAP_ID_BASE + k
            feats = FrameFeatures(index=kid, timestamp=float(a["kf_timestamp"][k]), uv=f["uv"].astype(np.float64),
                                  desc=np.ascontiguousarray(f["desc"]), pts=f["pts"].astype(np.float64),
                                  valid=f["valid"].copy(), n_detected=int(a["kf_n_detected"][k]),
                                  uv_raw=f["uv_raw"].astype(np.float64), response=f["response"].copy())
            kfs.append((feats, a["kf_pose"][k], a["kf_path"][k], a["kf_turn"][k], a["kf_segment"][k]))
            slam.map_poses[kid] = a["kf_pose"][k].copy()
            if graph is not None:
                graph.add_node(kid, a["kf_pose"][k])
        lc.add_map_keyframes(kfs, a["feat_desc"], a["kf_feature_start"])  # the index rebuilt in one pass
        lc.begin_session(map_only=self.localize)  # localising: only the map's keyframes are loop candidates
        if graph is None or not n:
            return
        if self.localize:  # a fixed map: every keyframe held where the map has it; loops keep the plain kernel
            for k in range(n):
                graph.add_prior(MAP_ID_BASE + k, a["kf_pose"][k], FIXED_SIGMA)
            if slam.cfg.loop.map_track_every > 0:  # tracked against the map between relocalisations
                from rgbdslam.session.tracking import MapTracker

                slam.map_tracker = MapTracker(lc, slam.cfg.loop, landmark_map(self.data, slam.cfg), slam.cfg.landmarks,
                                              self.data.camera)
            return
        # extending: the map's edges; loops get chain-aware kernels (slam_graph.kernel_scale) from the map's
        # covariance chains (each starts at a keyframe without an incoming odometry edge), this session's
        # from its first keyframe
        starts = set(range(n)) - {int(j) for _, j in a["odo_ij"]}
        chains = {MAP_ID_BASE + k: np.zeros((6, 6)) for k in starts}
        for (i, j), T, info in zip(a["odo_ij"], a["odo_T"], a["odo_info"]):
            graph.add_odometry(MAP_ID_BASE + int(i), MAP_ID_BASE + int(j), T, info)
            if MAP_ID_BASE + int(i) in chains:
                chains[MAP_ID_BASE + int(j)] = chains[MAP_ID_BASE + int(i)] + np.linalg.inv(info)
        for kid, cov in chains.items():
            graph.set_chain_covariance(kid, cov)
        for (i, j), T, info, nin, res in zip(a["loop_ij"], a["loop_T"], a["loop_info"], a["loop_inliers"],
                                             a["loop_residual"]):
            graph.add_loop(LoopEdge(MAP_ID_BASE + int(i), MAP_ID_BASE + int(j), T, info, int(nin), float(res)),
                           update=False)
        graph.new_chain = True

    # ------------------------------------------------------------------ after the run
    def localized(self, slam) -> tuple[dict[int, int], list[int]]:
        """({segment start: first localised frame}, frames not localised) of this session.

        A tracking segment (from the first frame or a restart) is localised from the first frame of a
        loop into the map, or into a segment localised before it; earlier frames of the segment, and
        every frame of a segment never linked, are not localised."""
        st = slam.state
        tracked = sorted(r.index for r in st.records)
        if not tracked:
            return {}, []
        starts = sorted({tracked[0], *(r for r in st.restarts if r > tracked[0])})
        seg_of = lambda i: starts[int(np.searchsorted(starts, i, side="right")) - 1]  # noqa: E731
        since: dict[int, int] = {}
        changed = True
        while changed:
            changed = False
            for i, j in sorted(st.loops, key=lambda x: min(x)):
                if i >= MAP_ID_BASE and j >= MAP_ID_BASE:
                    continue
                a, b = sorted((i, j))  # a map id is the larger: b is then this session's frame
                if max(i, j) >= MAP_ID_BASE:
                    a, b = b, a
                if a >= MAP_ID_BASE or seg_of(a) in since and since[seg_of(a)] <= a:
                    s = seg_of(b)
                    if s not in since or b < since[s]:
                        since[s] = b
                        changed = True
        out = [f for f in tracked if seg_of(f) not in since or f < since[seg_of(f)]]
        return since, out

    def finish(self, slam, summary: dict[str, Any], final: Trajectory) -> Trajectory:
        """run.json's session entry (and loops without map ids); in localisation mode the
        trajectory keeps only localised frames (run.json lists the others)."""
        since, not_loc = self.localized(slam)
        loops = [list(x) for x in slam.state.loops]
        a = self.data.arrays
        summary["loops"] = [x for x in loops if max(x) < MAP_ID_BASE]
        summary["map_loops"] = [
            {"session": int(a["kf_session"][x[0] - MAP_ID_BASE]), "map_frame": int(a["kf_frame"][x[0] - MAP_ID_BASE]),
             "frame": int(x[1])} for x in loops if x[0] >= MAP_ID_BASE and x[1] < MAP_ID_BASE]
        for g in summary.get("segments", []):
            g["localized_from"] = since.get(g["first"])
            g["map"] = g["first"] in since if since else g["map"]
        if slam.map_tracker is not None:
            summary["map_tracking"] = dict(slam.map_tracker.stats)
        summary["session"] = {
            "map": str(self.path.resolve()), "mode": "localize" if self.localize else "extend",
            "session": self.session, "map_keyframes": self.data.n_keyframes, "load_time_s": round(self.load_time_s, 4),
            "relocalized": bool(since), "first_localized_frame": min(since.values()) if since else None,
            "not_localized": _spans(not_loc),
            "not_localized_policy": ("left out of trajectory.tum (odometry.tum keeps every tracked frame in the "
                                     "session's own coordinates)") if self.localize else
            ("kept in trajectory.tum: the pose graph places them in the map's frame through odometry when their "
             "segment relocalised later; a segment never relocalised keeps its own coordinates (segments[].map false)"),
        }
        if not self.localize:
            return final
        drop = set(not_loc)
        idx = [r.index for r in slam.state.records]
        keep = np.array([i not in drop for i in idx], bool)
        return Trajectory(final.timestamps[keep], final.poses[keep])


def open_map(map_dir: str | Path, camera, out_dir: Path, localize: bool) -> MapSession:
    """Load and check ``map_dir``'s map before anything is written (one :class:`InputError` line)."""
    import time

    path = map_path(map_dir)
    if Path(out_dir).resolve() == path.parent.resolve():
        raise InputError(f"--out {out_dir} is the folder of the map given with --map; the saved run must stay "
                         f"untouched: choose another --out")
    t0 = time.perf_counter()
    data = load_map(path, camera)
    session = MapSession(data, path, localize)
    session.load_time_s = time.perf_counter() - t0
    return session


# ---------------------------------------------------------------------- saving
def _components(n: int, edges: list[tuple[int, int]]) -> np.ndarray:
    """Connected component of each of ``n`` nodes, numbered by size (0 = the largest)."""
    comp = components(n, edges)
    c = int(comp.max()) + 1 if n else 0
    sizes = np.bincount(comp, minlength=c) if n else np.zeros(0, int)
    rank = np.empty(c, np.int64)
    rank[np.argsort(-sizes, kind="stable")] = np.arange(c)
    return rank[comp].astype(np.int32)


def build_map(slam, seq, cfg, out_dir: Path, session: MapSession | None) -> MapData | None:
    """The map of a finished run: the loop closer's keyframes (the loaded map's and this session's)
    at their optimised poses, the pose graph's edges, the camera, the config and the sessions.
    None without loop closure (the keyframes' features live in the loop closer)."""
    lc, graph = slam.loop, slam.graph
    if lc is None:
        return None
    old = session.data.arrays if session is not None else None
    sid = session.session if session is not None else 0
    kfs = lc.keyframes
    pos = {kf.index: k for k, kf in enumerate(kfs)}
    opt = slam.optimised or {}
    sess, frame, stamp = [], [], []
    for kf in kfs:
        if kf.index >= MAP_ID_BASE:
            p = kf.index - MAP_ID_BASE
            sess.append(int(old["kf_session"][p]))
            frame.append(int(old["kf_frame"][p]))
            stamp.append(float(old["kf_timestamp"][p]))
        else:
            sess.append(sid)
            frame.append(int(kf.index))
            stamp.append(float(kf.features.timestamp))
    odo = [(pos[i], pos[j], T, I) for i, j, T, I in (graph.odometry if graph is not None else [])
           if i in pos and j in pos]
    loops = [e for e in (graph.loops if graph is not None else []) if e.i in pos and e.j in pos]
    seg = _components(len(kfs), [(i, j) for i, j, _, _ in odo] + [(pos[e.i], pos[e.j]) for e in loops])
    feats = [kf.features for kf in kfs]
    counts = np.array([len(f.desc) for f in feats], np.int64)
    cat = lambda get, shape, dt: (np.concatenate([np.asarray(get(f), dt).reshape(shape) for f in feats])  # noqa: E731
                                  if feats else np.zeros((0,) + shape[1:], dt))
    arrays = {
        "kf_session": np.array(sess, np.int32), "kf_frame": np.array(frame, np.int64),
        "kf_timestamp": np.array(stamp, np.float64),
        "kf_pose": np.array([opt.get(kf.index, kf.pose) for kf in kfs], np.float64).reshape(-1, 4, 4),
        "kf_segment": seg, "kf_path": np.array([kf.path for kf in kfs], np.float64),
        "kf_turn": np.array([kf.turn for kf in kfs], np.float64),
        "kf_n_detected": np.array([int(f.n_detected) for f in feats], np.int64),
        "kf_feature_start": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        "feat_uv": cat(lambda f: f.uv, (-1, 2), np.float32),
        "feat_uv_raw": cat(lambda f: f.uv_raw if len(f.uv_raw) == len(f.desc) else f.uv, (-1, 2), np.float32),
        "feat_desc": cat(lambda f: f.desc, (-1, 32), np.uint8),
        "feat_pts": cat(lambda f: f.pts, (-1, 3), np.float32),
        "feat_valid": cat(lambda f: f.valid, (-1,), bool),
        "feat_response": cat(lambda f: f.response if len(f.response) == len(f.desc) else np.zeros(len(f.desc)),
                             (-1,), np.float32),
        "odo_ij": np.array([(i, j) for i, j, _, _ in odo], np.int64).reshape(-1, 2),
        "odo_T": np.array([T for _, _, T, _ in odo], np.float64).reshape(-1, 4, 4),
        "odo_info": np.array([I for _, _, _, I in odo], np.float64).reshape(-1, 6, 6),
        "loop_ij": np.array([(pos[e.i], pos[e.j]) for e in loops], np.int64).reshape(-1, 2),
        "loop_T": np.array([e.T_ij for e in loops], np.float64).reshape(-1, 4, 4),
        "loop_info": np.array([e.information for e in loops], np.float64).reshape(-1, 6, 6),
        "loop_inliers": np.array([e.n_inliers for e in loops], np.int64),
        "loop_residual": np.array([e.residual for e in loops], np.float64),
    }
    arrays.update(_frames(slam, pos, sid, old))
    sessions = list(session.data.sessions) if session is not None else []
    sessions.append({"session": sid, "sequence": str(Path(seq.root).resolve()), "run": str(Path(out_dir).resolve()),
                     "dataset": asdict(cfg.dataset), "keyframes": int(np.sum(np.array(sess) == sid)),
                     "frames": len(slam.state.records)})
    landmarks = _landmarks(slam, pos, sid, session.data if session is not None else None, opt)
    return MapData(arrays, seq.camera, cfg.to_dict(), sessions, landmarks, f"rgbdslam {__version__}")


def _landmarks(slam, pos: dict[int, int], sid: int, old: MapData | None,
               opt: dict[int, np.ndarray]) -> dict[str, np.ndarray] | None:
    """The map's landmark section: the loaded map's landmarks (moved with their anchor keyframes'
    new poses, re-anchored to their new positions) then this session's live landmarks (already
    moved by ``LandmarkTracker.finish``); None when neither has a landmark map."""
    from rgbdslam.geometry.se3 import inv

    parts = []
    if old is not None and old.landmarks is not None:
        lm = {n: a.copy() for n, a in old.landmarks.items()}
        anchor = lm["lm_anchor"]
        for k in np.unique(anchor[anchor >= 0]):
            new_pose = opt.get(MAP_ID_BASE + int(k))
            if new_pose is None:
                continue
            C = new_pose @ inv(old.arrays["kf_pose"][k])  # how the pose graph moved that keyframe
            sel = anchor == k
            lm["lm_pos"][sel] = lm["lm_pos"][sel] @ C[:3, :3].T + C[:3, 3]
            lm["lm_cov"][sel] = np.einsum("ij,njk,lk->nil", C[:3, :3], lm["lm_cov"][sel], C[:3, :3])
        moved = np.array([pos.get(MAP_ID_BASE + k, -1) for k in range(old.n_keyframes)] + [-1], np.int64)
        lm["lm_anchor"] = moved[anchor]  # -1 stays -1 (the last entry)
        parts.append(lm)
    tracker = getattr(slam, "landmarks", None)
    if tracker is not None:
        m = tracker.map
        ids = m.live_ids()
        parts.append({"lm_pos": m.pos[ids], "lm_cov": m.cov[ids], "lm_desc": m.desc[ids],
                      "lm_session": np.full(len(ids), sid, np.int32), "lm_first": m.first[ids],
                      "lm_last": m.last[ids], "lm_seen": m.seen[ids],
                      "lm_anchor": np.array([pos.get(int(a), -1) for a in m.anchor[ids]], np.int64)})
    if not parts:
        return None
    return {n: np.concatenate([p[n] for p in parts]) for n in parts[0]}


def landmark_map(data: MapData, cfg) -> "LandmarkMap | None":  # noqa: F821
    """The map file's landmark section as a :class:`rgbdslam.landmarks.map.LandmarkMap` (the
    ``landmarks`` config section's store and filter settings; anchors are keyframe ids
    ``MAP_ID_BASE + position``, as the map's keyframes are named in the SLAM chain); None without one."""
    if data.landmarks is None:
        return None
    from rgbdslam.landmarks.map import LandmarkMap

    c, lm = cfg.landmarks, data.landmarks
    m = LandmarkMap(c.store, c.kalman, c.process_noise, c.min_seen, c.cull_after, c.store_n1, c.store_q)
    if not len(lm["lm_pos"]):
        return m
    anchor = np.where(lm["lm_anchor"] >= 0, lm["lm_anchor"] + MAP_ID_BASE, -1)
    ids = m.add(lm["lm_pos"], lm["lm_cov"], lm["lm_desc"], 0, 0)
    m.first[ids], m.last[ids], m.anchor[ids] = lm["lm_first"], lm["lm_last"], anchor
    m.seen[ids] = lm["lm_seen"]
    m.store.step(m.seen[: m.n])
    return m


def _frames(slam, pos: dict[int, int], sid: int, old: dict[str, np.ndarray] | None) -> dict[str, np.ndarray]:
    """The map's frame arrays: the loaded map's frames (re-attached to their keyframes' new
    positions) then this session's tracked frames, relative to their keyframes."""
    from rgbdslam.geometry.se3 import inv

    recs = [r for r in slam.state.records if r.keyframe in pos]
    kf_odo = {r.index: r.pose for r in slam.state.records if r.index == r.keyframe}
    new = {
        "frame_session": np.full(len(recs), sid, np.int32),
        "frame_index": np.array([r.index for r in recs], np.int64),
        "frame_timestamp": np.array([r.timestamp for r in recs], np.float64),
        "frame_kf": np.array([pos[r.keyframe] for r in recs], np.int64),
        "frame_rel": np.array([inv(kf_odo[r.keyframe]) @ r.pose for r in recs], np.float64).reshape(-1, 4, 4),
    }
    if old is None:
        return new
    moved = np.array([pos[MAP_ID_BASE + k] for k in range(len(old["kf_frame"]))], np.int64)
    prev = {name: old[name] for name in new}
    prev["frame_kf"] = moved[old["frame_kf"]]
    return {name: np.concatenate([prev[name], new[name]]) for name in new}


def write_session_trajectories(out_dir: Path, data: MapData) -> list[str]:
    """``sessions/session_<s>.tum``: every session's frames in the (joined) map's frame."""
    from rgbdslam.io.trajectory import write_tum

    names = []
    for s in sorted({int(x) for x in data.arrays["frame_session"]}):
        stamps, poses = data.session_poses(s)
        name = f"sessions/session_{s}.tum"
        write_tum(Trajectory(stamps, poses), out_dir / name)
        names.append(name)
    return names


def save_run_map(out_dir: Path, slam, seq, cfg, session: MapSession | None, summary: dict[str, Any]) -> None:
    """Save the run's map as ``out_dir/map.npz`` (not in localisation mode: the map is fixed) and
    note it in run.json's ``map_file``."""
    if session is not None and session.localize:
        summary["map_file"] = None
        return
    data = build_map(slam, seq, cfg, out_dir, session)
    if data is None:
        summary["map_file"] = None
        return
    save_map(out_dir / MAP_NAME, data)
    summary["map_file"] = {"path": MAP_NAME, "keyframes": data.n_keyframes, "sessions": len(data.sessions),
                           "landmarks": data.n_landmarks if data.landmarks is not None else None,
                           "bytes": (out_dir / MAP_NAME).stat().st_size}
    if session is not None:  # a joined map: every session's trajectory in its frame (Rerun: one colour each)
        summary["map_file"]["session_trajectories"] = write_session_trajectories(out_dir, data)
        for s in range(len(data.sessions)):
            slam.observer.log_trajectory(f"session_{s}", Trajectory(*data.session_poses(s)))
