"""A camera's rolling-shutter readout time from its own recording, without ground truth.

A rolling shutter reads the image rows one after the other; under rotation the rows read later see
the scene from a turned camera, and a yaw shears the image, which the registration takes partly for
a roll (``features.rolling_shutter``, docs/slam.md "Rolling shutter"). Its error does not average
out: the odometry's rotation drifts. Loop closures measure the same relative poses independently
of the chain of frames between them, so the readout that makes the odometry agree best with the
loop-closure edges is the estimate: for each candidate the whole pipeline runs
(:func:`rgbdslam.pipeline.run_sequence`, map fusion off), and each loop edge of ``posegraph.g2o``
is compared with the relative pose of its two keyframes in ``odometry.tum`` (before the pose
graph; matched by time stamp, within one tracking segment). The candidate with the smallest median
rotation discrepancy is the estimate; ground truth is not used (a run's ATE is reported for information only).

The residuals of consecutive frames' registrations are no criterion: neighbouring frames share
nearly the same distortion, which the registration absorbs.

The same criterion serves any other value: a config key (``key``) or keys of the camera file
``dataset.camera_file`` (``camera_keys``, e.g. ``fx,fy``: the colour focal length of 7-Scenes'
unregistered Kinect); each candidate's camera file is a copy with those keys set.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from rgbdslam.config import Config, load_config
from rgbdslam.errors import InputError
from rgbdslam.geometry.se3 import inv, rotation_angle
from rgbdslam.io.atomic import atomic_write_text
from rgbdslam.io.text import read_text
from rgbdslam.io.trajectory import read_tum
from rgbdslam.io.yamlfile import load_yaml
from rgbdslam.posegraph.graph_io import read_graph

KEY = "features.rolling_shutter"


def loop_discrepancies(run: Path, timestamps: np.ndarray | None = None) -> np.ndarray:
    """(K, 2): per loop edge of ``run``'s pose graph, the translation (m) and rotation (deg) between
    the edge's measured relative pose and the one of its keyframes in the run's odometry.

    odometry.tum has a line per tracked frame only (a lost frame has none), so a keyframe's line is
    found by its frame's time stamp (``timestamps``: the stamps of the run's frames, by default read
    from its sequence as run.json names it). An edge with an end without an odometry line, or
    whose ends lie in different tracking segments (run.json ``segments``: after a restart the
    odometry starts new coordinates), is left out."""
    from rgbdslam.mapping.fusion import match_frames
    from rgbdslam.runfolder.read import read_run

    run = Path(run)
    info, cfg, _ = read_run(run)
    if timestamps is None:
        from rgbdslam.datasets import open_sequence

        timestamps = open_sequence(info["sequence"], cfg).timestamps
    g = read_graph(run / "posegraph.g2o")
    odo = read_tum(run / "odometry.tum")
    row = match_frames(np.asarray(timestamps, dtype=np.float64), odo)
    starts = np.array(sorted(int(s["first"]) for s in info.get("segments") or []), dtype=np.int64)
    ids = [int(x) for x in g.ids]
    rank = {v: k for k, v in enumerate(sorted(ids))}
    out = []
    for k in range(g.n_edges):
        i, j = ids[g.edges_i[k]], ids[g.edges_j[k]]
        if abs(rank[i] - rank[j]) == 1:
            continue  # an odometry edge
        if not (0 <= i < len(row) and 0 <= j < len(row)) or row[i] < 0 or row[j] < 0:
            continue  # a frame without an odometry line
        if np.searchsorted(starts, i, side="right") != np.searchsorted(starts, j, side="right"):
            continue  # two tracking segments: two coordinate frames
        E = inv(inv(odo.poses[row[i]]) @ odo.poses[row[j]]) @ g.meas[k]
        out.append((np.linalg.norm(E[:3, 3]), np.degrees(rotation_angle(E[:3, :3]))))
    return np.array(out, dtype=np.float64).reshape(-1, 2)


@dataclass
class Candidate:
    value: float
    loops: int  # loop edges compared (0: the run closed no loop, nothing to judge by)
    rot_median: float = float("nan")  # degrees
    rot_rms: float = float("nan")
    trans_median: float = float("nan")  # metres
    trans_rms: float = float("nan")
    ate: float | None = None  # the run's ATE RMSE when the sequence has ground truth (not used)

    def line(self, what: str) -> str:
        if self.loops == 0:
            return f"{what} {self.value:g}: no loop closures; nothing to compare"
        return (f"{what} {self.value:g}: {self.loops} loop edges vs odometry: rotation median "
                f"{self.rot_median:.2f} deg, RMS {self.rot_rms:.2f} deg; translation median "
                f"{1e3 * self.trans_median:.1f} mm, RMS {1e3 * self.trans_rms:.1f} mm"
                + ("" if self.ate is None else f"   (ATE {self.ate:.4f} m, evaluation only)"))


def camera_variant(camera_file: str | Path, keys: list[str], value: float, work: Path) -> Path:
    """A copy of ``camera_file`` in ``work`` with each of ``keys`` set to ``value``."""
    camera_file = Path(camera_file)
    data = load_yaml(read_text(camera_file, "camera file"), str(camera_file), what="YAML (a camera file)")
    if not isinstance(data, dict):
        raise InputError(f"{camera_file} is not a camera file (a YAML mapping of fx, fy, cx, cy, ...)")
    data.update({k: value for k in keys})
    out = work / f"camera_{value:g}.yaml"
    atomic_write_text(out, yaml.safe_dump(data))
    return out


def calibrate(sequence: str | Path, values, work: Path, overrides: list[str] = (), key: str = KEY,
              camera_keys: list[str] | None = None, config: Callable[[list[str]], Config] | None = None,
              report: Callable[[Candidate], None] | None = None) -> list[Candidate]:
    """Run the sequence once per value (run folders ``work/value_V``) and measure each run's
    loop/odometry discrepancies; ``report`` is called with each candidate as it is measured.
    ``camera_keys``: the values are for these keys of the camera file ``dataset.camera_file`` (in
    ``overrides``) instead of the config key ``key``. ``config(overrides)`` makes a run's config
    (default: the defaults with the overrides; the command line passes the preset `run` picks)."""
    config = config or (lambda sets: load_config(None, sets))
    from rgbdslam.pipeline import run_sequence

    camera_file = next((s.split("=", 1)[1] for s in overrides if s.startswith("dataset.camera_file=")), None)
    if camera_keys and camera_file is None:
        raise InputError("--camera-key needs --set dataset.camera_file=FILE (the camera file to vary)")
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    out = []
    for v in values:
        v = float(v)
        sets = ([*overrides, f"dataset.camera_file={camera_variant(camera_file, camera_keys, v, work)}"]
                if camera_keys else [*overrides, f"{key}={v}"])
        cfg = config(["mapping.enabled=false", "output.plots=false", *sets])
        run = work / f"value_{v:g}"
        summary = run_sequence(sequence, run, cfg, progress=False)
        d = loop_discrepancies(run)
        c = Candidate(v, len(d), ate=((summary.get("evaluation") or {}).get("ate") or {}).get("rmse"))
        if len(d):
            c.rot_median, c.rot_rms = float(np.median(d[:, 1])), float(np.sqrt(np.mean(d[:, 1] ** 2)))
            c.trans_median, c.trans_rms = float(np.median(d[:, 0])), float(np.sqrt(np.mean(d[:, 0] ** 2)))
        if report is not None:
            report(c)
        out.append(c)
    return out


def best(candidates: list[Candidate]) -> Candidate | None:
    """The candidate with the smallest median rotation discrepancy (None when no run closed a loop)."""
    judged = [c for c in candidates if c.loops]
    return min(judged, key=lambda c: c.rot_median) if judged else None
