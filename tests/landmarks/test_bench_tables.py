"""The landmark benchmark tables built from rows by hand: benchmarks.landmarks' comparison with
Open3D's odometry on the loop-type sequences, benchmarks.slam's landmark ablation."""

from __future__ import annotations

from benchmarks import landmarks, slam


def _row(seq, variant, ate, rpe, fps=10.0, **kw):
    return {"sequence": seq, "variant": variant, "ate": ate, "rpe": rpe, "fps": fps, "loops": 0, "old_share": None, **kw}


def test_open3d_comparison_marks_and_counts_each_variant():
    md = landmarks.markdown([
        _row("loop seed 0", "default", 0.0030, 0.0020), _row("loop seed 0", "landmarks", 0.0020, 0.0009),
        _row("loop seed 0", "Open3D hybrid odometry", 0.2000, 0.0010, 0.5),
        _row("circle seed 0", "default", 0.0060, 0.0030), _row("circle seed 0", "landmarks", 0.0100, 0.0012),
        _row("circle seed 0", "Open3D hybrid odometry", 0.0100, 0.0010, 0.5),
        _row("xyz seed 0", "default", 0.0050, 0.0030), _row("xyz seed 0", "landmarks", 0.0020, 0.0020),
    ], "## T", ["cmd"], "machine")
    lines = md.splitlines()
    head = lines.index("| sequence | Open3D ATE / RPE | default | landmarks |")
    assert lines[head + 2] == "| loop seed 0 | 0.2000 / 0.0010 | 0.0030 <= / 0.0020 | 0.0020 <= / 0.0009 <= |"
    assert lines[head + 3] == "| circle seed 0 | 0.0100 / 0.0010 | 0.0060 <= / 0.0030 | 0.0100 <= / 0.0012 |"
    assert lines[head + 4] == "| at or below Open3D (ATE / RPE) | | 2 / 0 of 2 | 2 / 1 of 2 |"
    # Open3D (loop-type sequences only) stays out of the synthetic medians
    assert not [ln for ln in lines if ln.startswith("| Open3D hybrid odometry | 0.")]


def test_landmark_ablation_cost_table():
    rows = [_row("xyz seed 0", "default", 0.005, 0.003, 20.0, landmarks_ms=None),
            _row("xyz seed 0", "landmarks", 0.002, 0.002, 15.0, landmarks_ms=8.0),
            _row("xyz seed 0", "landmarks, Kalman off", 0.002, 0.002, 10.0, landmarks_ms=9.0),
            _row("rpy seed 0", "default", 0.005, 0.003, 40.0, landmarks_ms=None),
            _row("rpy seed 0", "landmarks", 0.004, 0.003, 20.0, landmarks_ms=6.0),
            _row("rpy seed 0", "landmarks, Kalman off", 0.004, 0.003, 20.0, landmarks_ms=7.0)]
    md = slam.landmark_markdown(rows, "## A", "cmd", "machine")
    assert "| landmarks | 7.0 | 0.62 |" in md  # medians of (8, 6) ms and of the ratios (0.75, 0.5)
    assert "| landmarks, Kalman off | 8.0 | 0.50 |" in md
    assert "| landmarks | 0.0030 | 0.0025 | 0.60 | 0.83 | 2 / 0 |" in md  # synthetic medians and ratios
    assert set(slam.LANDMARK_ABLATION) >= {
        "default", "thesis", "landmarks, Kalman off", "landmarks, uniform sampling", "landmarks, single k-d tree"}
