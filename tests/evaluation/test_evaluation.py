"""Evaluation: association, ATE, RPE (hand-worked cases), parity with evo on real TUM data, CLI."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from rgbdslam.cli import main
from rgbdslam.errors import InputError
from rgbdslam.evaluation.associate import associate
from rgbdslam.evaluation.ate import ate, umeyama_alignment
from rgbdslam.evaluation.report import evaluate_files, evaluate_trajectories
from rgbdslam.evaluation.rpe import delta_pairs, rpe
from rgbdslam.io.trajectory import Trajectory, read_tum, write_tum


def tum_associate_reference(ts_a, ts_b, max_difference, offset=0.0):
    """Literal transcription of TUM associate.py (quadratic), on indices."""
    cands = sorted(
        (abs(a - (b + offset)), a, b, i, j)
        for i, a in enumerate(ts_a)
        for j, b in enumerate(ts_b)
        if abs(a - (b + offset)) < max_difference
    )
    free_a, free_b, out = set(range(len(ts_a))), set(range(len(ts_b))), []
    for _, a, b, i, j in cands:
        if i in free_a and j in free_b:
            free_a.remove(i)
            free_b.remove(j)
            out.append((a, b, i, j))
    out.sort()
    return [o[2] for o in out], [o[3] for o in out]


def straight_line(n: int, step: np.ndarray, dt: float = 0.1, rot_step_deg: float = 0.0) -> Trajectory:
    """Poses moving by ``step`` (world frame) per frame, rotating about z by ``rot_step_deg``."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = np.arange(n)[:, None] * np.asarray(step, dtype=float)
    poses[:, :3, :3] = Rotation.from_euler("z", (np.arange(n) * rot_step_deg)[:, None], degrees=True).as_matrix()
    return Trajectory(np.arange(n) * dt, poses)


