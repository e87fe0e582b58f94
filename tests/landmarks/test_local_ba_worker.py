"""Local BA off the tracking thread (``landmarks.ba_worker``): the BA process gives exactly what
the tracking thread would (deferred to the same hand-over point), and the write-back keeps what
the Kalman filter added while the BA ran."""

from __future__ import annotations

import os

import numpy as np
import pytest

from rgbdslam.config import LandmarksConfig
from rgbdslam.landmarks.local_ba import BAWorker, LocalBA, make_problem, solve_problem
from rgbdslam.landmarks.map import LandmarkMap
from rgbdslam.landmarks.stage import _KeyframeObs
from tests.landmarks.scenes import CAM, pose, scene, seen


def _problem(seed: int = 4):
    """Four keyframes seeing 400 noisy landmarks, the last three off by ~2 cm (the local BA test's scene)."""
    rng = np.random.default_rng(seed)
    X = scene(400, 1)
    cfg = LandmarksConfig(ba_window=3, ba_iterations=10, depth_noise_a=0.001, depth_noise_b=0.0)
    lmap = LandmarkMap(store="single")
    ids = lmap.add(X + rng.normal(scale=0.01, size=X.shape), np.tile(np.eye(3) * 1e-4, (len(X), 1, 1)),
                   np.zeros((len(X), 32), np.uint8), 0, 0)
    kfs, poses = [], {}
    for k in range(4):
        P = pose([0, 0.03 * k, 0], [0.08 * k, 0, 0])
        _, uv, z = seen(P, X)
        kfs.append(_KeyframeObs(k, ids, uv + rng.normal(scale=0.5, size=uv.shape),
                                z + rng.normal(scale=0.001, size=z.shape)))
        poses[k] = P if k == 0 else P @ pose(rng.normal(scale=0.01, size=3), rng.normal(scale=0.02, size=3))
    return cfg, lmap, kfs, poses, ids


def test_the_ba_process_solves_exactly_as_the_tracking_thread():
    cfg, lmap, kfs, poses, _ = _problem()
    p = make_problem(cfg, lmap, kfs, poses)
    inline = solve_problem(cfg, LocalBA(cfg, CAM).factors, p)
    worker = BAWorker(cfg, CAM)
    try:
        worker.submit(p)
        assert worker.pending and worker._proc.pid != os.getpid()
        remote = worker.result()
    finally:
        worker.close()
    assert not worker._proc.is_alive()
    assert sorted(remote.poses) == sorted(inline.poses) == [1, 2, 3]
    for k in inline.poses:
        assert np.array_equal(remote.poses[k], inline.poses[k])
    assert np.array_equal(remote.after, inline.after) and remote.error == inline.error


def test_write_back_keeps_the_kalman_updates_made_while_the_ba_ran():
    """A landmark the filter moved after the problem was made moves by the BA's step from there;
    one it did not move gets the BA's position exactly; a culled one stays dead and unmoved."""
    cfg, lmap, kfs, poses, ids = _problem()
    ba = LocalBA(cfg, CAM)
    p = make_problem(cfg, lmap, kfs, poses)
    res = solve_problem(cfg, ba.factors, p)
    a, b, dead = (int(np.flatnonzero(res.use == i)[0]) for i in ids[:3])
    lmap.pos[ids[0]] += [0.01, 0.0, -0.02]  # a Kalman update while the BA ran
    lmap.alive[ids[2]] = False
    kept = lmap.pos[ids[2]].copy()
    out = ba.apply(lmap, res)
    assert sorted(out) == [1, 2, 3]
    step = res.after[a] - res.before[a]
    assert np.allclose(lmap.pos[ids[0]], res.before[a] + [0.01, 0.0, -0.02] + step, atol=1e-12)
    assert np.array_equal(lmap.pos[ids[1]], res.after[b])
    assert np.array_equal(lmap.pos[ids[2]], kept) and dead == 2
    assert np.linalg.norm(step) > 1e-4  # the BA did move it


@pytest.mark.data
def test_process_and_deferred_local_ba_give_the_same_trajectory(desk9):
    """fr1/desk 9 frames through the chain: the BA in its process and the BA on the tracking
    thread, both written back at the next keyframe (or both one frame later), give the same poses
    bit for bit (the hand-over point, not the process's speed, decides)."""
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.slam import SLAM

    out = {}
    for worker, handover in (("process", 0), ("deferred", 0), ("process", 1), ("deferred", 1)):
        cfg = load_config(None, ["landmarks.enabled=true", "landmarks.local_ba=true", "keyframes.max_gap=3",
                                 "landmarks.ba_min_observations=10", f"landmarks.ba_worker={worker}",
                                 f"landmarks.ba_handover={handover}"])
        seq = open_sequence(desk9, cfg.dataset)
        slam = SLAM(cfg, seq.camera)
        for i in range(len(seq)):
            slam.track(seq[i])
        odo = slam.odometry().poses.copy()
        final = slam.finish().poses
        s = slam.landmarks.summary()
        assert s["local_ba_runs"] >= 2 and s["local_ba_worker"] == worker
        out[worker, handover] = (odo, final, slam.landmarks.map.pos[: slam.landmarks.map.n].copy())
    for h in (0, 1):
        for a, b in zip(out["process", h], out["deferred", h]):
            assert np.array_equal(a, b)
    # the hand-over point matters: one frame later is not one keyframe later
    assert not np.allclose(out["deferred", 0][0], out["deferred", 1][0], atol=1e-9)


def _tracker_in_daemon(out) -> None:
    from rgbdslam.landmarks.stage import LandmarkTracker

    t = LandmarkTracker(LandmarksConfig(local_ba=True, ba_worker="process"), CAM)
    out.put(t._worker is None)


def test_inside_a_daemonic_process_the_ba_is_solved_on_the_tracking_thread():
    """A daemonic process may not start the BA process: the tracker falls back to solving the
    same deferred problems itself (the same results) instead of failing."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    p = ctx.Process(target=_tracker_in_daemon, args=(out,), daemon=True)
    p.start()
    try:
        assert out.get(timeout=120) is True
    finally:
        p.join(timeout=30)
