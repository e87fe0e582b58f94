"""Writing the run folder (docs/formats.md, docs/outputs.md): what a run writes, its summary (run.json) and its printout,
and its housekeeping.

* :func:`folder_lock`: an exclusive ``flock`` on ``FOLDER/.rgbdslam.lock`` while a run (or a
  fusion) writes into the folder. A second process gets one error line instead of mixing its
  outputs with the first one's; the kernel drops the lock when its process dies, so a killed
  run never blocks the next one.
* :func:`make_way_for_run`: a finished earlier run is moved to ``previous/``, an unfinished one
  removed, and only what the folder's manifest lists as a run's (:mod:`.manifest`): anything
  else in the way stops the run with one line naming it.
* :class:`RunRecord`: run.json says ``running`` until the run's very end, ``finished`` only then,
  ``interrupted`` or ``failed`` (with the stage) when Ctrl-C or an error stops it at any moment;
  the manifest is rewritten with it.

The trajectories, the keyframe pose graph and ``run.json`` are written atomically.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import math
import os
import shutil
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from rgbdslam import __version__
from rgbdslam.datasets import Sequence
from rgbdslam.errors import InputError
from rgbdslam.io.atomic import atomic_write_text, interrupts_deferred
from rgbdslam.io.kitti import write_kitti_poses
from rgbdslam.io.trajectory import Trajectory, write_tum
from rgbdslam.io.manifest import EXPORT, KINDS, MANIFEST, RUN, Manifest, remove_path
from rgbdslam.runfolder.read import finished_run

# what a run writes into its folder; a new run into the same folder first moves these to previous/
RUN_ARTEFACTS = ("trajectory.tum", "poses.txt", "odometry.tum", "posegraph.g2o", "config.yaml", "run.json", "evaluation.json",
                 "plots", "map", "keyframes", "recording.rrd", "map.npz", "sessions", "export")
EXPORT_DIR = "export"  # the default folder of `rgbdslam export RUN`, part of the run
PREVIOUS = "previous"
LOCK_NAME = ".rgbdslam.lock"


@contextlib.contextmanager
def folder_lock(folder: str | Path, what: str = "run") -> Iterator[None]:
    """Hold the folder's lock for the block; InputError (one line, exit 2) when another process
    holds it. ``what`` names the kind of work in the message."""
    folder = Path(folder)
    path = folder / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            if e.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            holder = os.pread(fd, 64, 0).decode("ascii", "replace").strip()
            raise InputError(f"{folder} is in use by another rgbdslam process"
                             + (f" ({holder})" if holder else "")
                             + f"; wait for it to end or choose another folder for this {what}") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}, {what}\n".encode("ascii"), 0)
        yield
    finally:
        os.close(fd)  # releases the lock; the file stays (removing it would race with a waiting process)


def _previous_is_ours(prev: Path) -> None:
    """An InputError unless ``prev`` is a folder holding nothing but what its manifest lists."""
    if not prev.is_dir() or prev.is_symlink() or not os.path.lexists(prev / MANIFEST):
        raise InputError(f"{prev} exists and is not an earlier run of rgbdslam (it has no {MANIFEST}); move it away "
                         f"or choose another --out (a new run keeps the last finished one in {PREVIOUS}/)")
    Manifest(prev).check_way(sorted(set(os.listdir(prev)) - {MANIFEST}), KINDS,
                             f"move it away or choose another --out (a new run keeps the last finished one in "
                             f"{PREVIOUS}/ and deletes an older {PREVIOUS}/ only when it holds nothing else)")


def make_way_for_run(out_dir: Path) -> bool:
    """Clear the names a run writes (:data:`RUN_ARTEFACTS`) in ``out_dir`` of an earlier run's
    outputs: a finished earlier run is moved to ``out_dir/previous`` (replacing an older
    ``previous`` made by rgbdslam), so that a new run that fails or is interrupted part-way never
    costs a finished one; an unfinished one (failed, interrupted, killed) is removed, and
    ``previous/`` keeps the last finished one. True when a run was moved.

    Only what the folder's manifest lists as a run's is moved or removed (:mod:`.manifest`):
    anything else at those names — a user's file, also inside ``map/`` or ``plots/``, a link,
    an export's folder written with ``--out`` — is an InputError naming it, before anything moves;
    so is anything in ``previous/`` its own manifest does not list. The moves are renames (no
    disk space needed) with Ctrl-C deferred; the manifest entries go along with the files they list
    (other entries, such as a batch's tables written here, stay)."""
    m = Manifest(out_dir)
    fix = "move it away or choose another --out (a new run replaces only what rgbdslam wrote there)"
    m.check_way([name for name in RUN_ARTEFACTS if name != EXPORT_DIR], [RUN], fix)
    m.check_way([EXPORT_DIR], [RUN, EXPORT], fix)  # the run's exports (`rgbdslam export RUN`) go with it
    present = [name for name in RUN_ARTEFACTS if os.path.lexists(out_dir / name)]
    if not present:
        return False
    if not finished_run(out_dir / "run.json"):
        with interrupts_deferred():  # the unfinished run is replaced: its files go, never a user's
            for name in present:
                remove_path(out_dir / name)
            m.forget(present)
        return False
    prev = out_dir / PREVIOUS
    if os.path.lexists(prev):
        _previous_is_ours(prev)
    with interrupts_deferred():  # Ctrl-C waits: never half an old run here, half in previous/
        if os.path.lexists(prev):
            shutil.rmtree(prev)
        prev.mkdir()
        if m.exists:
            os.replace(m.path, prev / MANIFEST)  # first (a rename: no disk space): previous/ says what is ours
        for name in present:
            os.replace(out_dir / name, prev / name)
        stay = {k: v for k, v in m.entries.items() if k.split("/", 1)[0] not in present}
        if stay:  # what stays here (a batch's or a sweep's tables) stays listed here, and only here
            here = Manifest(out_dir)
            here.entries, here.complete = stay, m.complete
            here.save()
            Manifest(prev).forget(stay)
    return True


def tracking_segments(tracked: list[int], restarts: list[int], loops: list[tuple[int, int]]) -> list[dict[str, Any]]:
    """The run's tracking segments and which of them share one map.

    A segment runs from the first tracked frame (or a restart after a tracking loss) to the
    frame before the next restart. Loops between two segments relate their coordinates; the
    segments connected by loops to the one with the most tracked frames form the map
    (``"map": true``). A segment outside it was never relocalised: its poses are right only up
    to an unknown offset, so fusing it would put a ghost copy of its scene into the map.
    Returns ``[{"first", "last", "frames", "map"}]`` in time order (empty without tracked frames).
    """
    tracked = sorted(int(i) for i in tracked)
    if not tracked:
        return []
    starts = sorted({tracked[0], *(int(r) for r in restarts if r > tracked[0])})
    seg_of = lambda i: int(np.searchsorted(starts, i, side="right")) - 1  # noqa: E731
    parent = list(range(len(starts)))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for i, j in loops:
        a, b = root(seg_of(i)), root(seg_of(j))
        if a != b:
            parent[max(a, b)] = min(a, b)
    counts = np.bincount([seg_of(i) for i in tracked], minlength=len(starts))
    size: dict[int, int] = {}
    for k, c in enumerate(counts):
        size[root(k)] = size.get(root(k), 0) + int(c)
    main = max(size, key=lambda r: (size[r], -r))  # most frames; ties: the earliest
    out = []
    for k, first in enumerate(starts):
        members = [i for i in tracked if seg_of(i) == k]
        out.append({"first": first, "last": members[-1] if members else first, "frames": len(members),
                    "map": root(k) == main})
    return out


def run_summary(seq: Sequence, slam, n_frames: int, wall: float, load_time: float,
                interrupted: bool) -> dict[str, Any]:
    """The contents of run.json (docs/formats.md) for a run of ``slam`` (:class:`rgbdslam.slam.SLAM`)."""
    st = slam.state
    tracked = len(st.records)
    proc = max(wall - load_time, 1e-9)
    per_stage = {k: {"median_ms": 1e3 * float(np.median(v)), "total_s": float(np.sum(v))}
                 for k, v in st.timings.items() if v}
    return {
        "version": __version__,
        "sequence": str(Path(seq.root).resolve()),
        "dataset_kind": type(seq).__name__,
        "camera": seq.camera.name,
        "camera_source": seq.camera_setup.source if seq.camera_setup is not None else "",
        "frames": n_frames,
        "tracked": tracked,
        "lost": len(st.lost),
        "skipped": len(st.skipped),
        "lost_frames": st.lost,
        "skipped_frames": st.skipped,
        "restarts": st.restarts,
        "relocalized": int(slam.loop.stats["n_relocalized"]) if slam.loop is not None else 0,
        "segments": tracking_segments([r.index for r in st.records], st.restarts, st.loops),
        # the loop closer's counters: searches, candidates, verifications, accepted and rejected loops
        "loop_closure": {k: (round(v, 3) if isinstance(v, float) else v) for k, v in slam.loop.stats.items()
                         if k not in ("isam2_failed", "batch_failed")} if slam.loop is not None else {},
        "keyframes": st.keyframes,
        "timestamps_keyframes": [r.timestamp for r in st.records if r.index == r.keyframe],
        "loops": [list(x) for x in st.loops],
        "sharp_frames": st.sharp,
        "wall_time_s": wall,
        "load_time_s": load_time,
        "fps": n_frames / wall if wall > 0 else math.nan,
        "processing_fps": n_frames / proc,
        "timings": per_stage,
        "landmarks": slam.landmarks.summary() if getattr(slam, "landmarks", None) is not None else {},
        "interrupted": interrupted,
        "status": "interrupted" if interrupted else "finished",  # "failed" when nothing could be tracked
    }


def write_summary(out_dir: Path, summary: dict[str, Any]) -> None:
    atomic_write_text(out_dir / "run.json", json.dumps(summary, indent=2))


def write_trajectories(out_dir: Path, odometry: Trajectory, final: Trajectory | None = None) -> None:
    """odometry.tum and trajectory.tum (the odometry until the pose graph is optimised)."""
    write_tum(odometry, out_dir / "odometry.tum")
    write_tum(final if final is not None else odometry, out_dir / "trajectory.tum")
    write_kitti_poses(final if final is not None else odometry, out_dir / "poses.txt")  # KITTI format, same poses


def write_outputs(out_dir: Path, slam, summary: dict, final: Trajectory | None) -> None:
    """Trajectories and the keyframe pose graph (posegraph.g2o) of a run (run.json: :class:`RunRecord`)."""
    write_trajectories(out_dir, slam.odometry(), final)
    if slam.graph is not None and slam.graph.order:
        from rgbdslam.posegraph.graph_io import write_g2o

        write_g2o(out_dir / "posegraph.g2o", slam.graph.as_graph(slam.optimised))
    if getattr(slam, "landmarks", None) is not None and slam.landmarks.map.size:  # the thesis' 2-D map
        slam.landmarks.top_view(out_dir / "map" / "landmarks_topview.png")


def summary_lines(s: dict[str, Any]) -> list[tuple[str, str]]:
    """The closing summary of a run as ``(style, text)`` lines of one sentence or clause each, short
    enough for an 80-column terminal (only a long folder name can make one longer): a window
    never breaks a sentence in the middle."""
    lines = [("", f"{s['frames']} frames: {s['tracked']} tracked, {s['lost']} lost"
                  + (f", {s['skipped']} unreadable" if s.get("skipped") else "")
                  + f"; {len(s['keyframes'])} keyframes, {len(s['loops'])} loops"),
             ("", f"speed: {s['fps']:.1f} frames/s ({s['processing_fps']:.1f} without waiting for images)")]
    if s.get("restarts"):
        n, r = len(s["restarts"]), s.get("relocalized", 0)
        lines.append(("yellow", f"tracking restarted {n}x after a loss (frame {', '.join(map(str, s['restarts']))})"))
        lines.append(("yellow", f"{r} of {n} new segment(s) relocalised against the map" if r else
                      "not relocalised: those segments' poses are known only up to an offset"))
        off = [g for g in s.get("segments", []) if not g["map"]]
        if off:
            spans = ", ".join(f"{g['first']}-{g['last']}" for g in off)
            lines.append(("yellow", f"no loop links frames {spans} to the map ({sum(g['frames'] for g in off)} "
                                    f"tracked):"))
            lines.append(("yellow", "trajectory.tum keeps them (up to an unknown offset), the map leaves them out"))
    ev = s.get("evaluation") or {}
    ate = (ev.get("ate") or {}).get("rmse")
    if ate is not None:
        lines.append(("", f"ATE RMSE {ate:.4f} m over {ev['ate'].get('n_pairs', '?')} poses"))
    return lines


def print_summary(s: dict[str, Any], out_dir: Path, console) -> None:
    from rich.text import Text

    for style, text in summary_lines(s) + [("", f"outputs in {out_dir}")]:
        console.print(Text(text, style=style), soft_wrap=True)


class RunRecord:
    """run.json as this run last wrote it: written while the run goes on with ``"status":
    "running"`` (a process killed part-way leaves that, never a claim of success), "finished" only
    at its very end; :meth:`close` turns it into "interrupted" or "failed" when the run stops on
    Ctrl-C or an error at any moment after its folder was prepared. ``stage`` names where it is."""

    def __init__(self, out_dir: Path, sequence: str):
        self.out_dir = out_dir
        self.summary: dict[str, Any] = {"version": __version__, "sequence": sequence, "frames": 0, "tracked": 0,
                                        "status": "running", "interrupted": False}
        self.stage = "start-up"
        self.owns = False  # True once an earlier finished run is out of the way (previous/)

    def start(self) -> None:
        """Claim the names a run writes in the folder's manifest (the earlier run is out of the
        way: :func:`make_way_for_run`); from now on run.json is this run's."""
        self.owns = True
        Manifest(self.out_dir).claim(RUN_ARTEFACTS, RUN)

    def write(self, summary: dict[str, Any], final: bool = False) -> None:
        """run.json, then the manifest listing every file the run has written so far (complete
        when ``final``)."""
        self.summary = summary
        self.owns = True
        if not final and summary.get("status") == "finished":
            summary = {**summary, "status": "running"}
        write_summary(self.out_dir, summary)
        Manifest(self.out_dir).record(RUN_ARTEFACTS, RUN, complete=final)

    def close(self, status: str, error: str | None = None) -> None:
        """Write run.json once more saying ``status`` (and where the run stopped); a second
        failure here (a full disk) leaves the last run.json, which never says finished."""
        s = dict(self.summary)
        if not self.owns or s.get("status") == status:
            return  # an earlier run's run.json is never touched; an interrupted run already says so
        s.update(status=status, interrupted=status == "interrupted", stopped_during=self.stage)
        if error:
            s["error"] = error
        try:
            with interrupts_deferred():
                write_summary(self.out_dir, s)
        except OSError:
            pass
        try:
            with interrupts_deferred():
                Manifest(self.out_dir).record(RUN_ARTEFACTS, RUN, complete=True)
        except (OSError, InputError):
            pass  # the claims stay: the next run into the folder still knows these files as a run's
