"""The SLAM back end: a GTSAM Pose3 graph over keyframes (docs/slam.md).

* nodes: keyframes (frame index -> ``gtsam.symbol('x', index)``), a prior on the first one;
* odometry edges between consecutive keyframes, information from registration quality;
* loop edges from the loop closer, under a robust kernel (Cauchy/Huber,
  ``gtsam.noiseModel.Robust``) so that a rare false loop does little harm;
* iSAM2: pending factors are pushed into an incremental solver whenever a loop arrives,
  so the current estimate (and the drift ``correction``) stays up to date during the run;
* ``optimize``: a final batch Levenberg–Marquardt (or Gauss–Newton) over all factors, from
  the initial values chosen by ``cfg.init``: MASAT (docs/references.md §5), weighted
  MASAT, odometry chaining, BFS spanning tree, or the iSAM2 estimate.
"""

from __future__ import annotations

import time
from collections import deque
from typing import Any

import gtsam
import numpy as np

from rgbdslam.backend.config import BackendConfig
from rgbdslam.errors import InputError, RgbdslamError
from rgbdslam.geometry.graph import components
from rgbdslam.geometry.se3 import inv, project_to_so3


def key(index: int) -> int:
    return gtsam.symbol("x", int(index))


def _pose3(T: np.ndarray) -> gtsam.Pose3:
    T = np.asarray(T, dtype=np.float64)
    return gtsam.Pose3(gtsam.Rot3(project_to_so3(T[:3, :3])), gtsam.Point3(*T[:3, 3]))


def _check_information(info: np.ndarray, what: str) -> np.ndarray:
    info = np.asarray(info, dtype=np.float64)
    if info.shape != (6, 6) or not np.all(np.isfinite(info)):
        raise RgbdslamError(f"{what}: information must be a finite 6x6 matrix; fix the registration's information")
    info = 0.5 * (info + info.T)
    w = np.linalg.eigvalsh(info)
    if w[0] <= 0:  # regularise a semi-definite information
        info = info + np.eye(6) * max(1e-9, 1e-9 * w[-1] - w[0])
    return info


