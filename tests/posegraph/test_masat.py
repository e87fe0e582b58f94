"""MASAT and the other initial guesses on small hand-made graphs (exact answers)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rgbdslam.geometry.se3 import inv
from rgbdslam.posegraph.graph import se2_between, se2_compose, se2_inverse
from rgbdslam.posegraph.masat import bfs_order, masat_initialize_pose2, masat_initialize_pose3, masat_se2
from rgbdslam.errors import InputError


def _pose3(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def test_bfs_order_and_parents():
    # 0-1, 0-2, 1-3, 2-3, 3-4
    order, parent = bfs_order(5, [0, 0, 1, 2, 3], [1, 2, 3, 3, 4])
    assert order.tolist() == [0, 1, 2, 3, 4]
    assert parent.tolist() == [-1, 0, 0, 1, 3]


def test_disconnected_graph_is_an_input_error():
    with pytest.raises(InputError, match="not connected"):
        bfs_order(4, [0, 2], [1, 3])


def test_masat_se2_consistent_measurements_are_exact():
    rng = np.random.default_rng(1)
    gt = np.column_stack([rng.uniform(-5, 5, 6), rng.uniform(-5, 5, 6), rng.uniform(-3, 3, 6)])
    gt[0] = 0
    pairs = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (0, 3), (5, 1), (2, 4)]
    edges = [(i, j, se2_between(gt[i], gt[j]), np.eye(3)) for i, j in pairs]
    for weighted in (False, True):
        est = masat_initialize_pose2(6, edges, weighted=weighted)
        np.testing.assert_allclose(est[:, :2], gt[:, :2], atol=1e-9)
        np.testing.assert_allclose(np.angle(np.exp(1j * (est[:, 2] - gt[:, 2]))), 0, atol=1e-9)


def test_masat_se2_two_fixed_neighbours_hand_computed():
    # BFS order 0, 1, 2; vertex 2 is predicted by 0 (z02) and 1 (z12).
    # vertex 1 = (1, 0, pi/2) from z01.
    # pred from 0: (2, 1, 0.2); pred from 1: (1,0,pi/2) ∘ (1, -1, -pi/2 + 0.4) = (1+1, 0+1, 0.4) = (2, 1, 0.4)
    # but shift the second by a translation error: z12 = (1.2, -1, -pi/2+0.4) -> pred (2, 1.2, 0.4)
    edges = [(0, 1, (1.0, 0.0, math.pi / 2), None), (0, 2, (2.0, 1.0, 0.2), None),
             (1, 2, (1.2, -1.0, -math.pi / 2 + 0.4), None)]
    est = masat_initialize_pose2(3, edges)
    np.testing.assert_allclose(est[1], [1.0, 0.0, math.pi / 2], atol=1e-12)
    np.testing.assert_allclose(est[2], [2.0, 1.1, 0.3], atol=1e-12)


def test_masat_se2_reversed_edge_is_inverted():
    # the edge 2->1 stored in the "wrong" direction must give the same prediction as 1->2
    z12 = np.array([1.2, -1.0, -math.pi / 2 + 0.4])
    z21 = se2_inverse(z12)
    edges = [(0, 1, (1.0, 0.0, math.pi / 2), None), (0, 2, (2.0, 1.0, 0.2), None), (2, 1, z21, None)]
    est = masat_initialize_pose2(3, edges)
    np.testing.assert_allclose(est[2], [2.0, 1.1, 0.3], atol=1e-12)


def test_masat_se2_circular_mean_across_pi():
    # two predictions of vertex 2's heading: pi - 0.1 and -pi + 0.3 -> circular mean pi + 0.1 (= -pi + 0.1)
    edges = [(0, 1, (0.0, 1.0, 0.0), None), (0, 2, (1.0, 0.0, math.pi - 0.1), None),
             (1, 2, (1.0, -1.0, -math.pi + 0.3), None)]
    est = masat_initialize_pose2(3, edges)
    assert est[2, 0] == pytest.approx(1.0) and est[2, 1] == pytest.approx(0.0)
    assert math.cos(est[2, 2] - (math.pi + 0.1)) == pytest.approx(1.0, abs=1e-12)
    assert abs(est[2, 2]) > 3.0  # a naive arithmetic mean would give ~0.1


def test_weighted_masat_se2_prefers_the_precise_prediction():
    # vertex 2: prediction from 0 is precise (info 1e4), from 1 is vague (info 1) -> close to the precise one
    precise, vague = np.eye(3) * 1e4, np.eye(3)
    edges = [(0, 1, (1.0, 0.0, 0.0), precise), (0, 2, (2.0, 0.0, 0.0), precise),
             (1, 2, (1.0, 1.0, 0.5), vague)]
    est = masat_initialize_pose2(3, edges, weighted=True)
    # hand computed: vt(pred0)=1e-4, vt(pred1)=vt1 + vt_e + |t12|^2 vr1 = 1e-4 + 1 + 2*1e-4
    w0, w1 = 1 / 1e-4, 1 / (1e-4 + 1.0 + 2e-4)
    assert est[2, 1] == pytest.approx(w1 * 1.0 / (w0 + w1), rel=1e-9)
    r0, r1 = 1 / 1e-4, 1 / (1e-4 + 1.0)
    assert est[2, 2] == pytest.approx(math.atan2(r1 * math.sin(0.5), r0 + r1 * math.cos(0.5)), rel=1e-9)
    plain = masat_initialize_pose2(3, edges)
    assert plain[2, 1] == pytest.approx(0.5)


def test_masat_se3_consistent_is_exact():
    rng = np.random.default_rng(2)
    gt = [np.eye(4)] + [_pose3(rng.normal(size=3), rng.normal(size=3) * 3) for _ in range(5)]
    pairs = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (0, 3), (5, 1), (4, 2)]
    edges = [(i, j, inv(gt[i]) @ gt[j], np.eye(6)) for i, j in pairs]
    for weighted in (False, True):
        est = masat_initialize_pose3(6, edges, weighted=weighted)
        np.testing.assert_allclose(est, np.array(gt), atol=1e-9)


def test_masat_se3_chordal_mean_hand_computed():
    # vertex 2 gets two predictions rotated about z by +0.2 and +0.6 and translated (1,0,0) / (1,0.4,0):
    # chordal mean of two rotations about the same axis = rotation by the mean angle 0.4.
    T01 = _pose3([0, 0, 0], [0, 1, 0])
    T02 = _pose3([0, 0, 0.2], [1, 0, 0])
    pred_from_1 = _pose3([0, 0, 0.6], [1, 0.4, 0])
    T12 = inv(T01) @ pred_from_1
    est = masat_initialize_pose3(3, [(0, 1, T01, None), (0, 2, T02, None), (1, 2, T12, None)])
    np.testing.assert_allclose(est[2, :3, 3], [1.0, 0.2, 0.0], atol=1e-12)
    np.testing.assert_allclose(est[2, :3, :3], Rotation.from_rotvec([0, 0, 0.4]).as_matrix(), atol=1e-12)


def test_masat_se3_chordal_mean_different_axes():
    # chordal mean of rotations about x by +a and about y by +a: project (Rx + Ry) onto SO(3)
    a = 0.5
    Rx = Rotation.from_rotvec([a, 0, 0]).as_matrix()
    Ry = Rotation.from_rotvec([0, a, 0]).as_matrix()
    T01 = _pose3([0, 0, 0], [0, 0, 1])
    T02 = np.eye(4); T02[:3, :3] = Rx
    P = np.eye(4); P[:3, :3] = Ry
    T12 = inv(T01) @ P
    est = masat_initialize_pose3(3, [(0, 1, T01, None), (0, 2, T02, None), (1, 2, T12, None)])
    U, _, Vt = np.linalg.svd(Rx + Ry)
    np.testing.assert_allclose(est[2, :3, :3], U @ Vt, atol=1e-12)
    # by symmetry it is the rotation by some angle about the (1,1,0) axis
    rv = Rotation.from_matrix(est[2, :3, :3]).as_rotvec()
    assert rv[0] == pytest.approx(rv[1]) and abs(rv[2]) < 1e-12


def test_masat_se3_weighted_info_order():
    # translation precise / rotation vague on one edge: order matters for the weights
    T01 = _pose3([0, 0, 0], [1, 0, 0])
    T02 = _pose3([0, 0, 0], [2, 0, 0])
    T12 = _pose3([0, 0, 0], [1, 1, 0])  # pred from 1: (2, 1, 0)
    info_rt = np.diag([1e4, 1e4, 1e4, 1, 1, 1])  # rot precise, trans vague (GTSAM order)
    edges = [(0, 1, T01, np.eye(6) * 1e4), (0, 2, T02, np.eye(6) * 1e4), (1, 2, T12, info_rt)]
    est = masat_initialize_pose3(3, edges, weighted=True)
    w0 = 1 / 1e-4
    w1 = 1 / (1e-4 + 1.0 + 2.0 * 1e-4)  # |t12|^2 = 2 times vertex 1's rotation variance
    assert est[2, 1, 3] == pytest.approx(w1 / (w0 + w1), rel=1e-9)
    # same numbers in g2o order give the same answer
    edges_g2o = [(i, j, T, np.roll(np.roll(I, 3, 0), 3, 1)) for i, j, T, I in edges]
    est2 = masat_initialize_pose3(3, edges_g2o, weighted=True, info_order="trans_rot")
    np.testing.assert_allclose(est2, est, atol=1e-12)


def _seed_queue(nbrs):
    """Algorithm 1's start: vertex 0 fixed, its neighbours queued in id order."""
    from collections import deque

    selected, q = {0}, deque()
    for v, _ in sorted(nbrs[0], key=lambda p: p[0]):
        if v not in selected:
            selected.add(v)
            q.append(v)
    return selected, q


