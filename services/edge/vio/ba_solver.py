"""Sparse Schur-complement Levenberg–Marquardt for the local bundle adjustment.

The reprojection terms (thousands) are linearised in numpy for all observations at once; the
few other factors (CombinedImuFactor, priors) stay a small gtsam graph that gtsam linearises
every iteration, and its information matrix joins the camera-side system. Map points are
eliminated with batched 3×3 inverses (Schur complement), the reduced camera system is solved
(densely up to ``SPARSE_MIN_DIM`` dimensions, beyond it as a sparse matrix by
:mod:`services.edge.vio.ba_sparse`: the VI refinements over every keyframe), and the points
are back-substituted.

The problem and the LM schedule are gtsam's, so both paths of
:func:`services.edge.vio.local_ba.bundle_adjust` agree: reprojection of a point ``p_world`` into
the camera of ``T_world_body @ T_body_cam`` on normalised coordinates, whitened by ``sigma``
and robustified by Cauchy(k) as iteratively reweighted least squares (cost
``0.5·k²·log(1 + r²/k²)``, as gtsam's ``Robust`` noise model; a point behind the camera gives
gtsam's constant residual ``(2, 2)`` with zero Jacobians); pose tangent ``(omega, v)`` with
``T·Exp(xi)``, points retracted additively; ``H + lambda·I`` damping of every variable with
gtsam's ``LevenbergMarquardtParams`` defaults (initial lambda 1e-5, factor 10, upper bound 1e5,
minimum model fidelity 1e-3, absolute error tolerance 1e-5). Variables not in ``free_keys`` are
constants (gtsam holds them with tight priors; the difference is of the order of that sigma).
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from services.edge.vio.ba_sparse import GraphScatter, SparseCameraSystem, sparse_spd_solve

logger = logging.getLogger(__name__)

_LAMBDA_INITIAL = 1e-5
_LAMBDA_FACTOR = 10.0
_LAMBDA_UPPER = 1e5
_MIN_MODEL_FIDELITY = 1e-3
_ABSOLUTE_ERROR_TOL = 1e-5
_BEHIND_RESIDUAL = 2.0  # gtsam's reprojection error for a point behind the camera (fx = 1)
# Reduced camera systems of more dimensions than this are kept sparse (ba_sparse.py).
SPARSE_MIN_DIM = 300


@dataclass(frozen=True, eq=False)
class Observations:
    """``M`` reprojection observations: ``pose`` (M,) index into the problem's pose keys,
    ``point`` (M,) index into its points, ``xy`` (M, 2) undistorted normalised coordinates,
    ``sigma`` (M,) noise in normalised units."""

    pose: np.ndarray
    point: np.ndarray
    xy: np.ndarray
    sigma: np.ndarray


@dataclass(frozen=True, eq=False)
class SchurResult:
    """``values`` the gtsam variables (poses, velocities, biases) and ``p_world`` (N, 3) the
    points after optimisation; errors are the total cost ``0.5·Σ robust`` (gtsam's graph
    error of the same problem); ``iterations`` accepted LM steps."""

    values: gtsam.Values
    p_world: np.ndarray
    error_before: float
    error_after: float
    iterations: int


@dataclass(frozen=True, eq=False)
class _Linearisation:
    """Gauss–Newton system of the current estimate: camera-side ``H_cc`` (C, C) and ``g_c``
    (C,), per point ``H_ll`` (N, 3, 3) and ``g_l`` (N, 3), per free-pose observation
    ``H_pl`` (F, 6, 3). A sparse problem has ``H_cc`` None and instead ``H_pose`` (P, 6, 6),
    the reprojection Hessian of each free pose, and ``h_graph``, the gtsam graph's Hessian
    entries (:class:`services.edge.vio.ba_sparse.GraphScatter`)."""

    H_cc: np.ndarray | None
    g_c: np.ndarray
    H_ll: np.ndarray
    g_l: np.ndarray
    H_pl: np.ndarray
    H_pose: np.ndarray | None = None
    h_graph: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class _Covisibility:
    """Pairs of free-pose observations ``(obs_a, obs_b)`` (P,) of the same point, poses
    ``a <= b``, grouped by pose pair: group ``g`` is ``bounds[g]:bounds[g + 1]``, between the
    camera-side offsets ``offset_a[g]`` and ``offset_b[g]`` (Schur fill-in)."""

    obs_a: np.ndarray
    obs_b: np.ndarray
    bounds: list[int]
    offset_a: list[int]
    offset_b: list[int]


def _covisibility(pose: np.ndarray, point: np.ndarray, offset: np.ndarray) -> _Covisibility:
    """For observations ``pose`` (F,), ``point`` (F,) of free poses with camera-side ``offset``
    (F,): every pair of observations of one point (itself included), grouped by pose pair."""
    order = np.lexsort((pose, point))  # by point, then pose (a point sees a pose once)
    p_sorted = point[order]
    end_of = np.searchsorted(p_sorted, p_sorted, side="right")
    reps = end_of - np.arange(len(order))  # pairs (i, j >= i) within each point
    first = np.repeat(np.arange(len(order)), reps)
    second = first + (np.arange(len(first)) - np.repeat(np.cumsum(reps) - reps, reps))
    ia, ib = order[first], order[second]
    n_pose = int(pose.max()) + 1
    key = pose[ia] * n_pose + pose[ib]
    if n_pose * n_pose < np.iinfo(np.int16).max:
        key = key.astype(np.int16)  # numpy's stable sort of 16-bit integers is a radix sort
    by_key = np.argsort(key, kind="stable")
    ia, ib, key = ia[by_key], ib[by_key], key[by_key]
    starts = np.flatnonzero(np.diff(key, prepend=-1) != 0)
    return _Covisibility(
        ia,
        ib,
        [*starts.tolist(), len(ia)],
        offset[ia[starts]].tolist(),
        offset[ib[starts]].tolist(),
    )


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise ``a × b`` of (M, 3) arrays (np.cross is slower on short rows)."""
    return np.stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ],
        axis=1,
    )


