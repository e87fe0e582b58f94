"""Pose-graph readers (g2o, TORO, iSAM) on small snippets, the g2o writer, and the real M3500 file."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rgbdslam.posegraph.graph_io import detect_format, graph_info, read_graph, write_g2o
from rgbdslam.errors import InputError

from tests.conftest import DATA, need

G2O_SE2 = """\
VERTEX_SE2 0 0 0 0
VERTEX_SE2 1 1.0 0.1 0.2
VERTEX_SE2 2 2.0 0.2 0.3
FIX 0
EDGE_SE2 0 1 1.030390 0.011350 -0.012958 44.635358 -7.962220 0.000000 376.516380 0.000000 9745.791650
EDGE_SE2 1 2 1.013900 -0.058639 -0.013225 45.125343 15.275266 0.000000 387.129544 0.000000 9740.656002
"""

G2O_SE3 = """\
VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1
VERTEX_SE3:QUAT 1 0.341895 -0.0416997 0.0330394 -0.00189341 0.00395691 0.0899835 0.995934
EDGE_SE3:QUAT 0 1 0.341895 -0.0416997 0.0330394 -0.00189341 0.00395691 0.0899835 0.995934  10 0 0 0 0 0 10 0 0 0 0 10 0 0 0 400.021 0.00193512 2.06612 399.993 0.496977 99.203
"""

TORO = """\
VERTEX2 0 1.26 -2.3 0.699
VERTEX2 1 2.06532 -1.70549 0.7195
VERTEX2 2 2.84659 -1.06456 0.7337
EDGE2 0 1 1.0 0.02 0.03 1 0.1 2 3 0.2 0.4
EDGE2 1 2 1.0 0 0 1 0 1 1 0 0
EQUIV 1 2
"""

ISAM2D = """\
ODOMETRY 0 1 1.03039 0.0113498 -0.0129577 44.72135955 0 0 44.72135955 0 44.72135955
ODOMETRY 1 2 1.0139 -0.0586393 -0.013225 2 1 0.5 3 0.25 4
EDGE2 2 0 -2.0 0.1 0.02 50 0 0 50 0 100
POINT2 2 7 1.0 1.0 1 0 1
"""

ISAM3D = """\
EDGE3 0 1 0.341895 -0.0416997 0.0330394 -0.00305942 0.00822248 0.1802 10 0 0 0 0 0 10 0 0 0 0 10 0 0 0 100 0 0 100 0 25
EDGE3 1 2 0.229005 0.138346 -0.0985239 -0.00165533 0.0168837 0.111357 10 0 0 0 0 0 10 0 0 0 0 10 0 0 0 100 0 0 100 0 25
"""


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_g2o_se2(tmp_path):
    g = read_graph(_write(tmp_path, "a.g2o", G2O_SE2))
    assert (g.dim, g.n_vertices, g.n_edges, g.has_poses) == (2, 3, 2, True)
    np.testing.assert_allclose(g.poses[1], [1.0, 0.1, 0.2])
    np.testing.assert_allclose(g.meas[0], [1.030390, 0.011350, -0.012958])
    I = g.info[0]
    assert I[0, 1] == I[1, 0] == pytest.approx(-7.962220)
    assert I[1, 1] == pytest.approx(376.516380) and I[2, 2] == pytest.approx(9745.791650) and I[0, 2] == 0


def test_g2o_se3_info_is_translation_first(tmp_path):
    g = read_graph(_write(tmp_path, "b.g2o", G2O_SE3))
    assert (g.dim, g.n_vertices, g.n_edges) == (3, 2, 1)
    R = Rotation.from_quat([-0.00189341, 0.00395691, 0.0899835, 0.995934]).as_matrix()
    np.testing.assert_allclose(g.meas[0, :3, :3], R, atol=1e-6)
    np.testing.assert_allclose(g.meas[0, :3, 3], [0.341895, -0.0416997, 0.0330394])
    assert g.info[0, 0, 0] == 10 and g.info[0, 3, 3] == pytest.approx(400.021)
    assert g.info[0, 3, 5] == g.info[0, 5, 3] == pytest.approx(2.06612)
    np.testing.assert_allclose(g.poses[1], g.meas[0], atol=1e-12)


def test_toro_information_order(tmp_path):
    g = read_graph(_write(tmp_path, "w.graph", TORO))
    assert detect_format(tmp_path / "w.graph") == "toro"
    assert (g.n_vertices, g.n_edges) == (3, 2)
    assert g.notes == ["ignored 1 EQUIV record(s)"]
    # TORO: xx xy yy thth xth yth = 1 0.1 2 3 0.2 0.4
    np.testing.assert_allclose(g.info[0], [[1, 0.1, 0.2], [0.1, 2, 0.4], [0.2, 0.4, 3]])
    np.testing.assert_allclose(g.poses[0], [1.26, -2.3, 0.699])


def test_isam_square_root_information(tmp_path):
    g = read_graph(_write(tmp_path, "m.txt", ISAM2D))
    assert detect_format(tmp_path / "m.txt") == "isam"
    assert (g.dim, g.n_vertices, g.n_edges, g.has_poses) == (2, 3, 3, False)
    assert g.notes == ["ignored 1 POINT2 record(s)"]
    np.testing.assert_allclose(g.info[0], np.eye(3) * 2000.0, rtol=1e-9)  # 44.72135955^2
    R = np.array([[2, 1, 0.5], [0, 3, 0.25], [0, 0, 4.0]])
    np.testing.assert_allclose(g.info[1], R.T @ R)
    assert (g.edges_i[2], g.edges_j[2]) == (2, 0)


def test_isam_3d_roll_pitch_yaw(tmp_path):
    g = read_graph(_write(tmp_path, "s.txt", ISAM3D))
    assert (g.dim, g.n_edges) == (3, 2)
    # the same edge in SE-Sync's g2o copy has this quaternion
    q = Rotation.from_matrix(g.meas[0, :3, :3]).as_quat()
    np.testing.assert_allclose(q, [-0.00189341, 0.00395691, 0.0899835, 0.995934], atol=1e-6)
    np.testing.assert_allclose(np.diagonal(g.info[0]), [100, 100, 100, 10000, 10000, 625])


@pytest.mark.parametrize("text,match", [
    ("EDGE_SE2 0 1 1 2 3 1 0 0 1 0\n", r"x\.g2o:1: EDGE_SE2 needs 11 numbers, found 10"),
    ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 2 abc 1 0 0 1 0 1\n", r"x\.g2o:2: EDGE_SE2 has a non-numeric field"),
    ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1.5 1 2 3 1 0 0 1 0 1\n", r"x\.g2o:2: EDGE_SE2 vertex id"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_XYZ 1 1 1\nEDGE_SE2 0 1 1 2 3 1 0 0 1 0 1\n", r"x\.g2o:2: unsupported record 'VERTEX_XYZ'"),
    ("EDGE_SE2 0 0 1 2 3 1 0 0 1 0 1\n", r"x\.g2o:1: edge from a vertex to itself"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 2\nEDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1" + " 1" * 21 + "\n", r"x\.g2o:1: .*not unit"),
    ("hello world\n", r"no g2o, TORO or iSAM"),
])
def test_malformed_lines_name_file_and_line(tmp_path, text, match):
    with pytest.raises(InputError, match=match):
        read_graph(_write(tmp_path, "x.g2o", text))


def test_missing_file_and_bad_format(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        read_graph(tmp_path / "nope.g2o")
    with pytest.raises(InputError, match="unknown pose-graph format"):
        read_graph(_write(tmp_path, "a.g2o", G2O_SE2), "xml")


@pytest.mark.parametrize("text,name", [(G2O_SE2, "a.g2o"), (G2O_SE3, "b.g2o"), (TORO, "w.graph"), (ISAM3D, "s.txt")])
def test_g2o_writer_round_trip(tmp_path, text, name):
    g = read_graph(_write(tmp_path, name, text))
    rng = np.random.default_rng(0)
    if g.dim == 2:
        poses = rng.normal(size=(g.n_vertices, 3))
        poses[:, 2] = (poses[:, 2] + np.pi) % (2 * np.pi) - np.pi
    else:
        poses = np.tile(np.eye(4), (g.n_vertices, 1, 1))
        poses[:, :3, :3] = Rotation.random(g.n_vertices, random_state=1).as_matrix()
        poses[:, :3, 3] = rng.normal(size=(g.n_vertices, 3))
    out = tmp_path / "out.g2o"
    write_g2o(out, g, poses)
    h = read_graph(out)
    assert h.source.endswith("(g2o)") and h.has_poses
    np.testing.assert_array_equal(h.ids, g.ids)
    np.testing.assert_array_equal(h.edges_i, g.edges_i)
    np.testing.assert_array_equal(h.edges_j, g.edges_j)
    np.testing.assert_allclose(h.poses, poses, atol=1e-12)
    np.testing.assert_allclose(h.info, g.info, rtol=1e-12)
    if g.dim == 2:
        np.testing.assert_allclose(h.meas, g.meas, atol=1e-12)
    else:
        np.testing.assert_allclose(h.meas, g.meas, atol=1e-12)


def test_sparse_vertex_ids_are_kept(tmp_path):
    g = read_graph(_write(tmp_path, "s.g2o", "EDGE_SE2 10 20 1 0 0 1 0 0 1 0 1\nEDGE_SE2 20 35 1 0 0 1 0 0 1 0 1\n"))
    assert g.ids.tolist() == [10, 20, 35] and g.edges_i.tolist() == [0, 1] and g.edges_j.tolist() == [1, 2]
    write_g2o(tmp_path / "o.g2o", g)
    assert "VERTEX_SE2 35 " in (tmp_path / "o.g2o").read_text()


@pytest.mark.data
def test_real_m3500_counts():
    path = need(DATA / "posegraph" / "iSAM" / "manhattanOlson3500.txt")
    g = read_graph(path)
    assert (g.dim, g.n_vertices, g.n_edges) == (2, 3500, 5598)
    np.testing.assert_allclose(g.info[0], np.eye(3) * 2000.0, rtol=1e-9)
    # the vertex pairs counted straight from the file's edge records (all ODOMETRY in M3500)
    per_pair = Counter()
    for line in path.read_text().splitlines():
        f = line.split()
        if f and f[0] in ("ODOMETRY", "EDGE2"):
            i, j = int(f[1]), int(f[2])
            per_pair[min(i, j), max(i, j)] += 1
    assert sum(per_pair.values()) == g.n_edges
    repeats = sum(c - 1 for c in per_pair.values())  # edges after the first on the same pair
    multi = sum(c > 1 for c in per_pair.values())  # pairs joined by more than one edge
    assert repeats > multi > 0  # some pairs have three edges, so the two counts differ
    assert (f"edges repeating a vertex pair: {repeats} (on {multi} vertex pairs with more than one edge)"
            in graph_info(path))
    assert math.isclose(g.meas[3, 2], 1.56679)


def test_cli_posegraph_info_counts_on_hand_made_file(tmp_path):
    """4 vertices, 7 edges: 1->2 twice, 0-2 three times (once stored 2->0).
    |i-j| = 1: 0-1, 1-2, 1-2, 2-3 -> 4; other: the three 0-2 edges.
    Repeating a pair: 1 (1-2) + 2 (0-2) = 3 edges on 2 pairs.  Degrees: 0: 1 + 3 = 4,
    1: 1 + 2 = 3, 2: 2 + 3 + 1 = 6, 3: 1 -> min 1, mean 14 / 4 = 3.50, max 6."""
    from click.testing import CliRunner

    from rgbdslam.cli import main

    e = " 1 0 0 1 0 0 1 0 1\n"
    text = ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 2 0 0\nVERTEX_SE2 3 3 0 0\nFIX 0\n"
            + "".join(f"EDGE_SE2 {i} {j}" + e for i, j in ((0, 1), (1, 2), (2, 3), (0, 2), (1, 2), (2, 0), (0, 2))))
    path = _write(tmp_path, "h.g2o", text)
    res = CliRunner().invoke(main, ["posegraph", "info", str(path)])
    assert res.exit_code == 0 and res.exception is None, res.output
    assert res.stdout.splitlines() == [
        f"SE(2) pose graph from {path} (g2o): 4 vertices, 7 edges (with vertex estimates)",
        ("odometry-like edges (between vertices adjacent in id order): 4; other edges: 3; "
         "edges repeating a vertex pair: 3 (on 2 vertex pairs with more than one edge)"),
        "vertex degree: min 1, mean 3.50, max 6",
        "note: ignored 1 FIX record(s)",
    ]
    res = CliRunner().invoke(main, ["posegraph", "info", str(path), "--format", "toro"])
    assert isinstance(res.exception, SystemExit) and res.exit_code == InputError.exit_code == 2
    assert res.stderr == f"error: {path}:1: unsupported record 'VERTEX_SE2'; remove it or convert the file to g2o\n"


def test_a_repeated_vertex_line_does_not_hide_a_missing_vertex(tmp_path):
    """Vertex 0 listed twice, vertex 2 not at all: the file does not give every estimate."""
    text = ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 0 0\nVERTEX_SE2 1 1 0 0\n"
            "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n")
    g = read_graph(_write(tmp_path, "r.g2o", text))
    assert g.n_vertices == 3 and not g.has_poses
    assert g.poses[0].tolist() == [1.0, 0.0, 0.0]  # the last line of vertex 0 wins, and says so
    assert any("1 repeated vertex line" in n for n in g.notes)
    full = read_graph(_write(tmp_path, "f.g2o", text + "VERTEX_SE2 2 2 0 0\n"))
    assert full.has_poses


# ----------------------------------------------------------------------- input validation (one line)

_V3 = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 2 0 0\n"
_E01 = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
_E12 = "EDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n"


from tests.conftest import assert_cli_error as _assert_cli_error, cli as _cli  # noqa: E402


def test_non_utf8_graph_file_is_one_line_error(tmp_path):
    data = b"VERTEX_SE2 0 0 0 0\n# caf\xe9\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
    p = tmp_path / "latin1.g2o"
    p.write_bytes(data)
    bad_byte = data.index(bytes([0xE9]))
    msg = (f"pose-graph file {p} is not UTF-8 text (byte {bad_byte}); give the text file itself, "
           f"not a binary or compressed copy")
    for fmt in ("auto", "g2o"):
        with pytest.raises(InputError) as e:
            read_graph(p, fmt)
        assert str(e.value) == msg
    _assert_cli_error(_cli(["posegraph", "info", p]), msg)
    _assert_cli_error(_cli(["posegraph", "optimize", p, "-q"]), msg)


@pytest.mark.parametrize("name,text,line,message", [
    ("neg_diag.g2o", _V3 + _E01 + "EDGE_SE2 1 2 1 0 0 -1 0 0 1 0 1\n", 5,
     ("EDGE_SE2 information matrix has a negative diagonal entry (-1), so it is not positive semi-definite; "
      "fix the line's information entries (an inverse covariance)")),
    ("zero.g2o", _V3 + _E01 + "EDGE_SE2 1 2 1 0 0 0 0 0 0 0 0\n", 5,
     ("EDGE_SE2 information matrix is all zero, so the edge constrains nothing; give its information "
      "(inverse covariance) or remove the line")),
    # TORO order xx xy yy thth xth yth
    ("neg.graph", "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nEDGE2 0 1 1 0 0 1 0 1 -2 0 0\n", 3,
     ("EDGE2 information matrix has a negative diagonal entry (-2), so it is not positive semi-definite; "
      "fix the line's information entries (an inverse covariance)")),
    # iSAM gives the square root R; R^T R would overflow: numbers beyond 1e16 are refused as read
    ("overflow.txt", "EDGE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE2 1 2 1 0 0 1e200 0 0 1 0 1\n", 2,
     "EDGE2 number 1e+200 is beyond ±1e+16; fix the line"),
    ("zero.txt", "EDGE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE2 1 2 1 0 0 0 0 0 0 0 0\n", 2,
     ("EDGE2 information matrix (R^T R of the square-root entries) is all zero, so the edge constrains nothing; "
      "give its information (inverse covariance) or remove the line")),
])
def test_bad_information_names_file_and_line(tmp_path, name, text, line, message):
    p = _write(tmp_path, name, text)
    with pytest.raises(InputError) as e:
        read_graph(p)
    assert str(e.value) == f"{p}:{line}: {message}"


def test_bad_information_is_refused_by_init_and_optimize(tmp_path):
    """Negative information used to give a ValueError traceback (init), "final chi2 -0.0046 ...
    converged" (--optimizer g2o); all-zero information a "converged" chi2 of 0."""
    for row, what in (("-1 0 0 1 0 1", ("has a negative diagonal entry (-1), so it is not positive semi-definite; "
                                        "fix the line's information entries (an inverse covariance)")),
                      ("0 0 0 0 0 0", ("is all zero, so the edge constrains nothing; give its information "
                                       "(inverse covariance) or remove the line"))):
        p = _write(tmp_path, "bad.g2o", _V3 + _E01 + f"EDGE_SE2 1 2 1 0 0 {row}\n")
        msg = f"{p}:5: EDGE_SE2 information matrix {what}"
        for method in ("masat", "weighted_masat", "odometry", "chordal", "lago"):
            _assert_cli_error(_cli(["posegraph", "init", p, "--method", method, "-o", tmp_path / "o.g2o"]), msg)
        for opt in ("gtsam", "g2o", "lm"):
            _assert_cli_error(_cli(["posegraph", "optimize", p, "-q", "--optimizer", opt]), msg)
    assert not (tmp_path / "o.g2o").exists()


