"""The MASAT paper's benchmark protocol: noise, convergence tests, tables, a tiny real run."""

from __future__ import annotations

import csv
import os

import numpy as np
import pytest

from rgbdslam.posegraph.graph import se2_between
from rgbdslam.posegraph.convergence import has_converged
from rgbdslam.posegraph.factors import chi2, degrees_of_freedom
from rgbdslam.posegraph.optimize import gauss_newton
from rgbdslam.posegraph.bench import (NOISE_LEVELS, first_convergence, noisy_instance, parse_noise,
                                              run_benchmark)
from rgbdslam.posegraph.synthetic import manhattan_world as manhattan_like
from rgbdslam.errors import InputError

from tests.conftest import DATA, need

def test_parse_noise():
    assert parse_noise("0.2,0.2,0.2") == [(0.2, 0.2, 0.2)]
    assert parse_noise("0.1") == [(0.1, 0.1, 0.1)]
    assert parse_noise("0.1;0.15,0.15,0.3") == [(0.1, 0.1, 0.1), (0.15, 0.15, 0.3)]
    assert parse_noise("all") == list(NOISE_LEVELS) and len(NOISE_LEVELS) == 8
    for bad, match in (("abc", r"--noise 'abc' is not 'all' or numbers like 0\.2,0\.2,0\.2"),
                       ("0.1,0.2", r"--noise '0\.1,0\.2' needs three positive standard deviations"),
                       ("-0.1,0.1,0.1", r"--noise '-0\.1,0\.1,0\.1' needs three positive standard deviations"),
                       ("0.1;0,0.1,0.1", r"--noise '0,0\.1,0\.1' needs three positive")):  # names the bad level
        with pytest.raises(InputError, match=match):
            parse_noise(bad)


def test_noisy_instance_statistics_and_information():
    ref, _ = manhattan_like(400)
    sig = (0.1, 0.2, 0.05)
    a = noisy_instance(ref, sig, np.random.default_rng(7))
    b = noisy_instance(ref, sig, np.random.default_rng(7))
    np.testing.assert_array_equal(a.meas, b.meas)  # seeded
    d = a.meas - ref.meas
    d[:, 2] = np.angle(np.exp(1j * d[:, 2]))
    np.testing.assert_allclose(d.std(axis=0), sig, rtol=0.15)
    np.testing.assert_allclose(a.info[5], np.diag([100.0, 25.0, 400.0]))
    np.testing.assert_array_equal(ref.meas, se2_between(ref.poses[ref.edges_i], ref.poses[ref.edges_j]))


def test_convergence_tests_on_hand_histories():
    assert has_converged(1000.0, 1000.0 - 5e-4, 1e-6, "relative")  # 5e-7 relative
    assert not has_converged(1000.0, 1000.0 - 5e-4, 1e-6, "absolute")
    assert has_converged(1000.0, 1000.0 - 5e-7, 1e-6, "absolute")
    assert not has_converged(float("nan"), 1.0, 1e-6, "absolute")
    # a graph that fits exactly: chi2 jitters around 1e-28, a 50 % relative change; at the rounding
    # floor (chi2_floor) it passes, and a real change above the floor still fails it
    assert has_converged(2e-28, 1e-28, 1e-6, "relative", floor=1e-20)
    assert not has_converged(2e-28, 1e-28, 1e-6, "relative")  # no floor: g2o's purely relative test
    assert not has_converged(0.5, 0.4, 1e-6, "relative", floor=1e-20)
    assert not has_converged(2.0, 1.0, 1e-6, "relative", floor=1e-20)
    # scale-free: the verdict does not change when chi2 (and its floor) are multiplied by 1e-8
    for prev, cur, floor in ((1000.0, 1000.0 - 5e-4, 1e-20), (0.5, 0.4, 1e-20), (2e-28, 1e-28, 1e-20)):
        assert has_converged(prev, cur, 1e-6, "relative", floor) == \
            has_converged(prev * 1e-8, cur * 1e-8, 1e-6, "relative", floor * 1e-8)