def wavy(n: int = 60, seed: int = 0) -> Trajectory:
    """A non-degenerate 3-D trajectory (positions span all three axes)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.05
    pos = np.stack([np.sin(t), np.cos(0.7 * t), 0.3 * t], axis=1) + rng.normal(0, 0.01, (n, 3))
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.3, (n, 3))).as_matrix()
    poses[:, :3, 3] = pos
    return Trajectory(1000.0 + t, poses)


# ----------------------------------------------------------------------------- association


def test_associate_hand_made_greedy_with_conflicts():
    # a=1.10 has two candidates (b=1.095 at 5 ms, b=1.102 at 2 ms): the closer one wins.
    # b=2.005 is wanted by a=2.000 (5 ms) and a=2.008 (3 ms): one-to-one, the closer one wins.
    # a=1.20 has no candidate within 20 ms (b=1.30 is 100 ms away).
    ts_a = [1.00, 1.10, 1.20, 2.000, 2.008]
    ts_b = [1.005, 1.095, 1.102, 1.30, 2.005]
    ia, ib = associate(ts_a, ts_b, max_difference=0.02)
    assert ia.tolist() == [0, 1, 4]
    assert ib.tolist() == [0, 2, 4]
    # The strict '<': a pair exactly max_difference apart is not a candidate.
    ia, ib = associate([0.0], [0.5], max_difference=0.5)
    assert len(ia) == 0
    # With offset 0.1 s added to b, b=1.005 (-> 1.105) is the best match of a=1.10 (5 ms).
    ia, ib = associate([1.10], [1.005, 1.10], max_difference=0.02, offset=0.1)
    assert ia.tolist() == [0] and ib.tolist() == [0]


def test_associate_long_conflict_chain_matches_greedy():
    # Stamps alternate b, a, b, a, ... with slowly growing gaps (all < max_difference, every
    # stamp conflicts with both neighbours): greedy takes gap 1, 3, 5, ... i.e. b_k with a_k.
    # Resolving this needs ~n rounds, so it also exercises the sequential fallback.
    n = 60
    gaps = 0.010 + 1e-5 * np.arange(2 * n - 1)
    p = np.concatenate([[0.0], np.cumsum(gaps)])
    ts_b, ts_a = p[0::2], p[1::2]
    ia, ib = associate(ts_a, ts_b, max_difference=0.015)
    assert ia.tolist() == list(range(n)) and ib.tolist() == list(range(n))
    assert (ia.tolist(), ib.tolist()) == tuple(map(list, tum_associate_reference(ts_a, ts_b, 0.015)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_associate_equals_tum_reference_on_dense_random_stamps(seed):
    rng = np.random.default_rng(seed)
    ts_a = np.round(rng.uniform(0, 2, 150), 3)  # rounding creates exact ties
    ts_b = np.round(rng.uniform(0, 2, 120), 3)
    ia, ib = associate(ts_a, ts_b, max_difference=0.02, offset=0.004)
    ra, rb = tum_associate_reference(ts_a.tolist(), ts_b.tolist(), 0.02, 0.004)
    assert ia.tolist() == ra and ib.tolist() == rb


def test_associate_is_fast_on_1e5_stamps():
    rng = np.random.default_rng(0)
    ts_a = np.cumsum(rng.uniform(0.005, 0.015, 100_000))
    ts_b = np.cumsum(rng.uniform(0.005, 0.015, 100_000))
    t0 = time.perf_counter()
    ia, ib = associate(ts_a, ts_b, max_difference=0.02)
    elapsed = time.perf_counter() - t0
    assert elapsed < 3.0, f"associate took {elapsed:.2f} s"
    assert len(np.unique(ia)) == len(ia) == len(np.unique(ib)) > 80_000
    assert np.all(np.abs(ts_a[ia] - ts_b[ib]) < 0.02)
    assert np.all(np.diff(ts_a[ia]) > 0)


# ----------------------------------------------------------------------------------- ATE


def test_ate_identical_is_zero():
    gt = wavy()
    r = ate(gt, gt)
    assert r.n_pairs == len(gt)
    assert r.rmse < 1e-12 and r.max < 1e-12


def test_align_recovers_known_similarity():
    rng = np.random.default_rng(3)
    model = rng.normal(size=(3, 40))
    R = Rotation.from_rotvec([0.3, -0.5, 1.1]).as_matrix()
    t = np.array([1.0, -2.0, 0.5])
    data = 2.5 * R @ model + t[:, None]
    R2, t2, s2 = umeyama_alignment(model, data, "sim3")
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-12)
    assert s2 == pytest.approx(2.5, abs=1e-12)
    R3, t3, s3 = umeyama_alignment(model, R @ model + t[:, None], "se3")
    np.testing.assert_allclose(R3, R, atol=1e-12)
    np.testing.assert_allclose(t3, t, atol=1e-12)
    assert s3 == 1.0


def test_ate_rigid_offset_removed_by_se3_but_not_by_none():
    gt = wavy()
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.2, 0.4, -0.9]).as_matrix()
    T[:3, 3] = [3.0, -1.0, 2.0]
    est = Trajectory(gt.timestamps, T @ gt.poses)
    r = ate(gt, est, align="se3")
    assert r.rmse < 1e-9
    # the returned transform maps the estimate back onto gt
    np.testing.assert_allclose(r.transform, np.linalg.inv(T), atol=1e-9)
    np.testing.assert_allclose(r.aligned.poses, gt.poses, atol=1e-9)
    # no alignment, a pure translation offset: every error is exactly |offset|
    shifted = gt.poses.copy()
    shifted[:, :3, 3] += [0.3, 0.0, 0.4]
    r = ate(gt, Trajectory(gt.timestamps, shifted), align="none")
    np.testing.assert_allclose(r.errors, 0.5, atol=1e-12)
    assert r.rmse == pytest.approx(0.5) and r.std == pytest.approx(0.0, abs=1e-12)


def test_ate_scale_removed_only_by_sim3():
    gt = wavy()
    poses = gt.poses.copy()
    poses[:, :3, 3] *= 0.5
    est = Trajectory(gt.timestamps, poses)
    assert ate(gt, est, align="se3").rmse > 0.05
    r = ate(gt, est, align="sim3")
    assert r.rmse < 1e-9
    assert r.scale == pytest.approx(2.0, abs=1e-9)


def test_ate_no_overlap_raises_with_hint():
    gt = wavy()
    est = Trajectory(gt.timestamps + 100.0, gt.poses)
    with pytest.raises(InputError, match="no overlapping timestamps.*--offset"):
        ate(gt, est)
    # ...and the offset option is the fix
    assert ate(gt, est, offset=-100.0).rmse < 1e-9


# ----------------------------------------------------------------------------------- RPE


def test_rpe_constant_translation_drift_hand_worked():
    # gt moves 1.0 m per frame along x, the estimate 1.1 m: every 1-frame pair is off by
    # exactly 0.1 m, every 3-frame pair by 0.3 m; no rotation error.
    gt = straight_line(20, [1.0, 0, 0])
    est = straight_line(20, [1.1, 0, 0])
    r = rpe(gt, est, delta=1, delta_unit="f")
    assert r.n_pairs == 19
    np.testing.assert_allclose(r.trans_errors, 0.1, atol=1e-12)
    assert r.trans.rmse == pytest.approx(0.1) and r.rot.max == pytest.approx(0.0, abs=1e-9)
    r3 = rpe(gt, est, delta=3, delta_unit="f")
    assert r3.n_pairs == 17
    np.testing.assert_allclose(r3.trans_errors, 0.3, atol=1e-12)
    # frames are 0.1 s apart: 1 s = 10 frames -> 1.0 m drift per second, 10 pairs
    rs = rpe(gt, est, delta=1.0, delta_unit="s")
    assert rs.n_pairs == 10
    np.testing.assert_allclose(rs.trans_errors, 1.0, atol=1e-9)
    # 5 m along gt = 5 frames -> 0.5 m error
    rm = rpe(gt, est, delta=5.0, delta_unit="m")
    np.testing.assert_allclose(rm.trans_errors, 0.5, atol=1e-9)
    assert rm.n_pairs == 15


def test_rpe_rotation_drift_hand_worked():
    # both stand still; the estimate turns 2 deg per frame about z, gt does not
    gt = straight_line(10, [0, 0, 0])
    est = straight_line(10, [0, 0, 0], rot_step_deg=2.0)
    r = rpe(gt, est, delta=2, delta_unit="f")
    np.testing.assert_allclose(r.rot_errors, 4.0, atol=1e-9)
    assert r.trans.max == pytest.approx(0.0, abs=1e-12)


def test_rpe_is_measured_in_the_body_frame():
    # E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) compares the motions in each trajectory's own body frame.
    # gt: heading 0, 1 m per frame along world x. est: the same world positions, but the camera
    # is yawed by a constant 90 deg, so in its body frame the same world step is [0, -1, 0]
    # (Rz(90)^T [1, 0, 0]). Body frame: E = (I, [0,-1,0] - [1,0,0]) -> trans sqrt(2), rot 0.
    # A world-frame comparison (t_j - t_i of each, and R_j R_i^T) would give 0 and 0.
    gt = straight_line(6, [1.0, 0, 0])
    est_poses = gt.poses.copy()
    est_poses[:, :3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    r = rpe(gt, Trajectory(gt.timestamps, est_poses), delta=1, delta_unit="f")
    assert r.n_pairs == 5
    np.testing.assert_allclose(r.trans_errors, np.sqrt(2.0), atol=1e-12)
    np.testing.assert_allclose(r.rot_errors, 0.0, atol=1e-9)
    # 2-frame pairs: body steps [2,0,0] (gt) and [0,-2,0] (est) -> 2 sqrt(2)
    r2 = rpe(gt, Trajectory(gt.timestamps, est_poses), delta=2, delta_unit="f")
    np.testing.assert_allclose(r2.trans_errors, 2.0 * np.sqrt(2.0), atol=1e-12)
    # the converse: est turns 90 deg per frame and steps 1 m along its own x each frame (world
    # positions differ from gt's), gt steps 1 m along x without turning: same body-frame
    # translation, so trans 0 (world frame: |[0,1,0] - [1,0,0]| etc. would not be 0); rot 90.
    step = np.eye(4)
    step[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    step[:3, 3] = [1.0, 0, 0]
    spin = np.stack([np.linalg.matrix_power(step, k) for k in range(6)])
    assert np.linalg.norm(spin[2, :3, 3] - spin[1, :3, 3] - [1.0, 0, 0]) > 1.0  # world steps differ
    r3 = rpe(gt, Trajectory(gt.timestamps, spin), delta=1, delta_unit="f")
    np.testing.assert_allclose(r3.trans_errors, 0.0, atol=1e-12)
    np.testing.assert_allclose(r3.rot_errors, 90.0, atol=1e-9)


def test_rpe_error_product_order():
    # gt: Q_rel = (I, [1,0,0]) per frame. est: P_rel = (Rz(10 deg), [1,0,0]) per frame, i.e. the
    # same body-frame step plus an extra turn. E = Q_rel^-1 P_rel = (Rz(10), 0): trans 0, rot 10.
    # (TUM's script order P_rel Q_rel^-1 would give trans |[1,0,0] - Rz(10)[1,0,0]| = 2 sin 5deg.)
    n = 8
    step = np.eye(4)
    step[:3, :3] = Rotation.from_euler("z", 10, degrees=True).as_matrix()
    step[:3, 3] = [1.0, 0, 0]
    est_poses = np.stack([np.linalg.matrix_power(step, k) for k in range(n)])
    gt = straight_line(n, [1.0, 0, 0])
    r = rpe(gt, Trajectory(gt.timestamps, est_poses), delta=1, delta_unit="f")
    np.testing.assert_allclose(r.trans_errors, 0.0, atol=1e-12)
    np.testing.assert_allclose(r.rot_errors, 10.0, atol=1e-9)


def test_delta_pairs_seconds_take_first_stamp_at_or_after():
    stamps = np.array([0.0, 0.4, 0.9, 1.0, 1.6, 1.95])
    poses = np.tile(np.eye(4), (6, 1, 1))
    pairs = delta_pairs(stamps, poses, 1.0, "s")
    # 0.0 -> 1.0 (idx 3, exactly delta), 0.4 -> 1.6 (idx 4), 0.9 -> 1.95 (idx 5), later: none
    assert pairs.tolist() == [[0, 3], [1, 4], [2, 5]]
    with pytest.raises(InputError, match="whole number"):
        delta_pairs(stamps, poses, 1.5, "f")
    with pytest.raises(InputError, match="unit"):
        delta_pairs(stamps, poses, 1.0, "h")


def test_report_without_rpe_pairs_keeps_ate():
    gt = straight_line(5, [1.0, 0, 0])
    rep = evaluate_trajectories(gt, gt, delta=10, delta_unit="f")
    assert rep.rpe is None and "no RPE pairs" in rep.rpe_note
    assert rep.ate.rmse < 1e-12
    assert rep.to_dict()["rpe"] is None


# ------------------------------------------------------------------- parity with evo (real data)


def make_perturbed_estimate(rpy200: Path, out: Path) -> Path:
    """gt at the rgb stamps, seeded random-walk drift + a rigid transform, stamps jittered <= 3 ms."""
    gt = read_tum(rpy200 / "groundtruth.txt")
    rgb = np.array([float(line.split()[0]) for line in (rpy200 / "rgb.txt").read_text().splitlines()
                    if line.strip() and not line.startswith("#")])
    ia, _ = associate(gt.timestamps, rgb, 0.02)
    sub = gt.subset(ia)
    rng = np.random.default_rng(42)
    poses = sub.poses.copy()
    poses[:, :3, 3] += np.cumsum(rng.normal(0, 0.003, (len(poses), 3)), axis=0)
    drift_rot = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.002, (len(poses), 3)), axis=0)).as_matrix()
    poses[:, :3, :3] = drift_rot @ poses[:, :3, :3]
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    T[:3, 3] = [1.0, 2.0, 3.0]
    stamps = sub.timestamps + rng.uniform(-0.003, 0.003, len(sub))
    path = out / "est.tum"
    write_tum(Trajectory(stamps, T @ poses), path)
    return path


@pytest.mark.data
def test_parity_with_evo_on_real_data(rpy200, tmp_path):
    from evo.core import metrics, sync
    from evo.core.metrics import PoseRelation, StatisticsType, Unit
    from evo.tools import file_interface as evo_file  # evo is a pinned test dependency: no skip

    gt_path = rpy200 / "groundtruth.txt"
    est_path = make_perturbed_estimate(rpy200, tmp_path)
    ref_e = evo_file.read_tum_trajectory_file(str(gt_path))
    est_e = evo_file.read_tum_trajectory_file(str(est_path))
    ref_s, est_s = sync.associate_trajectories(ref_e, est_e, max_diff=0.02)

    # Precondition: on this data evo's nearest-stamp association gives TUM's greedy pairs.
    gt, est = read_tum(gt_path), read_tum(est_path)
    ia, ib = associate(gt.timestamps, est.timestamps, 0.02)
    assert len(ia) == len(est) == ref_s.num_poses
    np.testing.assert_array_equal(gt.timestamps[ia], ref_s.timestamps)
    np.testing.assert_array_equal(est.timestamps[ib], est_s.timestamps)

    # RPE (evo: delta 1 frame, consecutive pairs == all pairs for delta 1), before alignment
    ours_rpe = rpe(gt, est, delta=1, delta_unit="f")
    for relation, ours_stat in ((PoseRelation.translation_part, ours_rpe.trans),
                                (PoseRelation.rotation_angle_deg, ours_rpe.rot)):
        m = metrics.RPE(relation, delta=1, delta_unit=Unit.frames, all_pairs=False)
        m.process_data((ref_s, est_s))
        assert ours_stat.rmse == pytest.approx(m.get_statistic(StatisticsType.rmse), abs=1e-6)
        assert ours_stat.mean == pytest.approx(m.get_statistic(StatisticsType.mean), abs=1e-6)
    assert ours_rpe.n_pairs == len(ref_s.timestamps) - 1

    for correct_scale, mode in ((False, "se3"), (True, "sim3")):
        est_a = sync.associate_trajectories(ref_e, est_e, max_diff=0.02)[1]
        est_a.align(ref_s, correct_scale=correct_scale)
        ape = metrics.APE(PoseRelation.translation_part)
        ape.process_data((ref_s, est_a))
        ours = ate(gt, est, max_difference=0.02, align=mode)
        assert ours.rmse == pytest.approx(ape.get_statistic(StatisticsType.rmse), abs=1e-6)
        assert ours.max == pytest.approx(ape.get_statistic(StatisticsType.max), abs=1e-6)
        assert ours.rmse > 0.005  # the perturbation is really there


# ----------------------------------------------------------------------------------- CLI


def _out(result) -> str:
    """stdout and stderr as the user sees them (click >= 8.2 interleaves both in ``output``)."""
    return result.output


def _assert_one_line_error(result, *names: str) -> str:
    """The CLI turned a RgbdslamError into exit code 2 and one ``error: ...`` line on stderr
    naming ``names``. An uncaught exception would instead be ``result.exception`` itself
    (exit code 1), and click's own usage errors print several lines."""
    assert isinstance(result.exception, SystemExit), repr(result.exception)
    assert result.exit_code == 2 and result.exception.code == 2, (result.exit_code, _out(result))
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert [ln for ln in _out(result).splitlines() if ln.strip()] == lines  # nothing else printed
    for name in names:
        assert name in lines[0], (name, lines[0])
    return lines[0]


