"""Tracking of every frame against the map points of its tracks.

The pose is first checked at the prediction (IMU preintegration from the last keyframe after
VI initialisation, constant velocity before). If enough tracks agree with it, RANSAC is skipped;
otherwise PnP RANSAC (cv2, EPnP) finds the inliers. A motion-only optimisation in gtsam then
refines the pose on the inliers with a Cauchy kernel; after VI initialisation the graph also
holds the CombinedImuFactor from the last keyframe (held fixed), so velocity and bias of the
frame come out too (ORB-SLAM3's pose-inertial optimisation).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from common.geometry import inverse_T, so3_exp
from services.edge.vio.imu import make_bias
from services.edge.vio.state import Keyframe, PinholeUndistorter, project
from services.edge.vio.types import TrackingOptions

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
    ``inlier_ids`` track ids agreeing with the pose."""

    T_world_body: np.ndarray
    v_world: np.ndarray | None
    bias_accel: np.ndarray | None
    bias_gyro: np.ndarray | None
    inlier_ids: np.ndarray
    used_ransac: bool


def _chi2(T_world_body, T_body_cam, P, xy, sigma) -> np.ndarray:
    proj, z = project(T_world_body, T_body_cam, P)
    e = np.sum((proj - xy) ** 2, axis=1) / sigma**2
    return np.where(z > 0, np.nan_to_num(e, nan=np.inf), np.inf)


def _ransac(P, xy, camera: PinholeUndistorter, options: TrackingOptions) -> np.ndarray | None:
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


def _optimise(
    T0: np.ndarray,
    P: np.ndarray,
    xy: np.ndarray,
    sigma: np.ndarray,
    camera: PinholeUndistorter,
    prior: ImuPrior | None,
    v0: np.ndarray | None,
    options: TrackingOptions,
) -> tuple[np.ndarray, np.ndarray | None, gtsam.imuBias.ConstantBias | None]:
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(T0))
    body_P_cam = gtsam.Pose3(camera.T_body_cam)
    cauchy = gtsam.noiseModel.mEstimator.Cauchy.Create(np.sqrt(options.chi2_threshold))
    tight3 = gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)
    noise: dict[float, gtsam.noiseModel.Base] = {}
    for i in range(len(P)):
        s = float(sigma[i])
        if s not in noise:
            noise[s] = gtsam.noiseModel.Robust.Create(
                cauchy, gtsam.noiseModel.Isotropic.Sigma(2, s)
            )
        values.insert(L(i), P[i])
        graph.add(gtsam.PriorFactorPoint3(L(i), P[i], tight3))
        graph.add(
            gtsam.GenericProjectionFactorCal3_S2(
                gtsam.Point2(*xy[i]), noise[s], X(0), L(i), _UNIT_K, body_P_cam
            )
        )
    if prior is not None:
        kf = prior.keyframe
        bias = make_bias(kf.bias_accel, kf.bias_gyro)
        values.insert(X(1), gtsam.Pose3(kf.T_world_body))
        values.insert(V(1), kf.v_world)
        values.insert(B(1), bias)
        values.insert(V(0), v0 if v0 is not None else kf.v_world)
        values.insert(B(0), bias)
        graph.add(
            gtsam.PriorFactorPose3(
                X(1), gtsam.Pose3(kf.T_world_body), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
            )
        )
        graph.add(gtsam.PriorFactorVector(V(1), kf.v_world, tight3))
        graph.add(
            gtsam.PriorFactorConstantBias(B(1), bias, gtsam.noiseModel.Isotropic.Sigma(6, 1e-6))
        )
        graph.add(gtsam.CombinedImuFactor(X(1), V(1), X(0), V(0), B(1), B(0), prior.pim))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(options.max_iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    T = result.atPose3(X(0)).matrix()
    if prior is None:
        return T, None, None
    return T, np.asarray(result.atVector(V(0)), float), result.atConstantBias(B(0))


def track_frame(
    P_world: np.ndarray,
    xy: np.ndarray,
    sigma: np.ndarray,
    ids: np.ndarray,
    camera: PinholeUndistorter,
    options: TrackingOptions,
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
    return (
        TrackResult(
            T_world_body=T,
            v_world=v if prior is not None else None,
            bias_accel=None if bias is None else np.asarray(bias.accelerometer(), float),
            bias_gyro=None if bias is None else np.asarray(bias.gyroscope(), float),
            inlier_ids=ids[inl],
            used_ransac=used_ransac,
        ),
        "",
    )