def test_noise_free_graph_from_ground_truth_converges_at_once():
    """Exact measurements, exact start: chi2 ~ 0; the first iteration must report convergence."""
    from rgbdslam.posegraph.graph import PoseGraphData

    rng = np.random.default_rng(3)
    poses = np.column_stack([rng.uniform(-5, 5, 12), rng.uniform(-5, 5, 12), rng.uniform(-3, 3, 12)])
    i = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 0, 3, 5])
    j = np.array([1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 6, 9, 11])
    g = PoseGraphData(dim=2, ids=np.arange(12), poses=poses, edges_i=i, edges_j=j,
                  meas=se2_between(poses[i], poses[j]), info=np.tile(np.eye(3) * 100.0, (len(i), 1, 1)))
    res = gauss_newton(g, poses, max_iter=50)
    assert res.chi2_final < 1e-12
    assert res.converged and res.iterations == 1
    hist = [100.0, 50.0, 40.0, 40.0 - 1e-5, 40.0 - 1e-5 - 1e-8]
    assert first_convergence(hist, 1e-6, "relative") == (True, 3, 40.0 - 1e-5)
    assert first_convergence(hist, 1e-6, "absolute") == (True, 4, hist[4])
    assert first_convergence(hist[:3], 1e-6, "absolute") == (False, 2, 40.0)


def test_chi2_and_dof_hand_computed():
    ref, gt = manhattan_like(30)
    assert chi2(ref, gt) == pytest.approx(0.0, abs=1e-12)
    moved = gt.copy()
    moved[5:, 0] += 0.5  # breaks the edge 4->5 (and loop edges across 5) by 0.5 m in x of the world frame
    ei, ej = ref.edges_i, ref.edges_j
    crossing = np.sum((ei < 5) != (ej < 5))
    # each crossing edge's error has norm 0.5 in translation (rotated into the edge frame), information I
    assert chi2(ref, moved) == pytest.approx(0.25 * crossing, rel=1e-9)
    assert degrees_of_freedom(ref) == 3 * ref.n_edges - 3 * (ref.n_vertices - 1)


def test_gauss_newton_from_ground_truth_reaches_unit_reduced_chi2():
    ref, gt = manhattan_like(200, seed=1)
    g = noisy_instance(ref, (0.05, 0.05, 0.02), np.random.default_rng(0))
    r = gauss_newton(g, gt, max_iter=50)
    assert r.converged and r.iterations <= 8
    assert r.chi2_final < r.chi2_initial
    assert 0.6 < r.chi2_final / degrees_of_freedom(g) < 1.4
    assert np.all(np.diff(r.chi2_history) <= 1e-6 * r.chi2_history[0])


def test_tiny_benchmark_masat_converges_and_workers_do_not_change_results(tmp_path):
    ref, gt = manhattan_like(150, seed=2)
    kw = dict(instances=3, max_iter=50, seed=5, progress=False, reference=(ref, gt, "synthetic grid"),
              methods=("odometry", "masat", "weighted_masat", "ground_truth"))
    r1 = run_benchmark("m3500", [(0.05, 0.05, 0.05)], workers=1, out_dir=tmp_path, **kw)
    r2 = run_benchmark("m3500", [(0.05, 0.05, 0.05)], workers=2, **kw)
    k = lambda r: (r.instance, r.method, r.converged_rel, r.iterations_rel, round(r.reduced_chi2_rel, 9))  # noqa: E731
    assert [k(r) for r in r1["records"]] == [k(r) for r in r2["records"]]
    by = {(r.instance, r.method): r for r in r1["records"]}
    for i in range(3):
        for m in ("masat", "weighted_masat"):
            assert by[(i, m)].converged_rel
            assert by[(i, m)].reduced_chi2_rel == pytest.approx(by[(i, "ground_truth")].reduced_chi2_rel, rel=1e-4)
    rows = list(csv.DictReader(open(tmp_path / "table1.csv")))
    assert rows[0]["masat_rate"] == "1.0" and rows[0]["noise"] == "0.05,0.05,0.05"
    assert "Table 1" in (tmp_path / "report.md").read_text()