@pytest.mark.data
def test_cli_evaluate_writes_json_and_plots(rpy200, tmp_path):
    est_path = make_perturbed_estimate(rpy200, tmp_path)
    gt_path = rpy200 / "groundtruth.txt"
    res = CliRunner().invoke(main, ["evaluate", str(gt_path), str(est_path), "--json", str(tmp_path / "e.json"),
                                    "--delta", "1", "--delta-unit", "s"])
    assert res.exit_code == 0, _out(res)
    assert "ATE (m)" in res.output and "RPE trans (m)" in res.output
    data = json.loads((tmp_path / "e.json").read_text())
    lib = evaluate_files(gt_path, est_path, delta=1, delta_unit="s")
    assert data["ate"]["rmse"] == pytest.approx(lib.ate.rmse, abs=1e-12)
    assert data["rpe"]["trans"]["rmse"] == pytest.approx(lib.rpe.trans.rmse, abs=1e-12)
    assert data["rpe"]["delta_unit"] == "s" and data["ate"]["n_pairs"] == 200
    # plots only when asked (as evo): none without --plot-dir
    assert not list(tmp_path.rglob("*.png"))
    # the names --help gives for one estimate
    res = CliRunner().invoke(main, ["evaluate", str(gt_path), str(est_path), "--plot-dir", str(tmp_path / "p")])
    assert res.exit_code == 0, _out(res)
    assert sorted(p.name for p in (tmp_path / "p").iterdir()) == ["ate_over_time.png", "ate_topview.png",
                                                                  "rpe_over_time.png"]
    for png in (tmp_path / "p").iterdir():
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    # long paths are printed whole on their own lines, never folded into a table title
    lines = res.stdout.splitlines()
    assert f"estimate: {est_path}" in lines and f"ground truth: {gt_path}" in lines