class KeyframeGraph:
    def __init__(self, cfg: BackendConfig):
        self.cfg = cfg
        self.order: list[int] = []  # keyframe indices in insertion order
        self.guess: dict[int, np.ndarray] = {}  # front-end poses
        self.odometry: list[tuple[int, int, np.ndarray, np.ndarray]] = []
        self._odo_factor: list[int] = []  # index in self.factors of each odometry edge's factor
        self.loops: list[Any] = []
        self.factors = gtsam.NonlinearFactorGraph()
        self._pending = gtsam.NonlinearFactorGraph()
        self._pending_values = gtsam.Values()
        self._isam: gtsam.ISAM2 | None = None
        self._estimate: dict[int, np.ndarray] = {}  # latest iSAM2 estimate
        self.stats: dict[str, Any] = {"isam2_updates": 0, "isam2_time_s": 0.0}
        # summed odometry covariance from the first keyframe along the keyframe chain
        self._chain_cov: dict[int, np.ndarray] = {}
        self.loop_kernel_widths: list[float] = []
        self.new_chain = False  # the next node starts a covariance chain (a session added to a loaded map)

    # ------------------------------------------------------------------ building
    def _noise(self, info: np.ndarray, robust: bool, width_scale: float = 1.0):
        base = gtsam.noiseModel.Gaussian.Information(info)
        kind = self.cfg.robust_kernel
        if not robust or kind == "none":
            return base
        w = self.cfg.kernel_width * width_scale
        est = gtsam.noiseModel.mEstimator.Cauchy.Create(w) if kind == "cauchy" else \
            gtsam.noiseModel.mEstimator.Huber.Create(w)
        return gtsam.noiseModel.Robust.Create(est, base)

    def _add_factor(self, f) -> None:
        self.factors.add(f)
        self._pending.add(f)

    def correction(self) -> np.ndarray:
        """World correction of the front end's drift: estimate(last) · guess(last)⁻¹."""
        for idx in reversed(self.order):
            if idx in self._estimate:
                return self._estimate[idx] @ inv(self.guess[idx])
        return np.eye(4)

    def add_node(self, index: int, pose_guess: np.ndarray) -> None:
        """A keyframe with its front-end pose (camera-to-world)."""
        index = int(index)
        if index in self.guess:
            raise RgbdslamError(f"keyframe {index} was added to the pose graph twice")
        pose_guess = np.array(pose_guess, dtype=np.float64)
        init = self.correction() @ pose_guess
        self.order.append(index)
        self.guess[index] = pose_guess
        if len(self.order) == 1 or self.new_chain:
            self._chain_cov[index] = np.zeros((6, 6))
            self.new_chain = False
        self._pending_values.insert(key(index), _pose3(init))
        if len(self.order) == 1:
            s = self.cfg.prior_sigma
            self._add_factor(gtsam.PriorFactorPose3(key(index), _pose3(pose_guess),
                                                    gtsam.noiseModel.Isotropic.Sigma(6, s)))

    def add_odometry(self, i: int, j: int, T_ij: np.ndarray, information: np.ndarray) -> None:
        """Relative pose ``pose_i⁻¹ · pose_j`` between keyframes (information rotation-first)."""
        self._require(i, j)
        info = _check_information(information, f"odometry edge {i}->{j}")
        T_ij = np.array(T_ij, dtype=np.float64)
        self.odometry.append((int(i), int(j), T_ij, info))
        self._odo_factor.append(int(self.factors.size()))
        if self.order and int(j) == self.order[-1] and int(i) in self._chain_cov:
            self._chain_cov[int(j)] = self._chain_cov[int(i)] + np.linalg.inv(info)
        self._add_factor(gtsam.BetweenFactorPose3(key(i), key(j), _pose3(T_ij), self._noise(info, False)))

    def refine_poses(self, poses: dict[int, np.ndarray]) -> int:
        """Keyframe poses refined by a stage of the chain (``SLAM._move_keyframes``): the nodes' guesses move and
        every odometry edge touching one of them is re-measured from the refined guesses (same
        information); the final batch sees the new measurements. iSAM2's running estimate keeps the
        edges it was given (it only serves ``correction`` during the run). Returns the edges re-measured."""
        moved = {int(k) for k in poses if int(k) in self.guess}
        for k in moved:
            self.guess[k] = np.array(poses[k], dtype=np.float64)
        n = 0
        for e, (i, j, _, info) in enumerate(self.odometry):
            if i in moved or j in moved:
                T_ij = inv(self.guess[i]) @ self.guess[j]
                self.odometry[e] = (i, j, T_ij, info)
                self.factors.replace(self._odo_factor[e], gtsam.BetweenFactorPose3(
                    key(i), key(j), _pose3(T_ij), self._noise(info, False)))
                n += 1
        return n

    def add_prior(self, index: int, pose: np.ndarray, sigma: float) -> None:
        """Hold a node at ``pose`` (isotropic ``sigma``; a loaded map kept fixed)."""
        self._require(index)
        self._add_factor(gtsam.PriorFactorPose3(key(index), _pose3(pose), gtsam.noiseModel.Isotropic.Sigma(6, sigma)))

    def set_chain_covariance(self, index: int, cov: np.ndarray) -> None:
        """The summed odometry covariance along the keyframe chain up to ``index`` (see :meth:`kernel_scale`;
        a loaded map's chains, which :meth:`add_odometry` follows only for the newest node)."""
        self._chain_cov[int(index)] = np.asarray(cov, dtype=np.float64)

    def add_loop(self, edge, update: bool = True) -> None:
        """A loop edge (robust kernel); triggers an iSAM2 update when ``cfg.isam2`` and ``update``."""
        self._require(edge.i, edge.j)
        info = _check_information(edge.information, f"loop edge {edge.i}->{edge.j}")
        self.loops.append(edge)
        scale = self.kernel_scale(int(edge.i), int(edge.j), info)
        self.loop_kernel_widths.append(self.cfg.kernel_width * scale)
        self._add_factor(gtsam.BetweenFactorPose3(key(edge.i), key(edge.j), _pose3(edge.T_ij),
                                                  self._noise(info, True, scale)))
        if self.cfg.isam2 and update:
            self.update()

    def kernel_scale(self, i: int, j: int, info: np.ndarray) -> float:
        """Chain-aware kernel width factor sqrt(1 + tr(Σ_chain Ω_loop) / 6).

        Before a loop is closed, its residual is expected to be as large as the odometry
        drift between i and j, whose covariance Σ_chain is (to first order, ignoring the
        rotation of the frames) the sum of the odometry covariances along the keyframe
        chain. Widening the kernel by that factor keeps legitimate loops in the kernel's
        near-quadratic zone while a false loop, far outside the chain's uncertainty, is
        down-weighted. ``cfg.kernel_chain_scaling = False`` gives the plain width.
        """
        if not self.cfg.kernel_chain_scaling or i not in self._chain_cov or j not in self._chain_cov:
            return 1.0
        cov = np.abs(self._chain_cov[j] - self._chain_cov[i])
        return float(np.sqrt(1.0 + max(np.trace(cov @ info), 0.0) / 6.0))

    def _require(self, *idx: int) -> None:
        for i in idx:
            if int(i) not in self.guess:
                raise RgbdslamError(f"pose-graph edge refers to keyframe {i}, which was never added with add_node")

    # ------------------------------------------------------------------ iSAM2
    def update(self) -> dict[int, np.ndarray]:
        """Push pending factors and values into iSAM2 and refresh the current estimate."""
        t0 = time.perf_counter()
        if self.stats.get("isam2_failed"):  # off for this run: the batch holds every factor anyway
            self._pending = gtsam.NonlinearFactorGraph()
            self._pending_values = gtsam.Values()
            return dict(self._estimate)
        if self._isam is None:
            params = gtsam.ISAM2Params()
            params.setRelinearizeThreshold(0.01)
            params.relinearizeSkip = 1
            self._isam = gtsam.ISAM2(params)
        try:
            self._isam.update(self._pending, self._pending_values)
            for _ in range(self.cfg.isam2_extra_updates):  # relinearisation steps after a loop
                self._isam.update()
            est = self._isam.calculateEstimate()
        except RuntimeError as e:  # e.g. an ill-conditioned system: keep going without iSAM2
            # every factor is also in self.factors, so the final batch still sees them all
            self.stats["isam2_failed"] = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            self._isam = None
            return self.update()  # clears what is pending
        self._pending = gtsam.NonlinearFactorGraph()
        self._pending_values = gtsam.Values()
        self._estimate = {i: est.atPose3(key(i)).matrix() for i in self.order if est.exists(key(i))}
        self.stats["isam2_updates"] += 1
        self.stats["isam2_time_s"] += time.perf_counter() - t0
        return dict(self._estimate)

    def estimate(self) -> dict[int, np.ndarray]:
        """The latest incremental estimate (front-end guesses, corrected, for newer nodes)."""
        c = self.correction()
        return {i: self._estimate.get(i, c @ self.guess[i]) for i in self.order}

    def as_graph(self, poses: dict[int, np.ndarray] | None = None):
        """The keyframe graph as a :class:`rgbdslam.posegraph.graph.PoseGraphData` (SE(3), vertex ids =
        frame indices, information in g2o order) for ``write_g2o``; vertices at ``poses``
        (default: the front-end guesses). The robust kernel of loop edges is not part of it."""
        from rgbdslam.posegraph.graph import PoseGraphData, info6_g2o_to_gtsam

        pos = {n: k for k, n in enumerate(self.order)}
        edges = self._edges()
        poses = poses or self.guess
        return PoseGraphData(
            dim=3,
            ids=np.array(self.order, dtype=np.int64),
            poses=np.array([poses.get(i, self.guess[i]) for i in self.order], float).reshape(-1, 4, 4),
            edges_i=np.array([pos[i] for i, _, _, _ in edges], dtype=np.int64),
            edges_j=np.array([pos[j] for _, j, _, _ in edges], dtype=np.int64),
            meas=np.array([T for _, _, T, _ in edges], float).reshape(-1, 4, 4),
            info=info6_g2o_to_gtsam(np.array([I for _, _, _, I in edges], float).reshape(-1, 6, 6)),  # swap back
            has_poses=True,
            source="rgbdslam run",
            notes=[f"{len(self.odometry)} odometry edges, then {len(self.loops)} loop edges"],
        )

    # ------------------------------------------------------------------ initial values
    def _edges(self) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
        return self.odometry + [(int(e.i), int(e.j), np.asarray(e.T_ij, float), np.asarray(e.information, float))
                                for e in self.loops]

    def _components(self) -> dict[int, int]:
        """Root keyframe (first in order) of each node's connected component over all edges."""
        pos = {k: n for n, k in enumerate(self.order)}
        label = components(len(self.order), [(pos[i], pos[j]) for i, j, _, _ in self._edges()])
        _, first = np.unique(label, return_index=True)
        return {k: self.order[first[label[n]]] for n, k in enumerate(self.order)}

    def initial_values(self, method: str | None = None) -> dict[int, np.ndarray]:
        """Initial poses for the batch optimisation (``cfg.init`` unless ``method`` is given)."""
        method = method or self.cfg.init
        if method == "isam2":
            if self._pending.size() or self._pending_values.size():
                self.update()
            return self.estimate()
        edges = self._edges()
        root = self._components()
        out: dict[int, np.ndarray] = {}
        for r in dict.fromkeys(root.values()):
            nodes = [i for i in self.order if root[i] == r]
            pos = {n: k for k, n in enumerate(nodes)}
            sub = [(pos[i], pos[j], T, I) for i, j, T, I in edges if i in pos]
            anchor = self.guess[r]
            if method in ("masat", "weighted_masat"):
                from rgbdslam.posegraph.masat import masat_initialize_pose3

                P = masat_initialize_pose3(len(nodes), sub, weighted=method == "weighted_masat", root=0)
            else:
                P = _chain(len(nodes), sub, tree=method == "spanning_tree")
            for n, k in pos.items():
                out[n] = anchor @ P[k]
        return out

    # ------------------------------------------------------------------ batch
    def optimize(self) -> dict[int, np.ndarray]:
        """Final batch optimisation; frame index -> optimised camera-to-world pose."""
        return self._batch(final=True)

    def batch_estimate(self) -> dict[int, np.ndarray]:
        """What :meth:`optimize` would give with the factors added so far, for the map fused while
        tracking. iSAM2's estimate is not that: on TUM fr1/rpy it stayed ~2 cm (median) from the
        final batch result up to the last loop (robust loop kernel, another linearisation path),
        while the batch of the factors so far was within millimetres of it once the last loops were
        in (docs/mapping.md). Changes nothing: neither iSAM2 nor the stats."""
        return self._batch(final=False)

    def _batch(self, final: bool) -> dict[int, np.ndarray]:
        if not self.order:
            return {}
        t0 = time.perf_counter()
        # during the run, initial values that would push pending factors into iSAM2 come from its estimate
        init = self.estimate() if not final and self.cfg.init == "isam2" else self.initial_values()
        graph = gtsam.NonlinearFactorGraph(self.factors)
        root = self._components()
        for r in dict.fromkeys(root.values()):
            if r != self.order[0]:  # anchor components that are not tied to the first keyframe
                graph.add(gtsam.PriorFactorPose3(key(r), _pose3(self.guess[r]),
                                                 gtsam.noiseModel.Isotropic.Sigma(6, self.cfg.prior_sigma)))
        values = gtsam.Values()
        for i in self.order:
            values.insert(key(i), _pose3(init[i]))
        if self.cfg.optimizer == "gn":
            params = gtsam.GaussNewtonParams()
            params.setMaxIterations(self.cfg.max_iterations)
            params.setRelativeErrorTol(self.cfg.relative_error_tol)
            opt = gtsam.GaussNewtonOptimizer(graph, values, params)
        else:
            params = gtsam.LevenbergMarquardtParams()
            params.setMaxIterations(self.cfg.max_iterations)
            params.setRelativeErrorTol(self.cfg.relative_error_tol)
            opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        initial_error = graph.error(values)
        try:
            result = opt.optimize()
        except RuntimeError as e:  # a failed batch must not lose the run: keep the initial guess
            if not final:
                return {i: init[i] for i in self.order}
            self.stats.update({"init": self.cfg.init, "nodes": len(self.order), "batch_failed": str(e).strip()[:200],
                               "batch_time_s": time.perf_counter() - t0})
            return {i: init[i] for i in self.order}
        if not final:
            return {i: result.atPose3(key(i)).matrix() for i in self.order}
        self.stats.update({
            "init": self.cfg.init, "nodes": len(self.order), "odometry_edges": len(self.odometry),
            "loop_edges": len(self.loops), "initial_error": float(initial_error),
            "final_error": float(graph.error(result)), "iterations": int(opt.iterations()),
            "batch_time_s": time.perf_counter() - t0,
        })
        return {i: result.atPose3(key(i)).matrix() for i in self.order}

    def loop_errors(self, poses: dict[int, np.ndarray]) -> list[float]:
        """Whitened (Mahalanobis) error of every loop edge under ``poses`` — large = outlier."""
        out = []
        for e in self.loops:
            f = gtsam.BetweenFactorPose3(key(e.i), key(e.j), _pose3(e.T_ij),
                                         gtsam.noiseModel.Gaussian.Information(_check_information(e.information, "loop")))
            v = gtsam.Values()
            v.insert(key(e.i), _pose3(poses[e.i]))
            v.insert(key(e.j), _pose3(poses[e.j]))
            out.append(float(np.sqrt(2.0 * f.error(v))))
        return out


def _chain(n: int, edges, tree: bool) -> np.ndarray:
    """Odometry (consecutive edges, in insertion order) or BFS spanning-tree chaining from 0."""
    P = np.tile(np.eye(4), (n, 1, 1))
    done = np.zeros(n, bool)
    done[0] = True
    if not tree:
        for i, j, T, _ in edges:
            if done[i] and not done[j]:
                P[j] = P[i] @ T
                done[j] = True
            elif done[j] and not done[i]:
                P[i] = P[j] @ inv(T)
                done[i] = True
        if done.all():
            return P
    adj: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(n)]
    for i, j, T, _ in edges:
        adj[i].append((j, T))
        adj[j].append((i, inv(T)))
    q = deque(np.flatnonzero(done).tolist())
    while q:
        w = q.popleft()
        for v, T in adj[w]:
            if not done[v]:
                P[v] = P[w] @ T
                done[v] = True
                q.append(v)
    if not done.all():
        raise InputError("the pose graph is not connected; every keyframe needs an edge")
    return P