def test_valid_information_that_is_singular_or_rounded_is_accepted(tmp_path):
    """PSD but singular (a zero heading information; a rank-1 translation block) is valid, and so is a
    singular matrix written with 6 significant digits whose rounding leaves an eigenvalue of -1e-7."""
    text = (_V3 + "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 0\n"  # no heading information
            + "EDGE_SE2 1 2 1 0 0 1 1 0 1 0 1\n"  # translation block [[1, 1], [1, 1]]: rank 1
            + "EDGE_SE2 0 2 2 0 0 1 1 0 0.999999 0 1\n")  # the same, rounded: eigenvalue -2.5e-7
    g = read_graph(_write(tmp_path, "ok.g2o", text))
    assert g.n_edges == 3 and np.linalg.eigvalsh(g.info[2])[0] < 0


@pytest.mark.parametrize("name,text,line,tag", [
    ("nan.g2o", "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 nan 0 0\n" + _E01, 2, "VERTEX_SE2"),
    ("inf.g2o", "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 inf 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1"
     + " 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1\n", 2, "VERTEX_SE3:QUAT"),
    ("nanq.g2o", "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 nan\nEDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1"
     + " 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1\n", 1, "VERTEX_SE3:QUAT"),
    ("nan.graph", "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 -inf\nEDGE2 0 1 1 0 0 1 0 1 1 0 0\n", 2, "VERTEX2"),
])
def test_non_finite_vertex_estimates_name_file_and_line(tmp_path, name, text, line, tag):
    """They used to reach Gauss-Newton and end as "Gauss-Newton failed (RuntimeError: )"."""
    p = _write(tmp_path, name, text)
    msg = f"{p}:{line}: {tag} has a non-finite number (nan or inf); fix the line"
    with pytest.raises(InputError) as e:
        read_graph(p)
    assert str(e.value) == msg
    _assert_cli_error(_cli(["posegraph", "optimize", p, "--init", "file", "-q"]), msg)