def test_cli_missing_file_one_line_error(tmp_path):
    gt = tmp_path / "gt.tum"
    write_tum(straight_line(5, [1.0, 0, 0]), gt)
    res = CliRunner().invoke(main, ["evaluate", str(gt), str(tmp_path / "nope.tum"), "--no-plots"])
    _assert_one_line_error(res, str(tmp_path / "nope.tum"))


def test_cli_malformed_line_names_file_and_line(tmp_path):
    gt = tmp_path / "gt.tum"
    write_tum(straight_line(5, [1.0, 0, 0]), gt)
    bad = tmp_path / "bad.tum"
    lines = gt.read_text().splitlines()
    lines[3] = "0.2 1.0 0.0 0.0 0.0 0.0 zero 1.0"
    bad.write_text("\n".join(lines) + "\n")
    res = CliRunner().invoke(main, ["evaluate", str(gt), str(bad), "--no-plots"])
    _assert_one_line_error(res, f"{bad}:4")


def test_cli_no_overlap_clear_message(tmp_path):
    gt, est = tmp_path / "gt.tum", tmp_path / "est.tum"
    traj = straight_line(5, [1.0, 0, 0])
    write_tum(traj, gt)
    write_tum(Trajectory(traj.timestamps + 50.0, traj.poses), est)
    res = CliRunner().invoke(main, ["evaluate", str(gt), str(est), "--no-plots"])
    _assert_one_line_error(res, "no overlapping timestamps", str(gt), str(est))
    assert not list(tmp_path.glob("*.png"))


