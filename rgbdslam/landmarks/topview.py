"""The 2-D top view of the landmark map (the thesis' own map): landmarks seen from above."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def up_axis(poses: list[np.ndarray]) -> int:
    """The world axis the cameras' y axes (image down) point along most: the vertical one."""
    if not poses:
        return 1
    down = np.mean([P[:3, 1] for P in poses], axis=0)
    return int(np.argmax(np.abs(down)))


def plot_top_view(path: str | Path, pos: np.ndarray, seen: np.ndarray, kf_poses: list[np.ndarray],
                  title: str = "landmarks (top view)") -> Path:
    """PNG of landmarks projected onto the horizontal plane (the axis the cameras' image-down
    direction is closest to is dropped), coloured by how often each was seen, with the keyframe
    positions; written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rgbdslam.io.atomic import atomic_path

    up = up_axis(kf_poses)
    ax_i = [k for k in range(3) if k != up]
    fig, ax = plt.subplots(figsize=(7, 7))
    if len(pos):
        sc = ax.scatter(pos[:, ax_i[0]], pos[:, ax_i[1]], c=np.log2(np.maximum(seen, 1)), s=1.5, cmap="viridis")
        fig.colorbar(sc, ax=ax, label="log2(times seen)")
    if kf_poses:
        C = np.array([P[:3, 3] for P in kf_poses])
        ax.plot(C[:, ax_i[0]], C[:, ax_i[1]], "-", color="tab:red", lw=1.0, label="keyframes")
        ax.legend(loc="upper right")
    ax.set_aspect("equal")
    ax.set_xlabel(f"{'xyz'[ax_i[0]]} (m)")
    ax.set_ylabel(f"{'xyz'[ax_i[1]]} (m)")
    ax.set_title(f"{title}: {len(pos)} landmarks")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path
