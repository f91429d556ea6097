"""The visual-inertial initialisation of one map as the VIO runs it (the paper's VI
initialisation, as in ORB-SLAM3): the first run and its scheduled refinements.

- :func:`first_vi_init`: inertial-only MAP over the newest ``max_span_s`` of keyframes
  (:func:`~services.edge.vio.vi_init.inertial_only_map`: gravity direction, scale, velocities
  and biases with the visual poses as weak priors); if the IMU and the visual poses agree and
  the scale is plausible, the map is rotated to gravity and scaled to metres, every keyframe
  gets its velocity and the biases, and one visual-inertial BA refines everything.
- :func:`refine_vi`: a re-run on a map that is already metric and gravity-aligned, where the
  joint visual-inertial BA over every keyframe is the well-posed estimator of scale (the
  inertial-only problem with fixed, noisy visual poses would shift it by its own bias); then
  :func:`reanchor` undoes the gauge motion that BA gave the newest keyframe.

Both change ``vmap`` in place; the caller (``VioManager.run_vi_init``) keeps the schedule, the
reasons and the statistics.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from common.geometry import make_T
from services.edge.vio.local_ba import BAStats, bundle_adjust
from services.edge.vio.state import Keyframe, PinholeUndistorter, VioMap, project
from services.edge.vio.types import LocalBAConfig, VioConfig
from services.edge.vio.vi_init import inertial_only_map, subsample_keyframes


@dataclass(frozen=True)
class ViInitOutcome:
    """What a first VI initialisation did: ``reason`` why it was refused ("" when it was
    applied), the final BA's statistics and the scale it found (None when refused)."""

    reason: str
    stats: BAStats | None = None
    scale: float | None = None
    scale_sigma_rel: float | None = None


def median_depth(vmap: VioMap, camera: PinholeUndistorter) -> float:
    """Median depth [map units] of the points seen by the newest keyframe (1 without any)."""
    kf = vmap.last_keyframe()
    assert kf is not None
    P = np.array([mp.p_world for t in kf.row_of if (mp := vmap.point_of(t)) is not None])
    if len(P) == 0:
        return 1.0
    _, z = project(kf.T_world_body, camera.T_body_cam, P)
    return float(np.median(z[z > 0])) if np.any(z > 0) else 1.0


def first_vi_init(
    vmap: VioMap,
    kfs: list[Keyframe],
    camera: PinholeUndistorter,
    imu_params: gtsam.PreintegrationCombinedParams,
    options: VioConfig,
    ba_options: LocalBAConfig,
    gyro_bias_guess: np.ndarray,
    noise_measured: bool = False,
) -> ViInitOutcome:
    """The first VI initialisation over ``kfs`` (keyframes connected by IMU segments, oldest
    first); the map changes only when it is applied (``reason == ""``). ``noise_measured``:
    the IMU is weighted by the noise it shows (``VioConfig.noise_from_data``), so its
    whitened residuals are judged by ``vi_init.max_cost_per_residual_measured_noise``. A
    refusal's reason gives the numbers (keyframes, span, scale and biases found)."""
    vopt = options.vi_init
    t_last = kfs[-1].timestamp_ns
    kfs = [k for k in kfs if (t_last - k.timestamp_ns) * 1e-9 <= vopt.max_span_s]
    sub = subsample_keyframes(kfs, vopt.min_interval_s)
    res, reason = inertial_only_map(
        sub,
        imu_params,
        options.gravity_mps2,
        np.zeros(3),
        gyro_bias_guess,
        vopt.accel_bias_prior_sigma_first,
        vopt.gyro_bias_prior_sigma_first,
        vopt.visual_position_sigma_rel * median_depth(vmap, camera),
        np.radians(vopt.visual_rotation_sigma_deg),
    )
    limit = (
        vopt.max_cost_per_residual_measured_noise if noise_measured else vopt.max_cost_per_residual
    )
    span = (kfs[-1].timestamp_ns - kfs[0].timestamp_ns) * 1e-9
    if res is not None and res.cost_per_residual > limit:
        reason = (
            f"IMU and visual poses disagree (cost/residual {res.cost_per_residual:.2f} > "
            f"{limit}; {len(sub)} keyframes over {span:.1f} s, scale {res.scale:.3g} "
            f"± {100 * res.scale_sigma_rel:.0f} %, gyro bias {np.round(res.bias_gyro, 3)} "
            f"rad/s, accel bias {np.round(res.bias_accel, 2)} m/s²)"
        )
        res = None
    if res is None or not (vopt.min_scale <= res.scale <= vopt.max_scale):
        return ViInitOutcome(
            reason
            or f"scale {res.scale if res else float('nan'):.3g} out of range "
            f"({len(sub)} keyframes over {span:.1f} s)"
        )
    vmap.transform(make_T(res.R_world_v, np.zeros(3)), res.scale)
    # Velocities at every keyframe: interpolated from the subsampled solution.
    t_sub = np.array([k.timestamp_ns for k in sub], dtype=np.float64)
    for kf in kfs:
        kf.v_world = np.array(
            [np.interp(float(kf.timestamp_ns), t_sub, res.velocities[:, c]) for c in range(3)]
        )
    for kf in vmap.keyframe_list():
        kf.bias_gyro = res.bias_gyro.copy()
        kf.bias_accel = res.bias_accel.copy()
    vmap.vi_initialized = True
    sigmas = (vopt.accel_bias_prior_sigma_first, vopt.gyro_bias_prior_sigma_first)
    stats = _vi_ba(vmap, kfs, camera, imu_params, options, ba_options, sigmas)
    return ViInitOutcome("", stats, res.scale, res.scale_sigma_rel)