def _masat2_reference(n, ei, ej, z):
    """Algorithm 1 for SE(2) written out literally: a FIFO queue from vertex 0, neighbours taken in
    increasing index; a vertex leaving the queue is placed at the mean of the predictions
    X_v ∘ z_vw of its already placed neighbours v (x, y averaged, heading = circular mean).
    Returns (poses, the order in which vertices were placed)."""

    nbrs = {v: [] for v in range(n)}
    for i, j, (x, y, t) in zip(ei, ej, z):
        c, s = math.cos(t), math.sin(t)
        nbrs[int(i)].append((int(j), (-(c * x + s * y), s * x - c * y, -t)))  # z_ji = z_ij^-1
        nbrs[int(j)].append((int(i), (x, y, t)))
    X = [None] * n
    X[0] = (0.0, 0.0, 0.0)
    placed = [0]
    selected, q = _seed_queue(nbrs)
    while q:
        w = q.popleft()
        preds = []
        for v, (x, y, t) in sorted(nbrs[w], key=lambda p: p[0]):
            if v not in selected:
                selected.add(v)
                q.append(v)
            elif X[v] is not None:
                xv, yv, tv = X[v]
                preds.append((xv + math.cos(tv) * x - math.sin(tv) * y, yv + math.sin(tv) * x + math.cos(tv) * y, tv + t))
        X[w] = (sum(p[0] for p in preds) / len(preds), sum(p[1] for p in preds) / len(preds),
                math.atan2(sum(math.sin(p[2]) for p in preds), sum(math.cos(p[2]) for p in preds)))
        placed.append(w)
    return np.array(X), placed


