"""The stage protocol of the per-frame chain (``rgbdslam.slam.Stage``): a refinement step plugs in
as one object in ``SLAM.stages``, and the corrections it returns reach the frame records, the front
end's references and the pose graph together (``SLAM._apply``)."""

from __future__ import annotations

import numpy as np
import pytest

from rgbdslam.geometry.se3 import inv


class Shift:
    """A stage that moves frame ``at`` by ``T`` (world frame) after the front end, and keyframe
    ``kf`` by ``K`` at frame ``kf_at``; it records what the chain hands it."""

    name = "shift"

    def __init__(self, at: int, T: np.ndarray, kf: int, kf_at: int, K: np.ndarray):
        self.at, self.T, self.kf, self.kf_at, self.K = at, T, kf, kf_at, K
        self.seen, self.finished = [], None
        self.kf_pose = None

    def on_tracked(self, frame, result, pose):
        self.seen.append(frame.index)
        return {frame.index: self.T @ pose} if frame.index == self.at else {}

    def on_loops(self, frame, result, loops):
        return loops

    def on_frame(self, frame, result, pose, keyframe):
        if frame.index == self.kf_at:
            return {self.kf: self.K @ self.kf_pose}
        if frame.index == self.kf:
            self.kf_pose = pose.copy()
        return {}

    def on_finish(self, optimised):
        self.finished = dict(optimised)


def _run(desk9, stage=None):
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.slam import SLAM

    # frame-to-frame registration (one reference): the next frame's motion is measured from the last pose alone;
    # the test stage alone (no landmark map, whose map pose would pull the shifted frames back)
    cfg = load_config(None, ["keyframes.max_gap=2", "mapping.enabled=false", "registration.method=ransac",
                             "landmarks.enabled=false"])
    seq = open_sequence(desk9, cfg.dataset)
    slam = SLAM(cfg, seq.camera)
    if stage is not None:
        slam.stages.append(stage)
    for i in range(len(seq)):
        slam.track(seq[i])
    return slam, slam.finish()


@pytest.mark.data
def test_a_stage_corrects_the_frame_and_a_keyframe_everywhere_at_once(desk9):
    """fr1/desk 9 frames, frame-to-frame registration, a keyframe every 2 frames. Frame 3 moved by 1 cm after the front end: its
    record is exactly the moved pose, and the front end continued from it (frame 4's motion from
    frame 3 is the run without the stage's, to the registration's noise). Keyframe 2 moved by 5 mm at
    frame 5: its record, the frame hanging from it (3: pose relative to the keyframe kept), the
    front end's references and the graph's node guess all hold the moved pose, and the odometry edges
    touching it are re-measured from it. The stage saw every frame and the final keyframe poses."""
    T = np.eye(4)
    T[0, 3] = 0.01
    K = np.eye(4)
    K[1, 3] = 0.005
    base, _ = _run(desk9)
    stage = Shift(3, T, 2, 5, K)
    slam, final = _run(desk9, stage)
    b = {r.index: r.pose for r in base.state.records}
    r = {x.index: x for x in slam.state.records}
    assert stage.seen == list(range(9)) and len(final) == 9
    assert r[2].keyframe == 2 and r[3].keyframe == 2 and 4 in slam.state.keyframes
    assert np.allclose(r[2].pose, K @ b[2], atol=1e-12)
    assert np.allclose(r[3].pose, K @ T @ b[3], atol=1e-12)  # moved at frame 3, then with its keyframe
    assert np.allclose(inv(T @ b[3]) @ slam_odometry_pose(slam, 4), inv(b[3]) @ b[4], atol=2e-3)
    assert np.allclose(slam.graph.guess[2], K @ b[2], atol=1e-12)
    for i, j, T_ij, _ in slam.graph.odometry:
        if 2 in (i, j):
            assert np.allclose(T_ij, inv(r[i].pose) @ r[j].pose, atol=1e-9)
    assert set(stage.finished) == set(slam.state.keyframes)


def slam_odometry_pose(slam, index):
    return next(x.pose for x in slam.state.records if x.index == index)