@pytest.mark.data
def test_cli_evaluate_compares_several_estimates(rpy200, tmp_path):
    """`rgbdslam evaluate GT EST EST ...`: one row per estimate, numbers equal to evaluating each alone."""
    gt_path = rpy200 / "groundtruth.txt"
    (tmp_path / "runA").mkdir()
    (tmp_path / "runB").mkdir()
    est_a = make_perturbed_estimate(rpy200, tmp_path / "runA")
    gt = read_tum(gt_path)
    shifted = gt.poses.copy()
    shifted[:, 0, 3] += 0.01 * np.cos(np.arange(len(gt)))  # a different, larger error
    est_b = tmp_path / "runB" / est_a.name
    write_tum(Trajectory(gt.timestamps, shifted), est_b)
    res = CliRunner().invoke(main, ["evaluate", str(gt_path), str(est_a), str(est_b), "--json",
                                    str(tmp_path / "c.json"), "--plot-dir", str(tmp_path / "plots")])
    assert res.exit_code == 0, _out(res)
    # the two files share a name: the table tells them apart by their folders
    assert f"runA/{est_a.name}" in res.output and f"runB/{est_a.name}" in res.output
    data = json.loads((tmp_path / "c.json").read_text())
    assert [e["estimate"] for e in data["estimates"]] == [str(est_a), str(est_b)]
    for e, path in zip(data["estimates"], (est_a, est_b)):
        alone = evaluate_files(gt_path, path)
        assert e["ate"]["rmse"] == pytest.approx(alone.ate.rmse, abs=1e-12)
        assert e["rpe"]["rot"]["rmse"] == pytest.approx(alone.rpe.rot.rmse, abs=1e-12)
    assert data["estimates"][0]["ate"]["rmse"] != data["estimates"][1]["ate"]["rmse"]
    # one overlay and each estimate's own plots, prefixed so that they do not overwrite each other
    pngs = sorted(p.name for p in (tmp_path / "plots").glob("*.png"))
    assert "comparison_topview.png" in pngs
    stem = est_a.stem
    assert {f"runA_{stem}_ate_topview.png", f"runB_{stem}_ate_topview.png"} <= set(pngs)