def test_masat_se2_matches_literal_algorithm_1_at_any_measurement_scale():
    """The visiting order and the set of predictions per vertex come from the graph alone (the basis
    of "run time independent of the noise", which needs a timer to test and is not tested here): the
    BFS order equals the literal algorithm's placement order, and the poses equal its answer for
    measurements at very different scales, on a random graph with reversed and repeated edges."""
    rng = np.random.default_rng(0)
    n = 60
    pairs = [(k, k + 1) for k in range(n - 1)] + [tuple(rng.choice(n, 2, replace=False)) for _ in range(50)]
    pairs += pairs[60:65]  # repeated vertex pairs: each copy is one prediction
    flip = rng.random(len(pairs)) < 0.3  # some edges stored j -> i
    ei = np.array([j if f else i for (i, j), f in zip(pairs, flip)])
    ej = np.array([i if f else j for (i, j), f in zip(pairs, flip)])
    order, _ = bfs_order(n, ei, ej)
    for scale in (0.01, 10.0):
        z = rng.normal(size=(len(ei), 3)) * scale
        z[:, 2] = np.angle(np.exp(1j * z[:, 2]))
        ref, placed = _masat2_reference(n, ei, ej, z)
        assert order.tolist() == placed
        np.testing.assert_array_equal(bfs_order(n, ei, ej)[0], order)
        est = masat_se2(n, ei, ej, z)
        np.testing.assert_allclose(est[:, :2], ref[:, :2], atol=1e-9 * max(1.0, scale), err_msg=f"scale {scale}")
        np.testing.assert_allclose(np.angle(np.exp(1j * (est[:, 2] - ref[:, 2]))), 0, atol=1e-9,
                                   err_msg=f"scale {scale}")


