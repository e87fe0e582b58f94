"""scripts/diag_segments.py: per-block errors of a trajectory against the ground truth (hand-worked cases)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


def _module():
    path = Path(__file__).resolve().parents[2] / "scripts" / "diag_segments.py"
    spec = importlib.util.spec_from_file_location("diag_segments", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _yaw_path(n: int, deg_per_frame: float, step: float = 0.01) -> np.ndarray:
    """Poses turning about the camera's y axis by ``deg_per_frame`` and moving ``step`` m along x per frame."""
    P = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        P[k, :3, :3] = Rotation.from_euler("y", k * deg_per_frame, degrees=True).as_matrix()
        P[k, :3, 3] = [k * step, 0.0, 0.0]
    return P


def test_segment_table_by_hand():
    mod = _module()
    G = _yaw_path(61, 0.5)
    rows = mod.segment_table(G, G.copy(), 30)
    assert [r[:2] for r in rows] == [(0, 30), (30, 60)]
    assert np.allclose([r[2:] for r in rows], 0.0, atol=1e-6)
    # the estimate turns 0.51 deg per frame instead of 0.5: 0.3 deg of rotation drift per 30 frames,
    # accumulated from frame 0 (rot0 0.3, then 0.6) and added by each block (seg 0.3, 0.3)
    E = _yaw_path(61, 0.51)
    rows = mod.segment_table(G, E, 30)
    assert np.allclose([r[3] for r in rows], [0.3, 0.6], atol=1e-6)
    assert np.allclose([r[4] for r in rows], [0.3, 0.3], atol=1e-6)
    # the same positions: block 0-30 starts at the same pose, no translation error; block 30-60 starts
    # 0.3 deg turned, so its 0.30 m step is seen 0.3 deg off: 0.30 * 2 sin(0.15 deg) = 1.571 mm
    assert rows[0][5] < 1e-9 and np.isclose(rows[1][5], 0.30 * 2 * np.sin(np.radians(0.15)), rtol=1e-6)
    assert all(r[2] < 1e-9 for r in rows)