@pytest.mark.data
def test_real_m3500_masat_converges_at_low_noise(tmp_path):
    need(DATA / "posegraph" / "iSAM" / "groundtruth" / "manhattanOlson3500_groundtruth.txt")
    res = run_benchmark("m3500", [(0.1, 0.1, 0.1)], instances=2, workers=1, seed=0, progress=False,
                        data_dir=DATA, methods=("masat", "weighted_masat", "ground_truth"))
    recs = res["records"]
    assert len(recs) == 6
    for r in recs:
        assert r.converged_rel, r
        assert 0.9 < r.reduced_chi2_rel < 1.1
        assert r.iterations_rel <= 12
    assert "| 0.1,0.1,0.1 | 2 | 1.00 (1.00) | 1.00 | 1.00 (1.00) |" in res["report"]


def test_runs_csv_round_trip_and_merge(tmp_path):
    from rgbdslam.posegraph.bench import format_report, load_runs, merge_runs

    ref, gt = manhattan_like(80, seed=4)
    kw = dict(instances=2, seed=1, progress=False, reference=(ref, gt, "synthetic"), workers=1)
    a = run_benchmark("m3500", [(0.1, 0.1, 0.1)], out_dir=tmp_path / "a", methods=("masat", "ground_truth"), **kw)
    b = run_benchmark("m3500", [(0.1, 0.1, 0.1)], out_dir=tmp_path / "b", methods=("weighted_masat",), **kw)
    loaded = load_runs(tmp_path / "a" / "runs.csv")
    assert [(r.instance, r.method, r.converged_rel, r.iterations_rel) for r in loaded] == \
        [(r.instance, r.method, r.converged_rel, r.iterations_rel) for r in a["records"]]
    assert format_report(loaded, "m3500", ("masat", "ground_truth")) == \
        format_report(a["records"], "m3500", ("masat", "ground_truth"))
    rep = merge_runs([tmp_path / "a" / "runs.csv", tmp_path / "b" / "runs.csv"], tmp_path / "m")
    assert "| MASAT | w-MASAT | GT |" in rep
    assert len(load_runs(tmp_path / "m" / "runs.csv")) == 6
    assert b["records"][0].method == "weighted_masat"
    with pytest.raises(InputError, match="does not exist"):
        load_runs(tmp_path / "nope.csv")


def test_chunked_runs_reproduce_one_run(tmp_path):
    """--first-instance pieces give exactly the records of the same instances in one long run
    (the 50-instance tables in docs/benchmarks.md are merged from such pieces)."""
    ref, gt = manhattan_like(60, seed=5)
    kw = dict(seed=3, progress=False, reference=(ref, gt, "synthetic"), workers=1, methods=("odometry", "masat"))
    whole = run_benchmark("city10k", [(0.2, 0.2, 0.2)], instances=3, **kw)["records"]
    piece = run_benchmark("city10k", [(0.2, 0.2, 0.2)], instances=2, first_instance=1, **kw)["records"]
    key = lambda r: (r.instance, r.method, r.chi2_initial, r.converged_rel, r.iterations_rel, r.reduced_chi2_rel)  # noqa: E731
    assert [key(r) for r in piece] == [key(r) for r in whole if r.instance >= 1]
    assert {r.instance for r in piece} == {1, 2}
    # a different instance index is a different noise draw
    assert whole[0].chi2_initial != whole[2].chi2_initial


def test_optimum_rate_counts_only_runs_ending_at_ground_truths_chi2():
    from rgbdslam.posegraph.bench import RunRecord, format_report, summarise

    def rec(inst, method, conv, rchi2):
        return RunRecord("m3500", 0.2, 0.2, 0.2, inst, method, 10.0, conv, 5, rchi2, conv, 5, rchi2, 0.0, 0.0)

    records = [rec(0, "ground_truth", True, 1.000), rec(1, "ground_truth", True, 0.990),
               rec(0, "masat", True, 1.0005),  # within 0.1 % of GT's: at the optimum
               rec(1, "masat", True, 1.050),  # converged, but into a local minimum
               rec(0, "chordal", False, 1.000), rec(1, "chordal", True, 0.990)]
    S = summarise(records)
    s = (0.2, 0.2, 0.2)
    assert S[(s, "masat")]["rate"] == 1.0 and S[(s, "masat")]["opt_rate"] == 0.5
    assert S[(s, "chordal")]["rate"] == 0.5 and S[(s, "chordal")]["opt_rate"] == 0.5
    assert S[(s, "ground_truth")]["opt_rate"] == 1.0
    assert "| 0.2,0.2,0.2 | 0.50 | 0.50 | 1.00 |" in format_report(records, "m3500", ("masat", "chordal", "ground_truth"))
    # without ground-truth runs there is no reference: no Table 1c
    assert np.isnan(summarise(records[2:])[(s, "masat")]["opt_rate"])
    assert "Table 1c" not in format_report(records[2:], "m3500", ("masat", "chordal"))


