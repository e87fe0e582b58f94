"""The local bundle adjustment of :mod:`rgbdslam.landmarks.local_ba` solved in NumPy (``ba_solver: schur``).

The same problem as the GTSAM graph — one stereo-style factor per (keyframe, landmark)
observation (depth as a virtual disparity, the correlated pixel/disparity covariance, Huber),
one Gaussian prior per landmark (its Kalman estimate), the older keyframes held — and the same
Levenberg–Marquardt as GTSAM's ``LevenbergMarquardtOptimizer`` with its default parameters
(λ₀ = 1e-5, ×/÷ 10, identity damping, step accepted when the model fidelity exceeds 1e-3, a λ
search stopped when the cost changes by less than ``relativeErrorTol`` · cost, the same outer
convergence test), so the two follow the same path and agree to rounding (tested against GTSAM).

What is cheaper is the linear algebra. The problem is tiny in poses (a handful of free
keyframes) and large in landmarks; GTSAM eliminates every landmark as a variable of its own
(per-variable overhead dominates at this size). Here every observation is linearised at once
(arrays of (N, 3, 6) and (N, 3, 3) Jacobians) and the landmarks are eliminated in closed form:
the Schur complement

    S = H_pp + λI − Σ_l H_pl (H_ll + λI)⁻¹ H_lp,

a dense 6K × 6K system (K free keyframes) built from the observation pairs that share a
landmark, is solved by Cholesky; the landmark steps follow by back substitution, 3 × 3 each.

Residuals (whitened). The factor's covariance C = [[s², s², 0], [s², s² + σ_d², 0], [0, 0, s²]]
(s = σ_px, σ_d the disparity noise) has C⁻¹ = WᵀW with W = [[1/s, 0, 0], [−1/σ_d, 1/σ_d, 0],
[0, 0, 1/s]], so the whitened residual is (e_uL / s, (e_uR − e_uL) / σ_d, e_v / s): the left
pixel, the disparity, the row. Pose perturbations are GTSAM's: right, ξ = (ω, v), retracted by
the exponential map.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve

from rgbdslam.geometry.se3 import skew_batch

# GTSAM's LevenbergMarquardtParams defaults (the ones local_ba.solve keeps)
LAMBDA_INITIAL = 1e-5
LAMBDA_FACTOR = 10.0
LAMBDA_UPPER = 1e5
MIN_MODEL_FIDELITY = 1e-3
ABSOLUTE_ERROR_TOL = 1e-5


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """(K, 6) tangent vectors (ω, v) -> (K, 4, 4): GTSAM's ``Pose3.Expmap`` (R = exp ω, t = J_l(ω) v)."""
    xi = np.asarray(xi, float).reshape(-1, 6)
    w, v = xi[:, :3], xi[:, 3:]
    th2 = np.einsum("ni,ni->n", w, w)
    th = np.sqrt(th2)
    small = th2 < 1e-10
    ths = np.where(small, 1.0, th)
    A = np.where(small, 1.0 - th2 / 6.0, np.sin(ths) / ths)
    B = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(ths)) / (ths * ths))
    Cc = np.where(small, 1.0 / 6.0 - th2 / 120.0, (ths - np.sin(ths)) / (ths * ths * ths))
    K = skew_batch(w)
    KK = K @ K
    eye = np.eye(3)
    T = np.zeros((len(xi), 4, 4))
    T[:, :3, :3] = eye + A[:, None, None] * K + B[:, None, None] * KK
    V = eye + B[:, None, None] * K + Cc[:, None, None] * KK
    T[:, :3, 3] = np.einsum("nij,nj->ni", V, v)
    T[:, 3, 3] = 1.0
    return T


def _inverse_sym3(H: np.ndarray) -> np.ndarray | None:
    """Inverses of symmetric 3x3 matrices (N, 3, 3) by the adjugate; None if one is not invertible
    (a non-positive or non-finite determinant: H_ll + λI is positive definite when well posed)."""
    a, b, c = H[:, 0, 0], H[:, 0, 1], H[:, 0, 2]
    d, e, f = H[:, 1, 1], H[:, 1, 2], H[:, 2, 2]
    A = np.empty_like(H)
    A[:, 0, 0], A[:, 0, 1], A[:, 0, 2] = d * f - e * e, c * e - b * f, b * e - c * d
    A[:, 1, 1], A[:, 1, 2], A[:, 2, 2] = a * f - c * c, b * c - a * e, a * d - b * b
    A[:, 1, 0], A[:, 2, 0], A[:, 2, 1] = A[:, 0, 1], A[:, 0, 2], A[:, 1, 2]
    det = a * A[:, 0, 0] + b * A[:, 0, 1] + c * A[:, 0, 2]
    if not np.all(np.isfinite(det) & (det > 0)):
        return None
    return A / det[:, None, None]


