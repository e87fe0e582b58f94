"""Pose-graph files: g2o, TORO and iSAM readers (format auto-detected) and a g2o writer.

Formats and the conventions that differ between them:

* **g2o** — ``VERTEX_SE2 id x y th``, ``EDGE_SE2 i j x y th`` + upper triangle of the 3x3
  information (``I11 I12 I13 I22 I23 I33``); ``VERTEX_SE3:QUAT id x y z qx qy qz qw``,
  ``EDGE_SE3:QUAT i j x y z qx qy qz qw`` + upper triangle of the 6x6 information in
  (t, r) order.  ``FIX`` lines are ignored.
* **TORO** — ``VERTEX2 id x y th``, ``EDGE2 i j x y th`` + information ``xx xy yy thth xth yth``;
  ``EQUIV`` records are skipped (with a note).
* **iSAM** — no vertices; ``ODOMETRY``/``EDGE2 i j x y th`` + upper triangle of the
  **square-root** information ``sxx sxy sxt syy syt stt`` (information = R^T R);
  ``EDGE3 i j x y z roll pitch yaw`` + the 21-entry square-root information upper triangle
  in (x, y, z, roll, pitch, yaw) order; rotation = Rz(yaw) Ry(pitch) Rx(roll).  Landmark
  records (``POINT2``, ``LANDMARK``, ...) are ignored with a note.  The roll-pitch-yaw
  information is used as rotation-vector information (they agree to first order).

SE(3) information is stored in g2o (t, r) order in :class:`PoseGraphData` (see graph.py).
Malformed lines raise :class:`rgbdslam.errors.InputError` naming ``file:line``.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rgbdslam.geometry.se3 import pose_from_tum, pose_to_tum
from rgbdslam.posegraph.graph import PoseGraphData, empty_poses, wrap_angle
from rgbdslam.errors import InputError, shorten
from rgbdslam.io.atomic import atomic_write_text
from rgbdslam.io.numbers import check_magnitude
from rgbdslam.io.text import read_lines, require_file

FORMATS = ("auto", "g2o", "toro", "isam")

# number of numeric fields after the tag
_G2O = {"VERTEX_SE2": 4, "EDGE_SE2": 11, "VERTEX_SE3:QUAT": 8, "EDGE_SE3:QUAT": 30}
_TORO = {"VERTEX2": 4, "EDGE2": 11}
_ISAM = {"ODOMETRY": 11, "EDGE2": 11, "EDGE3": 29}
_IGNORED = {"g2o": {"FIX"}, "toro": {"EQUIV"},
            "isam": {"POINT2", "POINT3", "LANDMARK", "LANDMARK2", "LANDMARK3", "POSE2D_POINT2D",
                     "EDGE_SE2_XY", "VERTEX_XY", "POINT"}}

_IU3 = np.triu_indices(3)
_IU6 = np.triu_indices(6)

# Vertex ids are parsed as floats: above 2**53 neighbouring integers collapse onto one float.
_MAX_ID = 2.0**53
# An information matrix counts as positive semi-definite when its smallest eigenvalue is above
# -_PSD_RTOL x its largest |eigenvalue|.  Files written with 6 significant digits (g2o's default)
# perturb the eigenvalues of a singular but valid 6x6 matrix by at most ~3e-6 of the largest one,
# so this tolerance accepts rounded files and still rejects real sign errors (e.g. SE-Sync's
# cubicle.g2o has edges at -0.47).
_PSD_RTOL = 1e-5


def _lines(path: Path) -> list[str]:
    return read_lines(path, "pose-graph file")


def detect_format(path: str | Path, lines: list[str] | None = None) -> str:
    """Guess the format from the record tags in the first lines of the file (``lines``: the
    file's lines, if already read)."""
    path = Path(path)
    if lines is None:
        lines = _lines(path)
    tags = set()
    for line in lines[:5001]:
        p = line.split(maxsplit=1)
        if p and not p[0].startswith("#"):
            tags.add(p[0])
    if tags & {"VERTEX_SE2", "EDGE_SE2", "VERTEX_SE3:QUAT", "EDGE_SE3:QUAT"}:
        return "g2o"
    if tags & {"ODOMETRY", "EDGE3"} or (tags & _IGNORED["isam"]):
        return "isam"
    if "VERTEX2" in tags:
        return "toro"
    if "EDGE2" in tags:  # EDGE2 without vertices: iSAM (TORO files always list VERTEX2)
        return "isam"
    raise InputError(f"{path}: no g2o, TORO or iSAM pose-graph records found; give a .g2o, TORO .graph or iSAM .txt file")


def _scan(path: Path, text_lines: list[str], spec: dict[str, int], ignored: set[str]):
    """Group numeric fields of each known tag; returns (rows by tag, line numbers by tag, notes)."""
    rows: dict[str, list[list[str]]] = defaultdict(list)
    lines: dict[str, list[int]] = defaultdict(list)
    skipped: dict[str, int] = defaultdict(int)
    for lineno, line in enumerate(text_lines, 1):
        p = line.split()
        if not p or p[0].startswith("#"):
            continue
        tag = p[0]
        if tag in spec:
            if len(p) - 1 != spec[tag]:
                raise InputError(f"{path}:{lineno}: {tag} needs {spec[tag]} numbers, found {len(p) - 1}; fix or remove the line")
            rows[tag].append(p[1:])
            lines[tag].append(lineno)
        elif tag in ignored:
            skipped[tag] += 1
        else:
            raise InputError(f"{path}:{lineno}: unsupported record {tag!r}; remove it or convert the file to g2o")
    notes = [f"ignored {c} {t} record(s)" for t, c in sorted(skipped.items())]
    return rows, lines, notes


def _numbers(path: Path, tag: str, rows, lines) -> np.ndarray:
    if not rows:
        return np.zeros((0, {**_G2O, **_TORO, **_ISAM}[tag]))
    try:
        return np.array(rows, dtype=float)
    except ValueError:
        for r, ln in zip(rows, lines):
            try:
                [float(x) for x in r]
            except ValueError:
                raise InputError(f"{path}:{ln}: {tag} has a non-numeric field; fix the line") from None
        raise


def _int_ids(path: Path, tag: str, a: np.ndarray, lines) -> np.ndarray:
    # range first (NaN fails it too), so the cast below never sees a value int64 cannot hold
    bad = np.flatnonzero(~((a >= 0) & (a < _MAX_ID)) | (a != np.floor(a)))
    if len(bad):
        raise InputError(f"{path}:{lines[bad[0]]}: {tag} vertex id must be a non-negative integer below 2^53; "
                         f"fix the line")
    return a.astype(np.int64)


MAX_GRAPH_NUMBER = 1e16  # poses, measurements and information entries


def _check_finite(path: Path, tag: str, a: np.ndarray, lines):
    if len(a) == 0:
        return
    bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
    if len(bad):
        raise InputError(f"{path}:{lines[bad[0]]}: {tag} has a non-finite number (nan or inf); fix the line")
    # finite but absurd: squares and chi2 sums of larger numbers overflow (ids, the leading
    # column(s), are checked on their own by _int_ids)
    check_magnitude(a[:, 1 if tag.startswith("VERTEX") else 2:], MAX_GRAPH_NUMBER, path, lines, f"{tag} number",
                    "fix the line")


def _check_info(path: Path, tag: str, info: np.ndarray, lines, what: str = "information matrix"):
    """Every edge's information must be finite, not all zero and without a negative diagonal
    entry (else an InputError names the first bad edge by ``file:line``); an otherwise
    indefinite matrix (beyond :data:`_PSD_RTOL`) is replaced by its nearest PSD matrix.
    Returns ``(info, note or None)``.  Vectorised: only matrices
    with off-diagonal entries need an eigen-decomposition (a diagonal one is PSD iff its diagonal
    is >= 0), so City10k / M10000 cost a few milliseconds."""
    n = len(info)
    if n == 0:
        return info, None
    d = info.shape[1]
    flat = info.reshape(n, d * d)
    finite = np.isfinite(flat).all(axis=1) if not np.isfinite(flat).all() else np.ones(n, bool)
    diag = flat[:, :: d + 1]
    iu = np.triu_indices(d, 1)
    has_off = (flat[:, iu[0] * d + iu[1]] != 0).any(axis=1)
    with np.errstate(invalid="ignore"):  # rows with inf/nan are reported as non-finite below
        zero = finite & ~has_off & ~(diag != 0).any(axis=1)
        # a PSD matrix has no negative diagonal entry, and rounding cannot make one: no tolerance here
        neg_diag = finite & (diag < 0).any(axis=1)
    bad_eig = np.zeros(n, bool)
    w_min = np.zeros(n)
    w_max = np.zeros(n)
    full = np.flatnonzero(finite & has_off & ~neg_diag)
    if len(full):
        w = np.linalg.eigvalsh(info[full])
        w_min[full], w_max[full] = w[:, 0], np.abs(w).max(axis=1)
        bad_eig[full] = w_min[full] < -_PSD_RTOL * w_max[full]
    bad = ~finite | zero | neg_diag
    if not bad.any():
        if not bad_eig.any():
            return info, None
        # finite, a non-negative diagonal, but indefinite: real benchmark files have such edges
        # (SE-Sync's cubicle.g2o: 5021 of 16869, z coupled to roll/pitch with ~1e5 off-diagonals).
        # Keep the file usable: clip the negative eigenvalues (the nearest PSD matrix, Frobenius).
        k = np.flatnonzero(bad_eig)
        w, V = np.linalg.eigh(info[k])
        info = info.copy()
        info[k] = np.einsum("nij,nj,nkj->nik", V, np.maximum(w, 0.0), V)
        first = int(k[0])
        return info, (f"{len(k)} {tag} {what}(s) are indefinite (first at line {lines[first]}: smallest eigenvalue "
                      f"{w_min[first]:.4g}, largest {w_max[first]:.4g}); each was replaced by the nearest positive "
                      f"semi-definite matrix (negative eigenvalues set to 0)")
    k = int(np.flatnonzero(bad)[0])
    where = f"{path}:{lines[k]}: {tag}"
    if not finite[k]:
        raise InputError(f"{where} {what} is not finite (its entries overflow); give finite information entries "
                         f"on the line")
    if zero[k]:
        raise InputError(f"{where} {what} is all zero, so the edge constrains nothing; give its information "
                         f"(inverse covariance) or remove the line")
    if neg_diag[k]:
        raise InputError(f"{where} {what} has a negative diagonal entry ({diag[k].min():.4g}), so it is not positive "
                         f"semi-definite; fix the line's information entries (an inverse covariance)")
    raise AssertionError("unreachable")  # pragma: no cover


def _assemble(path, dim, vid, vposes, ei_raw, ej_raw, meas, info, edge_lines, fmt, notes) -> PoseGraphData:
    if len(ei_raw) == 0:
        raise InputError(f"{path}: the file has no pose-graph edges; give a graph with EDGE records")
    ids = np.unique(np.concatenate([vid, ei_raw, ej_raw]))
    index = {int(v): k for k, v in enumerate(ids)}
    ei = np.searchsorted(ids, ei_raw)
    ej = np.searchsorted(ids, ej_raw)
    self_loops = np.flatnonzero(ei == ej)
    if len(self_loops):
        raise InputError(f"{path}:{edge_lines[self_loops[0]]}: edge from a vertex to itself; remove the line")
    poses = empty_poses(dim, len(ids))
    if len(vid):
        poses[np.searchsorted(ids, vid)] = vposes  # a repeated vertex: its last line wins
    n_est = len(np.unique(vid))
    if n_est < len(vid):
        notes = [*notes, f"{len(vid) - n_est} repeated vertex line(s): the last estimate of each vertex is used"]
    del index
    return PoseGraphData(dim=dim, ids=ids, poses=poses, edges_i=ei, edges_j=ej, meas=meas, info=info,
                     has_poses=n_est == len(ids), source=f"{path} ({fmt})", notes=notes)


def _sym_from_upper(vals: np.ndarray, d: int) -> np.ndarray:
    iu = np.triu_indices(d)
    M = np.zeros((len(vals), d, d))
    M[:, iu[0], iu[1]] = vals
    M[:, iu[1], iu[0]] = vals
    return M


def _check_fix(path: Path, text_lines: list[str], vertex_ids: np.ndarray) -> None:
    """A ``FIX id ...`` record (ignored: the first vertex is the gauge) must still name vertices
    of the file: a FIX of a missing vertex is a mistake in the file, not a no-op."""
    have = set(vertex_ids.tolist())
    for lineno, line in enumerate(text_lines, 1):
        p = line.split()
        if not p or p[0] != "FIX":
            continue
        for token in p[1:]:
            if not (token.isascii() and token.isdigit() and len(token) <= 16) or int(token) not in have:
                raise InputError(f"{path}:{lineno}: FIX names vertex {shorten(token)}, which is not a vertex id of the "
                                 f"file; fix or remove the line")


def _read_g2o(path: Path, text_lines: list[str]) -> PoseGraphData:
    rows, lines, notes = _scan(path, text_lines, _G2O, _IGNORED["g2o"])
    has2 = "EDGE_SE2" in rows or "VERTEX_SE2" in rows
    has3 = "EDGE_SE3:QUAT" in rows or "VERTEX_SE3:QUAT" in rows
    if has2 and has3:
        raise InputError(f"{path}: mixes SE2 and SE3 records; keep one kind per file")
    if has2:
        v = _numbers(path, "VERTEX_SE2", rows["VERTEX_SE2"], lines["VERTEX_SE2"])
        e = _numbers(path, "EDGE_SE2", rows["EDGE_SE2"], lines["EDGE_SE2"])
        _check_finite(path, "VERTEX_SE2", v, lines["VERTEX_SE2"])
        _check_finite(path, "EDGE_SE2", e, lines["EDGE_SE2"])
        vid = _int_ids(path, "VERTEX_SE2", v[:, 0], lines["VERTEX_SE2"]) if len(v) else np.zeros(0, np.int64)
        vposes = v[:, 1:4] if len(v) else np.zeros((0, 3))
        ei = _int_ids(path, "EDGE_SE2", e[:, 0], lines["EDGE_SE2"]) if len(e) else np.zeros(0, np.int64)
        ej = _int_ids(path, "EDGE_SE2", e[:, 1], lines["EDGE_SE2"]) if len(e) else np.zeros(0, np.int64)
        meas = e[:, 2:5] if len(e) else np.zeros((0, 3))
        info = _sym_from_upper(e[:, 5:11], 3) if len(e) else np.zeros((0, 3, 3))
        info, note = _check_info(path, "EDGE_SE2", info, lines["EDGE_SE2"])
        notes = notes + [note] if note else notes
        _check_fix(path, text_lines, vid)
        return _assemble(path, 2, vid, vposes, ei, ej, meas, info, lines["EDGE_SE2"], "g2o", notes)
    v = _numbers(path, "VERTEX_SE3:QUAT", rows["VERTEX_SE3:QUAT"], lines["VERTEX_SE3:QUAT"])
    e = _numbers(path, "EDGE_SE3:QUAT", rows["EDGE_SE3:QUAT"], lines["EDGE_SE3:QUAT"])
    _check_finite(path, "VERTEX_SE3:QUAT", v, lines["VERTEX_SE3:QUAT"])
    _check_finite(path, "EDGE_SE3:QUAT", e, lines["EDGE_SE3:QUAT"])
    for tag, a, q in (("VERTEX_SE3:QUAT", v, slice(4, 8)), ("EDGE_SE3:QUAT", e, slice(5, 9))):
        if len(a):
            bad = np.flatnonzero(np.abs(np.linalg.norm(a[:, q], axis=1) - 1.0) > 1e-2)
            if len(bad):
                raise InputError(f"{path}:{lines[tag][bad[0]]}: {tag} quaternion is not unit length; fix the line")
    vid = _int_ids(path, "VERTEX_SE3:QUAT", v[:, 0], lines["VERTEX_SE3:QUAT"]) if len(v) else np.zeros(0, np.int64)
    vposes = pose_from_tum(v[:, 1:4], v[:, 4:8]) if len(v) else np.zeros((0, 4, 4))
    _check_fix(path, text_lines, vid)
    if len(e) == 0:
        raise InputError(f"{path}: the file has no pose-graph edges; give a graph with EDGE records")
    ei = _int_ids(path, "EDGE_SE3:QUAT", e[:, 0], lines["EDGE_SE3:QUAT"])
    ej = _int_ids(path, "EDGE_SE3:QUAT", e[:, 1], lines["EDGE_SE3:QUAT"])
    meas = pose_from_tum(e[:, 2:5], e[:, 5:9])
    info = _sym_from_upper(e[:, 9:30], 6)
    info, note = _check_info(path, "EDGE_SE3:QUAT", info, lines["EDGE_SE3:QUAT"])
    notes = notes + [note] if note else notes
    return _assemble(path, 3, vid, vposes, ei, ej, meas, info, lines["EDGE_SE3:QUAT"], "g2o", notes)


def _read_toro(path: Path, text_lines: list[str]) -> PoseGraphData:
    rows, lines, notes = _scan(path, text_lines, _TORO, _IGNORED["toro"])
    v = _numbers(path, "VERTEX2", rows["VERTEX2"], lines["VERTEX2"])
    e = _numbers(path, "EDGE2", rows["EDGE2"], lines["EDGE2"])
    if len(e) == 0:
        raise InputError(f"{path}: the file has no pose-graph edges; give a graph with EDGE records")
    _check_finite(path, "VERTEX2", v, lines["VERTEX2"])
    _check_finite(path, "EDGE2", e, lines["EDGE2"])
    vid = _int_ids(path, "VERTEX2", v[:, 0], lines["VERTEX2"]) if len(v) else np.zeros(0, np.int64)
    vposes = v[:, 1:4] if len(v) else np.zeros((0, 3))
    ei = _int_ids(path, "EDGE2", e[:, 0], lines["EDGE2"])
    ej = _int_ids(path, "EDGE2", e[:, 1], lines["EDGE2"])
    xx, xy, yy, tt, xt, yt = e[:, 5:11].T
    info = np.stack([np.stack([xx, xy, xt], -1), np.stack([xy, yy, yt], -1), np.stack([xt, yt, tt], -1)], 1)
    info, note = _check_info(path, "EDGE2", info, lines["EDGE2"])
    notes = notes + [note] if note else notes
    return _assemble(path, 2, vid, vposes, ei, ej, e[:, 2:5], info, lines["EDGE2"], "TORO", notes)


def _read_isam(path: Path, text_lines: list[str]) -> PoseGraphData:
    rows, lines, notes = _scan(path, text_lines, _ISAM, _IGNORED["isam"])
    two = rows["ODOMETRY"] + rows["EDGE2"]
    two_lines = lines["ODOMETRY"] + lines["EDGE2"]
    if two and rows["EDGE3"]:
        raise InputError(f"{path}: mixes 2-D and 3-D iSAM records; keep one kind per file")
    if two:
        # keep file order (ODOMETRY and EDGE2 interleave in time)
        order = np.argsort(two_lines, kind="stable")
        e = _numbers(path, "EDGE2", [two[k] for k in order], [two_lines[k] for k in order])
        el = [two_lines[k] for k in order]
        _check_finite(path, "EDGE2", e, el)
        ei = _int_ids(path, "EDGE2", e[:, 0], el)
        ej = _int_ids(path, "EDGE2", e[:, 1], el)
        R = np.zeros((len(e), 3, 3))
        R[:, _IU3[0], _IU3[1]] = e[:, 5:11]
        with np.errstate(over="ignore", invalid="ignore"):
            info = np.einsum("nki,nkj->nij", R, R)
        info, note = _check_info(path, "EDGE2", info, el, "information matrix (R^T R of the square-root entries)")
        notes = notes + [note] if note else notes
        return _assemble(path, 2, np.zeros(0, np.int64), np.zeros((0, 3)), ei, ej, e[:, 2:5], info, el, "iSAM", notes)
    e = _numbers(path, "EDGE3", rows["EDGE3"], lines["EDGE3"])
    el = lines["EDGE3"]
    if len(e) == 0:
        raise InputError(f"{path}: the file has no pose-graph edges; give a graph with EDGE records")
    _check_finite(path, "EDGE3", e, el)
    ei = _int_ids(path, "EDGE3", e[:, 0], el)
    ej = _int_ids(path, "EDGE3", e[:, 1], el)
    meas = np.tile(np.eye(4), (len(e), 1, 1))
    meas[:, :3, :3] = Rotation.from_euler("ZYX", e[:, [7, 6, 5]]).as_matrix()
    meas[:, :3, 3] = e[:, 2:5]
    R = np.zeros((len(e), 6, 6))
    R[:, _IU6[0], _IU6[1]] = e[:, 8:29]
    with np.errstate(over="ignore", invalid="ignore"):
        info = np.einsum("nki,nkj->nij", R, R)  # (x, y, z, roll, pitch, yaw) = g2o (t, r) order
    info, note = _check_info(path, "EDGE3", info, el, "information matrix (R^T R of the square-root entries)")
    notes = notes + [note] if note else notes
    return _assemble(path, 3, np.zeros(0, np.int64), np.zeros((0, 4, 4)), ei, ej, meas, info, el, "iSAM", notes)


def read_graph(path: str | Path, fmt: str = "auto") -> PoseGraphData:
    """Read a pose graph (g2o, TORO or iSAM; ``fmt="auto"`` detects it from the records)."""
    path = Path(path)
    require_file(path, "pose-graph file")
    if fmt not in FORMATS:
        raise InputError(f"unknown pose-graph format {fmt!r}; use one of {', '.join(FORMATS)}")
    text_lines = _lines(path)
    if fmt == "auto":
        fmt = detect_format(path, text_lines)
    return {"g2o": _read_g2o, "toro": _read_toro, "isam": _read_isam}[fmt](path, text_lines)


def _upper(M: np.ndarray, d: int) -> np.ndarray:
    iu = np.triu_indices(d)
    return M[:, iu[0], iu[1]]


def graph_to_g2o_text(graph: PoseGraphData, poses: np.ndarray | None = None) -> str:
    """The graph as g2o text; ``poses`` (default ``graph.poses``) become the VERTEX records."""
    poses = graph.poses if poses is None else np.asarray(poses, float)
    ids = graph.ids
    out: list[str] = []
    if graph.dim == 2:
        for k in range(len(ids)):
            x, y, t = poses[k]
            out.append(f"VERTEX_SE2 {ids[k]} {x:.17g} {y:.17g} {float(wrap_angle(t)):.17g}")
        up = _upper(graph.info, 3)
        for k in range(graph.n_edges):
            z = graph.meas[k]
            out.append(f"EDGE_SE2 {ids[graph.edges_i[k]]} {ids[graph.edges_j[k]]} "
                       + " ".join(f"{v:.17g}" for v in (*z, *up[k])))
    else:
        t, q = pose_to_tum(poses)
        for k in range(len(ids)):
            out.append(f"VERTEX_SE3:QUAT {ids[k]} " + " ".join(f"{v:.17g}" for v in (*t[k], *q[k])))
        te, qe = pose_to_tum(graph.meas)
        up = _upper(graph.info, 6)
        for k in range(graph.n_edges):
            out.append(f"EDGE_SE3:QUAT {ids[graph.edges_i[k]]} {ids[graph.edges_j[k]]} "
                       + " ".join(f"{v:.17g}" for v in (*te[k], *qe[k], *up[k])))
    return "\n".join(out) + "\n"


def write_g2o(path: str | Path, graph: PoseGraphData, poses: np.ndarray | None = None) -> None:
    """Write the graph (with ``poses`` as vertex estimates) as a g2o file, atomically."""
    atomic_write_text(path, graph_to_g2o_text(graph, poses))


def graph_info(path: str | Path, fmt: str = "auto") -> str:
    """A few lines describing a pose-graph file (kind, counts, degrees, repeated vertex pairs, notes)."""
    g = read_graph(path, fmt)
    a = np.minimum(g.edges_i, g.edges_j)
    b = np.maximum(g.edges_i, g.edges_j)
    _, per_pair = np.unique(np.stack([a, b], 1), axis=0, return_counts=True)
    deg = np.bincount(np.concatenate([g.edges_i, g.edges_j]), minlength=g.n_vertices)
    seq = int(np.sum(np.abs(g.edges_i - g.edges_j) == 1))
    # an edge "repeats" when an earlier edge joins the same two vertices (either direction)
    lines = [g.summary(),
             (f"odometry-like edges (between vertices adjacent in id order): {seq}; other edges: {g.n_edges - seq}; "
              f"edges repeating a vertex pair: {g.n_edges - len(per_pair)} "
              f"(on {int(np.sum(per_pair > 1))} vertex pairs with more than one edge)"),
             f"vertex degree: min {deg.min()}, mean {deg.mean():.2f}, max {deg.max()}"]
    lines += [f"note: {n}" for n in g.notes]
    return "\n".join(lines)
