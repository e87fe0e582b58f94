"""What the SLAM chain tells an observer (the Rerun logger), and the observer that does nothing.

:class:`NullObserver` is the default, so the per-frame chain never asks whether anyone is
watching; :class:`rgbdslam.viz.rerun_log.RerunLogger` implements the same methods.
"""

from __future__ import annotations

import numpy as np


class NullObserver:
    """Accepts every observer call and does nothing."""

    logs_map = False  # the map's points need not be sent to it

    def log_frame(self, frame, result) -> None:
        pass

    def log_filtered_depth(self, index: int, timestamp: float, depth: np.ndarray) -> None:
        pass

    def log_gate(self, index: int, timestamp: float, measure: float, threshold: float, sharp: bool) -> None:
        pass

    def log_inlier_matches(self, index: int, uv_ref: np.ndarray, uv_cur: np.ndarray) -> None:
        pass

    def log_loop(self, i: int, j: int, pose_i: np.ndarray | None, pose_j: np.ndarray) -> None:
        pass

    def log_trajectory(self, name: str, traj) -> None:
        pass

    def log_landmarks(self, index: int, pos: np.ndarray, age: np.ndarray, uv_matched: np.ndarray | None) -> None:
        pass

    def log_map(self, points: np.ndarray, colors: np.ndarray) -> None:
        pass

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass


def make_observer(cfg, camera, groundtruth):
    """The Rerun logger when ``output.rerun`` or ``output.rerun_save`` asks for one, else a NullObserver."""
    if not (cfg.output.rerun or cfg.output.rerun_save):
        return NullObserver()
    from rgbdslam.viz.rerun_log import RerunLogger

    return RerunLogger(cfg, camera, groundtruth, spawn=cfg.output.rerun, save_path=cfg.output.rerun_save)
