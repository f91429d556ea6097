"""Global optimisation of a map (paper Eq. 20), full stage: bundle adjustment with gtsam.

The pose-graph stage (:mod:`services.cloud.optimization.global_optimization`) corrects drift quickly
with relative-pose constraints only. When there is time the service follows it with this stage,
which optimises keyframe poses *and* map points on Eq. 20's terms:

- ``e_prio``: a tight prior on the map's first keyframe (the same one the pose graph fixes),
- ``e_imu``: with ``FullBAConfig.imu_factors`` (the default), a preintegrated ``CombinedImuFactor``
  over pose, velocity and bias states between consecutive keyframes of each agent whose IMU the edge
  forwarded (:mod:`services.cloud.optimization.inertial`); otherwise, and for intervals without IMU,
  its stand-in: a ``BetweenFactor<Pose3>`` whose measurement is the current relative pose (what the
  edge's visual-inertial odometry and the pose graph left) with fixed sigmas
  (:class:`~services.cloud.config.FullBAConfig`),
- loop and merge constraints as the pose graph has them (Cauchy kernel); a loop whose
  whitened error at the initial estimate exceeds ``loop_outlier_whitened`` is left out (the
  pose graph, solved just before, rejects outliers with the same test),
- ``e_proj``: a reprojection factor per observation on undistorted normalised coordinates
  (unit-focal ``Cal3_S2``, camera extrinsic as ``body_P_sensor``, as the edge's local BA),
  sigma ``pixel_sigma · level_scale^level / fx``, under a Huber (or Cauchy) kernel.
  Observations that reproject worse than ``max_initial_reprojection_px`` or lie behind the
  camera at the start are left out, and so are points with fewer than two observations left.

As for the pose graph, everything is a pure function on plain arrays: :func:`build_full_ba`
snapshots one map of the atlas into a picklable :class:`FullBAProblem` (on the service's
worker thread), :func:`solve_full_ba` runs in the optimiser process with bounded iterations
and wall time, and :func:`apply_full_ba` writes :class:`FullBAResult` back (keyframe poses as
the pose graph's result, then the optimised point positions); the service then sends the
corrected poses to the edges exactly as after a pose-graph optimisation.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from common.calibration import CameraCalibration
from common.camera import camera_model
from common.geometry import inverse_T, transform_points
from services.cloud.atlas.atlas import Atlas
from services.cloud.atlas.map_types import CameraOf, camera_lookup, split_key
from services.cloud.config import FullBAConfig, GlobalOptimizationConfig
from services.cloud.optimization.global_optimization import (
    GlobalOptimizationError,
    PoseGraphResult,
    add_attitude_factors,
    apply_pose_graph,
    gauge_prior_noise,
    held_indices,
    pose3,
    up_in_body,
)
from services.cloud.optimization.inertial import (
    ImuOf,
    ImuStore,
    ImuTerms,
    add_imu_factors,
    build_imu_terms,
    imu_variance_factor,
    inertial_states,
)

log = logging.getLogger(__name__)

_UNIT_K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)


class FullBAError(GlobalOptimizationError):
    """Empty or inconsistent full-BA problem."""


@dataclass(frozen=True, eq=False)
class FullBAProblem:
    """Plain bundle-adjustment data of one map (picklable).

    keys (N,) keyframe keys; T_world_body (N, 4, 4) initial poses (map frame);
    point_keys (P,) map point keys; p_world (P, 3) initial positions, metres;
    obs_kf (M,) index into keys, obs_point (M,) index into point_keys, obs_xy (M, 2)
    undistorted normalised image coordinates, obs_sigma (M,) their standard deviation
    (normalised units); T_body_cam (N, 4, 4) camera extrinsic of each keyframe (its robot's);
    edge_i, edge_j (E,) indices into keys, T_i_j (E, 4, 4) measured relative poses (body j in
    body i), sigmas (E, 6) (rad, rad, rad, m, m, m), robust (E,) loop / merge edges;
    fixed: index of the keyframe held by the prior; fx: focal length, pixels (the median over
    the keyframes' cameras: reports RMS in pixels); dropped_observations: observations left
    out at build time (behind the camera, too far off, or of points seen once).
    """

    keys: np.ndarray
    T_world_body: np.ndarray
    point_keys: np.ndarray
    p_world: np.ndarray
    obs_kf: np.ndarray
    obs_point: np.ndarray
    obs_xy: np.ndarray
    obs_sigma: np.ndarray
    T_body_cam: np.ndarray
    edge_i: np.ndarray
    edge_j: np.ndarray
    T_i_j: np.ndarray
    sigmas: np.ndarray
    robust: np.ndarray
    fixed: int
    fx: float = 1.0
    dropped_observations: int = 0
    up_body: np.ndarray | None = None
    """(N, 3) the up direction in each body frame at build time (held roll and pitch, see
    :func:`services.cloud.optimization.global_optimization.add_attitude_factors`)."""
    imu: ImuTerms | None = None
    """IMU terms between consecutive keyframes (None: IMU factors off)."""
    held: np.ndarray | None = None
    """(H,) indices of keyframes held by a prior as tight as ``fixed``'s (a prior map)."""
    held_points: np.ndarray | None = None
    """(Q,) indices of points held where they are (a prior map's; None: none)."""

    @property
    def n_observations(self) -> int:
        return int(self.obs_kf.shape[0])


@dataclass(frozen=True, eq=False)
class FullBAResult:
    """Optimised ``T_world_body (N, 4, 4)`` of ``keys (N,)`` and ``p_world (P, 3)`` of
    ``point_keys (P,)``; graph errors before / after (gtsam: 0.5 · Σ robust cost);
    reprojection RMS in pixels (``fx`` units) over the used observations before / after;
    Levenberg–Marquardt iterations; loop edges left out as outliers; solve seconds (graph
    construction included)."""

    keys: np.ndarray
    T_world_body: np.ndarray
    point_keys: np.ndarray
    p_world: np.ndarray
    initial_error: float
    final_error: float
    initial_rms_px: float
    final_rms_px: float
    iterations: int
    rejected_edges: np.ndarray
    seconds: float
    inertial_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """(M,) indices into ``keys`` of the keyframes with inertial states (IMU factors on) ..."""
    velocity: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """... their optimised velocities (M, 3) m/s, map frame ..."""
    bias_gyro: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    bias_accel: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """... and biases (M, 3) rad/s and m/s²."""
    mode: str = "batch"
    """How it was solved: ``"batch"`` (Levenberg–Marquardt), ``"isam2"`` (an incremental
    update, :mod:`services.cloud.optimization.incremental_ba`; graph errors NaN) or
    ``"isam2-reset"`` (a batch solve that (re)built the map's iSAM2 graph)."""
    imu_noise_scale: float = float("nan")
    """The factor on the robots' IMU noise the solve ended with (``imu_noise_scale``, then
    re-weighted to fit, :func:`solve_full_ba`); NaN without IMU factors."""


def _project(
    T_body_cam: np.ndarray,
    T_world_body: np.ndarray,
    p_world: np.ndarray,
    obs_kf: np.ndarray,
    obs_point: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Normalised projections ``(M, 2)`` and depths ``(M,)`` of every observation."""
    T_cam_world = inverse_T(np.einsum("nij,njk->nik", T_world_body, T_body_cam))
    R = T_cam_world[obs_kf, :3, :3]
    t = T_cam_world[obs_kf, :3, 3]
    p_cam = np.einsum("mij,mj->mi", R, p_world[obs_point]) + t
    z = p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = p_cam[:, :2] / z[:, None]
    return xy, z


def build_full_ba(
    atlas: Atlas,
    map_id: int,
    camera: CameraCalibration | CameraOf,
    config: FullBAConfig,
    graph_config: GlobalOptimizationConfig,
    imu: ImuStore | None = None,
    imu_of: ImuOf | None = None,
) -> FullBAProblem:
    """Snapshot one map of the atlas as a bundle-adjustment problem (current estimates);
    ``camera``: each agent's camera (or one for all); with ``config.imu_factors``, ``imu``
    the forwarded IMU and ``imu_of`` each agent's IMU calibration."""
    keys = atlas.keyframe_keys(map_id=map_id)
    if not keys:
        raise FullBAError(f"map {map_id} has no keyframes")
    index = {k: i for i, k in enumerate(keys)}
    T = np.array([atlas.T_map_body(k) for k in keys])
    camera_of = camera_lookup(camera)
    cams = [camera_of(split_key(k)[0]) for k in keys]
    fx_kf = np.array([float(c.fx) for c in cams])
    fx = float(np.median(fx_kf))
    T_body_cam = np.array([np.asarray(c.T_body_cam, np.float64) for c in cams])
    kf_idx: list[np.ndarray] = []
    mp_keys: list[np.ndarray] = []
    xy: list[np.ndarray] = []
    sigma: list[np.ndarray] = []
    for i, k in enumerate(keys):
        v = atlas.keyframe(k)
        rows = np.flatnonzero(v.map_point_keys >= 0)
        if rows.size == 0:
            continue
        kf_idx.append(np.full(rows.size, i, np.int64))
        mp_keys.append(np.asarray(v.map_point_keys[rows], np.int64))
        model = camera_model(cams[i])
        xy.append(model.pixels_to_normalized(np.asarray(v.keypoints[rows], np.float64)))
        lv = np.asarray(v.levels[rows], np.float64)
        sigma.append(config.pixel_sigma * config.level_scale**lv / fx_kf[i])
    obs_kf = np.concatenate(kf_idx) if kf_idx else np.zeros(0, np.int64)
    obs_mk = np.concatenate(mp_keys) if mp_keys else np.zeros(0, np.int64)
    obs_xy = np.concatenate(xy) if xy else np.zeros((0, 2))
    obs_sigma = np.concatenate(sigma) if sigma else np.zeros(0)
    n_all = obs_kf.shape[0]
    point_keys, obs_point = np.unique(obs_mk, return_inverse=True)
    p_world = atlas.map_point_positions(point_keys) if point_keys.size else np.zeros((0, 3))
    # Leave out observations behind the camera or too far off to be inliers now.
    proj, z = _project(T_body_cam, T, p_world, obs_kf, obs_point)
    err_px = np.linalg.norm(proj - obs_xy, axis=1) * fx_kf[obs_kf]
    ok = (z > config.min_depth_m) & (err_px <= config.max_initial_reprojection_px)
    # ... and points with fewer than two observations left (repeat: rows drop together).
    counts = np.bincount(obs_point[ok], minlength=point_keys.size)
    ok &= counts[obs_point] >= 2
    used = np.flatnonzero(np.bincount(obs_point[ok], minlength=point_keys.size) >= 2)
    remap = np.full(point_keys.size, -1, np.int64)
    remap[used] = np.arange(used.size)
    terms = None
    if config.imu_factors and imu is not None and imu_of is not None:
        terms = build_imu_terms(atlas, map_id, keys, imu, imu_of, config)
    with_imu = (
        set()
        if terms is None
        else set(zip(terms.pair_i.tolist(), terms.pair_j.tolist(), strict=True))
    )
    # Relative-pose constraints (stand-in of the IMU terms where there are none) and loops.
    ei: list[int] = []
    ej: list[int] = []
    meas: list[np.ndarray] = []
    sig: list[np.ndarray] = []
    rob: list[bool] = []
    odo = np.array([config.odometry_sigma_rot_rad] * 3 + [config.odometry_sigma_trans_m] * 3)
    for agent in atlas.agents_in_map(map_id):
        for a, b in itertools.pairwise(atlas.keyframe_keys(map_id=map_id, agent_id=agent)):
            i, j = index[a], index[b]
            if (i, j) in with_imu or (j, i) in with_imu:
                continue
            ei.append(i)
            ej.append(j)
            meas.append(inverse_T(T[i]) @ T[j])
            sig.append(odo)
            rob.append(False)
    loop = np.array([graph_config.loop_sigma_rot_rad] * 3 + [graph_config.loop_sigma_trans_m] * 3)
    for e in atlas.loops():
        if e.key_a in index and e.key_b in index:
            ei.append(index[e.key_a])
            ej.append(index[e.key_b])
            meas.append(np.array(e.T_a_b))
            sig.append(loop)
            rob.append(True)
    own = atlas.keyframe_keys(map_id=map_id, agent_id=map_id)
    E = len(ei)
    return FullBAProblem(
        keys=np.array(keys, np.int64),
        T_world_body=T,
        point_keys=point_keys[used],
        p_world=p_world[used],
        obs_kf=obs_kf[ok],
        obs_point=remap[obs_point[ok]],
        obs_xy=obs_xy[ok],
        obs_sigma=obs_sigma[ok],
        T_body_cam=T_body_cam,
        edge_i=np.array(ei, np.int64),
        edge_j=np.array(ej, np.int64),
        T_i_j=np.array(meas).reshape(E, 4, 4),
        sigmas=np.array(sig).reshape(E, 6),
        robust=np.array(rob, bool),
        fixed=index[own[0]] if own else 0,
        fx=fx,
        dropped_observations=int(n_all - ok.sum()),
        up_body=up_in_body(T),
        imu=terms,
    )


def kernel(name: str, scale: float) -> gtsam.noiseModel.mEstimator.Base | None:
    if name == "huber":
        return gtsam.noiseModel.mEstimator.Huber.Create(scale)
    if name == "cauchy":
        return gtsam.noiseModel.mEstimator.Cauchy.Create(scale)
    if name == "none":
        return None
    raise FullBAError(f"unknown robust kernel {name!r}")


def rms_px(problem: FullBAProblem, T: np.ndarray, p: np.ndarray, stride: int = 1) -> float:
    """Reprojection RMS (px at level 0) of the observations at poses ``T`` (N, 4, 4) and
    points ``p`` (P, 3); ``stride``: of every ``stride``-th observation only."""
    if problem.n_observations == 0:
        return 0.0
    xy, _ = _project(
        problem.T_body_cam, T, p, problem.obs_kf[::stride], problem.obs_point[::stride]
    )
    err2 = np.sum((xy - problem.obs_xy[::stride]) ** 2, axis=1)
    return float(np.sqrt(np.mean(err2))) * problem.fx


def gauge_tilt_sigma(problem: FullBAProblem, config: FullBAConfig) -> float:
    """The roll / pitch sigma of the prior on the fixed keyframe: ``config.gauge_tilt_sigma_rad``
    when the problem has IMU factors (gravity then fixes the map's tilt) and no prior-map
    keyframes are held (they fix it), else 0 (all six degrees of freedom held)."""
    imu = problem.imu is not None and problem.imu.n_pairs > 0
    held = problem.held is not None and problem.held.size > 0
    return config.gauge_tilt_sigma_rad if imu and not held else 0.0


@dataclass
class _Graph:
    """A built full-BA graph: initial values, loop edges left out, the IMU factors' range."""

    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    rejected: list[int]
    imu_first: int
    n_imu: int


def _build_graph(
    problem: FullBAProblem,
    T_init: np.ndarray,
    p_init: np.ndarray,
    config: FullBAConfig,
    graph_config: GlobalOptimizationConfig,
) -> _Graph:
    """The problem's graph (module docstring) with initial poses ``T_init`` (N, 4, 4) and
    points ``p_init`` (P, 3); priors and loop tests at the problem's own estimates."""
    n, n_pts = problem.keys.shape[0], problem.point_keys.shape[0]
    X = gtsam.symbol_shorthand.X
    L = gtsam.symbol_shorthand.L
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i in range(n):
        values.insert(X(i), pose3(T_init[i]))
    for j in range(n_pts):
        values.insert(L(j), np.asarray(p_init[j], np.float64))
    prior = gtsam.noiseModel.Isotropic.Sigma(6, graph_config.prior_sigma)
    tilt = gauge_tilt_sigma(problem, config)
    for i in held_indices(problem.fixed, problem.held):
        held_noise: gtsam.noiseModel.Base = prior
        if i == problem.fixed and tilt > 0:
            held_noise = gauge_prior_noise(problem.T_world_body[i], graph_config.prior_sigma, tilt)
        graph.add(gtsam.PriorFactorPose3(X(i), pose3(problem.T_world_body[i]), held_noise))
    if problem.held_points is not None and problem.held_points.size:
        point_prior = gtsam.noiseModel.Isotropic.Sigma(3, graph_config.prior_sigma)
        for j in np.asarray(problem.held_points, np.int64).tolist():
            graph.add(
                gtsam.PriorFactorPoint3(L(j), np.asarray(problem.p_world[j], float), point_prior)
            )
    poses = [X(i) for i in range(n)]
    add_attitude_factors(graph, poses, problem.up_body, config.attitude_sigma_rad)
    loop_kernel = kernel(graph_config.loop_robust_kernel, graph_config.loop_kernel_scale)
    rejected: list[int] = []
    for e in range(problem.edge_i.shape[0]):
        i, j = int(problem.edge_i[e]), int(problem.edge_j[e])
        meas = pose3(problem.T_i_j[e])
        noise: gtsam.noiseModel.Base = gtsam.noiseModel.Diagonal.Sigmas(problem.sigmas[e])
        if problem.robust[e]:
            rel = pose3(problem.T_world_body[i]).between(pose3(problem.T_world_body[j]))
            err = np.asarray(gtsam.Pose3.Logmap(meas.between(rel))) / problem.sigmas[e]
            if np.linalg.norm(err) > graph_config.loop_outlier_whitened:
                rejected.append(e)
                continue
            if loop_kernel is not None:
                noise = gtsam.noiseModel.Robust.Create(loop_kernel, noise)
        graph.add(gtsam.BetweenFactorPose3(X(i), X(j), meas, noise))
    imu_first, n_imu = int(graph.size()), 0
    if problem.imu is not None and problem.imu.n_pairs:
        n_imu = add_imu_factors(graph, values, problem.imu, T_init, config)
    obs_kernel = kernel(config.robust_kernel, config.kernel_scale)
    body_P_cam = [pose3(Tbc) for Tbc in problem.T_body_cam]
    noise_of: dict[float, gtsam.noiseModel.Base] = {}
    factor = gtsam.GenericProjectionFactorCal3_S2
    for kf, pt, xy, s in zip(
        problem.obs_kf.tolist(),
        problem.obs_point.tolist(),
        problem.obs_xy,
        problem.obs_sigma.tolist(),
        strict=True,
    ):
        obs_noise = noise_of.get(s)
        if obs_noise is None:
            obs_noise = gtsam.noiseModel.Isotropic.Sigma(2, s)
            if obs_kernel is not None:
                obs_noise = gtsam.noiseModel.Robust.Create(obs_kernel, obs_noise)
            noise_of[s] = obs_noise
        graph.add(factor(xy, obs_noise, X(kf), L(pt), _UNIT_K, body_P_cam[kf]))
    return _Graph(graph, values, rejected, imu_first, n_imu)


def _levenberg_marquardt(
    built: _Graph, config: FullBAConfig, t0: float
) -> tuple[gtsam.Values, float, int]:
    """Solve ``built``: (values, initial error, iterations); bounded as :func:`solve_full_ba`
    says."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.max_iterations)
    params.setRelativeErrorTol(config.relative_error_tol)
    params.setVerbosityLM("SILENT")
    optimizer = gtsam.LevenbergMarquardtOptimizer(built.graph, built.values, params)
    initial_error = error = float(optimizer.error())
    iterations = 0
    try:
        while iterations < config.max_iterations:
            optimizer.iterate()
            iterations += 1
            new_error = float(optimizer.error())
            done = gtsam.checkConvergence(
                params.getRelativeErrorTol(),
                params.getAbsoluteErrorTol(),
                params.getErrorTol(),
                error,
                new_error,
            )
            error = new_error
            if done or time.perf_counter() - t0 > config.max_seconds:
                break
    except RuntimeError as exc:  # indeterminant system: keep the last good estimate
        log.warning("full BA: Levenberg-Marquardt stopped after %d iterations: %s", iterations, exc)
    return optimizer.values(), initial_error, iterations


def _estimates(values: gtsam.Values, n: int, n_pts: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``n`` poses (n, 4, 4) and ``n_pts`` points (n_pts, 3) of a full-BA solution."""
    X, L = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    T = np.array([values.atPose3(X(i)).matrix() for i in range(n)])
    return T, np.array([values.atPoint3(L(j)) for j in range(n_pts)]).reshape(n_pts, 3)


def reweighted_noise_scale(scale: float, factor: float, config: FullBAConfig) -> float:
    """The IMU noise scale after a solve whose IMU variance factor was ``factor``
    (:func:`~services.cloud.optimization.inertial.imu_variance_factor`): ``scale ·
    sqrt(factor)``, the step bounded to ``config.imu_reweight_max_step`` either way and the
    result to ``[imu_noise_scale_min, imu_noise_scale_max]``; ``scale`` unchanged when the
    factor is not finite and positive."""
    if not (np.isfinite(factor) and factor > 0):
        return scale
    step = float(
        np.clip(np.sqrt(factor), 1 / config.imu_reweight_max_step, config.imu_reweight_max_step)
    )
    return float(np.clip(scale * step, config.imu_noise_scale_min, config.imu_noise_scale_max))


def solve_full_ba(
    problem: FullBAProblem,
    config: FullBAConfig,
    graph_config: GlobalOptimizationConfig,
) -> FullBAResult:
    """Solve the bundle adjustment with Levenberg–Marquardt (pure; no atlas access).

    At most ``config.max_iterations`` iterations and, after the one that crosses it,
    ``config.max_seconds`` of wall time (graph construction included). With IMU factors and
    ``config.imu_reweight_rounds``, the IMU's noise is then re-weighted to fit (variance
    component estimation): the IMU variance factor of the solution scales the noise
    (:func:`reweighted_noise_scale`) and the problem is solved again from the solution, until
    the scale changes by less than ``imu_reweight_tolerance`` or the rounds run out."""
    t0 = time.perf_counter()
    n, n_pts = problem.keys.shape[0], problem.point_keys.shape[0]
    if n == 0:
        raise FullBAError("empty full-BA problem")
    if not 0 <= problem.fixed < n:
        raise FullBAError(f"fixed index {problem.fixed} outside 0..{n - 1}")
    built = _build_graph(problem, problem.T_world_body, problem.p_world, config, graph_config)
    result, initial_error, iterations = _levenberg_marquardt(built, config, t0)
    scale = config.imu_noise_scale
    terms = problem.imu
    rounds = config.imu_reweight_rounds if built.n_imu and terms is not None else 0
    for _ in range(rounds):
        if terms is None or time.perf_counter() - t0 > config.max_seconds:
            break
        factor = imu_variance_factor(built.graph, built.imu_first, built.n_imu, result, terms)
        new_scale = reweighted_noise_scale(scale, factor, config)
        if abs(np.log(new_scale / scale)) < np.log1p(config.imu_reweight_tolerance):
            break
        log.info(
            "full BA: IMU variance factor %.3g, noise scale %.3g -> %.3g", factor, scale, new_scale
        )
        scale = new_scale
        config = dataclasses.replace(config, imu_noise_scale=scale)
        built = _build_graph(problem, *_estimates(result, n, n_pts), config, graph_config)
        result, _, more = _levenberg_marquardt(built, config, t0)
        iterations += more
    T_out, p_out = _estimates(result, n, n_pts)
    idx, vel, bg, ba = np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))
    if built.n_imu and problem.imu is not None:
        idx, vel, bg, ba = inertial_states(result, problem.imu)
    seconds = time.perf_counter() - t0
    out = FullBAResult(
        keys=problem.keys.copy(),
        T_world_body=T_out,
        point_keys=problem.point_keys.copy(),
        p_world=p_out,
        initial_error=initial_error,
        final_error=float(built.graph.error(result)),
        initial_rms_px=rms_px(problem, problem.T_world_body, problem.p_world),
        final_rms_px=rms_px(problem, T_out, p_out),
        iterations=iterations,
        rejected_edges=np.array(built.rejected, np.int64),
        seconds=seconds,
        inertial_index=idx,
        velocity=vel,
        bias_gyro=bg,
        bias_accel=ba,
        imu_noise_scale=scale if built.n_imu else float("nan"),
    )
    log.info(
        "full BA: %d keyframes, %d points, %d observations, %d IMU factors (noise x%.3g), "
        "%d iterations in %.2f s: "
        "error %.4g -> %.4g, reprojection RMS %.2f -> %.2f px",
        n,
        n_pts,
        problem.n_observations,
        built.n_imu,
        scale,
        iterations,
        seconds,
        out.initial_error,
        out.final_error,
        out.initial_rms_px,
        out.final_rms_px,
    )
    return out


def apply_full_ba(atlas: Atlas, result: FullBAResult) -> int:
    """Write a full-BA result into the atlas; returns how many keyframe poses were written.

    Poses go in as a pose-graph result does (:func:`apply_pose_graph`: pruned keyframes are
    skipped, keyframes that arrived meanwhile get their agent's correction, map points move
    with their reference keyframe); then the optimised points that still exist get their
    optimised positions."""
    n = apply_pose_graph(
        atlas,
        PoseGraphResult(
            result.keys,
            result.T_world_body,
            result.initial_error,
            result.final_error,
            result.iterations,
            result.rejected_edges,
        ),
    )
    atlas.set_map_point_positions(
        {
            k: result.p_world[i]
            for i, k in enumerate(result.point_keys.tolist())
            if atlas.has_map_point(k)
        }
    )
    return n


def reprojection_rms_px(atlas: Atlas, map_id: int, camera: CameraCalibration | CameraOf) -> float:
    """RMS reprojection error, pixels (each keyframe's ``fx`` units), of every observation of
    a map's points in front of the camera at the atlas' current estimates (a diagnostic for
    tests and benchmarks); ``camera``: each agent's camera (or one for all)."""
    camera_of = camera_lookup(camera)
    errs: list[np.ndarray] = []
    for k in atlas.keyframe_keys(map_id=map_id):
        v = atlas.keyframe(k)
        rows = np.flatnonzero(v.map_point_keys >= 0)
        if rows.size == 0:
            continue
        cam = camera_of(v.agent_id)
        p = atlas.map_point_positions(v.map_point_keys[rows])
        p_cam = transform_points(inverse_T(np.asarray(v.T_map_body) @ cam.T_body_cam), p)
        front = p_cam[:, 2] > 1e-6
        xy = p_cam[front, :2] / p_cam[front, 2:3]
        uv = np.asarray(v.keypoints[rows][front], np.float64)
        obs = camera_model(cam).pixels_to_normalized(uv)
        errs.append(np.sum((xy - obs) ** 2, axis=1) * float(cam.fx) ** 2)
    if not errs:
        return 0.0
    return float(np.sqrt(np.mean(np.concatenate(errs))))