def test_cli_evaluate_same_estimate_twice_is_one_line(tmp_path):
    gt = tmp_path / "gt.tum"
    write_tum(straight_line(5, [1.0, 0, 0]), gt)
    res = CliRunner().invoke(main, ["evaluate", str(gt), str(gt), str(gt), "--no-plots"])
    _assert_one_line_error(res, f"estimate file {gt} is given twice")


def test_short_names_are_the_shortest_distinct_suffixes():
    from rgbdslam.evaluation.report import _short_names

    assert _short_names(["x/a.tum", "y/b.tum"]) == ["a.tum", "b.tum"]
    assert _short_names(["r/run1/trajectory.tum", "r/run2/trajectory.tum"]) == ["run1/trajectory.tum",
                                                                               "run2/trajectory.tum"]
    assert _short_names(["a/t.tum", "b/a/t.tum"]) == ["a/t.tum", "b/a/t.tum"]


# ------------------------------------------------------------------- degenerate inputs (one line each)


def test_cli_fewer_than_three_pairs_is_rejected_for_alignment(tmp_path):
    """One associated pose used to give "ATE 0.0000" (an SE(3) fit to one pose is exact)."""
    gt, one, two = tmp_path / "gt.tum", tmp_path / "one_pose.tum", tmp_path / "two.tum"
    traj = wavy(20)
    write_tum(traj, gt)
    write_tum(traj.subset(np.array([3])), one)
    write_tum(traj.subset(np.array([3, 9])), two)
    res = CliRunner().invoke(main, ["evaluate", str(gt), str(one), "--no-plots"])
    assert _assert_one_line_error(res) == (
        f"error: {gt} and {one}: only 1 pose pair matched in time, but SE(3) alignment needs at least 3 (it would "
        f"fit fewer almost exactly, so the ATE would mean nothing); check that both files are of the same sequence, "
        f"raise --max-difference, or use --align none")
    res = CliRunner().invoke(main, ["evaluate", str(gt), str(two), "--no-plots", "--align", "sim3"])
    assert "only 2 pose pairs matched in time, but Sim(3) alignment needs at least 3" in _assert_one_line_error(res)
    # without alignment one pair is a plain distance: allowed
    assert ate(traj, traj.subset(np.array([3])), align="none").n_pairs == 1
    assert not list(tmp_path.glob("*.png"))