# ------------------------------------------------------------------------ other initial guesses

from rgbdslam.posegraph.graph import PoseGraphData  # noqa: E402
from rgbdslam.posegraph.initializers import initialize, odometry, spanning_tree  # noqa: E402


def _se2_close(a, b, atol=1e-12):
    a, b = np.atleast_2d(a), np.atleast_2d(b)
    np.testing.assert_allclose(a[:, :2], b[:, :2], atol=atol)
    np.testing.assert_allclose(np.angle(np.exp(1j * (a[:, 2] - b[:, 2]))), 0, atol=atol)


def _graph2(poses_gt, pairs, noise=None):
    ei = np.array([p[0] for p in pairs])
    ej = np.array([p[1] for p in pairs])
    z = se2_between(poses_gt[ei], poses_gt[ej])
    if noise is not None:
        z = z + noise
    n = len(poses_gt)
    return PoseGraphData(2, np.arange(n), np.zeros((n, 3)), ei, ej, z, np.tile(np.eye(3) * 100, (len(ei), 1, 1)))


def test_odometry_and_spanning_tree_hand_computed():
    # chain 0-1-2-3 plus a loop edge 0->3 that disagrees with the chain
    gt = np.array([[0, 0, 0], [1, 0, math.pi / 2], [1, 1, math.pi], [0, 1, -math.pi / 2]], float)
    noise = np.zeros((4, 3))
    noise[3] = [0.3, 0.0, 0.1]  # corrupt the loop edge 0->3
    g = _graph2(gt, [(0, 1), (1, 2), (2, 3), (0, 3)], noise)
    _se2_close(odometry(g), gt)  # odometry ignores the loop edge
    # BFS from 0: parents 1<-0, 3<-0 (the corrupted edge), 2<-1
    st = spanning_tree(g)
    _se2_close(st[:3], gt[:3])
    _se2_close(st[3], [0.3, 1.0, -math.pi / 2 + 0.1])
    # MASAT: vertex 3 is placed from 0 only (vertex 2 is later in BFS order), vertex 2 from 1 and 3
    ms = initialize(g, "masat")
    _se2_close(ms[3], st[3])
    pred_from_3 = se2_compose(st[3], se2_between(gt[3], gt[2]))
    np.testing.assert_allclose(ms[2, :2], (gt[2, :2] + pred_from_3[:2]) / 2, atol=1e-12)


