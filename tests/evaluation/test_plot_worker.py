"""The plot process of a run: real plots of a real evaluation, drawn in another process, the
same files as drawing them in this one; its errors come back as the run's warning."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.data

from rgbdslam.errors import RgbdslamError
from rgbdslam.evaluation.plot_worker import PlotWorker
from rgbdslam.evaluation.report import evaluate_trajectories, write_plots
from rgbdslam.io.trajectory import Trajectory, read_tum

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture
def report(desk9):
    gt = read_tum(desk9 / "groundtruth.txt")
    rng = np.random.default_rng(0)
    poses = gt.poses[::10].copy()
    poses[:, :3, 3] += rng.normal(scale=0.01, size=(len(poses), 3))  # an estimate 1 cm off
    return evaluate_trajectories(gt, Trajectory(gt.timestamps[::10], poses))


def test_plot_process_draws_the_plots_this_process_would(report, tmp_path):
    worker = PlotWorker(nice=0)
    try:
        worker.submit(report, tmp_path / "a")
        paths = worker.result()
    finally:
        worker.close()
    here = write_plots(report, tmp_path / "b")
    assert [p.replace("/a/", "/b/") for p in paths] == here
    assert [p.rsplit("/", 1)[1] for p in paths] == ["ate_topview.png", "ate_over_time.png", "rpe_over_time.png"]
    for p in paths:
        data = open(p, "rb").read()
        assert data[:8] == PNG and len(data) > 10_000
        assert data == open(p.replace("/a/", "/b/"), "rb").read()  # byte for byte: the same drawing


def test_plot_process_error_is_raised_by_result_and_close_without_a_job_ends_it(report, tmp_path):
    (tmp_path / "file").write_text("x")
    worker = PlotWorker()
    worker.submit(report, tmp_path / "file" / "plots")  # a folder under a file: cannot be written
    with pytest.raises(RgbdslamError, match="cannot write"):
        worker.result()
    worker.close()
    idle = PlotWorker()
    idle.close()
    assert not idle._proc.is_alive() and idle._proc.exitcode is not None
