"""The run folder (docs/formats.md): what a run writes, its summary (run.json) and its printout.

A new run into a folder first moves the finished run there to ``previous/``; the trajectories,
the keyframe pose graph and ``run.json`` are written atomically.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from rgbdslam import __version__
from rgbdslam.datasets import Sequence
from rgbdslam.errors import InputError
from rgbdslam.io.atomic import atomic_write_text
from rgbdslam.io.trajectory import Trajectory, write_tum

# what a run writes into its folder; a new run into the same folder first moves these to previous/
RUN_ARTEFACTS = ("trajectory.tum", "odometry.tum", "posegraph.g2o", "config.yaml", "run.json", "evaluation.json",
                 "plots", "map", "keyframes", "recording.rrd")


def _finished_run(run_json: Path) -> bool:
    """True when ``run_json`` records a run that ran to its end (``status`` "finished"; older
    run.json files without a status count as finished unless they say ``interrupted``)."""
    try:
        info = json.loads(run_json.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    if not isinstance(info, dict):
        return False
    return info.get("status", "interrupted" if info.get("interrupted") else "finished") == "finished"


def keep_previous_run(out_dir: Path) -> bool:
    """Move a finished earlier run's files in ``out_dir`` to ``out_dir/previous`` (replacing an
    older ``previous``), so that a new run that fails or is interrupted part-way never overwrites
    a finished one. A failed or interrupted run in ``out_dir`` is not moved: the new run replaces
    it, and ``previous/`` keeps the last finished one. True when a run was moved."""
    if not _finished_run(out_dir / "run.json"):
        return False
    prev = out_dir / "previous"
    if prev.exists():
        if not (prev.is_dir() and (prev / "run.json").is_file()):  # not ours: never delete it
            raise InputError(f"{prev} exists and is not an earlier run of rgbdslam; move it away or choose "
                             f"another --out (a new run keeps the last one there)")
        shutil.rmtree(prev)
    prev.mkdir()
    for name in RUN_ARTEFACTS:
        if (out_dir / name).exists():
            (out_dir / name).replace(prev / name)
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
        "camera_source": seq.camera_setup.source if getattr(seq, "camera_setup", None) is not None else "",
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


def write_outputs(out_dir: Path, slam, summary: dict, final: Trajectory | None) -> None:
    """Trajectories, the keyframe pose graph (posegraph.g2o) and run.json of a finished run."""
    write_trajectories(out_dir, slam.odometry(), final)
    if slam.graph is not None and slam.graph.order:
        from rgbdslam.posegraph.graph_io import write_g2o

        write_g2o(out_dir / "posegraph.g2o", slam.graph.as_graph(slam.optimised))
    if getattr(slam, "landmarks", None) is not None and slam.landmarks.map.size:  # the thesis' 2-D map
        slam.landmarks.top_view(out_dir / "map" / "landmarks_topview.png")
    write_summary(out_dir, summary)


def print_summary(s: dict[str, Any], out_dir: Path, console) -> None:
    msg = (f"{s['frames']} frames, {s['tracked']} tracked, {s['lost']} lost"
           + (f", {s['skipped']} unreadable" if s["skipped"] else "")
           + f", {len(s['keyframes'])} keyframes, {len(s['loops'])} loops; "
           f"{s['fps']:.1f} frames/s ({s['processing_fps']:.1f} without waiting for images)")
    console.print(msg)
    if s.get("restarts"):
        n, r = len(s["restarts"]), s.get("relocalized", 0)
        frames = ", ".join(str(i) for i in s["restarts"])
        console.print(f"[yellow]tracking restarted {n}× after a loss (frame {frames}); "
                      + (f"{r} of {n} new segment(s) relocalised against the map[/]" if r else
                         "not relocalised: those segments' poses are only known up to an offset[/]"))
        off = [g for g in s.get("segments", []) if not g["map"]]
        if off:
            spans = ", ".join(f"{g['first']}–{g['last']}" for g in off)
            console.print(f"[yellow]frames {spans} ({sum(g['frames'] for g in off)} tracked) are not linked to the "
                          f"map by any loop: trajectory.tum keeps them (up to an unknown offset), the map leaves "
                          f"them out[/]")
    ev = s.get("evaluation") or {}
    ate = (ev.get("ate") or {}).get("rmse")
    if ate is not None:
        console.print(f"ATE RMSE {ate:.4f} m over {ev['ate'].get('n_pairs', '?')} poses")
    console.print(f"outputs in {out_dir}")