def test_compare_to_paper_script(tmp_path, capsys):
    """benchmarks.masat.compare_to_paper: counts, Wilson interval and Fisher verdicts on hand-made runs."""
    from benchmarks.masat import compare_to_paper as mod
    from rgbdslam.posegraph.bench import RunRecord, compare_with_paper, format_report, write_outputs

    s = (0.15, 0.15, 0.3)  # City10k: the paper's MASAT 0.22 (11/50), ground truth 0.80 (40/50)

    def rec(inst, method, conv):
        return RunRecord("city10k", *s, inst, method, 10.0, conv, 5, 1.0, conv, 5, 1.0, 0.0, 0.0)

    records = ([rec(i, "masat", i < 11) for i in range(50)] + [rec(i, "weighted_masat", True) for i in range(50)]
               + [rec(i, "ground_truth", False) for i in range(50)])
    rows = {r["method"]: r for r in compare_with_paper(records, ["masat", "weighted_masat", "ground_truth"])}
    assert (rows["masat"]["k"], rows["masat"]["n"], rows["masat"]["p"], rows["masat"]["verdict"]) == (11, 50, 1.0, "same")
    assert rows["weighted_masat"]["paper_column"] == "masat" and rows["weighted_masat"]["verdict"] == "above"
    assert rows["ground_truth"]["verdict"] == "below" and rows["ground_truth"]["lo"] == pytest.approx(0.0, abs=1e-12)
    # Wilson upper bound of 0/n is z²/(n + z²)
    assert rows["ground_truth"]["hi"] == pytest.approx(1.959964 ** 2 / (50 + 1.959964 ** 2), rel=1e-5)
    # the bench report names the differences beyond sampling noise
    rep = format_report(records, "city10k", ("masat", "weighted_masat", "ground_truth"))
    assert ("0.15,0.15,0.3 w-MASAT 1.00 vs the paper's MASAT 0.22 (above, p = 0.000, "
            "Holm-adjusted over the table's 3 comparisons 0.000)") in rep
    assert "0.15,0.15,0.3 GT 0.00 vs 0.80 (below, p = 0.000, " in rep and "MASAT 0.22 vs" not in rep
    write_outputs(tmp_path, records, "city10k", ("masat", "weighted_masat", "ground_truth"), "report")
    assert mod.main([str(tmp_path / "runs.csv")]) == 0
    out = capsys.readouterr().out
    assert "| 0.15,0.15,0.3 | w-MASAT | 50/50 | 1.00 [0.93, 1.00] | 0.22 (MASAT) |" in out
    assert "3 comparisons at alpha 0.05, each cell on its own: 1 above, 1 same, 1 below the paper" in out
    assert "3 comparisons at alpha 0.05, Holm-adjusted over the table: 1 above, 1 same, 1 below the paper" in out
    assert mod.main([str(tmp_path / "nope.csv")]) == 2


