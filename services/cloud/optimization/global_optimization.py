"""Global optimisation of a map (paper Eq. 20), pose-graph stage, with gtsam.

Eq. 20 minimises a prior on the first keyframe, IMU terms between consecutive keyframes of the
same robot, and robust reprojection terms. The pose-graph stage used here keeps the structure
and replaces the heavy terms by relative-pose constraints (as ORB-SLAM's essential graph and
COVINS' pose graph do):

- a prior on the map's first keyframe (``e_prio``),
- a ``BetweenFactor<Pose3>`` between consecutive keyframes of each agent whose measurement is
  the current relative pose (what the edge's visual-inertial odometry estimated) and whose
  information grows with the covisibility weight (shared map points) — the stand-in of
  ``e_imu``,
- the same for strongly covisible pairs (weight ≥ ``covisibility_min_weight``),
- loop and merge constraints (verified relative poses) under a robust kernel (Cauchy by
  default); loop edges whose whitened error is still above ``loop_outlier_whitened`` after
  the robust solve are dropped and the graph solved once more, so a bad one cannot tear the
  map.

Map points then move rigidly with their reference keyframe. Everything here is a pure
function on plain arrays (:class:`PoseGraphProblem` in, :class:`PoseGraphResult` out), so a
service runs it in an executor off its event loop and applies the result afterwards.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from common.errors import RecslamError
from common.geometry import inverse_T
from services.cloud.atlas.atlas import Atlas, split_key
from services.cloud.config import GlobalOptimizationConfig

log = logging.getLogger(__name__)


class GlobalOptimizationError(RecslamError):
    """Empty or inconsistent pose-graph problem."""


@dataclass(frozen=True, eq=False)
class PoseGraphProblem:
    """Plain pose-graph data.

    keys (N,) keyframe keys; T_world_body (N, 4, 4) initial poses; edge_i, edge_j (E,) indices
    into keys; T_i_j (E, 4, 4) measured relative poses (body j in body i); sigmas (E, 6)
    standard deviations (rad, rad, rad, m, m, m); robust (E,) use the robust kernel;
    fixed: index of the keyframe held by the prior.
    """

    keys: np.ndarray
    T_world_body: np.ndarray
    edge_i: np.ndarray
    edge_j: np.ndarray
    T_i_j: np.ndarray
    sigmas: np.ndarray
    robust: np.ndarray
    fixed: int
    up_body: np.ndarray | None = None
    """(N, 3) the map's up direction (z) in each keyframe's body frame when the graph was
    built: the roll and pitch :func:`add_attitude_factors` holds (None: not held)."""
    held: np.ndarray | None = None
    """(H,) indices of keyframes held where they are by a prior as tight as ``fixed``'s
    (a prior map's, see ``services.cloud.store.mission``; None: only ``fixed``)."""


def up_in_body(T_world_body: np.ndarray) -> np.ndarray:
    """(N, 3) unit vectors: the world's z axis in each body frame of ``T_world_body`` (N, 4,
    4), i.e. the third row of each rotation."""
    return np.array(T_world_body, np.float64).reshape(-1, 4, 4)[:, 2, :3].copy()


def add_attitude_factors(
    graph: gtsam.NonlinearFactorGraph,
    keys: list[int],
    up_body: np.ndarray | None,
    sigma_rad: float,
) -> int:
    """Hold each keyframe's roll and pitch: an attitude factor per pose ``keys[i]`` that the
    world's z axis stays ``up_body[i]`` in its body frame (2-DoF, ``sigma_rad``; yaw and
    position stay free). Returns the factors added (none when off or without ``up_body``)."""
    if up_body is None or sigma_rad <= 0:
        return 0
    noise = gtsam.noiseModel.Isotropic.Sigma(2, sigma_rad)
    z = gtsam.Unit3(np.array([0.0, 0.0, 1.0]))
    for key, up in zip(keys, np.asarray(up_body, np.float64), strict=True):
        graph.add(gtsam.AttitudeFactorPose3(key, z, noise, gtsam.Unit3(up)))
    return len(keys)


@dataclass(frozen=True, eq=False)
class PoseGraphResult:
    """Optimised poses ``T_world_body (N, 4, 4)`` of ``keys (N,)``; graph errors before and
    after; Levenberg–Marquardt iterations; ``rejected_edges`` indices of loop edges dropped
    as outliers."""

    keys: np.ndarray
    T_world_body: np.ndarray
    initial_error: float
    final_error: float
    iterations: int
    rejected_edges: np.ndarray


def _sigmas(rot: float, trans: float, scale: float) -> np.ndarray:
    return np.array([rot, rot, rot, trans, trans, trans]) / np.sqrt(scale)


def build_pose_graph(
    atlas: Atlas, map_id: int, config: GlobalOptimizationConfig
) -> PoseGraphProblem:
    """Pose graph of one map from the atlas' current estimates, covisibility and loops."""
    keys = atlas.keyframe_keys(map_id=map_id)
    if not keys:
        raise GlobalOptimizationError(f"map {map_id} has no keyframes")
    index = {k: i for i, k in enumerate(keys)}
    T = np.array([atlas.T_map_body(k) for k in keys])
    ei: list[int] = []
    ej: list[int] = []
    meas: list[np.ndarray] = []
    sig: list[np.ndarray] = []
    rob: list[bool] = []
    seen: set[tuple[int, int]] = set()

    def rel_edge(a: int, b: int, weight: float) -> None:
        i, j = index[a], index[b]
        if (min(i, j), max(i, j)) in seen:
            return
        seen.add((min(i, j), max(i, j)))
        scale = float(np.clip(weight / config.reference_weight, 0.25, 4.0))
        ei.append(i)
        ej.append(j)
        meas.append(inverse_T(T[i]) @ T[j])
        sig.append(_sigmas(config.odometry_sigma_rot_rad, config.odometry_sigma_trans_m, scale))
        rob.append(False)

    for agent in atlas.agents_in_map(map_id):
        ak = atlas.keyframe_keys(map_id=map_id, agent_id=agent)
        for a, b in itertools.pairwise(ak):
            w = dict(atlas.covisible(a)).get(b, 0)
            rel_edge(a, b, w)
    if config.covisibility_min_weight > 0:
        for a in keys:
            for b, w in atlas.covisible(a, config.covisibility_min_weight):
                if b in index:
                    rel_edge(a, b, w)
    for e in atlas.loops():
        if e.key_a in index and e.key_b in index:
            ei.append(index[e.key_a])
            ej.append(index[e.key_b])
            meas.append(np.array(e.T_a_b))
            sig.append(_sigmas(config.loop_sigma_rot_rad, config.loop_sigma_trans_m, 1.0))
            rob.append(True)
    own = atlas.keyframe_keys(map_id=map_id, agent_id=map_id)
    fixed = index[own[0]] if own else 0
    E = len(ei)
    return PoseGraphProblem(
        keys=np.array(keys, np.int64),
        T_world_body=T,
        edge_i=np.array(ei, np.int64),
        edge_j=np.array(ej, np.int64),
        T_i_j=np.array(meas).reshape(E, 4, 4),
        sigmas=np.array(sig).reshape(E, 6),
        robust=np.array(rob, bool),
        fixed=fixed,
        up_body=up_in_body(T),
    )


def held_indices(fixed: int, held: np.ndarray | None) -> list[int]:
    """The keyframe indices a solve holds with a tight prior: ``fixed`` and ``held``."""
    extra = [] if held is None else np.asarray(held, np.int64).tolist()
    return sorted({int(fixed), *extra})


def gauge_prior_noise(
    T_world_body: np.ndarray, sigma: float, tilt_sigma_rad: float
) -> gtsam.noiseModel.Base:
    """Noise of the prior that fixes a map's gauge at its first keyframe (pose ``T_world_body``
    (4, 4)): ``sigma`` on all six degrees of freedom, or, with ``tilt_sigma_rad`` > 0, that on
    position and yaw only and ``tilt_sigma_rad`` on roll and pitch (the map's tilt against
    gravity, which a solve with IMU factors observes: the 4-DoF gauge of visual-inertial
    estimation). The tangent of a ``Pose3`` is in its body frame, so the world-frame rotation
    covariance ``diag(tilt², tilt², sigma²)`` is rotated into it."""
    if tilt_sigma_rad <= 0:
        return gtsam.noiseModel.Isotropic.Sigma(6, sigma)
    R = np.asarray(T_world_body[:3, :3], np.float64)
    cov = np.zeros((6, 6))
    cov[:3, :3] = R.T @ np.diag([tilt_sigma_rad**2, tilt_sigma_rad**2, sigma**2]) @ R
    cov[:3, :3] += np.eye(3) * sigma**2  # keeps the block positive definite
    cov[3:, 3:] = np.eye(3) * sigma**2
    return gtsam.noiseModel.Gaussian.Covariance(cov)


def pose3(T: np.ndarray) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3(np.asarray(T[:3, :3])), np.asarray(T[:3, 3]))