def refine_vi(
    vmap: VioMap,
    kfs: list[Keyframe],
    camera: PinholeUndistorter,
    imu_params: gtsam.PreintegrationCombinedParams,
    options: VioConfig,
    ba_options: LocalBAConfig,
) -> tuple[BAStats, np.ndarray]:
    """A visual-inertial BA over ``kfs`` of a VI-initialised map; returns its statistics and
    the correction ``(4, 4)`` :func:`reanchor` applied to the map afterwards."""
    vopt = options.vi_init
    T_newest_before = kfs[-1].T_world_body.copy()
    sigmas = (vopt.accel_bias_prior_sigma, vopt.gyro_bias_prior_sigma)
    stats = _vi_ba(vmap, kfs, camera, imu_params, options, ba_options, sigmas)
    return stats, reanchor(vmap, kfs[-1], T_newest_before)


def _vi_ba(
    vmap: VioMap,
    kfs: list[Keyframe],
    camera: PinholeUndistorter,
    imu_params: gtsam.PreintegrationCombinedParams,
    options: VioConfig,
    ba_options: LocalBAConfig,
    bias_prior_sigmas: tuple[float, float],
) -> BAStats:
    """The visual-inertial BA over ``kfs`` (gauge: the oldest), with these bias priors."""
    ids = [k.id for k in kfs]
    return bundle_adjust(
        vmap,
        ids,
        camera,
        imu_params,
        ba_options,
        options.mapping,
        gauge_ids=(ids[0],),
        max_iterations=options.vi_init.full_ba_iterations,
        bias_prior_sigmas=bias_prior_sigmas,
    )


def reanchor(vmap: VioMap, newest: Keyframe, T_before: np.ndarray) -> np.ndarray:
    """Undo the gauge motion (yaw and translation, unobservable) a full BA gave the newest
    keyframe, so that corrections land behind the robot and its pose stays continuous;
    returns the transform ``(4, 4)`` applied to the map."""
    D = T_before[:3, :3] @ newest.T_world_body[:3, :3].T
    yaw = np.arctan2(D[1, 0] - D[0, 1], D[0, 0] + D[1, 1])
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    t = T_before[:3, 3] - R @ newest.T_world_body[:3, 3]
    T = make_T(R, t)
    vmap.transform(T, 1.0)
    return T
