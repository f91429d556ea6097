"""Sparse reduced camera system of the Schur-complement BA, for big windows.

:class:`services.edge.vio.ba_solver.SchurLM` solves its reduced camera system ``S`` (C, C)
densely, which is O(C³) time and O(C²) memory: right for a local BA of ten keyframes (C ≈
150), not for the VI refinements over every keyframe (C = 15 per keyframe, up to a few
thousand). Here ``S`` stays sparse: the camera-side Hessian of the reprojection terms (one
6×6 block per free pose), the per-factor information of the linearised gtsam graph (IMU
factors, priors) restricted to the free variables, the 6×6 Schur fill-in of every co-visible
pose pair and the LM damping are summed as triplets into a CSC matrix, which SuperLU factors
with a fill-reducing symmetric ordering and no pivoting off the diagonal (a symmetric
positive definite ``S`` needs none; a pivot that is not positive marks ``S`` indefinite).
SuperLU runs single-threaded without BLAS threads, unlike numpy's dense LAPACK.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

logger = logging.getLogger(__name__)


def _block_indices(offsets: np.ndarray, offsets_col: np.ndarray, size: int) -> np.ndarray:
    """Row and column indices (2, G·size²) of ``size``×``size`` blocks at ``offsets`` (G,)
    rows and ``offsets_col`` (G,) columns, each block row-major."""
    r = np.arange(size)
    shape = (len(offsets), size, size)
    rows = np.broadcast_to(np.asarray(offsets)[:, None, None] + r[:, None], shape)
    cols = np.broadcast_to(np.asarray(offsets_col)[:, None, None] + r[None, :], shape)
    return np.stack([rows.ravel(), cols.ravel()])


class GraphScatter:
    """The linearised gtsam ``graph``'s information restricted to the free variables.

    ``slices`` maps each free key to ``(offset, dim)`` in the camera-side vector; ``dims``
    gives the tangent dimension of every key of the graph (constants too: their rows and
    columns are dropped, i.e. they are held at their value).
    """

    def __init__(
        self,
        graph: gtsam.NonlinearFactorGraph,
        dims: dict[int, int],
        slices: dict[int, tuple[int, int]],
    ) -> None:
        self._keep: list[np.ndarray] = []  # per factor: its free rows in its own ordering
        rows, cols, g_rows = [], [], []
        for i in range(graph.size()):
            factor_keys = list(graph.at(i).keys())
            idx = np.concatenate(
                [
                    slices[k][0] + np.arange(dims[k]) if k in slices else np.full(dims[k], -1)
                    for k in factor_keys
                ]
            ).astype(np.int64)
            keep = np.flatnonzero(idx >= 0)
            self._keep.append(keep)
            free = idx[keep]
            rows.append(np.repeat(free, len(free)))
            cols.append(np.tile(free, len(free)))
            g_rows.append(free)
        empty = np.zeros(0, np.int64)
        self.rows = np.concatenate(rows) if rows else empty
        self.cols = np.concatenate(cols) if cols else empty
        self.g_rows = np.concatenate(g_rows) if g_rows else empty

    def values(self, linear: gtsam.GaussianFactorGraph) -> tuple[np.ndarray, np.ndarray]:
        """Hessian entries (at ``rows``, ``cols``) and gradient entries (at ``g_rows``) of the
        linearised graph ``linear`` (same factors, same order as the nonlinear graph)."""
        h, g = [], []
        for i, keep in enumerate(self._keep):
            if not len(keep):
                continue
            info = linear.at(i).augmentedInformation()  # [AᵀA  Aᵀb; bᵀA  bᵀb]
            h.append(info[np.ix_(keep, keep)].ravel())
            g.append(info[keep, -1])
        if not h:
            return np.zeros(0), np.zeros(0)
        return np.concatenate(h), np.concatenate(g)


class SparseCameraSystem:
    """Structure of ``S`` for one problem: ``n_c`` camera-side dimensions, free poses at
    offsets ``pose_offsets`` (P,), co-visible pose pairs ``a <= b`` at offsets
    ``pair_a``/``pair_b`` (G,) (Schur fill-in; ``a == b`` the diagonal blocks), the graph's
    triplets of ``graph``."""

    def __init__(
        self,
        n_c: int,
        pose_offsets: np.ndarray,
        pair_a: np.ndarray,
        pair_b: np.ndarray,
        graph: GraphScatter,
    ) -> None:
        self.n_c = n_c
        off_diag = pair_a != pair_b
        self._off_diag = off_diag
        diag = np.arange(n_c)
        index = [
            _block_indices(pose_offsets, pose_offsets, 6),
            np.stack([graph.rows, graph.cols]),
            _block_indices(pair_a, pair_b, 6),
            _block_indices(pair_b[off_diag], pair_a[off_diag], 6),
            np.stack([diag, diag]),
        ]
        self._rows = np.concatenate([i[0] for i in index])
        self._cols = np.concatenate([i[1] for i in index])

    def matrix(
        self, H_pose: np.ndarray, h_graph: np.ndarray, fill: np.ndarray, lam: float
    ) -> sp.csc_matrix:
        """``S = H_cc − fill + lam·I`` (C, C) in CSC: ``H_pose`` (P, 6, 6) the reprojection
        Hessian of each free pose, ``h_graph`` the graph's Hessian entries, ``fill`` (G, 6, 6)
        the Schur fill-in ``Σ H_pl·H_ll⁻¹·H_plᵀ`` of each pose pair (rows of ``a``)."""
        data = np.concatenate(
            [
                H_pose.ravel(),
                h_graph,
                -fill.ravel(),
                -fill[self._off_diag].transpose(0, 2, 1).ravel(),
                np.full(self.n_c, lam),
            ]
        )
        S = sp.coo_matrix((data, (self._rows, self._cols)), shape=(self.n_c, self.n_c))
        return S.tocsc()  # duplicates summed


def sparse_spd_solve(S: sp.csc_matrix, rhs: np.ndarray) -> np.ndarray | None:
    """``S⁻¹·rhs`` for a sparse symmetric positive definite ``S`` (C, C); None if ``S`` is
    singular or not positive definite (a pivot of its symmetric factorisation is not
    positive)."""
    try:
        lu = splu(
            S,
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
    except RuntimeError:  # exactly singular
        return None
    if not np.all(lu.U.diagonal() > 0.0):
        return None
    return lu.solve(rhs)