def optimize_pose_graph(
    problem: PoseGraphProblem, config: GlobalOptimizationConfig
) -> PoseGraphResult:
    """Solve the pose graph with Levenberg–Marquardt (pure; no atlas access)."""
    n = problem.keys.shape[0]
    if n == 0:
        raise GlobalOptimizationError("empty pose graph")
    if not 0 <= problem.fixed < n:
        raise GlobalOptimizationError(f"fixed index {problem.fixed} outside 0..{n - 1}")
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i in range(n):
        values.insert(i, pose3(problem.T_world_body[i]))
    prior = gtsam.noiseModel.Isotropic.Sigma(6, config.prior_sigma)
    for i in held_indices(problem.fixed, problem.held):
        graph.add(gtsam.PriorFactorPose3(i, pose3(problem.T_world_body[i]), prior))
    add_attitude_factors(graph, list(range(n)), problem.up_body, config.attitude_sigma_rad)
    kernels: dict[str, Callable[[float], gtsam.noiseModel.mEstimator.Base]] = {
        "cauchy": gtsam.noiseModel.mEstimator.Cauchy.Create,
        "huber": gtsam.noiseModel.mEstimator.Huber.Create,
    }
    kernel = kernels.get(config.loop_robust_kernel)
    if kernel is None and config.loop_robust_kernel != "none":
        raise GlobalOptimizationError(f"unknown robust kernel {config.loop_robust_kernel!r}")
    base_graph = gtsam.NonlinearFactorGraph(graph)
    use = np.ones(problem.edge_i.shape[0], bool)
    rejected: list[int] = []
    for _ in range(2):
        graph = gtsam.NonlinearFactorGraph(base_graph)
        for e in np.flatnonzero(use).tolist():
            noise: gtsam.noiseModel.Base = gtsam.noiseModel.Diagonal.Sigmas(problem.sigmas[e])
            if problem.robust[e] and kernel is not None:
                noise = gtsam.noiseModel.Robust.Create(kernel(config.loop_kernel_scale), noise)
            graph.add(
                gtsam.BetweenFactorPose3(
                    int(problem.edge_i[e]), int(problem.edge_j[e]), pose3(problem.T_i_j[e]), noise
                )
            )
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(config.max_iterations)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        initial_error = float(graph.error(values))
        result = optimizer.optimize()
        # Loop edges still far off after the robust solve are outliers: drop them, solve again.
        bad = [
            e
            for e in np.flatnonzero(use & problem.robust).tolist()
            if _whitened(problem, e, result) > config.loop_outlier_whitened
        ]
        if not bad:
            break
        use[bad] = False
        rejected.extend(bad)
        log.info("pose graph: dropped %d outlier loop constraints", len(bad))
    out = np.array([result.atPose3(i).matrix() for i in range(n)])
    final_error = float(graph.error(result))
    log.debug("pose graph %d nodes: error %.3g -> %.3g", n, initial_error, final_error)
    return PoseGraphResult(
        problem.keys.copy(),
        out,
        initial_error,
        final_error,
        optimizer.iterations(),
        np.array(sorted(rejected), np.int64),
    )