def test_holm_adjustment_by_hand():
    """Holm–Bonferroni: sorted p (0.005, 0.01, 0.03, 0.04) times (4, 3, 2, 1) = (0.02, 0.03, 0.06, 0.04),
    then the running maximum (0.02, 0.03, 0.06, 0.06), returned in the input order."""
    from rgbdslam.posegraph.bench import RunRecord, compare_with_paper, holm_adjust

    np.testing.assert_allclose(holm_adjust([0.01, 0.04, 0.03, 0.005]), [0.03, 0.06, 0.06, 0.02])
    np.testing.assert_allclose(holm_adjust([0.5, 0.6]), [1.0, 1.0])  # capped at 1
    assert holm_adjust([]).shape == (0,)
    # a cell "below" on its own (p < 0.05) but not after adjusting over the table's cells
    s = [(0.15, 0.15, 0.3), (0.3, 0.3, 0.3)]  # M3500: the paper's MASAT 0.76 and 0.80

    def rec(k, inst, conv):
        return RunRecord("m3500", *s[k], inst, "masat", 10.0, conv, 5, 1.0, conv, 5, 1.0, 0.0, 0.0)

    recs = [rec(0, i, i < 27) for i in range(50)] + [rec(1, i, i < 40) for i in range(50)]
    rows = compare_with_paper(recs, ["masat"])
    assert [(r["k"], r["verdict"]) for r in rows] == [(40, "same"), (27, "below")]  # level order: 0.3 before (0.15,0.15,0.3)
    assert rows[1]["p"] < 0.05 and rows[1]["p_holm"] == pytest.approx(min(1.0, 2 * rows[1]["p"]))
    assert rows[0]["p_holm"] == pytest.approx(1.0) and rows[1]["verdict_holm"] == "same"  # 2 x 0.035 = 0.07


def test_paired_comparison_exact_mcnemar_by_hand():
    """8 instances where only A converged, none where only B did: p = 2 * 0.5**8 (two-sided)."""
    from benchmarks.masat.paper_stats import format_paired, paired_comparison
    from rgbdslam.posegraph.bench import RunRecord

    s = (0.2, 0.2, 0.2)

    def rec(inst, method, conv, rchi2=1.0):
        return RunRecord("m3500", *s, inst, method, 10.0, conv, 5, rchi2, conv, 5, rchi2, 0.0, 0.0)

    recs = ([rec(i, "weighted_masat", i < 10, 1.0 if i < 2 else 1.5) for i in range(20)]
            + [rec(i, "masat", i < 2) for i in range(20)] + [rec(i, "ground_truth", True) for i in range(20)])
    (row,) = paired_comparison(recs, "weighted_masat", "masat")
    c, o = row["converged"], row["optimum"]
    assert row["n"] == 20 and (c["rate_a"], c["rate_b"], c["only_a"], c["only_b"]) == (0.5, 0.1, 8, 0)
    assert c["p"] == pytest.approx(2 * 0.5 ** 8) and c["verdict"] == "weighted_masat better"
    # A's 8 extra runs end 50 % above ground truth's χ²: local minima, so at the optimum the two are equal
    assert (o["rate_a"], o["rate_b"], o["only_a"], o["only_b"], o["p"], o["verdict"]) == (0.1, 0.1, 0, 0, 1.0, "same")
    assert "| 0.2,0.2,0.2 | 20 | 0.50 / 0.10 | 8 / 0 | 0.008 | 0.10 / 0.10 | 0 / 0 | 1.000 |" in \
        format_paired([row], "weighted_masat", "masat")
    # without ground-truth runs there is no optimum to compare with
    assert paired_comparison(recs[:40], "weighted_masat", "masat")[0]["optimum"] is None


def test_cli_bench_without_dataset_is_a_usage_error(tmp_path):
    """``posegraph bench`` with neither --dataset nor --merge-runs: one line saying what is missing,
    exit code 2 (InputError, rgbdslam/cli.py), nothing run or written."""
    from click.testing import CliRunner

    from rgbdslam.cli import main

    res = CliRunner().invoke(main, ["posegraph", "bench", "--instances", "1", "-q", "--out", str(tmp_path / "o")])
    assert isinstance(res.exception, SystemExit) and res.exit_code == InputError.exit_code == 2, res.exception
    assert res.stdout == ""
    assert res.stderr == "error: --dataset is required (m3500, city10k or m10000) unless --merge-runs is given\n"
    assert not (tmp_path / "o").exists()
    # an unknown dataset is refused by click itself (also exit code 2, usage text on stderr)
    res = CliRunner().invoke(main, ["posegraph", "bench", "--dataset", "m999", "-q"])
    assert isinstance(res.exception, SystemExit) and res.exit_code == 2
    assert "Invalid value for '--dataset': 'm999' is not one of 'm3500', 'city10k', 'm10000'." in res.stderr


# ----------------------------------------------------------------------- input validation (one line)


from tests.conftest import assert_cli_error as _assert_cli_error, cli as _cli  # noqa: E402


