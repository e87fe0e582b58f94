"""Options that make the landmark map cheaper per frame (issue 17's speed target): what each one
changes, exactly."""

from __future__ import annotations

import numpy as np
import pytest


def _run(desk9, sets):
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.slam import SLAM

    cfg = load_config(None, ["landmarks.enabled=true", "keyframes.max_gap=2", "landmarks.ba_min_observations=10",
                             *sets])
    seq = open_sequence(desk9, cfg.dataset)
    slam = SLAM(cfg, seq.camera)
    for i in range(len(seq)):
        slam.track(seq[i])
    return slam


@pytest.mark.data
def test_ba_every_runs_the_local_ba_on_every_kth_keyframe(desk9):
    """fr1/desk 9 frames: ``ba_every`` k runs the local BA on keyframes k, 2k, ... only; with k beyond
    the run's keyframes no BA runs and the trajectory is the one without local BA, bit for bit; k = 1
    runs it on every keyframe and moves the trajectory."""
    runs, odo = {}, {}
    for name, sets in (("off", []), ("1", ["landmarks.local_ba=true"]),
                       ("2", ["landmarks.local_ba=true", "landmarks.ba_every=2"]),
                       ("never", ["landmarks.local_ba=true", "landmarks.ba_every=1000"])):
        slam = _run(desk9, sets)
        runs[name] = (slam.landmarks.summary()["local_ba_runs"], len(slam.state.keyframes))
        odo[name] = slam.odometry().poses.copy()
    n_kf = runs["1"][1]
    assert n_kf >= 4
    assert runs["1"][0] == n_kf and runs["2"][0] == runs["2"][1] // 2 and runs["never"][0] == 0
    assert np.array_equal(odo["never"], odo["off"])
    assert not np.allclose(odo["1"], odo["off"], atol=1e-9)