def test_cli_sim3_with_static_ground_truth_is_rejected(tmp_path):
    """A ground truth that does not move used to give "scale 0.0000" (the estimate shrunk to a point)."""
    est_traj = wavy(30)
    static = np.tile(np.eye(4), (30, 1, 1))
    static[:, :3, 3] = [1.0, 2.0, 3.0]
    gt, est = tmp_path / "static.tum", tmp_path / "est.tum"
    write_tum(Trajectory(est_traj.timestamps, static), gt)
    write_tum(est_traj, est)
    res = CliRunner().invoke(main, ["evaluate", str(gt), str(est), "--align", "sim3", "--no-plots"])
    assert _assert_one_line_error(res) == (
        f"error: {gt} and {est}: the ground truth does not move (the spread of its 30 matched positions is below "
        f"1e-06 m), so the Sim(3) scale is undefined (it would come out as 0); use --align se3")
    # rigid alignment stays valid: the rotation is not unique, but every choice gives the same errors,
    # the estimate's distances from its own centroid
    r = ate(read_tum(gt), read_tum(est), align="se3")
    p = read_tum(est).positions
    np.testing.assert_allclose(r.errors, np.linalg.norm(p - p.mean(axis=0), axis=1), atol=1e-6)


@pytest.mark.parametrize("delta", ["inf", "nan", "-1"])
def test_cli_delta_must_be_finite_and_positive(tmp_path, delta):
    gt = tmp_path / "gt.tum"
    write_tum(wavy(10), gt)
    res = CliRunner().invoke(main, ["evaluate", str(gt), str(gt), "--delta", delta, "--no-plots"])
    shown = {"inf": "inf", "nan": "nan", "-1": "-1.0"}[delta]
    assert _assert_one_line_error(res) == f"error: RPE delta must be a finite positive number, got {shown}; pass e.g. --delta 1"
    # a huge whole number of frames simply has no pair (it used to overflow)
    assert len(delta_pairs(np.arange(5.0), np.tile(np.eye(4), (5, 1, 1)), 1e300, "f")) == 0


def test_cli_max_difference_must_be_finite(tmp_path):
    gt = tmp_path / "gt.tum"
    write_tum(wavy(10), gt)
    res = CliRunner().invoke(main, ["evaluate", str(gt), str(gt), "--max-difference", "inf", "--no-plots"])
    assert _assert_one_line_error(res) == "error: --max-difference must be a positive number of seconds (e.g. 0.02) up to 1e4; got inf"


