"""The SE(2) chordal initial guess: exact on consistent graphs, hand-worked least-squares answers."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from rgbdslam.posegraph.chordal2d import (chordal_headings, chordal_se2, positions_given_headings,
                                        refine_headings)
from rgbdslam.posegraph.graph import PoseGraphData, se2_between
from rgbdslam.posegraph.initializers import initialize
from rgbdslam.errors import InputError

from tests.conftest import DATA, need


def _graph(pairs, z, info=None, n=None):
    ei = np.array([p[0] for p in pairs])
    ej = np.array([p[1] for p in pairs])
    n = n or int(max(ei.max(), ej.max()) + 1)
    info = np.tile(np.eye(3), (len(pairs), 1, 1)) if info is None else info
    return PoseGraphData(2, np.arange(n), np.zeros((n, 3)), ei, ej, np.asarray(z, float), info)


def _wrapdiff(a, b):
    return np.angle(np.exp(1j * (np.asarray(a) - np.asarray(b))))


def test_consistent_graph_is_recovered_exactly_even_with_headings_past_pi():
    rng = np.random.default_rng(4)
    n = 12
    gt = np.column_stack([rng.uniform(-8, 8, n), rng.uniform(-8, 8, n), rng.uniform(-3.1, 3.1, n)])
    gt[0] = 0
    pairs = [(k, k + 1) for k in range(n - 1)] + [(0, 6), (3, 9), (11, 2), (5, 10), (8, 1)]
    ei = np.array([p[0] for p in pairs]); ej = np.array([p[1] for p in pairs])
    info = np.array([np.diag([100.0, 40.0, 300.0])] * len(pairs))
    info[::3, 0, 1] = info[::3, 1, 0] = 20.0  # non-diagonal translation information
    g = _graph(pairs, se2_between(gt[ei], gt[ej]), info)
    est = chordal_se2(g)
    np.testing.assert_allclose(est[:, :2], gt[:, :2], atol=1e-9)
    np.testing.assert_allclose(_wrapdiff(est[:, 2], gt[:, 2]), 0, atol=1e-9)
    np.testing.assert_allclose(initialize(g, "chordal"), est, atol=0)


def test_headings_least_squares_on_a_triangle_hand_worked():
    # edges 0->1 (a), 1->2 (b), 0->2 (c), equal weights.  Minimising
    # (t1-a)^2 + (t2-t1-b)^2 + (t2-c)^2 gives t1 = (2a - b + c)/3, t2 = (a + b + 2c)/3.
    a, b, c = 0.5, 0.7, 1.0
    g = _graph([(0, 1), (1, 2), (0, 2)], [[1, 0, a], [1, 0, b], [1, 0, c]])
    th = refine_headings(g, np.array([0.0, a, a + b]))
    np.testing.assert_allclose(th, [0.0, (2 * a - b + c) / 3, (a + b + 2 * c) / 3], atol=1e-12)


def test_heading_refinement_unwraps_edges_across_pi():
    # the same triangle rotated so that the angles cross +-pi: measurements given wrapped
    a, b = 2.0, 2.0
    c = math.remainder(a + b + 0.3, 2 * math.pi)  # inconsistent by 0.3, wrapped to (-pi, pi]
    g = _graph([(0, 1), (1, 2), (0, 2)], [[1, 0, a], [1, 0, b], [1, 0, c]])
    th = refine_headings(g, chordal_headings(g))
    # unwrapped, c is a + b + 0.3: t1 = (2a - b + a + b + 0.3)/3 = a + 0.1, t2 = a + b + 0.2
    np.testing.assert_allclose(_wrapdiff(th, [0.0, a + 0.1, a + b + 0.2]), 0, atol=1e-12)


def test_chordal_headings_hand_worked_two_paths():
    # vertex 1 reached by two parallel edges 0->1 with angles +d and -d (equal weight): the chordal
    # solution is the mean of the two unit vectors, (cos d, 0) -> heading 0 after projection
    d = 0.4
    g = _graph([(0, 1), (0, 1)], [[1, 0, d], [1, 0, -d]])
    np.testing.assert_allclose(chordal_headings(g), [0.0, 0.0], atol=1e-12)
    # weights 3:1 -> (c, s) = (cos d, (3 sin d - sin d)/4) -> heading atan2(sin d / 2, cos d)
    info = np.array([np.diag([1, 1, 3.0]), np.eye(3)])
    g = _graph([(0, 1), (0, 1)], [[1, 0, d], [1, 0, -d]], info)
    np.testing.assert_allclose(chordal_headings(g)[1], math.atan2(math.sin(d) / 2, math.cos(d)), atol=1e-12)


def test_positions_least_squares_on_a_triangle_hand_worked():
    # headings 0; 0->1 (1, 0), 1->2 (0, 1), 0->2 (1, 1 + e), unit weights.
    # x: exact (1, 1); y: min y1^2 + (y2 - y1 - 1)^2 + (y2 - 1 - e)^2 -> y1 = e/3, y2 = 1 + 2e/3
    e = 0.3
    g = _graph([(0, 1), (1, 2), (0, 2)], [[1, 0, 0], [0, 1, 0], [1, 1 + e, 0]])
    p = positions_given_headings(g, np.zeros(3))
    np.testing.assert_allclose(p, [[0, 0, 0], [1, e / 3, 0], [1, 1 + 2 * e / 3, 0]], atol=1e-12)


def test_positions_use_the_rotated_translation_information():
    # vertex 1 measured twice from 0 (heading of 0 is pi/2): once precise along the edge's x,
    # vague along its y, once the other way round; world answer takes each precise component
    info = np.array([np.diag([100.0, 1e-4, 1.0]), np.diag([1e-4, 100.0, 1.0])])
    g = _graph([(0, 1), (0, 1)], [[2.0, 5.0, 0.0], [7.0, 3.0, 0.0]], info)
    p = positions_given_headings(g, np.array([math.pi / 2, math.pi / 2]))
    # frame of 0 is rotated by pi/2: edge (x, y) -> world (-y, x); precise x=2 -> world y=2,
    # precise y=3 -> world x=-3
    np.testing.assert_allclose(p[1, :2], [-3.0, 2.0], atol=1e-4)


def test_disconnected_graph_is_a_clear_error():
    g = _graph([(0, 1), (2, 3)], [[1, 0, 0], [1, 0, 0]])
    with pytest.raises(InputError, match="not connected"):
        chordal_se2(g)


@pytest.mark.data
def test_real_city10k_chordal_beats_masat_initial_chi2():
    need(DATA / "posegraph" / "iSAM" / "groundtruth" / "city10000_groundtruth.txt")
    from rgbdslam.posegraph.factors import chi2, degrees_of_freedom
    from rgbdslam.posegraph.bench import noisy_instance, reference_graph

    ref, gt, _ = reference_graph("city10k", DATA)
    g = noisy_instance(ref, (0.3, 0.3, 0.3), np.random.default_rng(7))
    dof = degrees_of_freedom(g)
    r_chordal = chi2(g, initialize(g, "chordal")) / dof
    r_masat = chi2(g, initialize(g, "masat")) / dof
    # measured: chordal ≈ 1.3-1.5, MASAT ≈ 20-140 at this noise level
    assert r_chordal < 2.0
    assert r_chordal < r_masat / 5


def test_cli_init_and_optimize_with_chordal_and_lm(tmp_path):
    from click.testing import CliRunner

    from rgbdslam.posegraph.graph_io import read_graph, write_g2o
    from rgbdslam.cli import main

    rng = np.random.default_rng(11)
    n = 40
    gt = np.zeros((n, 3))
    for k in range(1, n):  # a spiral walk, headings sweeping past ±pi
        th = gt[k - 1, 2] + 0.35
        gt[k] = [gt[k - 1, 0] + np.cos(th), gt[k - 1, 1] + np.sin(th), math.remainder(th, 2 * math.pi)]
    pairs = [(k, k + 1) for k in range(n - 1)] + [(k, k + 18) for k in range(0, n - 18, 3)]
    ei = np.array([p[0] for p in pairs]); ej = np.array([p[1] for p in pairs])
    z = se2_between(gt[ei], gt[ej]) + rng.normal(size=(len(pairs), 3)) * 0.02
    g = _graph(pairs, z, np.tile(np.diag([2500.0, 2500.0, 2500.0]), (len(pairs), 1, 1)), n)
    src = tmp_path / "spiral.g2o"
    write_g2o(src, g, np.zeros((n, 3)))
    runner = CliRunner()
    res = runner.invoke(main, ["posegraph", "init", str(src), "--method", "chordal", "--out", str(tmp_path / "i.g2o")])
    assert res.exit_code == 0, res.output
    assert "chordal initial guess" in res.output
    init = read_graph(tmp_path / "i.g2o").poses
    assert np.abs(init[:, :2] - gt[:, :2]).max() < 0.2  # the noise is 0.02 per edge
    res = runner.invoke(main, ["posegraph", "optimize", str(src), "--init", "chordal", "--optimizer", "lm", "-q",
                               "--out", str(tmp_path / "o.g2o")])
    assert res.exit_code == 0, res.output
    assert "optimizer lm" in res.output
    assert re.search(r"; \d+ iteration\(s\), converged; ", res.output), res.output  # not "not converged"
    opt = read_graph(tmp_path / "o.g2o").poses
    # GTSAM's optimum (error Logmap(Z^-1 X_i^-1 X_j)), vertex 0 at the chordal guess's origin, found
    # independently by SciPy least squares from the ground truth
    np.testing.assert_allclose(opt[0], [0.0, 0.0, 0.0], atol=1e-9)
    ref = _gtsam_optimum(g, gt)
    # converged (3 iterations): 2e-7 off; stopped after 2 (not converged): 9e-6 off, after 1: 2e-3 off
    np.testing.assert_allclose(opt[:, :2], ref[:, :2], atol=1e-6)
    np.testing.assert_allclose(_wrapdiff(opt[:, 2], ref[:, 2]), 0, atol=1e-6)
    assert np.abs(opt[:, :2] - gt[:, :2]).max() < 0.2  # and the optimum is near the truth
    missing = tmp_path / "missing.g2o"
    res = runner.invoke(main, ["posegraph", "init", str(missing), "--method", "chordal",
                               "--out", str(tmp_path / "x.g2o")])
    # an RgbdslamError becomes sys.exit(error.exit_code) (rgbdslam/cli.py); InputError's code is 2
    assert isinstance(res.exception, SystemExit) and res.exit_code == InputError.exit_code == 2, res.exception
    assert res.stdout == ""
    assert res.stderr == f"error: pose-graph file {missing} does not exist; check the path\n"
    assert not (tmp_path / "x.g2o").exists()


def _pose2_logmap(p):
    """Pose2 logarithm: (v, w) with t = V(w) v, V(w) = [[s, -(1-c)], [1-c, s]] / w (V = I at w = 0)."""
    w = p[:, 2]
    s, omc = np.sin(w), 1.0 - np.cos(w)
    small = np.abs(w) < 1e-10
    k = np.where(small, 1.0, w / np.where(small, 1.0, s * s + omc * omc))
    vx = np.where(small, p[:, 0], k * (s * p[:, 0] + omc * p[:, 1]))
    vy = np.where(small, p[:, 1], k * (-omc * p[:, 0] + s * p[:, 1]))
    return np.column_stack([vx, vy, w])


def _compose(a, b):
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack([a[:, 0] + c * b[:, 0] - s * b[:, 1], a[:, 1] + s * b[:, 0] + c * b[:, 1],
                            np.angle(np.exp(1j * (a[:, 2] + b[:, 2])))])


def _inverse(a):
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack([-(c * a[:, 0] + s * a[:, 1]), s * a[:, 0] - c * a[:, 1], -a[:, 2]])


def _gtsam_optimum(g, start):
    """argmin sum e^T Omega e, e = Logmap(Z^-1 X_i^-1 X_j), vertex 0 at the origin (diagonal Omega)."""
    from scipy.optimize import least_squares

    w = np.sqrt(np.diagonal(g.info, axis1=1, axis2=2))

    def f(v):
        p = np.vstack([np.zeros((1, 3)), v.reshape(-1, 3)])
        err = _pose2_logmap(_compose(_inverse(g.meas), _compose(_inverse(p[g.edges_i]), p[g.edges_j])))
        return (err * w).ravel()

    r = least_squares(f, np.asarray(start, float)[1:].ravel(), method="lm", jac="3-point",
                      xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return np.vstack([np.zeros((1, 3)), r.x.reshape(-1, 3)])


def test_rounded_singular_translation_information_does_not_crash_cholesky(tmp_path):
    """A rank-1 translation block written with 6 digits ([[1, 1], [1, 0.999999]], eigenvalue -2.5e-7)
    passes the readers' positive-semi-definite test (tolerance 1e-5 of the largest eigenvalue); its
    Cholesky factor used to raise numpy's LinAlgError ("Matrix is not positive definite")."""
    from click.testing import CliRunner

    from rgbdslam.posegraph.graph_io import read_graph
    from rgbdslam.cli import main

    src = tmp_path / "rounded.g2o"
    src.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 2 0 0\nVERTEX_SE2 3 2 1 0\n"
                   "EDGE_SE2 0 1 1 0 0 100 0 0 100 0 100\nEDGE_SE2 1 2 1 0 0 1 1 0 0.999999 0 100\n"
                   "EDGE_SE2 2 3 0 1 0 100 0 0 100 0 100\nEDGE_SE2 0 3 2 1 0 100 0 0 100 0 100\n")
    g = read_graph(src)
    assert np.linalg.eigvalsh(g.info[1])[0] < 0
    est = chordal_se2(g)
    np.testing.assert_allclose(est, [[0, 0, 0], [1, 0, 0], [2, 0, 0], [2, 1, 0]], atol=1e-6)
    res = CliRunner().invoke(main, ["posegraph", "init", str(src), "--method", "chordal", "-o", str(tmp_path / "o.g2o")])
    assert res.exit_code == 0 and res.exception is None, res.output