def test_spanning_tree_tie_breaking_hand_computed():
    """Square 0-2, 0-1, 1-3, 2-3 (edges in that file order): vertex 3 has two parents one level up.
    By index, 1 is dequeued before 2 and places 3; in file order (g2o's), 0's first edge leads to 2."""
    from rgbdslam.posegraph.initializers import bfs_tree_ordered

    gt = np.array([[0, 0, 0], [1, 0, 0.5], [0, 1, -0.5], [1, 1, 1.0]], float)
    noise = np.zeros((4, 3))
    noise[2] = [0.2, 0.0, 0.0]  # corrupt 1->3
    noise[3] = [0.0, -0.1, 0.05]  # corrupt 2->3
    g = _graph2(gt, [(0, 2), (0, 1), (1, 3), (2, 3)], noise)
    order, parent, edge_of = bfs_tree_ordered(4, g.edges_i, g.edges_j, "index")
    assert order.tolist() == [0, 1, 2, 3] and parent.tolist() == [-1, 0, 0, 1] and edge_of[3] == 2
    order, parent, edge_of = bfs_tree_ordered(4, g.edges_i, g.edges_j, "edge_order")
    assert order.tolist() == [0, 2, 1, 3] and parent.tolist() == [-1, 0, 0, 2] and edge_of[3] == 3
    by_index, by_file = spanning_tree(g), spanning_tree(g, "edge_order")
    _se2_close(by_index[:3], gt[:3])
    _se2_close(by_file[:3], gt[:3])
    _se2_close(by_index[3], se2_compose(gt[1], g.meas[2]))
    _se2_close(by_file[3], se2_compose(gt[2], g.meas[3]))
    # a random order (seeded) is a valid BFS tree: every parent is one level up, and reproducible
    depth = {0: 0, 1: 1, 2: 1, 3: 2}
    for seed in range(5):
        o, p, e = bfs_tree_ordered(4, g.edges_i, g.edges_j, seed)
        assert all(depth[int(p[v])] == depth[v] - 1 for v in (1, 2, 3))
        for v in (1, 2, 3):  # the placing edge joins the vertex and its parent
            assert {int(g.edges_i[e[v]]), int(g.edges_j[e[v]])} == {v, int(p[v])}
        np.testing.assert_array_equal(p, bfs_tree_ordered(4, g.edges_i, g.edges_j, seed)[1])
    with pytest.raises(InputError, match="tie break"):
        spanning_tree(g, "nope")


def test_odometry_inverts_backward_edges_and_reports_gaps():
    gt = np.array([[0, 0, 0], [1, 0, 0.5], [2, 1, 1.0]])
    g = _graph2(gt, [(1, 0), (1, 2)])
    _se2_close(odometry(g), gt)
    g2 = _graph2(np.vstack([gt, [[3, 1, 0]]]), [(0, 1), (1, 2), (1, 3)])
    with pytest.raises(InputError, match="no odometry edge between vertices 2 and 3"):
        odometry(g2)


def test_gtsam_initialisers_exact_on_consistent_graphs():
    rng = np.random.default_rng(3)
    gt = np.column_stack([rng.uniform(-3, 3, 8), rng.uniform(-3, 3, 8), rng.uniform(-1, 1, 8)])
    gt[0] = 0
    pairs = [(k, k + 1) for k in range(7)] + [(0, 4), (2, 6), (7, 1)]
    g = _graph2(gt, pairs)
    _se2_close(initialize(g, "lago"), gt, atol=1e-6)
    # SE(3): chordal
    gt3 = [np.eye(4)] + [_pose3(rng.normal(size=3) * 0.5, rng.normal(size=3)) for _ in range(5)]
    p3 = [(k, k + 1) for k in range(5)] + [(0, 3), (1, 5)]
    ei = np.array([p[0] for p in p3]); ej = np.array([p[1] for p in p3])
    z = np.array([inv(gt3[i]) @ gt3[j] for i, j in p3])
    g3 = PoseGraphData(3, np.arange(6), np.tile(np.eye(4), (6, 1, 1)), ei, ej, z, np.tile(np.eye(6), (len(ei), 1, 1)))
    for m in ("chordal", "odometry", "spanning_tree", "masat", "weighted_masat"):
        np.testing.assert_allclose(initialize(g3, m), np.array(gt3), atol=1e-6, err_msg=m)


