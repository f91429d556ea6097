"""Local bundle adjustment with gtsam (paper Eq. 15–18, Fig. 5b).

Variables: pose ``X`` (T_world_body), velocity ``V`` and bias ``B`` of every keyframe of the
window, and the map points ``L`` they observe. Factors: reprojection of every observation on
undistorted normalised coordinates (unit-focal Cal3_S2 with the camera extrinsic as
``body_P_sensor``) under a Cauchy kernel; a CombinedImuFactor (preintegration + bias random
walk) under a Huber kernel between consecutive keyframes. Keyframes outside the window that
observe window points, and the keyframe just before the window, are held fixed by tight priors.

Two solvers of this one problem (``LocalBAConfig.solver``): "schur" (default,
:mod:`services.edge.vio.ba_solver`: reprojection terms in numpy, points eliminated by Schur
complement, the IMU factors and priors of the same gtsam graph linearised by gtsam; fixed
keyframes are constants) and "gtsam" (the whole graph with a projection factor per
observation, gtsam's LM; the reference, also used for windows of more than
``LocalBAConfig.schur_max_keyframes`` free keyframes). Both follow gtsam's LM schedule and
report gtsam's graph error.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from common.preintegration import make_bias, preintegrate
from services.edge.vio.ba_solver import Observations, SchurLM, observation_chi2
from services.edge.vio.state import MapPoint, PinholeUndistorter, VioMap, project
from services.edge.vio.types import LocalBAConfig, MappingConfig

logger = logging.getLogger(__name__)

_UNIT_K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class BAStats:
    """Summary of one bundle adjustment (errors are gtsam graph errors, 0.5·Σ robust cost)."""

    n_keyframes: int
    n_fixed: int
    n_points: int
    n_observations: int
    error_before: float
    error_after: float
    culled_observations: int
    culled_points: int


def _pose(T: np.ndarray) -> gtsam.Pose3:
    return gtsam.Pose3(np.asarray(T, dtype=np.float64))


class _NoiseCache:
    """One robust noise model per distinct sigma (sigmas repeat: one per pyramid level)."""

    def __init__(self, cauchy_k: float) -> None:
        self._k = cauchy_k
        self._cache: dict[float, gtsam.noiseModel.Base] = {}

    def __call__(self, sigma: float) -> gtsam.noiseModel.Base:
        m = self._cache.get(sigma)
        if m is None:
            m = gtsam.noiseModel.Robust.Create(
                gtsam.noiseModel.mEstimator.Cauchy.Create(self._k),
                gtsam.noiseModel.Isotropic.Sigma(2, sigma),
            )
            self._cache[sigma] = m
        return m


def bundle_adjust(
    vmap: VioMap,
    window_ids: list[int],
    camera: PinholeUndistorter,
    imu_params: gtsam.PreintegrationCombinedParams | None,
    options: LocalBAConfig,
    mapping: MappingConfig,
    gauge_ids: tuple[int, ...] = (),
    max_iterations: int | None = None,
    bias_prior_sigmas: tuple[float, float] = (1.0, 0.1),
) -> BAStats:
    """Optimise the keyframes ``window_ids`` (time order) and their points in place.

    ``imu_params`` None gives a visual-only BA (before VI initialisation). ``gauge_ids`` are
    window keyframes whose pose is held fixed when nothing outside the window anchors the map.
    ``bias_prior_sigmas`` (accel m/s², gyro rad/s) is the prior on the first window keyframe's
    bias around its current value when no fixed keyframe precedes the window (ORB-SLAM3's
    priorA / priorG of the full inertial BA; the default only conditions the problem).
    """
    window = [vmap.keyframes[k] for k in window_ids if k in vmap.keyframes]
    in_window = {kf.id for kf in window}
    track_point, all_points = vmap.track_point, vmap.points
    point_ids = sorted(
        {p for kf in window for t in kf.row_of if (p := track_point.get(t)) in all_points}
    )
    table = _observation_table(vmap, [vmap.points[p] for p in point_ids])
    obs_kf = np.asarray(table.keyframe_ids, dtype=np.int64)[table.obs.pose]
    selected = np.ones(len(point_ids), dtype=bool)
    if 0 < options.max_points < len(point_ids):
        # The points with the most window observations (ties: lower id).
        in_win = np.isin(obs_kf, np.fromiter(in_window, np.int64, len(in_window)))
        n_in_win = np.bincount(table.obs.point[in_win], minlength=len(point_ids))
        best = np.lexsort((np.asarray(point_ids), -n_in_win))[: options.max_points]
        selected[:] = False
        selected[best] = True
    observers = set(np.unique(obs_kf[selected[table.obs.point]]).tolist())
    fixed = sorted(observers - in_window, key=lambda k: vmap.keyframes[k].timestamp_ns)
    fixed = fixed[-options.max_fixed_observers :]
    use_imu = imu_params is not None
    prev_fixed: int | None = None
    if use_imu and window and window[0].previous_id in vmap.keyframes:
        prev_fixed = window[0].previous_id
        if prev_fixed not in fixed:
            fixed.append(prev_fixed)
    fixed_set = set(fixed)
    if not fixed_set:
        fixed_set = {k for k in gauge_ids if k in in_window}
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    tight6 = gtsam.noiseModel.Isotropic.Sigma(6, options.fixed_sigma)
    tight3 = gtsam.noiseModel.Isotropic.Sigma(3, options.fixed_sigma)
    variables = [kf.id for kf in window] + [k for k in fixed if k not in in_window]
    for k in variables:
        kf = vmap.keyframes[k]
        values.insert(X(k), _pose(kf.T_world_body))
        if k in fixed_set:
            graph.add(gtsam.PriorFactorPose3(X(k), _pose(kf.T_world_body), tight6))
    n_imu = 0
    if imu_params is not None:
        huber = gtsam.noiseModel.mEstimator.Huber.Create(options.imu_huber_k)
        chain = ([vmap.keyframes[prev_fixed]] if prev_fixed is not None else []) + window
        for kf in chain:
            values.insert(V(kf.id), np.asarray(kf.v_world, float))
            values.insert(B(kf.id), make_bias(kf.bias_accel, kf.bias_gyro))
        first = chain[0]
        if first.id == prev_fixed:  # outside the window: its whole state is held
            graph.add(gtsam.PriorFactorVector(V(first.id), first.v_world, tight3))
            graph.add(
                gtsam.PriorFactorConstantBias(
                    B(first.id),
                    make_bias(first.bias_accel, first.bias_gyro),
                    gtsam.noiseModel.Isotropic.Sigma(6, options.fixed_sigma),
                )
            )
        else:
            sa, sg = bias_prior_sigmas
            graph.add(
                gtsam.PriorFactorConstantBias(
                    B(first.id),
                    make_bias(first.bias_accel, first.bias_gyro),
                    gtsam.noiseModel.Diagonal.Sigmas(np.array([sa, sa, sa, sg, sg, sg])),
                )
            )
        for a, b in itertools.pairwise(chain):
            if b.previous_id != a.id or b.imu_from_previous is None:
                continue
            pim = preintegrate(imu_params, b.imu_from_previous, a.bias_accel, a.bias_gyro)
            f = gtsam.CombinedImuFactor(X(a.id), V(a.id), X(b.id), V(b.id), B(a.id), B(b.id), pim)
            noise = gtsam.noiseModel.Robust.Create(
                huber, gtsam.noiseModel.Gaussian.Covariance(pim.preintMeasCov())
            )
            graph.add(f.cloneWithNewNoiseModel(noise))
            n_imu += 1
    # Observations of the points seen at least twice by the variable keyframes.
    used, obs_arrays = _select(table, selected, variables, min_observations=2)
    used_points = [mp for mp, u in zip(table.points, used.tolist(), strict=True) if u]
    n_obs = len(obs_arrays.pose)
    if n_obs == 0:
        return BAStats(len(window), len(fixed_set), 0, 0, 0.0, 0.0, 0, 0)
    p_world = np.array([mp.p_world for mp in used_points], dtype=np.float64)
    n_iter = max_iterations or options.max_iterations
    n_free = sum(kf.id not in fixed_set for kf in window)
    if options.solver == "gtsam" or n_free > options.schur_max_keyframes:
        solved = _solve_gtsam(
            graph, values, variables, p_world, obs_arrays, camera, options, n_iter
        )
    else:  # "schur" (LocalBAConfig checks the name)
        free = [X(kf.id) for kf in window if kf.id not in fixed_set]
        if use_imu:
            free += [key(kf.id) for kf in window for key in (V, B)]
        solved = _solve_schur(
            graph, values, free, variables, p_world, obs_arrays, camera, options, n_iter
        )
    result, p_after, err0, err1 = solved
    if result is None:  # failed: the old estimate is kept
        return BAStats(len(window), len(fixed_set), len(used_points), n_obs, err0, err0, 0, 0)
    for kf in window:
        if kf.id in fixed_set:
            continue
        kf.T_world_body = result.atPose3(X(kf.id)).matrix()
        if use_imu:
            kf.v_world = np.asarray(result.atVector(V(kf.id)), float)
            bias = result.atConstantBias(B(kf.id))
            kf.bias_accel = np.asarray(bias.accelerometer(), float)
            kf.bias_gyro = np.asarray(bias.gyroscope(), float)
    for mp, p in zip(used_points, p_after, strict=True):
        mp.p_world = p.copy()
    vmap.mark_dirty([kf.id for kf in window], [mp.id for mp in used_points])
    _, cull_obs = _select(table, used, table.keyframe_ids, min_observations=1)
    n_cobs, n_cpts = _cull(vmap, used_points, cull_obs, table.keyframe_ids, camera, mapping)
    return BAStats(len(window), len(fixed_set), len(used_points), n_obs, err0, err1, n_cobs, n_cpts)


_Solved = tuple[gtsam.Values | None, np.ndarray, float, float]


def _solve_gtsam(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    variables: list[int],
    p_world: np.ndarray,
    obs: Observations,
    camera: PinholeUndistorter,
    options: LocalBAConfig,
    max_iterations: int,
) -> _Solved:
    """The reference path: one gtsam graph with a projection factor per observation, gtsam's
    LM. Returns (values or None if it failed, points (N, 3), error before, error after)."""
    graph = gtsam.NonlinearFactorGraph(graph)
    values = gtsam.Values(values)
    body_P_cam = _pose(camera.T_body_cam)
    noise_of = _NoiseCache(options.cauchy_k)
    pose_key = [X(k) for k in variables]
    for j, p in enumerate(p_world):
        values.insert(L(j), p)
    projection_factor = gtsam.GenericProjectionFactorCal3_S2
    for i, j, xy, sigma in zip(
        obs.pose.tolist(), obs.point.tolist(), obs.xy, obs.sigma.tolist(), strict=True
    ):
        graph.add(projection_factor(xy, noise_of(sigma), pose_key[i], L(j), _UNIT_K, body_P_cam))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(options.relative_error_tol)
    params.setVerbosityLM("SILENT")
    err0 = graph.error(values)
    try:
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except RuntimeError as exc:  # indeterminant system: keep the old estimate
        logger.warning("local BA failed (%s); estimate kept", exc)
        return None, p_world, err0, err0
    p_after = np.array([result.atPoint3(L(j)) for j in range(len(p_world))]).reshape(-1, 3)
    return result, p_after, err0, graph.error(result)


def _solve_schur(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    free_keys: list[int],
    variables: list[int],
    p_world: np.ndarray,
    obs: Observations,
    camera: PinholeUndistorter,
    options: LocalBAConfig,
    max_iterations: int,
) -> _Solved:
    """Schur-complement LM (:mod:`services.edge.vio.ba_solver`): reprojection in numpy, the
    IMU factors and priors of ``graph`` linearised by gtsam. Same return as the gtsam path."""
    problem = SchurLM(
        graph,
        values,
        free_keys,
        [X(k) for k in variables],
        p_world,
        obs,
        camera.T_body_cam,
        options.cauchy_k,
    )
    try:
        res = problem.optimize(max_iterations, options.relative_error_tol)
    except RuntimeError as exc:  # gtsam failed on the IMU part: keep the old estimate
        logger.warning("local BA failed (%s); estimate kept", exc)
        err0 = problem.cost(values, p_world)
        return None, p_world, err0, err0
    if not (np.isfinite(res.error_after) and np.all(np.isfinite(res.p_world))):
        logger.warning("local BA diverged (error %s); estimate kept", res.error_after)
        return None, p_world, res.error_before, res.error_before
    return res.values, res.p_world, res.error_before, res.error_after


@dataclass(frozen=True, eq=False)
class _ObservationTable:
    """Every observation of ``points`` by a keyframe of the map: ``obs.pose`` indexes
    ``keyframe_ids`` (the observers, in id order), ``obs.point`` indexes ``points``."""

    points: list[MapPoint]
    keyframe_ids: list[int]
    obs: Observations


def _observation_table(vmap: VioMap, points: list[MapPoint]) -> _ObservationTable:
    counts = [len(mp.observations) for mp in points]
    items = itertools.chain.from_iterable(mp.observations.items() for mp in points)
    flat = np.fromiter(itertools.chain.from_iterable(items), np.int64, 2 * sum(counts))
    kf_id, row = flat[0::2], flat[1::2]
    point = np.repeat(np.arange(len(points)), counts)
    ids = np.array([k for k in np.unique(kf_id).tolist() if k in vmap.keyframes], np.int64)
    if len(ids) == 0:
        empty = np.zeros(0, np.int64)
        return _ObservationTable(
            points, [], Observations(empty, empty, np.zeros((0, 2)), np.zeros(0))
        )
    at = np.minimum(np.searchsorted(ids, kf_id), len(ids) - 1)
    keep = ids[at] == kf_id
    pose, point, row = at[keep], point[keep], row[keep]
    kfs = [vmap.keyframes[k] for k in ids.tolist()]
    first_row = np.cumsum([0] + [len(kf.xy) for kf in kfs[:-1]])
    rows = first_row[pose] + row
    obs = Observations(
        pose=pose,
        point=point,
        xy=np.concatenate([kf.xy for kf in kfs])[rows],
        sigma=np.concatenate([kf.sigma for kf in kfs])[rows],
    )
    return _ObservationTable(points, ids.tolist(), obs)


def _select(
    table: _ObservationTable,
    points: np.ndarray,
    keyframe_ids: list[int],
    min_observations: int,
) -> tuple[np.ndarray, Observations]:
    """Observations of the table's points where ``points`` (N,) bool by ``keyframe_ids``;
    points with fewer than ``min_observations`` of them are dropped. Returns the kept points
    (N,) bool and their observations (``pose`` indexes ``keyframe_ids``, ``point`` the kept
    points in table order)."""
    position = {k: i for i, k in enumerate(keyframe_ids)}
    pose_of = np.array([position.get(k, -1) for k in table.keyframe_ids], dtype=np.int64)
    obs = table.obs
    pose = pose_of[obs.pose] if len(pose_of) else np.zeros(0, np.int64)
    keep = points[obs.point] & (pose >= 0)
    used = points & (np.bincount(obs.point[keep], minlength=len(points)) >= min_observations)
    keep &= used[obs.point]
    new_index = np.cumsum(used) - 1
    return used, Observations(pose[keep], new_index[obs.point[keep]], obs.xy[keep], obs.sigma[keep])


def cull_observations(
    vmap: VioMap, points: list, camera: PinholeUndistorter, mapping: MappingConfig
) -> tuple[int, int]:
    """Remove observations with chi2 above ``mapping.cull_chi2`` or behind the camera, then
    points left with fewer than ``mapping.min_observations``. Returns (observations, points)."""
    live = [mp for mp in points if mp.id in vmap.points]
    table = _observation_table(vmap, live)
    _, obs = _select(table, np.ones(len(live), dtype=bool), table.keyframe_ids, 0)
    return _cull(vmap, live, obs, table.keyframe_ids, camera, mapping)


def _cull(
    vmap: VioMap,
    points: list[MapPoint],
    obs: Observations,
    keyframe_ids: list[int],
    camera: PinholeUndistorter,
    mapping: MappingConfig,
) -> tuple[int, int]:
    """:func:`cull_observations` on a table of every observation of ``points`` (``obs.pose``
    indexes ``keyframe_ids``, ``obs.point`` indexes ``points``)."""
    n_obs = 0
    if len(obs.pose):
        T = np.array([vmap.keyframes[k].T_world_body for k in keyframe_ids])
        P = np.array([mp.p_world for mp in points], dtype=np.float64)
        chi2 = observation_chi2(T, P, obs, camera.T_body_cam)
        bad = np.flatnonzero(~(chi2 < mapping.cull_chi2))
        for i, j in zip(obs.pose[bad].tolist(), obs.point[bad].tolist(), strict=True):
            vmap.remove_observation(points[j].id, keyframe_ids[i])
        n_obs = len(bad)
    n_pts = 0
    for mp in points:
        if mp.id in vmap.points and len(mp.observations) < mapping.min_observations:
            vmap.remove_point(mp.id, ban=True)
            n_pts += 1
    return n_obs, n_pts


def reprojection_chi2(vmap: VioMap, keyframe_ids: list[int], camera: PinholeUndistorter) -> float:
    """Mean whitened squared reprojection error of every observation made by these keyframes."""
    total, n = 0.0, 0
    for k in keyframe_ids:
        kf = vmap.keyframes[k]
        items = []
        for t, r in kf.row_of.items():
            mp = vmap.point_of(t)
            if mp is not None and mp.observations.get(k) == r:
                items.append((mp.id, r))
        if not items:
            continue
        P = np.array([vmap.points[p].p_world for p, _ in items])
        rows = np.array([r for _, r in items])
        xy, _ = project(kf.T_world_body, camera.T_body_cam, P)
        total += float(np.sum(np.sum((xy - kf.xy[rows]) ** 2, 1) / kf.sigma[rows] ** 2))
        n += len(items)
    return total / max(n, 1)