def _whitened(problem: PoseGraphProblem, e: int, values: gtsam.Values) -> float:
    """Norm of the whitened error of edge ``e`` at ``values``."""
    pi = values.atPose3(int(problem.edge_i[e]))
    pj = values.atPose3(int(problem.edge_j[e]))
    err = gtsam.Pose3.Logmap(pose3(problem.T_i_j[e]).between(pi.between(pj)))
    return float(np.linalg.norm(np.asarray(err) / problem.sigmas[e]))


def apply_pose_graph(atlas: Atlas, result: PoseGraphResult) -> int:
    """Write optimised poses into the atlas (map points follow their reference keyframe).

    Keyframes pruned meanwhile are skipped; keyframes that arrived while the optimisation ran
    get the correction of their agent's latest optimised keyframe (as ORB-SLAM propagates a
    loop correction). Returns how many poses were written."""
    poses: dict[int, np.ndarray] = {}
    corr_of_agent: dict[int, tuple[int, np.ndarray]] = {}
    for i, k in enumerate(result.keys.tolist()):
        if not atlas.has_keyframe(k):
            continue
        poses[k] = result.T_world_body[i]
        agent = split_key(k)[0]
        if agent not in corr_of_agent or k > corr_of_agent[agent][0]:
            corr_of_agent[agent] = (k, result.T_world_body[i] @ inverse_T(atlas.T_map_body(k)))
    done = set(poses)
    map_ids = {atlas.map_id_of_keyframe(k) for k in done}
    for m in map_ids:
        for k in atlas.keyframe_keys(map_id=m):
            a = split_key(k)[0]
            if k not in done and a in corr_of_agent:
                poses[k] = corr_of_agent[a][1] @ atlas.T_map_body(k)
    atlas.set_keyframe_poses(poses)
    return len(poses)


def warm_up() -> None:
    """No-op: submitted once so that a worker process imports gtsam before it is needed."""