def test_unknown_method():
    g = _graph2(np.zeros((2, 3)), [(0, 1)])
    with pytest.raises(InputError, match="unknown initialisation method"):
        initialize(g, "magic")


def _masat3_reference(n, edges):
    """Algorithm 1 written out literally (queue, selected/fixed flags), for SE(3)."""

    nbrs = {v: [] for v in range(n)}
    for i, j, T, _ in edges:
        nbrs[i].append((j, inv(T)))  # prediction of i from j: X_j T_ij^-1
        nbrs[j].append((i, T))  # prediction of j from i: X_i T_ij
    X = [None] * n
    X[0] = np.eye(4)
    selected, q = _seed_queue(nbrs)
    while q:
        w = q[0]
        preds = []
        for v, Tvw in sorted(nbrs[w], key=lambda p: p[0]):
            if v not in selected:
                selected.add(v)
                q.append(v)
            elif X[v] is not None:
                preds.append(X[v] @ Tvw)
        M = sum(p[:3, :3] for p in preds)
        U, _, Vt = np.linalg.svd(M)
        P = np.eye(4)
        P[:3, :3] = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
        P[:3, 3] = np.mean([p[:3, 3] for p in preds], axis=0)
        X[w] = P
        q.popleft()
    return np.array(X)


def test_masat_se3_matches_literal_algorithm_1_on_inconsistent_graph():
    rng = np.random.default_rng(11)
    n = 40
    gt = [np.eye(4)] + [_pose3(rng.normal(size=3), rng.normal(size=3) * 2) for _ in range(n - 1)]
    pairs = [(k, k + 1) for k in range(n - 1)] + [tuple(sorted(rng.choice(n, 2, replace=False))) for _ in range(40)]
    edges = []
    for i, j in pairs:
        T = inv(gt[i]) @ gt[j] @ _pose3(rng.normal(size=3) * 0.2, rng.normal(size=3) * 0.3)
        edges.append((int(j), int(i), inv(T), None) if rng.random() < 0.3 else (int(i), int(j), T, None))
    np.testing.assert_allclose(masat_initialize_pose3(n, edges), _masat3_reference(n, edges), atol=1e-10)


def test_weighted_masat_conservative_variance_propagation_hand_computed():
    # isotropic edges: info = I / v, so an edge's translation and rotation variance are both v
    def e(i, j, z, v):
        return (i, j, z, np.eye(3) / v)

    v01, v02, v12, v23, v03 = 0.01, 0.05, 0.02, 0.03, 0.2
    edges = [e(0, 1, (1.0, 0.0, 0.0), v01), e(0, 2, (0.0, 1.0, 0.0), v02), e(1, 2, (-1.0, 1.0, 0.0), v12),
             e(2, 3, (1.0, 0.0, 0.0), v23), e(0, 3, (1.0, 1.5, 0.0), v03)]
    est = masat_initialize_pose2(4, edges, weighted=True)
    # vertex 1: VT = VR = v01.  Vertex 2: predictions from 0 (vt = vr = v02) and from 1
    # (vt = v01 + v12 + |(-1,1)|^2 v01, vr = v01 + v12) -> kept variance = the smaller one
    vt2 = min(v02, v01 + v12 + 2 * v01)
    vr2 = min(v02, v01 + v12)
    # vertex 3: prediction from 2 is (1, 1) with vt = vt2 + v23 + 1 * vr2, from 0 is (1, 1.5) with vt = v03
    w2, w0 = 1 / (vt2 + v23 + vr2), 1 / v03
    assert est[3, 1] == pytest.approx((w2 * 1.0 + w0 * 1.5) / (w2 + w0), rel=1e-12)
    assert est[3, 0] == pytest.approx(1.0, rel=1e-12)