def test_huge_or_nan_vertex_id_is_an_error_without_numpy_warnings(tmp_path):
    import warnings

    ids = {"1e30": "vertex id must be a non-negative integer below 2^53",
           "9007199254740993": "vertex id must be a non-negative integer below 2^53",  # 2^53 + 1: not a float
           "nan": "has a non-finite number (nan or inf)"}
    for ident, what in ids.items():
        p = _write(tmp_path, "id.g2o", f"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 {ident} 1 0 0\n" + _E01)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # the int64 cast of 1e30 used to warn "invalid value encountered"
            with pytest.raises(InputError) as e:
                read_graph(p)
        assert str(e.value) == f"{p}:2: VERTEX_SE2 {what}; fix the line"
    p = _write(tmp_path, "eid.g2o", "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1e300 1 0 0 1 0 0 1 0 1\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match=r"eid\.g2o:2: EDGE_SE2 vertex id must be a non-negative integer"):
            read_graph(p)


def test_indefinite_information_is_projected_and_noted(tmp_path):
    """A finite, non-negative diagonal but indefinite matrix (real files have them: SE-Sync's
    cubicle.g2o) is replaced by its nearest PSD matrix. Hand-worked: [[1, 2], [2, 1]] has
    eigenvalues 3 (vector (1, 1)/sqrt 2) and -1, so the projection is 3 * vv^T = [[1.5, 1.5], [1.5, 1.5]]."""
    p = _write(tmp_path, "indefinite.g2o", _V3 + _E01 + "EDGE_SE2 1 2 1 0 0 1 2 0 1 0 1\n")
    g = read_graph(p)
    np.testing.assert_allclose(g.info[1], [[1.5, 1.5, 0], [1.5, 1.5, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(g.info[0], np.eye(3))  # the valid edge is untouched
    assert any(n.startswith("1 EDGE_SE2 information matrix(s) are indefinite (first at line 5: smallest "
                            "eigenvalue -1, largest 3)") for n in g.notes)
    se3 = _write(tmp_path, "se3.g2o", "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 "
                 + "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 3 0 1 0 1\n")
    g3 = read_graph(se3)
    assert np.linalg.eigvalsh(g3.info[0])[0] > -1e-9 and len(g3.notes) == 1


@pytest.mark.data
def test_real_cubicle_is_read_with_its_indefinite_edges_projected():
    g = read_graph(need(DATA / "posegraph" / "SE-Sync" / "cubicle.g2o"))
    assert g.dim == 3 and g.n_edges == 16869
    assert np.linalg.eigvalsh(g.info).min() > -1e-6 * np.abs(g.info).max()
    assert any(n.startswith("5021 EDGE_SE3:QUAT information matrix(s) are indefinite") for n in g.notes)


@pytest.mark.parametrize("fix", ["FIX 7", "FIX 0 1 9", "FIX x"])
def test_fix_of_a_missing_vertex_is_refused(tmp_path, fix):
    from rgbdslam.errors import InputError
    from rgbdslam.posegraph.graph_io import read_graph

    p = tmp_path / "g.g2o"
    p.write_text(f"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n{fix}\n")
    with pytest.raises(InputError, match=r"g.g2o:4: FIX names vertex '(7|9|x)', which is not a vertex id"):
        read_graph(p)
    p.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nFIX 0\n")
    read_graph(p)  # FIX of a vertex of the file: still read (and ignored: the first vertex is the gauge)
