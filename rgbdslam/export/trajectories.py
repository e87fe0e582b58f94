"""Trajectory exports: TUM, KITTI, EuRoC CSV and evo's result zip.

All poses are the run's final camera-to-world poses (``trajectory.tum``), every tracked frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rgbdslam.errors import InputError
from rgbdslam.geometry.se3 import pose_to_tum
from rgbdslam.io.atomic import atomic_path, atomic_write_text
from rgbdslam.io.kitti import write_kitti_poses
from rgbdslam.io.trajectory import Trajectory, write_tum


def write_tum_export(run, out: Path) -> list[Path]:
    write_tum(run.trajectory, out / "trajectory.tum")
    return [out / "trajectory.tum"]


def write_kitti_export(run, out: Path) -> list[Path]:
    """``poses.txt``: one row-major 3x4 camera-to-world matrix per tracked frame; ``times.txt``:
    its time stamp (s), line for line (KITTI's odometry layout; evo reads poses.txt with
    ``evo_traj kitti``)."""
    traj: Trajectory = run.trajectory
    write_kitti_poses(traj, out / "poses.txt")
    atomic_write_text(out / "times.txt", "".join(f"{t:.6f}\n" for t in traj.timestamps))
    return [out / "poses.txt", out / "times.txt"]


def format_euroc(traj: Trajectory) -> str:
    """EuRoC MAV ground-truth CSV: time stamp in ns, position (m), quaternion w x y z."""
    t, q = pose_to_tum(traj.poses)
    lines = ["#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"]
    ns = np.round(traj.timestamps * 1e9).astype(np.int64)
    for s, p, r in zip(ns, t, q):
        lines.append(f"{s},{p[0]:.9f},{p[1]:.9f},{p[2]:.9f},{r[3]:.9f},{r[0]:.9f},{r[1]:.9f},{r[2]:.9f}")
    return "\n".join(lines) + "\n"


def write_euroc_export(run, out: Path) -> list[Path]:
    atomic_write_text(out / "trajectory.csv", format_euroc(run.trajectory))
    return [out / "trajectory.csv"]


def _evo():
    try:
        import evo  # noqa: F401
    except ImportError:
        raise InputError("the evo export needs evo (pip install evo, or the project's test extra: "
                         "pip install '.[test]')") from None


def check_evo(run) -> None:
    _evo()
    if run.groundtruth() is None:
        raise InputError(f"the evo export needs ground truth, and the run's sequence {run.info['sequence']} has "
                         f"none (groundtruth.txt)")


def write_evo_export(run, out: Path) -> list[Path]:
    """``evo_ape.zip``: evo's own APE (translation part, SE(3) Umeyama alignment, time stamps
    associated within the run's evaluation setting, else 0.02 s) of the run against its ground
    truth, saved with evo's ``save_res_file``: ``evo_res evo_ape.zip other.zip`` tables it with
    other systems' results. The run's own ATE (evaluation.json) agrees with it (tests)."""
    check_evo(run)
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D
    from evo.main_ape import ape
    from evo.tools import file_interface

    gt = run.groundtruth()
    max_diff = 0.02
    ev = run.info.get("evaluation") or {}
    if isinstance(ev.get("settings"), dict) and isinstance(ev["settings"].get("max_difference"), (int, float)):
        max_diff = float(ev["settings"]["max_difference"])

    def evo_traj(t: Trajectory) -> PoseTrajectory3D:
        return PoseTrajectory3D(poses_se3=list(t.poses), timestamps=np.array(t.timestamps))

    try:
        ref, est = sync.associate_trajectories(evo_traj(gt), evo_traj(run.trajectory), max_diff=max_diff)
        if ref.num_poses < 3:
            raise ValueError(f"only {ref.num_poses} poses match the ground truth in time; SE(3) alignment needs 3")
        res = ape(ref, est, metrics.PoseRelation.translation_part, align=True)
    except Exception as e:  # noqa: BLE001 - evo's own exceptions (sync, geometry) all mean the same here
        raise InputError(f"evo could not evaluate {run.run_dir / 'trajectory.tum'} against the ground truth: {e}") \
            from None
    res.info["ref_name"] = str(Path(run.info["sequence"]) / "groundtruth.txt")
    res.info["est_name"] = str(run.run_dir / "trajectory.tum")
    res.info["title"] = f"APE w.r.t. translation part (m), SE(3) Umeyama alignment: {run.run_dir.name}"
    path = out / "evo_ape.zip"
    with atomic_path(path) as tmp:
        file_interface.save_res_file(tmp, res)
    return [path]
