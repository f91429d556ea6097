"""How firmly a map's IMU fixes its scale: the inertial-only cost against the map's scale.

A monocular map's scale comes from its IMU alone (the images fix everything but the scale;
only the camera's lever arm adds a little). ORB-SLAM3 refines a monocular-inertial map's
scale with an inertial-only optimisation: the poses held up to one scale factor, velocities
and biases free (Campos et al., "ORB-SLAM3", IEEE T-RO 37(6), 2021, Sec. V-B). The same
problem, swept over the scale, measures how well the flight determines it:

for scales ``s`` on a grid, the keyframe positions of a solved full BA are scaled by ``s`` about its
fixed keyframe and held (orientations unchanged, gravity along the map's -z), and each keyframe's
velocity and bias are solved against the IMU factors alone (the full BA's own ``CombinedImuFactor``
terms, :func:`services.cloud.optimization.inertial.add_imu_factors`, with its noise scaling). A
parabola fitted to the cost gives the scale the IMU prefers for this map's shape (``best_scale``,
relative to the map) and its curvature ``a`` the scale's standard deviation from the IMU alone,
``sigma = sqrt(0.5 / a)`` (gtsam's error is half the squared whitened residual). A flight that
barely accelerates gives a flat parabola: its map's scale is only as good as whatever else holds it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import gtsam
import numpy as np

from services.cloud.config import FullBAConfig
from services.cloud.optimization.global_optimization import pose3
from services.cloud.optimization.inertial import ImuTerms, add_imu_factors


@dataclass(frozen=True)
class ScaleProfile:
    """``scales (G,)`` tried (relative to the map as given) and the inertial-only ``costs
    (G,)`` (gtsam error); ``best_scale`` the fitted minimum; ``sigma`` the scale's standard
    deviation from the IMU alone (relative, 0.001 = 0.1 %); ``pairs`` IMU factors used."""

    scales: np.ndarray
    costs: np.ndarray
    best_scale: float
    sigma: float
    pairs: int


def inertial_cost(
    T_world_body: np.ndarray, terms: ImuTerms, config: FullBAConfig, max_iterations: int = 50
) -> float:
    """The IMU factors' cost at the poses ``T_world_body`` (N, 4, 4), held, after solving the
    velocities and biases of the keyframes in ``terms``' pairs (Levenberg–Marquardt)."""
    X = gtsam.symbol_shorthand.X
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    hold = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    for i in np.unique(np.concatenate([terms.pair_i, terms.pair_j])).tolist():
        values.insert(X(i), pose3(T_world_body[i]))
        graph.add(gtsam.PriorFactorPose3(X(i), pose3(T_world_body[i]), hold))
    add_imu_factors(graph, values, terms, T_world_body, config)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-10)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return float(graph.error(result))


def scale_profile(
    T_world_body: np.ndarray,
    fixed: int,
    terms: ImuTerms,
    config: FullBAConfig,
    span: float = 0.004,
    steps: int = 9,
) -> ScaleProfile:
    """The inertial-only cost of the map ``T_world_body`` (N, 4, 4) scaled about keyframe
    ``fixed`` by ``1 ± span`` in ``steps`` steps, and its parabola (module docstring).
    ValueError without IMU pairs, or when the cost does not curve upwards (no minimum: widen
    ``span``)."""
    if terms.n_pairs == 0:
        raise ValueError("scale_profile: the map has no IMU factors")
    if steps < 3 or span <= 0:
        raise ValueError(f"scale_profile: need steps >= 3 and span > 0, got {steps}, {span}")
    c0 = np.asarray(T_world_body[fixed][:3, 3], np.float64)
    scales = np.linspace(1.0 - span, 1.0 + span, steps)
    costs = []
    for s in scales:
        T = np.array(T_world_body, np.float64, copy=True)
        T[:, :3, 3] = c0 + s * (T[:, :3, 3] - c0)
        costs.append(inertial_cost(T, terms, config))
    cost = np.asarray(costs)
    a, b, _ = np.polyfit(scales, cost, 2)
    if a <= 0:
        raise ValueError(
            f"scale_profile: the inertial cost does not curve upwards over 1 ± {span} "
            f"(costs {np.round(cost, 3).tolist()})"
        )
    return ScaleProfile(scales, cost, float(-b / (2 * a)), float(np.sqrt(0.5 / a)), terms.n_pairs)


def nominal(config: FullBAConfig) -> FullBAConfig:
    """``config`` with the robots' IMU noise as calibrated (``imu_noise_scale`` 1): the scale's
    spread the sensor itself allows, rather than the one the full BA assumes."""
    return dataclasses.replace(config, imu_noise_scale=1.0)