def test_posegraph_edge_list3_feeds_masat_initialize_pose3():
    from rgbdslam.posegraph.masat import masat

    rng = np.random.default_rng(5)
    n = 12
    gt = [np.eye(4)] + [_pose3(rng.normal(size=3) * 0.3, rng.normal(size=3)) for _ in range(n - 1)]
    pairs = [(k, k + 1) for k in range(n - 1)] + [(0, 5), (3, 9), (11, 2)]
    ei = np.array([p[0] for p in pairs]); ej = np.array([p[1] for p in pairs])
    z = np.array([inv(gt[i]) @ gt[j] @ _pose3(rng.normal(size=3) * 0.05, rng.normal(size=3) * 0.05)
                  for i, j in pairs])
    info = np.tile(np.diag([100.0, 100, 100, 400, 400, 400]), (len(pairs), 1, 1))  # g2o order: t then r
    info[3] = np.diag([1.0, 1, 1, 2, 2, 2])
    g = PoseGraphData(3, np.arange(n), np.tile(np.eye(4), (n, 1, 1)), ei, ej, z, info)
    for w in (False, True):
        np.testing.assert_allclose(masat_initialize_pose3(n, g.edge_list3(), weighted=w), masat(g, weighted=w),
                                   atol=1e-12)


# ----------------------------------------------------------------------- input validation (one line)


from tests.conftest import assert_cli_error as _assert_cli_error, cli as _cli  # noqa: E402


def test_weighted_masat_survives_variances_that_overflow():
    """A 1e200 m measurement makes |t|^2 * var(heading) overflow: every weight of vertex 2 became 0
    and the fused position 0/0 (ZeroDivisionError).  Capped variances keep the plain chained answer."""
    gt = np.array([[0, 0, 0], [1, 0, 0.1], [1e200, 0, 0.2], [1e200, 1, 0.3]], float)
    pairs = [(0, 1), (1, 2), (2, 3)]
    ei, ej = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
    z = se2_between(gt[ei], gt[ej])
    for info in (np.eye(3), np.diag([1.0, 1.0, 1e-300])):  # ordinary and near-zero heading information
        p = masat_se2(4, ei, ej, z, np.tile(info, (3, 1, 1)), weighted=True)
        assert np.all(np.isfinite(p))
        np.testing.assert_allclose(p, masat_se2(4, ei, ej, z), rtol=1e-12)
    # SE(3): the same chain
    T = [np.eye(4), _pose3([0, 0, 0.1], [1, 0, 0]), _pose3([0, 0, 0.2], [1e200, 0, 0]), _pose3([0, 0, 0.3], [1e200, 1, 0])]
    edges = [(i, j, inv(T[i]) @ T[j], np.eye(6)) for i, j in pairs]
    p3 = masat_initialize_pose3(4, edges, weighted=True)
    assert np.all(np.isfinite(p3))
    np.testing.assert_allclose(p3, masat_initialize_pose3(4, edges), rtol=1e-9)


def test_weighted_masat_singular_information_means_an_unmeasured_direction():
    """An edge without heading information says nothing about the heading: its heading variance is
    infinite (capped), not the pseudo-inverse's 0 (which made it the most trusted prediction)."""
    from rgbdslam.posegraph.masat import _MAX_VAR, _edge_variances

    vt, vr = _edge_variances(np.array([np.diag([4.0, 4.0, 0.0]), np.diag([1.0, 1.0, 2.0])]), 2, slice(0, 2), slice(2, 3))
    np.testing.assert_allclose(vt, [0.25, 1.0])
    np.testing.assert_allclose(vr, [_MAX_VAR, 0.5])
    # vertex 2 is predicted from 0 (heading measured, -0.2) and from 1 (no heading information, +0.4)
    gt = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0]], float)
    z = se2_between(gt[[0, 0, 1]], gt[[1, 2, 2]])
    z[1, 2], z[2, 2] = -0.2, 0.4
    info = np.array([np.eye(3), np.eye(3), np.diag([1.0, 1.0, 0.0])])
    p = masat_se2(3, [0, 0, 1], [1, 2, 2], z, info, weighted=True)
    assert p[2, 2] == pytest.approx(-0.2, abs=1e-9)


