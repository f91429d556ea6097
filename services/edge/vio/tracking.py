"""Tracking of every frame against the map points of its tracks.

The pose is first checked at the prediction (IMU preintegration from the last keyframe after
VI initialisation, constant velocity before). If enough tracks agree with it, RANSAC is skipped;
otherwise PnP RANSAC (cv2, EPnP) finds the inliers. A motion-only optimisation then refines
the pose on the inliers with a Cauchy kernel (reprojection linearised in numpy, map points
fixed); after VI initialisation the problem also holds gtsam's CombinedImuFactor from the last
keyframe (held fixed), so velocity and bias of the frame come out too (ORB-SLAM3's
pose-inertial optimisation).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from common.geometry import inverse_T, make_T, so3_exp
from common.preintegration import make_bias
from services.edge.vio.state import Keyframe, PinholeUndistorter, project
from services.edge.vio.types import TrackingConfig

logger = logging.getLogger(__name__)

_UNIT_K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True, eq=False)
class ImuPrior:
    """Preintegration from keyframe ``keyframe`` to the frame being tracked."""

    keyframe: Keyframe
    pim: gtsam.PreintegratedCombinedMeasurements


@dataclass(frozen=True, eq=False)
class TrackResult:
    """``T_world_body`` (4, 4); ``v_world`` (3,) and biases only when an IMU prior was used;
    ``inlier_ids`` track ids agreeing with the pose; ``R_world_body_visual`` below."""

    T_world_body: np.ndarray
    v_world: np.ndarray | None
    bias_accel: np.ndarray | None
    bias_gyro: np.ndarray | None
    inlier_ids: np.ndarray
    used_ransac: bool
    # (3, 3) the rotation the reprojections alone give (Gauss-Newton from ``T_world_body`` on
    # the inliers without the IMU): what the camera-IMU time offset is measured on, since the
    # IMU prior pulls ``T_world_body`` towards the gyro at the offset in use.
    R_world_body_visual: np.ndarray | None = None


def _chi2(
    T_world_body: np.ndarray,
    T_body_cam: np.ndarray,
    P: np.ndarray,
    xy: np.ndarray,
    sigma: np.ndarray,
) -> np.ndarray:
    proj, z = project(T_world_body, T_body_cam, P)
    e = np.sum((proj - xy) ** 2, axis=1) / sigma**2
    return np.where(z > 0, np.nan_to_num(e, nan=np.inf), np.inf)


def _ransac(
    P: np.ndarray, xy: np.ndarray, camera: PinholeUndistorter, options: TrackingConfig
) -> np.ndarray | None:
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        np.ascontiguousarray(P, dtype=np.float64),
        np.ascontiguousarray(xy, dtype=np.float64),
        np.eye(3),
        None,
        iterationsCount=options.ransac_iterations,
        reprojectionError=options.ransac_threshold_px / camera.focal,
        confidence=0.999,
        flags=cv2.SOLVEPNP_EPNP,
    )
    if not ok or inl is None or len(inl) < options.min_inliers:
        return None
    T_cam_world = np.eye(4)
    T_cam_world[:3, :3] = so3_exp(rvec.reshape(3))
    T_cam_world[:3, 3] = tvec.reshape(3)
    return inverse_T(T_cam_world) @ camera.T_cam_body


def _visual_system(
    T_world_body: np.ndarray,
    T_body_cam: np.ndarray,
    P: np.ndarray,
    xy: np.ndarray,
    sigma: np.ndarray,
    cauchy_c2: float,
    jacobians: bool = True,
) -> tuple[np.ndarray | None, np.ndarray | None, float]:
    """Whitened, Cauchy-weighted (IRLS) linearisation of the reprojection of ``P`` (M, 3) at
    ``T_world_body`` for gtsam's Pose3 tangent ``xi = (omega, v)`` with ``T·Exp(xi)``.

    Returns ``A`` (2M, 6) and ``b`` (2M,) such that ``‖A·xi − b‖²`` is the weighted
    Gauss–Newton model, and the robust cost ``Σ 0.5·c²·log(1 + r²/c²)`` (gtsam's Cauchy loss).
    """
    R_wb, t_wb = T_world_body[:3, :3], T_world_body[:3, 3]
    R_bc, t_bc = T_body_cam[:3, :3], T_body_cam[:3, 3]
    p_body = (P - t_wb) @ R_wb
    p_cam = (p_body - t_bc) @ R_bc
    z = p_cam[:, 2]
    inv_z = 1.0 / z
    proj = p_cam[:, :2] * inv_z[:, None]
    r = (proj - xy) / sigma[:, None]  # (M, 2) whitened residual
    s2 = np.sum(r * r, axis=1)
    cost = float(np.sum(0.5 * cauchy_c2 * np.log1p(s2 / cauchy_c2)))
    if not jacobians:
        return None, None, cost
    sqrt_w = np.sqrt(1.0 / (1.0 + s2 / cauchy_c2)) / sigma  # (M,) robust weight and whitening
    # d proj / d p_cam (M, 2, 3)
    J_proj = np.zeros((len(P), 2, 3))
    J_proj[:, 0, 0] = inv_z
    J_proj[:, 1, 1] = inv_z
    J_proj[:, :, 2] = -proj * inv_z[:, None]
    # d p_body / d xi = [ [p_body]x , -I ]  (right perturbation of T_world_body)
    J_body = np.zeros((len(P), 3, 6))
    x, y, w = p_body[:, 0], p_body[:, 1], p_body[:, 2]
    J_body[:, 0, 1], J_body[:, 0, 2] = -w, y
    J_body[:, 1, 0], J_body[:, 1, 2] = w, -x
    J_body[:, 2, 0], J_body[:, 2, 1] = -y, x
    J_body[:, 0, 3] = J_body[:, 1, 4] = J_body[:, 2, 5] = -1.0
    J = (J_proj @ R_bc.T) @ J_body  # (M, 2, 6)
    A = (J * sqrt_w[:, None, None]).reshape(-1, 6)
    b = -(r * (sqrt_w * sigma)[:, None]).reshape(-1)
    return A, b, cost


def _optimise(
    T0: np.ndarray,
    P: np.ndarray,
    xy: np.ndarray,
    sigma: np.ndarray,
    camera: PinholeUndistorter,
    prior: ImuPrior | None,
    v0: np.ndarray | None,
    options: TrackingConfig,
) -> tuple[np.ndarray, np.ndarray | None, gtsam.imuBias.ConstantBias | None]:
    """Motion-only optimisation: Gauss–Newton with backtracking on the pose (and, with an
    IMU prior, velocity and bias of the frame). The reprojection terms are linearised here in
    numpy (map points fixed: no landmark variables); the IMU part stays a gtsam
    CombinedImuFactor from the fixed keyframe, linearised by gtsam each iteration."""
    c2 = float(options.chi2_threshold)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(T0))
    graph = gtsam.NonlinearFactorGraph()
    if prior is not None:
        kf = prior.keyframe
        bias = make_bias(kf.bias_accel, kf.bias_gyro)
        tight3 = gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)
        tight6 = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
        values.insert(X(1), gtsam.Pose3(kf.T_world_body))
        values.insert(V(1), kf.v_world)
        values.insert(B(1), bias)
        values.insert(V(0), v0 if v0 is not None else kf.v_world)
        values.insert(B(0), bias)
        graph.add(gtsam.PriorFactorPose3(X(1), gtsam.Pose3(kf.T_world_body), tight6))
        graph.add(gtsam.PriorFactorVector(V(1), kf.v_world, tight3))
        graph.add(gtsam.PriorFactorConstantBias(B(1), bias, tight6))
        graph.add(gtsam.CombinedImuFactor(X(1), V(1), X(0), V(0), B(1), B(0), prior.pim))
    unit = gtsam.noiseModel.Unit.Create(2 * len(P))
    T_body_cam = camera.T_body_cam

    def total_cost(vals: gtsam.Values) -> float:
        T = vals.atPose3(X(0)).matrix()
        _, _, c = _visual_system(T, T_body_cam, P, xy, sigma, c2, jacobians=False)
        return c + (graph.error(vals) if prior is not None else 0.0)

    cost = total_cost(values)
    trial: gtsam.Values | None
    for _ in range(options.max_iterations):
        T = values.atPose3(X(0)).matrix()
        A, b, _ = _visual_system(T, T_body_cam, P, xy, sigma, c2)
        assert A is not None and b is not None  # jacobians=True
        gfg = graph.linearize(values) if prior is not None else gtsam.GaussianFactorGraph()
        gfg.add(gtsam.JacobianFactor(X(0), A, b, unit))
        delta = gfg.optimize()
        step = 1.0
        while True:
            trial = values.retract(delta.scale(step))
            new_cost = total_cost(trial)
            if np.isfinite(new_cost) and new_cost <= cost:
                break
            step *= 0.5
            if step < 1e-3:
                trial = None
                break
        if trial is None:
            break
        values, improvement = trial, cost - new_cost
        cost = new_cost
        if improvement <= 1e-6 * max(cost, 1e-12):
            break
    T = values.atPose3(X(0)).matrix()
    if prior is None:
        return T, None, None
    return T, np.asarray(values.atVector(V(0)), float), values.atConstantBias(B(0))


def _visual_rotation(
    T: np.ndarray,
    P: np.ndarray,
    xy: np.ndarray,
    sigma: np.ndarray,
    camera: PinholeUndistorter,
    c2: float,
) -> np.ndarray:
    """The rotation (3, 3) of the pose that the reprojections of ``P`` (M, 3) at ``xy`` (M, 2)
    alone give, by two Gauss-Newton steps from ``T`` (4, 4)."""
    for _ in range(2):
        A, b, _ = _visual_system(T, camera.T_body_cam, P, xy, sigma, c2)
        assert A is not None and b is not None
        xi = np.linalg.lstsq(A, b, rcond=None)[0]
        T = T @ make_T(so3_exp(xi[:3]), xi[3:])
    return T[:3, :3]


def track_frame(
    P_world: np.ndarray,
    xy: np.ndarray,
    sigma: np.ndarray,
    ids: np.ndarray,
    camera: PinholeUndistorter,
    options: TrackingConfig,
    T_pred: np.ndarray | None,
    prior: ImuPrior | None = None,
    v_pred: np.ndarray | None = None,
) -> tuple[TrackResult | None, str]:
    """Pose of a frame from its tracks' map points ``P_world`` (M, 3) seen at ``xy`` (M, 2)
    (normalised, noise ``sigma`` (M,)), track ``ids`` (M,). Returns (result, "") or
    (None, reason)."""
    m = len(P_world)
    if m < options.min_inliers:
        return None, f"{m} tracks with map points (< {options.min_inliers})"
    T0 = None
    used_ransac = False
    if T_pred is not None:
        chi2 = _chi2(T_pred, camera.T_body_cam, P_world, xy, sigma)
        inl = chi2 < 4.0 * options.chi2_threshold
        if inl.sum() >= max(options.min_inliers, options.prior_inlier_ratio * m):
            T0 = T_pred
    if T0 is None:
        T0 = _ransac(P_world, xy, camera, options)
        used_ransac = True
        if T0 is None:
            return None, f"PnP RANSAC failed on {m} tracks"
        inl = _chi2(T0, camera.T_body_cam, P_world, xy, sigma) < 4.0 * options.chi2_threshold
    v = v_pred
    bias = None
    T = T0
    for _ in range(2):
        if inl.sum() < options.min_inliers:
            return None, f"{int(inl.sum())} inliers (< {options.min_inliers})"
        try:
            T, v_opt, bias = _optimise(
                T, P_world[inl], xy[inl], sigma[inl], camera, prior, v, options
            )
        except RuntimeError as exc:
            return None, f"motion-only optimisation failed: {exc}"
        v = v_opt if v_opt is not None else v
        inl = _chi2(T, camera.T_body_cam, P_world, xy, sigma) < options.chi2_threshold
    n = int(inl.sum())
    if n < options.min_inliers:
        return None, f"{n} inliers after refinement (< {options.min_inliers})"
    R_visual = T[:3, :3]
    if prior is not None:
        c2 = float(options.chi2_threshold)
        R_visual = _visual_rotation(T, P_world[inl], xy[inl], sigma[inl], camera, c2)
    return (
        TrackResult(
            T_world_body=T,
            v_world=v if prior is not None else None,
            bias_accel=None if bias is None else np.asarray(bias.accelerometer(), float),
            bias_gyro=None if bias is None else np.asarray(bias.gyroscope(), float),
            inlier_ids=ids[inl],
            used_ransac=used_ransac,
            R_world_body_visual=R_visual,
        ),
        "",
    )


def track_with_fallback(
    P_world: np.ndarray,
    has: np.ndarray,
    xy: np.ndarray,
    sigma: np.ndarray,
    ids: np.ndarray,
    camera: PinholeUndistorter,
    options: TrackingConfig,
    T_pred: np.ndarray | None,
    prior: ImuPrior | None = None,
    v_pred: np.ndarray | None = None,
) -> tuple[TrackResult | None, str]:
    """:func:`track_frame` on a frame's features ``has`` (N,) bool of its ``xy`` (N, 2),
    ``sigma`` (N,), ``ids`` (N,), whose map points are ``P_world`` (has.sum(), 3): IMU-aided,
    and if the IMU disagrees with the vision (a bad inertial state), visual alone."""
    args = (P_world, xy[has], sigma[has], ids[has], camera, options)
    res, reason = track_frame(*args, T_pred, prior, v_pred)
    if res is None and prior is not None:
        logger.debug("IMU-aided tracking failed (%s); visual only", reason)
        res, reason = track_frame(*args, None, None, None)
    return res, reason