def test_cli_duplicate_estimate_stamps_are_an_error(tmp_path):
    """Two poses at one time stamp used to be accepted silently (association took one of them)."""
    gt, est = tmp_path / "gt.tum", tmp_path / "dup.tum"
    traj = wavy(10)
    write_tum(traj, gt)
    lines = gt.read_text().splitlines()
    est.write_text("\n".join(lines + [lines[4], lines[4]]) + "\n")
    res = CliRunner().invoke(main, ["evaluate", str(gt), str(est), "--no-plots"])
    assert _assert_one_line_error(res) == (
        f"error: {gt} and {est}: the estimate has more than one pose at time stamp {traj.timestamps[3]:.6f} (and 1 "
        f"more repeat); a trajectory needs one pose per time stamp: remove the duplicate lines")


def test_cli_compare_checks_every_estimate_before_writing(tmp_path):
    gt, good, bad = tmp_path / "gt.tum", tmp_path / "good.tum", tmp_path / "one.tum"
    traj = wavy(20)
    write_tum(traj, gt)
    write_tum(traj, good)
    write_tum(traj.subset(np.array([0])), bad)
    res = CliRunner().invoke(main, ["evaluate", str(gt), str(good), str(bad), "--plot-dir", str(tmp_path / "p"),
                                    "--json", str(tmp_path / "c.json")])
    assert "only 1 pose pair matched in time" in _assert_one_line_error(res, str(bad))
    assert not (tmp_path / "p").exists() and not (tmp_path / "c.json").exists()


def test_a_written_trajectory_read_back_writes_the_same_bytes(tmp_path):
    """A rounding residue of ~1e-17 (a pose that is the identity up to rounding, as a fused first frame)
    prints as 0.000000000, not -0.000000000: its sign does not survive a read-back (the quaternion is
    recomputed from the matrix), so an export of the run's trajectory.tum would differ from the file."""
    P = np.tile(np.eye(4), (2, 1, 1))
    P[0, :3, :3] = Rotation.from_rotvec([-3e-17, -1e-17, -2e-17]).as_matrix()
    P[0, :3, 3] = [-1e-17, 0.0, -4e-12]
    P[1, :3, 3] = [0.25, -0.5, 1.0]
    write_tum(Trajectory(np.array([1.0, 2.0]), P), tmp_path / "a.tum")
    text = (tmp_path / "a.tum").read_text()
    assert "-0.000000000" not in text and "0.250000000 -0.500000000 1.000000000" in text
    write_tum(read_tum(tmp_path / "a.tum"), tmp_path / "b.tum")
    assert (tmp_path / "b.tum").read_bytes() == (tmp_path / "a.tum").read_bytes()


def test_as_written_is_exactly_what_read_tum_reads_back(tmp_path):
    """``as_written`` gives the poses of the written file bit for bit (the ones `fuse` and `evaluate` read),
    also for a pose that is the identity up to 1e-30 and for rounding residues of both signs."""
    from rgbdslam.io.trajectory import Trajectory, as_written, format_tum, read_tum, write_tum

    rng = np.random.default_rng(3)
    poses = np.tile(np.eye(4), (6, 1, 1))
    poses[0, :3, :3] += rng.normal(0, 1e-30, (3, 3))
    poses[1, :3, 3] = [-1e-17, 2e-10, -6e-10]
    for k in range(2, 6):
        poses[k, :3, :3] = Rotation.from_rotvec(rng.normal(0, 1, 3)).as_matrix()
        poses[k, :3, 3] = rng.normal(0, 3, 3)
    traj = Trajectory(1600000000.0 + 0.033 * np.arange(6), poses)
    write_tum(traj, tmp_path / "t.tum")
    back = read_tum(tmp_path / "t.tum")
    mine = as_written(traj)
    assert np.array_equal(mine.timestamps, back.timestamps)
    assert np.array_equal(mine.poses, back.poses)
    assert not np.array_equal(mine.poses, traj.poses)  # it is the file's rounding, not the input
    assert format_tum(mine) == format_tum(traj)
    assert np.array_equal(mine.poses[0], np.eye(4))