_SE3_CHAIN = ("VERTEX_SE3:QUAT 3 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 5 1 0 0 0 0 0 1\nVERTEX_SE3:QUAT 8 2 0 0 0 0 0 1\n"
              "EDGE_SE3:QUAT 3 5 1 0 0 0 0 0 1 10 0 0 0 0 0 10 0 0 0 0 10 0 0 0 {r} 0 0 {r} 0 {r}\n"
              "EDGE_SE3:QUAT 5 8 1 0 0 0 0 0 1 10 0 0 0 0 0 10 0 0 0 0 10 0 0 0 {r} 0 0 {r} 0 {r}\n")


def test_lago_on_a_3d_graph_is_an_error_not_a_relabelled_chordal_run(tmp_path):
    src = tmp_path / "pg_3d.g2o"
    src.write_text(_SE3_CHAIN.format(r=10))
    msg = (f"{src} (g2o): LAGO is for 2-D (SE(2)) graphs only and this graph is 3-D (SE(3)); "
           "use --method chordal (GTSAM's chordal initialiser) or masat")
    out = tmp_path / "o.g2o"
    _assert_cli_error(_cli(["posegraph", "init", src, "--method", "lago", "-o", out]), msg)
    _assert_cli_error(_cli(["posegraph", "optimize", src, "--init", "lago", "-q"]), msg)
    assert not out.exists()
    # chordal works on it; on a tree (here a chain) GTSAM's InitializePose3 would throw, but the
    # relaxation's optimum is the exact chain
    res = _cli(["posegraph", "init", src, "--method", "chordal", "-o", out])
    assert res.exit_code == 0 and "chordal initial guess" in res.stdout, res.output
    from rgbdslam.posegraph.graph_io import read_graph

    np.testing.assert_allclose(read_graph(out).poses[:, :3, 3], [[0, 0, 0], [1, 0, 0], [2, 0, 0]], atol=1e-12)


def test_lago_needs_diagonal_information():
    """GTSAM's LAGO raised ValueError("buildLinearOrientationGraph: invalid noise model ...")."""
    gt = np.array([[0, 0, 0], [1, 0, 0.1], [2, 0, 0.2]])
    g = _graph2(gt, [(0, 1), (1, 2), (0, 2)])
    g.ids = np.array([3, 5, 9])
    g.source = "h.g2o (g2o)"
    g.info[1] = [[100, 10, 0], [10, 100, 0], [0, 0, 100]]
    with pytest.raises(InputError) as e:
        initialize(g, "lago")
    assert str(e.value) == ("h.g2o (g2o): GTSAM's LAGO needs diagonal information matrices, and 1 edge(s) have "
                            "off-diagonal terms (the first joins vertices 5 and 9); use --method chordal (our SE(2) "
                            "chordal relaxation uses the full information) or masat")


def test_gtsam_initialiser_failure_is_one_line(tmp_path):
    """No rotation information: GTSAM's InitializePose3 throws its 12-line IndeterminantLinearSystem
    text (with a URL); the error keeps its first sentence, names the file's vertex id, adds the fix."""
    src = tmp_path / "pg_3d.g2o"
    loop = "EDGE_SE3:QUAT 3 8 2 0 0 0 0 0 1 10 0 0 0 0 0 10 0 0 0 0 10 0 0 0 0 0 0 0 0 0\n"  # not a tree
    src.write_text(_SE3_CHAIN.format(r=0) + loop)
    _assert_cli_error(_cli(["posegraph", "init", src, "--method", "chordal", "-o", tmp_path / "o.g2o"]),
                      f"{src} (g2o): GTSAM's chordal initialiser (InitializePose3) failed (Indeterminate linear "
                      "system detected while working near vertex 3.); check that the information of that vertex's "
                      "edges constrains its rotation, or use --method masat")
