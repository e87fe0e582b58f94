"""Fusion while tracking: de-/re-integration gives the map that fusing the final poses gives."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from rgbdslam.config import MappingConfig
from rgbdslam.datasets import open_sequence
from rgbdslam.mapping.fusion import VoxelCloud, Tsdf, Undistorter, integrate_frame, prepare_frame
from rgbdslam.mapping.live import MapState, merge_tsdf

from tests.conftest import cli


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    from rgbdslam.datasets.synthetic import generate_sequence

    d = tmp_path_factory.mktemp("live") / "seq"
    generate_sequence(d, frames=12, motion="loop", width=320, height=240, noise=True, seed=3)
    return open_sequence(d)


def _fresh(seq, cfg, poses: dict[int, np.ndarray], camera=None):
    """The map fusing ``poses`` from scratch, the way `rgbdslam fuse` does."""
    camera = camera or seq.camera
    tsdf, cloud = Tsdf(cfg, camera), VoxelCloud(cfg.voxel_size)
    und = Undistorter(camera, cfg.undistort)
    for i, p in poses.items():
        f = seq.load(i)
        rgb, depth = prepare_frame(f.rgb, f.depth, und, cfg)
        integrate_frame(tsdf, cloud, rgb, depth, p, camera, cfg)
    return tsdf, cloud


def _voxels(vbg):
    """{block key: (tsdf, weight)} of the blocks with any weight."""
    import open3d.core as o3c

    hm = vbg.hashmap()
    idx = hm.active_buf_indices().to(o3c.int64)
    keys = hm.key_tensor()[idx].numpy()
    idx = idx.numpy()
    t, w = vbg.attribute("tsdf").numpy()[idx], vbg.attribute("weight").numpy()[idx]
    return {tuple(k): (t[n], w[n]) for n, k in enumerate(keys) if w[n].any()}


def _same_map(a, b, seq, cfg):
    (ta, ca), (tb, cb) = a, b
    va, vb = _voxels(ta.vol), _voxels(tb.vol)
    assert va.keys() == vb.keys()
    for k in va:
        np.testing.assert_array_equal(va[k][1], vb[k][1])  # the same frames saw every voxel
        seen = va[k][1] > 0
        np.testing.assert_allclose(va[k][0][seen], vb[k][0][seen], atol=1e-5)
    pa, cola = ca.result()
    pb, colb = cb.result()
    order_a, order_b = np.argsort(ca.keys), np.argsort(cb.keys)
    np.testing.assert_array_equal(ca.keys[order_a], cb.keys[order_b])
    np.testing.assert_allclose(pa[order_a], pb[order_b], atol=1e-9)
    assert np.abs(cola[order_a].astype(int) - colb[order_b].astype(int)).max() <= 1


def test_merging_two_volumes_equals_integrating_all_frames_into_one(synth):
    cfg = MappingConfig()
    gt = synth.groundtruth()
    poses = {i: gt.poses[i] for i in range(6)}
    one = _fresh(synth, cfg, poses)
    a = _fresh(synth, cfg, {i: poses[i] for i in range(3)})
    b = _fresh(synth, cfg, {i: poses[i] for i in range(3, 6)})
    merge_tsdf(a[0].vol, b[0].vol)
    a[1].pending.append((*(b[1].merge() or (b[1].keys, b[1].sums, b[1].counts)),))
    _same_map(one, a, synth, cfg)


def test_moved_and_dropped_keyframes_are_reintegrated_to_the_final_poses(synth):
    cfg = MappingConfig(live_lag=0)
    gt = synth.groundtruth()
    load = lambda i: (synth.load(i).rgb, synth.load(i).depth)  # noqa: E731
    live = MapState(cfg, synth.camera, load)
    kfs = [0, 2, 4, 6, 8, 10]
    drift = np.eye(4)
    drift[:3, 3] = [0.03, -0.02, 0.01]  # a loop closure moves the later keyframes by ~4 cm
    for i in kfs:
        f = synth.load(i)
        live.add(i, f.rgb, f.depth, gt.poses[i] @ drift if i >= 6 else gt.poses[i])
    final = {i: gt.poses[i] for i in kfs}
    final[2] = final[2].copy()
    final[2][:3, 3] += 1e-4  # below the quarter-voxel tolerance: stays where it is
    live.refresh(final, keep=set(kfs) - {10})  # 10: in a segment left out of the map
    tsdf, cloud, fused, _ = live.result()
    assert fused == [0, 2, 4, 6, 8]
    assert live.stats["deintegrated"] == 3 and live.stats["reintegrated"] == 2 and live.stats["rebuilds"] == 0
    expect = {i: final[i] for i in fused}
    expect[2] = gt.poses[2]  # the map keeps the pose it was integrated at, within the tolerance
    _same_map(_fresh(synth, cfg, expect), (tsdf, cloud), synth, cfg)


def _shifted_map(synth, cfg, frames, shifted, axis: int, metres: float):
    """A live map of ``frames`` at the ground-truth poses, those in ``shifted`` moved ``metres``
    along camera ``axis`` (as a loop closure would find them off); and the ground truth."""
    gt = synth.groundtruth()
    live = MapState(cfg, synth.camera, lambda i: (synth.load(i).rgb, synth.load(i).depth))
    shift = np.eye(4)
    shift[axis, 3] = metres
    for i in frames:
        f = synth.load(i)
        live.add(i, f.rgb, f.depth, gt.poses[i] @ shift if i in shifted else gt.poses[i])
    return live, gt


def _idle_jobs(synth, final: dict):
    """A job queue with the keyframes ``final`` added at those poses; the finish comes when the map
    process waits for a job (has nothing else to do)."""
    import queue

    class Idle(queue.Queue):
        def get(self, block=True, timeout=None):
            if block and self.empty():
                self.put(("finish", final, None, "", False))
            return super().get(block, timeout)

    jobs = Idle()
    for i in final:
        jobs.put(("add", i, synth.load(i).rgb, synth.load(i).depth, final[i]))
    return jobs


def test_most_keyframes_moved_rebuilds_and_still_matches(synth):
    cfg = MappingConfig(live_lag=0)
    live, gt = _shifted_map(synth, cfg, (0, 3, 6), (0, 3, 6), 0, 0.05)
    live.refresh({i: gt.poses[i] for i in (0, 3)})  # during tracking, after a loop: 6 stays
    assert live.stats["rebuilds"] == 1 and live.used[6] is not None
    live.refresh({i: gt.poses[i] for i in (0, 3, 6)})  # the end
    tsdf, cloud, fused, _ = live.result()
    assert live.stats["rebuilds"] == 1 and live.stats["deintegrated"] == 1  # 1 of 3 moved at the end
    _same_map(_fresh(synth, cfg, {i: gt.poses[i] for i in (0, 3, 6)}), (tsdf, cloud), synth, cfg)


@pytest.mark.data
@pytest.mark.parametrize("method", ["statistical", "voxel"])
def test_run_writes_the_live_map_and_it_matches_fusing_afterwards(tmp_path, desk9, method):
    out = tmp_path / "run"
    res = cli(["run", desk9, "-c", "tum_fr1", "--out", out, "-q", "--set", "keyframes.min_translation=0.02",
               "--set", f"mapping.outlier_method={method}"])
    assert res.exit_code == 0, res.output
    info = json.loads((out / "run.json").read_text())
    assert info["map"]["live"] is True and info["map"]["frames_fused"] == len(info["keyframes"]) >= 2
    # the plots, drawn by the plot process meanwhile, are written and named in evaluation.json and run.json
    plots = json.loads((out / "evaluation.json").read_text())["plots"]
    assert [p.rsplit("/", 1)[1] for p in plots] == ["ate_topview.png", "ate_over_time.png", "rpe_over_time.png"]
    assert all(open(p, "rb").read(8) == b"\x89PNG\r\n\x1a\n" for p in plots)
    assert info["evaluation"]["plots"] == plots and "plots" in info["after_tracking_s"]
    import open3d as o3d

    live = np.asarray(o3d.io.read_point_cloud(str(out / "map" / "cloud.ply")).points)
    res = cli(["fuse", out, "-q"])
    assert res.exit_code == 0, res.output
    after = np.asarray(o3d.io.read_point_cloud(str(out / "map" / "cloud.ply")).points)
    assert len(live) == len(after)
    if method == "voxel":  # fuse filtered with the run's method: its cloud is the voxel filter's of the unfiltered one
        from rgbdslam.mapping.fusion import voxel_keep

        assert cli(["fuse", out, "-q", "--set", "mapping.outlier_min_neighbors=0"]).exit_code == 0
        unfiltered = np.asarray(o3d.io.read_point_cloud(str(out / "map" / "cloud.ply")).points)
        keep = voxel_keep(unfiltered, 0.01, MappingConfig().outlier_min_neighbors)
        assert 0 < len(unfiltered) - len(keep) < 0.2 * len(unfiltered)
        np.testing.assert_allclose(unfiltered[keep], after, atol=1e-6)  # PLY float32 round trip
    from scipy.spatial import cKDTree

    d, _ = cKDTree(after).query(live)
    # keyframes the final optimisation moved by less than a quarter voxel (2.5 mm, and 2.5 mm at
    # depth_max by rotation) stay where they were integrated: a voxel mean moves at most that much
    assert d.max() <= 0.005 and np.median(d) == 0


@pytest.mark.parametrize("cache_mb", [0, 64])
def test_reintegration_takes_the_cached_images_or_reads_them_again(synth, cache_mb):
    cfg = MappingConfig(live_lag=0)
    gt = synth.groundtruth()
    reads = []

    def load(i):
        reads.append(i)
        return synth.load(i).rgb, synth.load(i).depth

    # a lens with distortion: the images are undistorted once, whether cached or read again
    camera = dataclasses.replace(synth.camera, dist=(0.08, -0.05, 0.001, 0.0, 0.0))
    live = MapState(cfg, camera, load, cache_mb=cache_mb)
    shift = np.eye(4)
    shift[1, 3] = 0.02
    for i in (0, 4, 8):
        f = synth.load(i)
        live.add(i, f.rgb, f.depth, gt.poses[i] @ shift if i == 8 else gt.poses[i])
    assert live.cache_bytes == (0 if cache_mb == 0 else sum(a.nbytes + b.nbytes for a, b in live.cache.values()))
    if cache_mb:  # the synthetic depth is in 1/5000 m steps: kept as 2-byte steps, lossless
        assert all(d.dtype == np.uint16 for _, d in live.cache.values())
    live.refresh({i: gt.poses[i] for i in (0, 4, 8)})  # 8 is taken out and put in again
    assert live.stats["deintegrated"] == 1 and live.stats["rebuilds"] == 0
    assert reads == ([] if cache_mb else [8]) and live.stats["reloaded"] == len(reads)
    _same_map(_fresh(synth, cfg, {i: gt.poses[i] for i in (0, 4, 8)}, camera), live.result()[:2], synth, cfg)


def test_shift_is_the_largest_point_motion_over_the_box_corners():
    from rgbdslam.mapping.live import shift_m

    box = np.array([[-1.0, -0.5, 0.5], [1.2, 0.7, 2.5]])
    a = np.eye(4)
    th = np.deg2rad(1.0)  # a turn about the optical axis: a point moves 2 sin(th/2) x its distance from the axis
    b = np.eye(4)
    b[:2, :2] = [[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]
    assert shift_m(a, b, 3.0, box) == pytest.approx(2 * np.sin(th / 2) * np.hypot(1.2, 0.7), rel=1e-12)
    # the old bound (rotation angle x depth_max) ignores that the axis does not move the centre
    assert shift_m(a, b, 3.0) == pytest.approx(th * 3.0)
    t = np.eye(4)
    t[:3, 3] = [0.001, -0.002, 0.002]  # a translation moves every point alike
    assert shift_m(a, t, 3.0, box) == pytest.approx(0.003)
    rng = np.random.default_rng(0)  # any pose: no point inside the box moves further than the bound
    from scipy.spatial.transform import Rotation

    for _ in range(20):
        rel = np.eye(4)
        rel[:3, :3] = Rotation.from_rotvec(rng.normal(scale=0.02, size=3)).as_matrix()
        rel[:3, 3] = rng.normal(scale=0.01, size=3)
        p = rng.uniform(box[0], box[1], size=(2000, 3))
        moved = np.linalg.norm(p @ (rel[:3, :3] - np.eye(3)).T + rel[:3, 3], axis=1)
        bound = shift_m(a, rel, 3.0, box)
        assert moved.max() <= bound + 1e-12 and moved.max() > 0.8 * bound


@pytest.mark.data
def test_points_box_holds_every_point_of_a_real_keyframe(desk9):
    from rgbdslam.mapping.fusion import backproject_image
    from rgbdslam.mapping.live import points_box

    seq = open_sequence(desk9)
    cfg = MappingConfig()
    f = seq.load(0)
    _, depth = prepare_frame(f.rgb, f.depth, Undistorter(seq.camera, True), cfg)
    pts, _ = backproject_image(depth, seq.camera)
    box = points_box(depth, seq.camera)
    np.testing.assert_allclose(box, [pts.min(axis=0), pts.max(axis=0)], atol=1e-5)
    # the same numbers as every pixel's point in float64 (the box takes each column's nearest and
    # farthest depth only)
    cam = seq.camera
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    x, y = (u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy
    np.testing.assert_array_equal(box, [[x.min(), y.min(), z.min()], [x.max(), y.max(), z.max()]])
    one = np.zeros_like(depth)
    one[7, 11] = 1.5
    np.testing.assert_array_equal(points_box(one, cam), [[(11 - cam.cx) * 1.5 / cam.fx, (7 - cam.cy) * 1.5 / cam.fy, 1.5]] * 2)
    assert points_box(np.zeros_like(depth), seq.camera) is None


def test_the_end_gives_the_cloud_before_the_tsdf_is_redone(synth):
    """At the end of a run the cloud goes to the run first (it makes cloud.ply and the 2-D map
    meanwhile); both parts still equal fusing the final poses."""
    cfg = MappingConfig(live_lag=0)
    live, gt = _shifted_map(synth, cfg, (0, 3, 6, 9), (9,), 2, 0.03)
    final = {i: gt.poses[i] for i in (0, 3, 6, 9)}
    fresh = _fresh(synth, cfg, {i: final[i] for i in (0, 3, 9)})
    seen = []

    def between(fused):
        seen.append(fused)
        tsdf_now = _voxels(live.tsdf.vol)
        assert tsdf_now.keys() != _voxels(fresh[0].vol).keys()  # the TSDF still has 6 in and 9 where it was
        _same_map((fresh[0], fresh[1]), (fresh[0], live.cloud), synth, cfg)  # the cloud is final already

    assert live.refresh(final, keep={0, 3, 9}, between=between) == 2  # 6 leaves, 9 moves
    assert seen == [[0, 3, 9]]
    _same_map(fresh, live.result()[:2], synth, cfg)


def test_without_a_mesh_the_map_is_the_cloud_alone(synth):
    cfg = MappingConfig(mesh=False, live_lag=0)
    live, gt = _shifted_map(synth, cfg, (0, 5, 10), (0, 5, 10), 0, 0.02)
    seen = []
    assert live.refresh({i: gt.poses[i] for i in (0, 5, 10)}, between=seen.append) == 3  # a rebuild
    assert seen == [[0, 5, 10]] and live.tsdf is None and live.stats["rebuilds"] == 1
    fresh = VoxelCloud(cfg.voxel_size)
    for i in (0, 5, 10):
        f = synth.load(i)
        integrate_frame(None, fresh, *prepare_frame(f.rgb, f.depth, Undistorter(synth.camera, True), cfg),
                        gt.poses[i], synth.camera, cfg)
    np.testing.assert_allclose(np.sort(live.cloud.result()[0], axis=0), np.sort(fresh.result()[0], axis=0), atol=1e-9)


def test_the_newest_keyframes_wait_and_enter_the_map_once_at_their_final_poses(synth):
    """``live_lag``: the newest keyframes are not integrated while loop closures still move them;
    a pose update only changes the pose they will be integrated at, and the end integrates them
    once (no de-integration) - the map still equals fusing the final poses."""
    cfg = MappingConfig(live_lag=2)
    kfs = (0, 3, 6, 9, 11)
    live, gt = _shifted_map(synth, cfg, kfs, (9, 11), 0, 0.04)  # 9 and 11 still wait: not in the map
    assert sorted(live.used) == [0, 3, 6] and list(live.waiting) == [9, 11]
    assert live.stats["integrated"] == 3
    final = {i: gt.poses[i] for i in kfs}
    assert live.refresh(final) == 0  # during tracking: nothing in the map moved, 9 and 11 take the new poses
    assert live.stats["deintegrated"] == 0 and live.stats["integrated"] == 3
    assert all(live.waiting[i] is final[i] for i in (9, 11))
    seen = []

    def between(fused):
        seen.append(fused)
        _same_map(_fresh(synth, cfg, final), (_fresh(synth, cfg, final)[0], live.cloud), synth, cfg)

    assert live.refresh(final, between=between, flush=True) == 0
    assert seen == [list(kfs)] and not live.waiting and live.stats["final_waiting"] == 2
    assert live.stats["integrated"] == 5 and live.stats["deintegrated"] == 0 and live.stats["reintegrated"] == 0
    tsdf, cloud, fused, _ = live.result()
    assert fused == list(kfs)
    _same_map(_fresh(synth, cfg, final), (tsdf, cloud), synth, cfg)


def test_a_waiting_keyframe_of_a_segment_left_out_never_enters_the_map(synth):
    cfg = MappingConfig(live_lag=3)
    live, gt = _shifted_map(synth, cfg, (0, 4, 8, 11), (), 0, 0.0)
    assert sorted(live.used) == [0] and list(live.waiting) == [4, 8, 11]
    final = {i: gt.poses[i] for i in (0, 4, 8, 11)}
    live.refresh(final, keep={0, 4, 11}, flush=True)
    tsdf, cloud, fused, _ = live.result()
    assert fused == [0, 4, 11] and 8 not in live.box and 8 not in live.cache
    _same_map(_fresh(synth, cfg, {i: final[i] for i in (0, 4, 11)}), (tsdf, cloud), synth, cfg)


def test_the_map_process_applies_queued_poses_before_it_integrates(synth, tmp_path):
    """The map process's loop (:func:`rgbdslam.mapping.live._serve`, here in this process on real
    queues): keyframes that are queued together with a pose update go into the map at the
    update's poses, never at the poses they came with (which would be redone); the map at the
    end is the one fusing the final poses gives."""
    import queue
    import signal

    from rgbdslam.mapping.live import _serve

    cfg = MappingConfig(live_lag=0, live_nice=0, map2d=False)
    gt = synth.groundtruth()
    off = np.eye(4)
    off[0, 3] = 0.05  # the front end's poses, 5 cm off
    kfs = (0, 1, 2, 3)  # overlapping views: a mesh (voxels seen by 2 frames)
    jobs, results = queue.Queue(), queue.Queue()
    for i in kfs:
        f = synth.load(i)
        jobs.put(("add", i, f.rgb, f.depth, gt.poses[i] @ off))
    final = {i: gt.poses[i] for i in kfs}
    jobs.put(("poses", final))  # a loop closure found them
    jobs.put(("finish", final, None, str(tmp_path), False))
    old = signal.getsignal(signal.SIGINT)
    try:
        _serve(cfg, synth.camera, lambda i: (synth.load(i).rgb, synth.load(i).depth), jobs, results)
    finally:
        signal.signal(signal.SIGINT, old)
        import open3d as o3d

        o3d.utility.set_max_threads(0)
    status, fused = results.get_nowait()
    status_end, out = results.get_nowait()
    assert (status, status_end) == ("cloud", "ok") and fused == list(kfs)
    from rgbdslam.mapping.live import CLOUD_POINTS

    points = np.load(tmp_path / CLOUD_POINTS)  # the cloud is handed to the cloud process in a file
    t = out["timings"]
    assert t["integrated"] == 4 and t["deintegrated"] == 0 and t["reintegrated"] == 0 and t["final_moved"] == 0
    _, cloud = _fresh(synth, cfg, final)
    np.testing.assert_allclose(np.sort(points, axis=0), np.sort(cloud.result()[0], axis=0), atol=1e-9)
    assert out["n_vertices"] > 0 and (tmp_path / "mesh.ply").is_file()


def _niced_map(synth):
    """A map state for the tests of the niced thread: live_lag 1, live_backlog 2, live_nice 3."""
    import sys

    if not sys.platform.startswith("linux"):
        pytest.skip("threads have a niceness of their own on Linux only")
    cfg = MappingConfig(live_lag=1, live_backlog=2, live_nice=3, map2d=False)
    return cfg, synth.groundtruth(), MapState(cfg, synth.camera, lambda i: (synth.load(i).rgb, synth.load(i).depth))


def test_a_map_that_falls_behind_catches_up_at_the_run_priority_then_is_niced_again(synth):
    """``mapping.live_backlog``: the map's work while tracking runs in a niced thread; when more
    keyframes wait or are queued than ``live_lag`` + ``live_backlog`` (the niced thread got too little CPU), the
    map process's own thread, at the run's priority, integrates until none waits beyond the lag,
    then the work goes back to a niced thread. The niceness each keyframe was integrated at is
    read from the kernel (Linux: per thread)."""
    import os
    import queue
    import threading

    from rgbdslam.mapping.live import _while_tracking

    cfg, gt, state = _niced_map(synth)
    nice_at: dict[int, int] = {}
    settle = state.settle

    def recording(prepared=None):  # the real step, and the niceness of the thread that took it
        first = next(iter(state.waiting))
        settle(prepared)
        nice_at[first] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    state.settle = recording
    jobs = queue.Queue()
    final = {i: gt.poses[i] for i in range(7)}

    images = {i: (synth.load(i).rgb, synth.load(i).depth) for i in final}

    def add(*frames):  # queued at once, as keyframes queue up while the map is busy
        with jobs.mutex:
            jobs.queue.extend(("add", i, *images[i], final[i]) for i in frames)
            jobs.not_empty.notify()

    def when(done, then) -> bool:  # wait (at most a minute) until ``done()``, then ``then()``
        for _ in range(6000):
            if done():
                then()
                return True
            threading.Event().wait(0.01)
        jobs.put(None)  # never: stop the map's loop, the test fails below
        return False

    def feed():  # as tracking would: two keyframes, four at once (the map falls behind), one more
        add(0, 1)
        if when(lambda: 0 in nice_at, lambda: add(2, 3, 4, 5)) and when(lambda: 4 in nice_at, lambda: add(6)):
            when(lambda: 5 in nice_at, lambda: jobs.put(("finish", final, None, "", False)))

    helper = threading.Thread(target=feed, daemon=True)
    helper.start()
    base = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    out = _while_tracking(state, cfg, jobs)
    helper.join()
    assert out is not None and out[0] == "finish"
    assert state.stats["catch_ups"] == 1
    assert nice_at == {0: base + 3, 1: base, 2: base, 3: base, 4: base, 5: base + 3}
    assert sorted(state.used) == [0, 1, 2, 3, 4, 5] and list(state.waiting) == [6]  # live_lag 1: 6 waits
    state.refresh(final, flush=True)
    _same_map(_fresh(synth, cfg, final), state.result()[:2], synth, cfg)


def test_a_niced_thread_that_took_many_queued_keyframes_hands_them_back_when_behind(synth):
    """The niced thread takes every queued job at once (pose updates coalesced) but asks whether the
    map is behind after every keyframe it prepares: with more queued than ``live_lag`` +
    ``live_backlog`` it hands the rest back, in order, and the map process's own thread (the run's
    priority) prepares them — before, the niced thread prepared all of them first, so on a busy
    machine the backlog grew past its bound. The map is still the one of the final poses."""
    import os
    import queue
    import threading

    from rgbdslam.mapping.live import _while_tracking

    cfg, gt, state = _niced_map(synth)
    prepared_at: dict[int, int] = {}
    add = state.add

    def recording(index, *rest, **kw):
        prepared_at[index] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        add(index, *rest, **kw)

    state.add = recording
    final = {i: gt.poses[i] for i in range(6)}
    moved = {i: p.copy() for i, p in final.items()}
    for p in moved.values():
        p[0, 3] += 0.05  # the keyframes are queued at poses that a later pose update corrects
    burst = [("add", i, synth.load(i).rgb, synth.load(i).depth, moved[i]) for i in range(1, 6)]
    burst += [("poses", dict(final)), ("finish", final, None, "", False)]

    class Burst(queue.Queue):
        """Keyframe 0 alone when the niced thread asked whether it was behind; the rest queued
        (all at once, as tracking does while a starved niced thread waits for the CPU) by the time
        it takes keyframe 0 and drains the queue."""

        def get(self, *a, **kw):
            job = super().get(*a, **kw)
            while burst:
                self.put(burst.pop(0))
            return job

    jobs = Burst()
    jobs.put(("add", 0, synth.load(0).rgb, synth.load(0).depth, moved[0]))
    base = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    out = _while_tracking(state, cfg, jobs)
    assert out is not None and out[0] == "finish"
    assert prepared_at == {0: base + 3, 1: base, 2: base, 3: base, 4: base, 5: base}
    assert state.stats["catch_ups"] == 1
    # the pose update handed back with them was applied (coalesced with the finish: the end applies it)
    state.refresh(final, flush=True)
    _same_map(_fresh(synth, cfg, final), state.result()[:2], synth, cfg)


def test_an_idle_map_process_leaves_the_waiting_keyframes_for_the_end(synth):
    """The map process's loop: once the queue is empty and nothing waits beyond ``live_lag``, it
    waits for the next job; the newest keyframes go in at the end, at their final poses."""
    from rgbdslam.mapping.live import _while_tracking

    gt = synth.groundtruth()
    final = {i: gt.poses[i] for i in (0, 3, 6, 9)}
    cfg = MappingConfig(live_lag=2, live_nice=0, map2d=False)
    state = MapState(cfg, synth.camera, lambda i: (synth.load(i).rgb, synth.load(i).depth))
    assert _while_tracking(state, cfg, _idle_jobs(synth, final))[0] == "finish"
    assert sorted(state.used) == [0, 3] and list(state.waiting) == [6, 9]
    state.refresh(final, flush=True)
    assert state.stats["final_waiting"] == 2
    _same_map(_fresh(synth, cfg, final), state.result()[:2], synth, cfg)


def test_the_run_writes_cloud_ply_from_the_kept_indices_without_importing_open3d(tmp_path):
    """The run's share of the end (:func:`rgbdslam.mapping.live._write_kept_cloud`): cloud.ply of
    the points whose indices the cloud process saved, the hand-over files removed — in a fresh
    interpreter, which must not import Open3D for it (~1 s of CPU after the last frame)."""
    import subprocess
    import sys

    from rgbdslam.io.ply import write_cloud_ply
    from rgbdslam.mapping.live import CLOUD_COLORS, CLOUD_KEEP, CLOUD_POINTS

    rng = np.random.default_rng(2)
    points, colors = rng.normal(size=(500, 3)), rng.integers(0, 256, (500, 3), dtype=np.uint8)
    keep = np.flatnonzero(rng.random(500) < 0.9)
    np.save(tmp_path / CLOUD_POINTS, points)
    np.save(tmp_path / CLOUD_COLORS, colors)
    np.save(tmp_path / CLOUD_KEEP, keep)
    code = ("import sys; from rgbdslam.mapping.live import _write_kept_cloud; "
            f"print(_write_kept_cloud({str(tmp_path)!r}).name, 'open3d' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["cloud.ply", "False"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cloud.ply"]
    write_cloud_ply(tmp_path / "want.ply", points[keep], colors[keep])
    assert (tmp_path / "cloud.ply").read_bytes() == (tmp_path / "want.ply").read_bytes()


@pytest.mark.skipif(not __import__("os").path.isdir("/proc/self/task") or (__import__("os").cpu_count() or 1) < 2,
                    reason="counts threads in /proc on a machine with several cores")
def test_helper_processes_start_numpy_with_one_blas_thread():
    """:func:`rgbdslam.mapping.live.one_blas_thread` (called by :class:`LiveMap` before it starts
    the map process): a process started afterwards imports NumPy without OpenBLAS's worker threads
    (their spinning cost 145 instead of 5 ms of CPU for the 2-D map's 380k x 3 product beside a busy
    core); a user's ``OPENBLAS_NUM_THREADS`` is kept. The threads are counted in /proc."""
    import os
    import subprocess
    import sys

    child = "import numpy, os; print(len(os.listdir('/proc/self/task')))"
    parent = ("import subprocess, sys; import numpy; {call}"
              f"print(subprocess.run([sys.executable, '-c', {child!r}], capture_output=True, text=True).stdout)")
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}

    def threads(call: str, **extra) -> int:
        out = subprocess.run([sys.executable, "-c", parent.format(call=call)], env={**env, **extra},
                             capture_output=True, text=True, check=True).stdout
        return int(out.split()[-1])

    assert threads("") >= 2  # NumPy's OpenBLAS starts a worker per further core
    assert threads("from rgbdslam.mapping.live import one_blas_thread; one_blas_thread(); ") == 1
    assert threads("from rgbdslam.mapping.live import one_blas_thread; one_blas_thread(); ",
                   OPENBLAS_NUM_THREADS="2") == 2
