"""Evaluation plots (PNG). Drawing only: the numbers come from ate.py / rpe.py.

Figures are built with ``matplotlib.figure.Figure`` on an Agg canvas, so importing this
module never changes the global matplotlib backend and works without a display.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from rgbdslam.io.atomic import atomic_path
from rgbdslam.io.trajectory import Trajectory

_AXES = "xyz"


def _save(fig: Figure, path: str | Path, margins: dict[str, float]) -> Path:
    """``fig`` as PNG at ``path``. The margins are fixed (``subplots_adjust``): ``bbox_inches="tight"``
    drew every figure twice to measure it, 0.3 of the 0.8 s of CPU the three plots of a run took."""
    path = Path(path)
    FigureCanvasAgg(fig)
    fig.subplots_adjust(**margins)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    return path


def topview_axes(*position_sets: np.ndarray) -> tuple[int, int]:
    """The two axes (indices into x, y, z) with the largest extent, in ascending order."""
    P = np.concatenate([np.asarray(p).reshape(-1, 3) for p in position_sets], axis=0)
    extent = P.max(axis=0) - P.min(axis=0)
    a, b = sorted(np.argsort(-extent, kind="stable")[:2].tolist())
    return a, b


def _topview(gt: Trajectory, estimates: dict[str, Trajectory], colors: list[str], errors: bool,
             title: str, path: str | Path) -> Path:
    """Ground truth and estimates on the two axes of largest extent (equal aspect); with ``errors``
    (one estimate associated pose for pose) the error segments too, thinned to ~100."""
    a, b = topview_axes(gt.positions, *[e.positions for e in estimates.values()])
    fig = Figure(figsize=(6.4, 5.6))
    ax = fig.add_subplot(1, 1, 1)
    g = gt.positions
    ax.plot(g[:, a], g[:, b], "-", color="0.25", lw=1.6, label="ground truth")
    for color, (name, est) in zip(colors, estimates.items()):
        e = est.positions
        ax.plot(e[:, a], e[:, b], "-", color=color, lw=1.2, label=name)
        if errors and len(g) == len(e):
            step = max(1, len(g) // 100)
            for p, q in zip(g[::step], e[::step]):
                ax.plot([p[a], q[a]], [p[b], q[b]], "-", color="tab:red", lw=0.5, alpha=0.6)
    ax.plot(g[0, a], g[0, b], "o", color="0.25", ms=6, label="start")
    ax.set_xlabel(f"{_AXES[a]} [m]")
    ax.set_ylabel(f"{_AXES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, lw=0.4, alpha=0.5)
    ax.legend(loc="best", fontsize=8 if len(estimates) == 1 else 7)
    ax.set_title(f"{title}, top view ({_AXES[a]}-{_AXES[b]})")
    return _save(fig, path, dict(left=0.13, right=0.97, bottom=0.09, top=0.94))


def plot_trajectory_topview(
    gt: Trajectory, est_aligned: Trajectory, path: str | Path, title: str | None = None
) -> Path:
    """Ground truth vs aligned estimate, with error segments between associated poses."""
    return _topview(gt, {"estimate (aligned)": est_aligned}, ["tab:blue"], True, title or "trajectory", path)


def plot_trajectories_topview(gt: Trajectory, estimates: dict[str, Trajectory], path: str | Path,
                              title: str | None = None) -> Path:
    """Ground truth and several aligned estimates in one top view (``rgbdslam evaluate GT EST EST ...``)."""
    colors = [f"C{k % 10}" for k in range(len(estimates))]
    return _topview(gt, estimates, colors, False, title or f"{len(estimates)} estimates (aligned)", path)


def plot_error_over_time(ate_result, path: str | Path, title: str | None = None) -> Path:
    """ATE per associated pose against time since the first pose, with RMSE / mean / median lines."""
    t = ate_result.timestamps - ate_result.timestamps[0]
    fig = Figure(figsize=(7.5, 3.6))
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(t, ate_result.errors, "-", color="tab:blue", lw=1.0, label="position error")
    for value, name, style in (
        (ate_result.rmse, "rmse", "--"),
        (ate_result.mean, "mean", ":"),
        (ate_result.median, "median", "-."),
    ):
        ax.axhline(value, color="tab:red", ls=style, lw=1.0, label=f"{name} {value:.4f} m")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("ATE [m]")
    ax.set_ylim(bottom=0)
    ax.grid(True, lw=0.4, alpha=0.5)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(title or f"absolute trajectory error ({ate_result.align} alignment, {ate_result.n_pairs} poses)")
    return _save(fig, path, dict(left=0.1, right=0.97, bottom=0.13, top=0.91))


def plot_rpe(rpe_result, path: str | Path, title: str | None = None) -> Path:
    """RPE translation (m) and rotation (deg) per pair against time since the first pair."""
    t = rpe_result.timestamps - rpe_result.timestamps[0]
    fig = Figure(figsize=(7.5, 5.0))
    ax_t = fig.add_subplot(2, 1, 1)
    ax_r = fig.add_subplot(2, 1, 2, sharex=ax_t)
    ax_t.plot(t, rpe_result.trans_errors, "-", color="tab:blue", lw=1.0)
    ax_t.axhline(rpe_result.trans.rmse, color="tab:red", ls="--", lw=1.0, label=f"rmse {rpe_result.trans.rmse:.4f} m")
    ax_t.set_ylabel("translation [m]")
    ax_r.plot(t, rpe_result.rot_errors, "-", color="tab:green", lw=1.0)
    ax_r.axhline(rpe_result.rot.rmse, color="tab:red", ls="--", lw=1.0, label=f"rmse {rpe_result.rot.rmse:.3f} deg")
    ax_r.set_ylabel("rotation [deg]")
    ax_r.set_xlabel("time [s]")
    for ax in (ax_t, ax_r):
        ax.set_ylim(bottom=0)
        ax.grid(True, lw=0.4, alpha=0.5)
        ax.legend(loc="upper left", fontsize=8)
    unit = {"f": "frames", "s": "s", "m": "m", "rad": "rad", "deg": "deg"}[rpe_result.delta_unit]
    ax_t.set_title(title or f"relative pose error, delta {rpe_result.delta:g} {unit} ({rpe_result.n_pairs} pairs)")
    return _save(fig, path, dict(left=0.11, right=0.97, bottom=0.1, top=0.93, hspace=0.25))