@pytest.mark.parametrize("text,message", [
    ("nan", "--noise 'nan' needs three positive standard deviations sx,sy,stheta"),
    ("0.1,nan,0.1", "--noise '0.1,nan,0.1' needs three positive standard deviations sx,sy,stheta"),
    ("inf", "--noise 'inf' has an infinite standard deviation; give finite values like 0.2,0.2,0.2"),
    ("0.1;0.1,0.1,1e400", ("--noise '0.1,0.1,1e400' has an infinite standard deviation; give finite values like "
                           "0.2,0.2,0.2")),
    ("1e-200", ("--noise '1e-200' has a standard deviation so small that its information 1/σ² is not a usable "
                "number; give values like 0.2,0.2,0.2")),
    ("1e200", ("--noise '1e200' has a standard deviation so large that its information 1/σ² is not a usable "
               "number; give values like 0.2,0.2,0.2")),
])
def test_parse_noise_rejects_non_finite_and_unusable_levels(text, message):
    with pytest.raises(InputError) as e:
        parse_noise(text)
    assert str(e.value) == message


_METHODS = "odometry,spanning_tree,masat,weighted_masat,lago,chordal,ground_truth"


@pytest.mark.parametrize("args,message", [
    (["--seed", "-1"], "--seed must be a whole number >= 0, not -1; give e.g. --seed 0"),
    (["--methods", ","], f"--methods ',' names no initial guess; give a comma-separated list from {_METHODS}"),
    (["--methods", " "], f"--methods ' ' names no initial guess; give a comma-separated list from {_METHODS}"),
    (["--methods", "masat,magic"], f"--methods: unknown initial guess(es) magic; use {_METHODS}"),
    (["--noise", "nan"], "--noise 'nan' needs three positive standard deviations sx,sy,stheta"),
    (["--noise", "inf"], "--noise 'inf' has an infinite standard deviation; give finite values like 0.2,0.2,0.2"),
    (["--instances", "0"], "--instances must be a whole number >= 1, not 0"),
    (["--workers", "0"], "--workers must be a whole number >= 1, not 0"),
    (["--workers", "100000"], f"--workers 100000 is more than 4x this machine's {os.cpu_count()} CPUs; give at most "
                              f"{4 * (os.cpu_count() or 1)} (each worker holds a copy of the graph)"),
    (["--first-instance", "-1"], "--first-instance must be a whole number >= 0, not -1"),
    (["--max-iter", "0"], "--max-iter must be a whole number of at least 1, not 0; give e.g. --max-iter 50"),
    (["--timing-only", "--seed", "-2"], "--seed must be a whole number >= 0, not -2; give e.g. --seed 0"),
    (["--timing-only", "--methods", "ground_truth"],
     "--timing-only times initial guesses and ground_truth is none; add a method to --methods"),
])
def test_cli_bench_rejects_bad_numbers_and_method_lists(tmp_path, args, message):
    """Checked before any data is read (the data folder here does not exist) or anything is written."""
    out = tmp_path / "o"
    _assert_cli_error(_cli(["posegraph", "bench", "--dataset", "m3500", "-q", "--data", tmp_path / "nodata",
                            "--out", out, *args]), message)
    assert not out.exists()


def test_run_benchmark_validates_its_arguments():
    ref, gt = manhattan_like(30, seed=2)
    kw = {"instances": 1, "progress": False, "reference": (ref, gt, "synthetic")}
    for extra, message in (
            ({"methods": ()}, "no initial guesses to compare; give --methods from " + _METHODS),
            ({"methods": ("masat", "masat")}, "a benchmark method is listed twice in masat,masat; list each once"),
            ({"seed": -1}, "--seed must be a whole number >= 0, not -1; give e.g. --seed 0"),
            ({"tol": float("nan")}, "--tol must be a finite number above 0, not nan; give e.g. --tol 1e-6")):
        with pytest.raises(InputError) as e:
            run_benchmark("m3500", [(0.1, 0.1, 0.1)], **{"methods": ("masat",), **kw, **extra})
        assert str(e.value) == message
    with pytest.raises(InputError) as e:
        run_benchmark("m3500", [(0.1, float("nan"), 0.1)], methods=("masat",), **kw)
    assert str(e.value) == "noise level (0.1, nan, 0.1) needs three positive standard deviations sx,sy,stheta"
    with pytest.raises(InputError) as e:
        run_benchmark("m3500", [], methods=("masat",), **kw)
    assert str(e.value) == "no noise levels given; give --noise, e.g. 0.2,0.2,0.2 or all"


