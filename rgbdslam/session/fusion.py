"""Fusion (cloud, mesh, 2-D map) of a map made over several sessions.

A joined map (``map.npz`` with more than one session) holds every session's frames relative to
its keyframes (:meth:`MapData.session_poses`): :class:`SessionsSequence` puts the sessions'
sequences one after the other behind the one ``Sequence`` interface fusion reads, the frames are
posed in the map's frame (:func:`joined_source`), and :func:`rgbdslam.mapping.fusion.fuse` does
the rest. The fused frames per session are listed in the result (``FuseResult.sessions``). Keyframes of a map
component not connected to the main one (a session that never relocalised) are left out, as
unlinked segments are in a single run. Raw depth is fused (the runs' filtered keyframe depth is
per run folder).
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np

from rgbdslam.config import Config
from rgbdslam.datasets import open_sequence
from rgbdslam.datasets.base import Frame, Sequence
from rgbdslam.datasets.config import DatasetConfig
from rgbdslam.errors import InputError
from rgbdslam.io.trajectory import Trajectory
from rgbdslam.session.mapfile import MapData, load_map


class SessionsSequence(Sequence):
    """Several sequences (one per session, same camera) read as one: frame ``offset[s] + i`` is
    frame ``i`` of session ``s``."""

    def __init__(self, sequences: list[Sequence]):
        self.parts = sequences
        self.camera = sequences[0].camera
        self.root = Path(sequences[0].root)
        self.name = "+".join(s.name for s in sequences)
        self.offsets = np.concatenate([[0], np.cumsum([len(s) for s in sequences])]).astype(int)
        self._stamps = np.concatenate([np.asarray(s.timestamps, float) for s in sequences])

    @property
    def timestamps(self) -> np.ndarray:
        return self._stamps

    def load(self, i: int) -> Frame:
        s = int(np.searchsorted(self.offsets, i, side="right")) - 1
        frame = self.parts[s].load(i - int(self.offsets[s]))
        frame.index = int(i)
        return frame


def open_sessions(data: MapData, cfg: Config | None = None) -> SessionsSequence:
    """Every session's sequence, read as it was (its own ``dataset`` settings; the rest of ``cfg``)."""
    seqs = []
    for s in data.sessions:
        try:
            dc = DatasetConfig(**(s.get("dataset") or {}))
        except TypeError as e:
            raise InputError(f"the map's session {s.get('session')} has an unreadable dataset entry ({e})") from None
        full = copy.deepcopy(cfg) if cfg is not None else Config()
        full.dataset = dc
        seqs.append(open_sequence(s["sequence"], full, purpose="map"))
    return SessionsSequence(seqs)


def joined_source(run_dir: str | Path, keyframes_only: bool, cfg: Config | None = None, data: MapData | None = None
                  ) -> tuple[SessionsSequence, Trajectory, list[int], dict[int, int]]:
    """What :func:`rgbdslam.mapping.fusion.fuse` needs to fuse every session of ``run_dir``'s
    joined map: the sessions as one sequence, every frame's map pose, the frames to fuse
    (keyframes when ``keyframes_only``) and how many of them each session gives."""
    run_dir = Path(run_dir)
    data = data or load_map(run_dir / "map.npz")
    seq = open_sessions(data, cfg)
    a = data.arrays
    main = a["kf_segment"] == 0  # the main component: sessions that never relocalised stay out
    stamps, poses, frames, per_session = [], [], [], {}
    for s, part in enumerate(seq.parts):
        sel = np.flatnonzero(a["frame_session"] == s)
        sel = sel[np.argsort(a["frame_timestamp"][sel], kind="stable")]  # the order of session_poses
        keep = main[a["frame_kf"][sel]]
        ts, P = data.session_poses(s)
        stamps.append(ts[keep])
        poses.append(P[keep])
        chosen = a["kf_frame"][(a["kf_session"] == s) & main] if keyframes_only else a["frame_index"][sel][keep]
        chosen = [int(i) for i in chosen if 0 <= i < len(part)]
        per_session[s] = len(chosen)
        frames += [int(seq.offsets[s]) + i for i in chosen]
    if not frames:
        raise InputError(f"{run_dir / 'map.npz'}: no frame of the map's main part to fuse")
    t, P = np.concatenate(stamps), np.concatenate(poses).reshape(-1, 4, 4)
    order = np.argsort(t, kind="stable")
    return seq, Trajectory(t[order], P[order]), frames, per_session