def _huber_loss(e: np.ndarray, k: float) -> np.ndarray:
    a = np.abs(e)
    return np.where(a <= k, 0.5 * e * e, k * (a - 0.5 * k))


class SchurBA:
    """One local BA problem in arrays (built once; :meth:`optimize` runs LM on it).

    ``poses`` (P, 4, 4) camera-to-world of every keyframe in the problem, ``free`` (P,) bool which
    of them move; observations ``obs_pose`` (N,) index into ``poses``, ``obs_lm`` (N,) into the
    landmarks ``X0`` (L, 3); ``meas`` (N, 3) = (u_left, v, z) measured; ``sigma_d`` (N,) the
    disparity noise (px) of each observation; ``prior_info`` (L, 3, 3) the priors' information
    (None: no priors); camera (fx, fy, cx, cy) and ``fb`` = fx · baseline; ``sigma_px``; ``huber``.
    """

    def __init__(self, poses, free, obs_pose, obs_lm, meas, sigma_d, X0, prior_info, fx, fy, cx, cy, fb,
                 sigma_px, huber):
        self.poses = np.asarray(poses, float).copy()
        self.free = np.asarray(free, bool)
        self.slot = np.cumsum(self.free) - 1  # pose -> free slot
        self.K = int(self.free.sum())
        self.op, self.ol = np.asarray(obs_pose, np.int64), np.asarray(obs_lm, np.int64)
        self.um, self.vm, self.zm = meas[:, 0], meas[:, 1], meas[:, 2]
        self.X0 = np.asarray(X0, float)
        self.L = len(self.X0)
        self.prior = prior_info
        self.fx, self.fy, self.cx, self.cy, self.fb = fx, fy, cx, cy, fb
        self.s = sigma_px if np.ndim(sigma_px) == 0 else np.asarray(sigma_px, float)  # scalar or one per observation
        self.sd, self.k = np.asarray(sigma_d, float), float(huber)
        self.dm = fb / self.zm  # measured disparity
        # the observations of free keyframes, grouped by keyframe (H_pp: one GEMM per keyframe)
        self.of = np.flatnonzero(self.free[self.op])
        self.of = self.of[np.argsort(self.slot[self.op[self.of]], kind="stable")]
        self.oslot = self.slot[self.op[self.of]]
        self.p_starts = np.flatnonzero(np.r_[True, np.diff(self.oslot) != 0]) if len(self.of) else np.zeros(0, int)
        self.p_ids = self.oslot[self.p_starts]
        self.olf = self.ol[self.of]
        # H_lp as a dense grid of 3x6 blocks (landmark, keyframe): one observation per cell is
        # assigned; a keyframe that sees a landmark twice has its blocks summed
        cell = self.oslot * self.L + self.olf
        self.unique_cells = len(np.unique(cell)) == len(cell)
        self._last = None  # (poses, X, camera points, rotations) of the last projection

    # ------------------------------------------------------------------ model
    def _project(self, poses: np.ndarray, X: np.ndarray):
        """Camera points (N, 3) of every observation and the rotations (N, 3, 3) used (the last
        evaluation is kept: LM linearises where it last computed the error)."""
        if self._last is not None and self._last[0] is poses and self._last[1] is X:
            return self._last[2], self._last[3]
        R = poses[self.op, :3, :3]
        t = poses[self.op, :3, 3]
        P = np.einsum("nji,nj->ni", R, X[self.ol] - t)  # Rᵀ (X − t)
        self._last = (poses, X, P, R)
        return P, R

    def _residuals(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residuals (N, 3) and the cheirality mask (z <= 0: GTSAM's constant error)."""
        z = P[:, 2]
        bad = z <= 0
        zs = np.where(bad, 1.0, z)
        e_u = self.fx * P[:, 0] / zs + self.cx - self.um
        e_v = self.fy * P[:, 1] / zs + self.cy - self.vm
        e_d = self.dm - self.fb / zs  # (u_R − u_L) predicted − measured
        r = np.stack([e_u / self.s, e_d / self.sd, e_v / self.s], axis=1)
        if bad.any():  # GTSAM returns (2 fx, 2 fx, 2 fx) unwhitened, no Jacobian
            c = 2.0 * self.fx
            w = np.broadcast_to(c / (self.s if np.ndim(self.s) == 0 else self.s[bad]), bad.sum())
            r[bad] = np.stack([w, np.zeros(bad.sum()), w], axis=1)
        return r, bad

    def error(self, poses: np.ndarray, X: np.ndarray) -> float:
        """The graph's error: Σ Huber(‖whitened‖) + ½ Σ priors' Mahalanobis² (GTSAM's ``graph.error``)."""
        P, _ = self._project(poses, X)
        r, _ = self._residuals(P)
        e = float(_huber_loss(np.sqrt(np.einsum("ni,ni->n", r, r)), self.k).sum())
        if self.prior is not None:
            d = X - self.X0
            e += 0.5 * float(np.einsum("ni,nij,nj->", d, self.prior, d))
        return e

    def _linearize(self, poses: np.ndarray, X: np.ndarray):
        """Whitened, Huber-reweighted (√w) residuals b (N, 3) and Jacobians A_p (N, 3, 6), A_l (N, 3, 3),
        written out per entry: d(whitened)/d(camera point) D = [[d00, 0, d02], [0, 0, d12], [0, d21, d22]],
        A_p = D [[P]x | −I] (right perturbation), A_l = D Rᵀ."""
        P, R = self._project(poses, X)
        r, bad = self._residuals(P)
        norm = np.sqrt(np.einsum("ni,ni->n", r, r))
        sw = np.sqrt(np.where(norm <= self.k, 1.0, self.k / np.maximum(norm, 1e-300)))
        sw = np.where(bad, 0.0, sw)  # behind the camera: no Jacobian (the residual keeps its weight below)
        z = np.where(bad, 1.0, P[:, 2])
        iz = 1.0 / z
        x, y = P[:, 0], P[:, 1]
        d00, d02 = sw * self.fx * iz / self.s, -sw * self.fx * x * iz * iz / self.s
        d12 = sw * self.fb * iz * iz / self.sd
        d21, d22 = sw * self.fy * iz / self.s, -sw * self.fy * y * iz * iz / self.s
        px, py, pz = x, y, P[:, 2]
        n = len(P)
        Jp = np.zeros((n, 3, 6))
        Jp[:, 0, 0], Jp[:, 0, 1], Jp[:, 0, 2] = -d02 * py, d02 * px - d00 * pz, d00 * py
        Jp[:, 1, 0], Jp[:, 1, 1] = -d12 * py, d12 * px
        Jp[:, 2, 0], Jp[:, 2, 1], Jp[:, 2, 2] = d21 * pz - d22 * py, d22 * px, -d21 * px
        Jp[:, 0, 3], Jp[:, 0, 5] = -d00, -d02
        Jp[:, 1, 5] = -d12
        Jp[:, 2, 4], Jp[:, 2, 5] = -d21, -d22
        Jl = np.empty((n, 3, 3))  # rows of D Rᵀ: combinations of R's columns
        Jl[:, 0] = d00[:, None] * R[:, :, 0] + d02[:, None] * R[:, :, 2]
        Jl[:, 1] = d12[:, None] * R[:, :, 2]
        Jl[:, 2] = d21[:, None] * R[:, :, 1] + d22[:, None] * R[:, :, 2]
        sr = np.sqrt(np.where(norm <= self.k, 1.0, self.k / np.maximum(norm, 1e-300)))
        return r * sr[:, None], Jp, Jl

    # ------------------------------------------------------------------ linear algebra
    def _sum_lm(self, v: np.ndarray) -> np.ndarray:
        """Per-landmark sums (L,) of per-observation values ``v`` (N,)."""
        return np.bincount(self.ol, weights=v, minlength=self.L)

    def _normal(self, b, Jp, Jl, X):
        """The undamped normal equations' blocks: H_pp (K, 6, 6), H_pl as G (L, 3, 6K) (G[l] = H_lp,
        the landmark's rows), H_ll (L, 3, 3), gradients g_p (K, 6), g_l (L, 3) (H δ = −g)."""
        K, L = self.K, self.L
        Jpo = Jp[self.of]
        Hpp = np.zeros((K, 6, 6))
        gp = np.zeros((K, 6))
        ends = np.r_[self.p_starts[1:], len(self.of)]
        Jf, bf = Jpo.reshape(-1, 6), b[self.of].reshape(-1)
        for k, i0, i1 in zip(self.p_ids, 3 * self.p_starts, 3 * ends):  # one GEMM per free keyframe
            Hpp[k] = Jf[i0:i1].T @ Jf[i0:i1]
            gp[k] = Jf[i0:i1].T @ bf[i0:i1]
        blocks = Jl[self.of].transpose(0, 2, 1) @ Jpo  # H_lp per observation (M, 3, 6)
        G = np.zeros((L, 3, K, 6))
        if self.unique_cells:
            G[self.olf, :, self.oslot, :] = blocks
        else:
            np.add.at(G, (self.olf, slice(None), self.oslot, slice(None)), blocks)
        # H_ll and g_l entry by entry (6 + 3 sums per landmark)
        Hll = np.empty((L, 3, 3))
        for i in range(3):
            for j in range(i, 3):
                Hll[:, i, j] = Hll[:, j, i] = self._sum_lm(np.einsum("nk,nk->n", Jl[:, :, i], Jl[:, :, j]))
        gl = np.stack([self._sum_lm(np.einsum("nk,nk->n", Jl[:, :, i], b)) for i in range(3)], axis=1)
        if self.prior is not None:
            Hll += self.prior
            gl += (self.prior @ (X - self.X0)[:, :, None])[..., 0]
        return Hpp, G.reshape(L, 3, 6 * K), Hll, gp, gl

    def _solve(self, Hpp, G, Hll, gp, gl, lam: float):
        """The damped step (δ_p (K, 6), δ_l (L, 3)); None when the system is not positive definite."""
        K, L = self.K, self.L
        Hinv = _inverse_sym3(Hll + lam * np.eye(3))
        if Hinv is None:
            return None
        YT = Hinv @ G  # ((H_ll + λ)⁻¹ H_lp) per landmark (L, 3, 6K)
        Gf, Yf = G.reshape(3 * L, 6 * K), YT.reshape(3 * L, 6 * K)
        S = -(Gf.T @ Yf)  # Σ_l H_pl (H_ll + λ)⁻¹ H_lp
        for k in range(K):
            S[6 * k:6 * k + 6, 6 * k:6 * k + 6] += Hpp[k]
        S[np.diag_indices(6 * K)] += lam
        rhs = -gp.reshape(-1) + Yf.T @ gl.reshape(-1)
        try:
            dp = cho_solve(cho_factor(S, lower=True, check_finite=False), rhs, check_finite=False)
        except (LinAlgError, ValueError):
            return None
        if not np.all(np.isfinite(dp)):
            return None
        t = gl + (Gf @ dp).reshape(L, 3)
        dl = -(Hinv @ t[:, :, None])[..., 0]
        return dp.reshape(K, 6), dl

    def _linear_error(self, b, Jp, Jl, X, dp, dl) -> float:
        """½ ‖A δ − (−b)‖² over the undamped linear system (GTSAM's ``GaussianFactorGraph.error``)."""
        a = b + (Jl @ dl[self.ol][:, :, None])[..., 0]
        of = self.of
        a[of] += (Jp[of] @ dp[self.oslot][:, :, None])[..., 0]
        e = 0.5 * float(np.einsum("ni,ni->", a, a))
        if self.prior is not None:
            d = X - self.X0 + dl
            e += 0.5 * float(np.einsum("ni,nij,nj->", d, self.prior, d))
        return e

    def _retract(self, poses, X, dp, dl):
        new = poses.copy()
        if self.K:
            new[self.free] = poses[self.free] @ se3_exp(dp)
        return new, X + dl

    # ------------------------------------------------------------------ Levenberg-Marquardt
    def optimize(self, max_iterations: int, relative_tol: float):
        """GTSAM's LM loop (module doc); returns (poses, X, initial error, final error, iterations)."""
        poses, X = self.poses, self.X0.copy()
        err0 = err = self.error(poses, X)
        lam, it = LAMBDA_INITIAL, 0
        if err <= 0 or max_iterations <= 0:
            return poses, X, err0, err, it
        new_err = err
        while True:
            cur = new_err
            b, Jp, Jl = self._linearize(poses, X)
            Hpp, Hpl, Hll, gp, gl = self._normal(b, Jp, Jl, X)
            old_lin = self._linear_error(b, Jp, Jl, X, np.zeros((self.K, 6)), np.zeros((self.L, 3)))
            while True:  # tryLambda until it returns true
                success = stop = False
                step = self._solve(Hpp, Hpl, Hll, gp, gl, lam)
                if step is not None:
                    dp, dl = step
                    new_lin = self._linear_error(b, Jp, Jl, X, dp, dl)
                    lin_change = old_lin - new_lin
                    if lin_change >= 0:
                        cand_poses, cand_X = self._retract(poses, X, dp, dl)
                        cand_err = self.error(cand_poses, cand_X)
                        change = err - cand_err
                        if lin_change > np.finfo(float).eps * old_lin:
                            success = change / lin_change > MIN_MODEL_FIDELITY
                        if abs(change) < relative_tol * err:
                            stop = True
                if success:
                    poses, X, err = cand_poses, cand_X, cand_err
                    lam /= LAMBDA_FACTOR
                    it += 1
                    break
                if stop:
                    break
                lam *= LAMBDA_FACTOR
                if lam >= LAMBDA_UPPER:
                    break
            new_err = err
            if not (it < max_iterations and not _converged(relative_tol, cur, new_err) and np.isfinite(cur)):
                break
        return poses, X, err0, err, it


def _converged(relative_tol: float, cur: float, new: float) -> bool:
    """GTSAM's ``checkConvergence`` (errorTol 0, absoluteErrorTol 1e-5)."""
    if new <= 0:
        return True
    dec = cur - new
    return (relative_tol and dec / cur <= relative_tol) or dec <= ABSOLUTE_ERROR_TOL
