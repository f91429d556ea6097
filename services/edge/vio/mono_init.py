"""Monocular initialisation: two-view geometry between two keyframes (ORB-SLAM-like).

Both an essential matrix and a homography are fitted with RANSAC; the model is chosen by the
ratio of their robust scores ``S_H / (S_H + S_E)``; the chosen motion is decomposed, points are
triangulated and accepted only with enough parallax. The scale is arbitrary: the median depth
of the triangulated points in the first camera is set to 1.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from services.edge.vio.types import MonoInitConfig

logger = logging.getLogger(__name__)

_CHI2_1DOF = 3.841
_CHI2_2DOF = 5.991


@dataclass(frozen=True, eq=False)
class TwoViewResult:
    """``R_c1_c0`` (3, 3), ``t_c1_c0`` (3,) with ``p_c1 = R p_c0 + t``; ``p_c0`` (N, 3) points in
    the first camera (NaN rows where not triangulated); ``good`` (N,) bool."""

    R_c1_c0: np.ndarray
    t_c1_c0: np.ndarray
    p_c0: np.ndarray
    good: np.ndarray
    model: str
    median_parallax_deg: float


def _homography_score(H: np.ndarray, x0: np.ndarray, x1: np.ndarray, sigma: float) -> float:
    def transfer(Hm: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        ah = np.c_[a, np.ones(len(a))] @ Hm.T
        with np.errstate(divide="ignore", invalid="ignore"):
            proj = ah[:, :2] / ah[:, 2:3]
        e = np.sum((proj - b) ** 2, axis=1) / sigma**2
        return np.where(np.isfinite(e), e, np.inf)

    try:
        Hinv = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return 0.0
    score = 0.0
    for e in (transfer(H, x0, x1), transfer(Hinv, x1, x0)):
        score += float(np.sum(np.where(e < _CHI2_2DOF, _CHI2_2DOF - e, 0.0)))
    return score


def _essential_score(E: np.ndarray, x0: np.ndarray, x1: np.ndarray, sigma: float) -> float:
    h0 = np.c_[x0, np.ones(len(x0))]
    h1 = np.c_[x1, np.ones(len(x1))]
    score = 0.0
    for a, b, M in ((h0, h1, E), (h1, h0, E.T)):
        lines = a @ M.T  # epipolar lines in the other image
        num = np.sum(lines * b, axis=1) ** 2
        den = lines[:, 0] ** 2 + lines[:, 1] ** 2 + 1e-18
        e = num / den / sigma**2
        score += float(np.sum(np.where(e < _CHI2_1DOF, _CHI2_2DOF - e, 0.0)))
    return score


def triangulate_two_view(
    R: np.ndarray,
    t: np.ndarray,
    x0: np.ndarray,
    x1: np.ndarray,
    sigma: float,
    min_parallax_deg: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (N, 3) in camera 0, a good mask (N,) and parallax (N,) in degrees."""
    P0 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P1 = np.hstack([R, t.reshape(3, 1)])
    X = cv2.triangulatePoints(P0, P1, x0.T.astype(np.float64), x1.T.astype(np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        p0 = (X[:3] / X[3]).T
    p1 = p0 @ R.T + t
    finite = np.all(np.isfinite(p0), axis=1)
    C1 = -R.T @ t
    r0 = p0
    r1 = p0 - C1
    with np.errstate(divide="ignore", invalid="ignore"):
        cosp = np.sum(r0 * r1, 1) / (np.linalg.norm(r0, axis=1) * np.linalg.norm(r1, axis=1))
        e0 = np.sum((p0[:, :2] / p0[:, 2:3] - x0) ** 2, 1) / sigma**2
        e1 = np.sum((p1[:, :2] / p1[:, 2:3] - x1) ** 2, 1) / sigma**2
    parallax = np.degrees(np.arccos(np.clip(np.nan_to_num(cosp, nan=1.0), -1.0, 1.0)))
    good = (
        finite
        & (p0[:, 2] > 0)
        & (p1[:, 2] > 0)
        & (e0 < 4 * _CHI2_2DOF)
        & (e1 < 4 * _CHI2_2DOF)
        & (parallax >= min_parallax_deg)
    )
    return p0, good, parallax


def _refine_two_view(
    R: np.ndarray,
    t: np.ndarray,
    x0: np.ndarray,
    x1: np.ndarray,
    p0: np.ndarray,
    good: np.ndarray,
    sigma: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two-view bundle adjustment (camera 0 fixed; the scale gauge is held by LM damping and
    re-normalised by the caller). Returns refined ``R``, ``t`` and points (N, 3)."""
    import gtsam
    from gtsam.symbol_shorthand import L, X

    K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(np.sqrt(_CHI2_2DOF)),
        gtsam.noiseModel.Isotropic.Sigma(2, sigma),
    )
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    T_w_c1 = np.eye(4)
    T_w_c1[:3, :3] = R.T
    T_w_c1[:3, 3] = -R.T @ t
    values.insert(X(0), gtsam.Pose3())
    values.insert(X(1), gtsam.Pose3(T_w_c1))
    graph.add(
        gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-8))
    )
    idx = np.flatnonzero(good)
    for i in idx:
        values.insert(L(int(i)), p0[i])
        for k, xy in ((0, x0), (1, x1)):
            graph.add(
                gtsam.GenericProjectionFactorCal3_S2(
                    gtsam.Point2(*xy[i]), noise, X(k), L(int(i)), K
                )
            )
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(20)
    try:
        res = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except RuntimeError:
        return R, t, p0
    T1 = res.atPose3(X(1)).matrix()
    R_new = T1[:3, :3].T
    t_new = -R_new @ T1[:3, 3]
    p_new = p0.copy()
    for i in idx:
        p_new[i] = res.atPoint3(L(int(i)))
    norm = np.linalg.norm(t_new)
    if norm < 1e-9:
        return R, t, p0
    return R_new, t_new / norm, p_new / norm


def two_view_geometry(
    x0: np.ndarray, x1: np.ndarray, focal_px: float, options: MonoInitConfig
) -> tuple[TwoViewResult | None, str]:
    """Relative motion and structure from matched normalised coordinates (N, 2) each.

    Returns ``(result, "")`` on success or ``(None, reason)``.
    """
    n = len(x0)
    if n < options.min_tracks:
        return None, f"only {n} shared tracks (< {options.min_tracks})"
    sigma = 1.0 / focal_px
    thr = options.ransac_threshold_px / focal_px
    x0 = np.ascontiguousarray(x0, dtype=np.float64)
    x1 = np.ascontiguousarray(x1, dtype=np.float64)
    # Rotation-compensated flow is not available here; a cheap pre-check on raw displacement
    # avoids fitting models when nothing moved.
    flow_px = float(np.median(np.linalg.norm(x1 - x0, axis=1))) * focal_px
    if flow_px < 1.0:
        return None, f"median image motion {flow_px:.2f} px: no parallax"
    E, _maskE = cv2.findEssentialMat(x0, x1, np.eye(3), cv2.RANSAC, 0.999, thr)
    H, _maskH = cv2.findHomography(x0, x1, cv2.RANSAC, thr)
    if E is None or E.shape != (3, 3):
        return None, "essential matrix estimation failed"
    s_e = _essential_score(E, x0, x1, sigma)
    s_h = _homography_score(H, x0, x1, sigma) if H is not None else 0.0
    ratio = s_h / max(s_h + s_e, 1e-12)
    candidates: list[tuple[np.ndarray, np.ndarray]] = []
    if ratio > options.homography_ratio and H is not None:
        model = "H"
        _, Rs, ts, _ = cv2.decomposeHomographyMat(H, np.eye(3))
        candidates = [(R, t.reshape(3)) for R, t in zip(Rs, ts, strict=True)]
    else:
        model = "E"
        R1, R2, t = cv2.decomposeEssentialMat(E)
        t = t.reshape(3)
        candidates = [(R1, t), (R1, -t), (R2, t), (R2, -t)]
    best: tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
    counts = []
    for R, t in candidates:
        if np.linalg.norm(t) < 1e-12:
            counts.append(0)
            continue
        tn = t / np.linalg.norm(t)
        p0, good, par = triangulate_two_view(R, tn, x0, x1, sigma, options.min_parallax_deg)
        counts.append(int(good.sum()))
        if best is None or good.sum() > best[0]:
            best = (int(good.sum()), R, tn, p0, good, par)
    if best is None:
        return None, f"no valid decomposition of {model}"
    n_good, R, t, p0, good, par = best
    counts.sort(reverse=True)
    if len(counts) > 1 and counts[1] > 0.75 * counts[0]:
        return None, f"ambiguous {model} decomposition ({counts[0]} vs {counts[1]} points)"
    if n_good < options.min_triangulated:
        return (
            None,
            f"{n_good} points with parallax >= {options.min_parallax_deg} deg (model {model})",
        )
    med_par = float(np.median(par[good]))
    if med_par < options.min_median_parallax_deg:
        return None, f"median parallax {med_par:.2f} deg < {options.min_median_parallax_deg} deg"
    R, t, p0 = _refine_two_view(R, t, x0, x1, p0, good, sigma)
    depth = float(np.median(p0[good, 2]))
    scale = 1.0 / depth
    p0 = np.where(good[:, None], p0 * scale, np.nan)
    logger.debug("two-view init: model %s, %d points, median parallax %.2f", model, n_good, med_par)
    return TwoViewResult(R, t * scale, p0, good, model, med_par), ""