def test_cli_merge_runs_non_utf8_or_broken_csv_is_one_line(tmp_path):
    bad = tmp_path / "runs.csv"
    data = b"dataset,sigma_x\nm3500,0.1\xff\n"
    bad.write_bytes(data)
    _assert_cli_error(_cli(["posegraph", "bench", "--merge-runs", bad]),
                      f"benchmark runs file {bad} is not UTF-8 text (byte {data.index(bytes([0xFF]))}); "
                      "give the text file itself, not a binary or compressed copy")
    other = tmp_path / "other.csv"
    other.write_text("dataset,sigma_x\nm3500,0.1\n")
    _assert_cli_error(_cli(["posegraph", "bench", "--merge-runs", other]),
                      f"{other}:2: not a runs.csv row of rgbdslam posegraph bench; give the runs.csv of a bench "
                      "--out folder")


def test_noise_models_weigh_singular_and_projected_information_exactly():
    """GTSAM's Gaussian.Information factors Omega by Cholesky; for a singular Omega (a valid
    rank-deficient edge, or one the reader projected onto the PSD cone) the weights must still
    be e^T Omega e, which SqrtInformation(diag(sqrt w) V^T) gives exactly."""
    from rgbdslam.posegraph.factors import _dense_models

    rng = np.random.default_rng(4)
    A = rng.normal(size=(6, 3))
    singular = A @ A.T  # rank 3 of 6
    B = rng.normal(size=(6, 6))
    full = B @ B.T + np.eye(6)
    axis = np.diag([0.0, 0, 0, 4, 0, 0])  # a diagonal R with zeros (GTSAM's "smart" path refuses it)
    for omega in (singular, full, axis):
        model = _dense_models(omega[None])[0]
        for _ in range(5):
            e = rng.normal(size=6)
            assert np.sum(np.asarray(model.whiten(e)) ** 2) == pytest.approx(e @ omega @ e, rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("optimizer", ["gtsam", "g2o"])
def test_relative_criterion_is_scale_free(optimizer):
    """Information scaled by 1e-8 (issue 16, class 11): the same iterations, the same optimum and
    chi2 scaled by 1e-8; the old 'chi2 below 1 counts as 1' stopped such a graph after one step."""
    from rgbdslam.posegraph.graph import PoseGraphData as PoseGraph
    from rgbdslam.posegraph.initializers import initialize
    from rgbdslam.posegraph.optimize import run_gauss_newton

    rng = np.random.default_rng(7)
    n = 40
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    poses = np.column_stack([5 * np.cos(ang), 5 * np.sin(ang), ang + np.pi / 2])
    i = np.concatenate([np.arange(n - 1), [0, 5, 10]])
    j = np.concatenate([np.arange(1, n), [n - 1, 25, 30]])
    meas = se2_between(poses[i], poses[j]) + rng.normal(0, [0.05, 0.05, 0.03], (len(i), 3))
    info = np.tile(np.diag([400.0, 400.0, 1000.0]), (len(i), 1, 1))
    g = PoseGraph(dim=2, ids=np.arange(n), poses=poses, edges_i=i, edges_j=j, meas=meas, info=info)
    small = PoseGraph(dim=2, ids=np.arange(n), poses=poses, edges_i=i, edges_j=j, meas=meas, info=info * 1e-8)
    init = initialize(g, "odometry")
    a = run_gauss_newton(g, init, optimizer, max_iter=50, tol=1e-6, criterion="relative")
    b = run_gauss_newton(small, init, optimizer, max_iter=50, tol=1e-6, criterion="relative")
    assert a.converged and b.converged and a.iterations == b.iterations > 2
    np.testing.assert_allclose(b.chi2_final, a.chi2_final * 1e-8, rtol=1e-6)
    np.testing.assert_allclose(b.poses, a.poses, atol=1e-8)