def _camera_points(
    T_world_body: np.ndarray, p_world: np.ndarray, obs: Observations, T_body_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per observation ``R_cam_world`` (M, 3, 3) and the point in the camera frame (M, 3)."""
    R_bc, t_bc = T_body_cam[:3, :3], T_body_cam[:3, 3]
    R_wc = T_world_body[:, :3, :3] @ R_bc  # (K, 3, 3)
    t_wc = T_world_body[:, :3, :3] @ t_bc + T_world_body[:, :3, 3]
    R_cw = R_wc.transpose(0, 2, 1)
    t_cw = -(R_cw @ t_wc[:, :, None])[:, :, 0]
    R_cw_obs = R_cw[obs.pose]
    p_obs = p_world[obs.point]
    p_cam = R_cw_obs[:, :, 0] * p_obs[:, 0:1] + R_cw_obs[:, :, 1] * p_obs[:, 1:2]
    p_cam += R_cw_obs[:, :, 2] * p_obs[:, 2:3] + t_cw[obs.pose]
    return R_cw_obs, p_cam


def observation_chi2(
    T_world_body: np.ndarray, p_world: np.ndarray, obs: Observations, T_body_cam: np.ndarray
) -> np.ndarray:
    """Whitened squared reprojection error (M,) of every observation; inf behind the camera
    or where it is not finite."""
    _, p_cam = _camera_points(T_world_body, p_world, obs, T_body_cam)
    z = p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.sum((p_cam[:, :2] / z[:, None] - obs.xy) ** 2, axis=1) / obs.sigma**2
    return np.where(z > 0, np.nan_to_num(e, nan=np.inf), np.inf)


def reprojection_terms(
    T_world_body: np.ndarray,
    p_world: np.ndarray,
    obs: Observations,
    T_body_cam: np.ndarray,
    cauchy_k: float,
    jacobians: bool = True,
) -> tuple[float, np.ndarray | None, np.ndarray | None]:
    """Robust cost and IRLS-weighted whitened linearisation of every observation.

    ``T_world_body`` (K, 4, 4), ``p_world`` (N, 3). Returns ``(cost, J (M, 2, 9), b (M, 2))``
    with ``J = [J_pose | J_point]`` (pose tangent ``(omega, v)``, then the point) and
    ``‖J·(xi, dp) − b‖²`` the Gauss–Newton model of the robust cost (gtsam's
    ``Robust::WhitenSystem``); ``J`` and ``b`` None when ``jacobians`` is False.
    """
    R_cw_obs, p_cam = _camera_points(T_world_body, p_world, obs, T_body_cam)
    z = p_cam[:, 2]
    front = z > 0
    inv_z = np.where(front, 1.0 / np.where(front, z, 1.0), 0.0)
    proj = p_cam[:, :2] * inv_z[:, None]
    err = np.where(front[:, None], proj - obs.xy, _BEHIND_RESIDUAL)
    r = err / obs.sigma[:, None]  # whitened (M, 2)
    c2 = cauchy_k * cauchy_k
    s2 = r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1]
    cost = float(np.sum(0.5 * c2 * np.log1p(s2 / c2)))
    if not jacobians:
        return cost, None, None
    sqrt_w = np.sqrt(1.0 / (1.0 + s2 / c2))
    b = -r * sqrt_w[:, None]
    scale = np.where(front, sqrt_w / obs.sigma, 0.0) * inv_z  # whitening, IRLS, 1/z
    R_bc, t_bc = T_body_cam[:3, :3], T_body_cam[:3, 3]
    p_body = p_cam @ R_bc.T + t_bc
    R_cb = R_bc.T
    J = np.empty((len(z), 2, 9))
    for i in range(2):
        # Row i of d proj / d p_cam is (e_i − proj_i·e_z)/z; through R_cw (point) and
        # R_cb (body): d p_body / d xi = [ [p_body]x , −I ] (right perturbation).
        s_i = scale[:, None]
        J[:, i, 6:] = s_i * (R_cw_obs[:, i, :] - proj[:, i, None] * R_cw_obs[:, 2, :])
        B_i = s_i * (R_cb[i] - proj[:, i, None] * R_cb[2])
        J[:, i, :3] = _cross(B_i, p_body)  # row a of B times [p]x is a × p
        J[:, i, 3:6] = -B_i
    return cost, J, b


def _inverse_spd3(H: np.ndarray, lam: float) -> np.ndarray | None:
    """Inverses (N, 3, 3) of the symmetric ``H + lam·I`` (N, 3, 3) by cofactors (several
    times faster than np.linalg.inv on small matrices); None if one is not positive."""
    a, b, c = H[:, 0, 0] + lam, H[:, 0, 1], H[:, 0, 2]
    d, e, f = H[:, 1, 1] + lam, H[:, 1, 2], H[:, 2, 2] + lam
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A + b * B + c * C
    if not np.all(det > 0.0):
        return None
    inv = np.stack([A, B, C, B, D, E, C, E, F], axis=1).reshape(-1, 3, 3)
    return inv / det[:, None, None]


def _dense_solve(S: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``S⁻¹·rhs`` for a symmetric positive definite ``S`` (C, C), by gtsam's (Eigen's) dense
    Cholesky. Not LAPACK: the multithreaded OpenBLAS that numpy and scipy bundle spends
    ~250 ms CPU on a 165×165 Cholesky when the other core is busy (threads spin waiting for a
    preempted peer); Eigen's single-threaded one takes 0.25 ms. Raises RuntimeError if ``S``
    is not positive definite."""
    gfg = gtsam.GaussianFactorGraph()
    gfg.add(gtsam.HessianFactor(0, S, rhs, 0.0))
    return np.asarray(gfg.optimize().at(0), dtype=np.float64)


class SchurLM:
    """One bundle-adjustment problem: gtsam ``graph`` (non-reprojection factors) over
    ``values``, reprojection ``obs`` of points ``p_world`` (N, 3) from the poses
    ``pose_keys`` (K keys of ``values``), optimised over ``free_keys`` and every point."""

    def __init__(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        free_keys: list[int],
        pose_keys: list[int],
        p_world: np.ndarray,
        obs: Observations,
        T_body_cam: np.ndarray,
        cauchy_k: float,
    ) -> None:
        self.graph = graph
        self.values = values
        self.pose_keys = list(pose_keys)
        self.p_world = np.array(p_world, dtype=np.float64).reshape(-1, 3)
        self.T_body_cam = np.asarray(T_body_cam, dtype=np.float64)
        self.cauchy_k = float(cauchy_k)
        zero = values.zeroVectors()
        self.free_keys = list(free_keys)
        dims = [int(zero.at(k).size) for k in self.free_keys]
        starts = np.concatenate([[0], np.cumsum(dims)]).astype(np.int64)
        self.n_c = int(starts[-1])
        self._slices = {k: (int(starts[i]), dims[i]) for i, k in enumerate(self.free_keys)}
        # Column offset of each pose in the camera-side vector (-1: constant pose).
        self._pose_offset = np.array(
            [self._slices[k][0] if k in self._slices else -1 for k in self.pose_keys],
            dtype=np.int64,
        )
        n = len(self.p_world)
        if np.any(np.bincount(obs.point, minlength=n) == 0):
            raise ValueError("SchurLM: every point needs at least one observation")
        # Observations reordered once: those of free poses first, grouped by pose.
        off = self._pose_offset[obs.pose]
        order = np.lexsort((obs.point, obs.pose, off < 0))
        obs = Observations(obs.pose[order], obs.point[order], obs.xy[order], obs.sigma[order])
        self.obs = obs
        off = off[order]
        n_free = int(np.sum(off >= 0))
        self._n_free = n_free
        self._free_point = obs.point[:n_free]
        rows6 = off[:n_free, None] + np.arange(6)  # (F, 6) camera-side rows of each observation
        self._rows6 = rows6
        self._pose_starts = np.flatnonzero(np.diff(obs.pose[:n_free], prepend=-1) != 0)
        self._pose_rows = rows6[self._pose_starts]
        self._pose_bounds = list(itertools.pairwise([*self._pose_starts.tolist(), n_free]))
        self._by_point = np.argsort(obs.point, kind="stable")
        self._point_starts = np.searchsorted(obs.point[self._by_point], np.arange(n))
        self._idx_lf = (self._free_point[:, None] * 3 + np.arange(3)).ravel()
        self._n = n
        self._covis = (
            _covisibility(obs.pose[:n_free], self._free_point, off[:n_free]) if n_free else None
        )
        # The gtsam graph's keys: free ones first (their block of its Hessian), then constants.
        graph_keys = set(graph.keys())
        self._graph_free = [k for k in self.free_keys if k in graph_keys]
        self._graph_idx = (
            np.concatenate(
                [self._slices[k][0] + np.arange(self._slices[k][1]) for k in self._graph_free]
            )
            if self._graph_free
            else np.zeros(0, dtype=np.int64)
        )
        self._ordering = gtsam.Ordering()
        for k in self._graph_free + sorted(graph_keys - set(self._graph_free)):
            self._ordering.push_back(k)
        # Big problems keep the reduced camera system sparse (the VI refinements).
        self._system: SparseCameraSystem | None = None
        self._scatter: GraphScatter | None = None
        if self.n_c > SPARSE_MIN_DIM and self._covis is not None:
            key_dims = {k: int(zero.at(k).size) for k in graph_keys}
            self._scatter = GraphScatter(graph, key_dims, self._slices)
            cv = self._covis
            self._system = SparseCameraSystem(
                self.n_c,
                self._pose_rows[:, 0],
                np.asarray(cv.offset_a, np.int64),
                np.asarray(cv.offset_b, np.int64),
                self._scatter,
            )

    # ------------------------------------------------------------------ pieces
    def _poses(self, values: gtsam.Values) -> np.ndarray:
        return np.array([values.atPose3(k).matrix() for k in self.pose_keys]).reshape(-1, 4, 4)

    def cost(self, values: gtsam.Values, p_world: np.ndarray) -> float:
        """Total cost ``0.5·Σ robust`` (reprojection plus the gtsam graph)."""
        c, _, _ = reprojection_terms(
            self._poses(values), p_world, self.obs, self.T_body_cam, self.cauchy_k, False
        )
        return c + (self.graph.error(values) if self.graph.size() else 0.0)

    def _linearise(self, values: gtsam.Values, p_world: np.ndarray) -> _Linearisation:
        _, J, b = reprojection_terms(
            self._poses(values), p_world, self.obs, self.T_body_cam, self.cauchy_k
        )
        assert J is not None and b is not None
        n_c, f = self.n_c, self._n_free
        # Transposes are copied: numpy hands ``Aᵀ @ A`` of one buffer to BLAS syrk per item.
        J_point = J[:, :, 6:]
        J_point_t = np.ascontiguousarray(J_point.transpose(0, 2, 1))  # (M, 3, 2)
        bp, starts = self._by_point, self._point_starts
        H_ll = np.add.reduceat((J_point_t @ J_point)[bp], starts)
        g_l = np.add.reduceat(
            (J_point_t[:, :, 0] * b[:, :1] + J_point_t[:, :, 1] * b[:, 1:])[bp], starts
        )
        J_pose = np.ascontiguousarray(J[:f, :, :6])  # (F, 2, 6)
        J_pose_t = np.ascontiguousarray(J_pose.transpose(0, 2, 1))  # (F, 6, 2)
        H_pl = J_pose_t @ np.ascontiguousarray(J[:f, :, 6:])  # (F, 6, 3)
        H_pose = np.empty((len(self._pose_bounds), 6, 6))  # per free pose, one GEMM each
        for i, (s0, s1) in enumerate(self._pose_bounds):
            A = J_pose[s0:s1].reshape(-1, 6)
            H_pose[i] = A.T @ A
        g_c = np.zeros(n_c)
        if f:
            g_p = J_pose_t[:, :, 0] * b[:f, :1] + J_pose_t[:, :, 1] * b[:f, 1:]  # (F, 6)
            g_c[self._pose_rows] = np.add.reduceat(g_p, self._pose_starts)
        if self._scatter is not None:  # sparse (then there are free observations)
            h_graph, g_graph = self._scatter.values(self.graph.linearize(values))
            np.add.at(g_c, self._scatter.g_rows, g_graph)
            return _Linearisation(None, g_c, H_ll, g_l, H_pl, H_pose, h_graph)
        H_cc = np.zeros((n_c, n_c))
        if f:
            rows = self._pose_rows
            H_cc[rows[:, :, None], rows[:, None, :]] = H_pose
        if self._graph_free:
            H_g, eta_g = self.graph.linearize(values).hessian(self._ordering)
            m = len(self._graph_idx)
            H_cc[np.ix_(self._graph_idx, self._graph_idx)] += H_g[:m, :m]
            g_c[self._graph_idx] += np.asarray(eta_g).reshape(-1)[:m]
        return _Linearisation(H_cc, g_c, H_ll, g_l, H_pl)

    def _solve(self, lin: _Linearisation, lam: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Damped step ``(delta_c (C,), delta_l (N, 3))`` or None if the system is singular.

        Points are eliminated: ``S = H_cc − Σ H_pl·H_ll⁻¹·H_plᵀ`` over co-visible pose pairs,
        ``S·delta_c = g_c − Σ H_pl·H_ll⁻¹·g_l``, then ``delta_l = H_ll⁻¹·(g_l − H_plᵀ·delta_c)``.
        """
        H_ll_inv = _inverse_spd3(lin.H_ll, lam)
        if H_ll_inv is None:
            return None
        if not self.n_c:
            return np.zeros(0), (H_ll_inv @ lin.g_l[:, :, None])[:, :, 0]
        pts = self._free_point
        cv = self._covis
        assert cv is not None
        Ht = np.ascontiguousarray(lin.H_pl.transpose(0, 2, 1))  # (F, 3, 6)
        Wt = H_ll_inv[pts] @ Ht  # (F, 3, 6): Wᵀ of W = H_pl·H_ll⁻¹ (H_ll⁻¹ symmetric)
        S = lin.H_cc.copy() if lin.H_cc is not None else None
        fill = np.empty((len(cv.offset_a), 6, 6)) if S is None else None
        for g in range(len(cv.offset_a)):
            s0, s1 = cv.bounds[g], cv.bounds[g + 1]
            # Σ over the points both see of W_a·H_plᵀ_b (6, 6).
            blk = Wt[cv.obs_a[s0:s1]].reshape(-1, 6).T @ Ht[cv.obs_b[s0:s1]].reshape(-1, 6)
            if S is None:
                assert fill is not None  # allocated exactly when S is None
                fill[g] = blk
                continue
            a, b = cv.offset_a[g], cv.offset_b[g]
            S[a : a + 6, b : b + 6] -= blk
            if a != b:
                S[b : b + 6, a : a + 6] -= blk.T
        g_pts = lin.g_l[pts]
        rhs = lin.g_c.copy()
        rhs[self._pose_rows] -= np.add.reduceat(  # Σ per pose of W·g_l (observations by pose)
            Wt[:, 0] * g_pts[:, :1] + Wt[:, 1] * g_pts[:, 1:2] + Wt[:, 2] * g_pts[:, 2:],
            self._pose_starts,
        )
        if S is None:
            assert self._system is not None and lin.H_pose is not None
            assert lin.h_graph is not None and fill is not None
            S_sparse = self._system.matrix(lin.H_pose, lin.h_graph, fill, lam)
            delta_c = sparse_spd_solve(S_sparse, rhs)
            if delta_c is None:
                return None
        else:
            S[np.diag_indices_from(S)] += lam
            try:
                delta_c = _dense_solve(S, rhs)
            except RuntimeError:  # not positive definite
                return None
        if not np.all(np.isfinite(delta_c)):
            return None
        back = lin.H_pl.transpose(0, 2, 1) @ delta_c[self._rows6][:, :, None]  # H_plᵀ·d_pose
        back = np.bincount(self._idx_lf, back.ravel(), 3 * self._n).reshape(-1, 3)
        delta_l = (H_ll_inv @ (lin.g_l - back)[:, :, None])[:, :, 0]
        return delta_c, delta_l

    def _retract(self, values: gtsam.Values, delta_c: np.ndarray) -> gtsam.Values:
        vv = gtsam.VectorValues()
        for k in self.free_keys:
            s, d = self._slices[k]
            vv.insert(k, delta_c[s : s + d])
        return values.retract(vv)

    # ------------------------------------------------------------------ LM
    def optimize(self, max_iterations: int, relative_error_tol: float) -> SchurResult:
        """gtsam's LevenbergMarquardtOptimizer schedule (``iterate`` / ``tryLambda``)."""
        values, p = self.values, self.p_world
        error = self.cost(values, p)
        error0 = error
        lam = _LAMBDA_INITIAL
        iterations = 0
        while error > 0.0 and iterations < max_iterations:
            current = error
            lin = self._linearise(values, p)
            while True:  # tryLambda until a step is taken or the search stops
                success = stop = False
                step = self._solve(lin, lam)
                if step is not None:
                    delta_c, delta_l = step
                    # Decrease of the undamped model: with (H + lam·I)·d = g it is
                    # g·d − 0.5·d·H·d = 0.5·(g·d + lam·|d|²).
                    g_dot = float(lin.g_c @ delta_c + np.sum(lin.g_l * delta_l))
                    sq = float(delta_c @ delta_c + np.sum(delta_l * delta_l))
                    lin_change = 0.5 * (g_dot + lam * sq)
                    if lin_change >= 0.0:
                        new_values = self._retract(values, delta_c)
                        new_p = p + delta_l
                        new_error = self.cost(new_values, new_p)
                        change = error - new_error
                        if lin_change > np.finfo(float).eps * error:
                            success = change / lin_change > _MIN_MODEL_FIDELITY
                        stop = abs(change) < relative_error_tol * error
                if success:
                    values, p, error = new_values, new_p, new_error
                    lam = lam / _LAMBDA_FACTOR
                    iterations += 1
                    break
                if stop:
                    break
                lam *= _LAMBDA_FACTOR
                if lam >= _LAMBDA_UPPER:
                    logger.debug("Schur LM: no decrease with the largest lambda")
                    break
            decrease = current - error
            if not np.isfinite(current) or decrease <= _ABSOLUTE_ERROR_TOL:
                break
            if decrease <= relative_error_tol * current:
                break
        return SchurResult(values, p, error0, error, iterations)
