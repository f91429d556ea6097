"""Incremental visual-inertial global BA (paper Eq. 20, full stage) with gtsam's iSAM2.

The batch solve (:func:`services.cloud.optimization.full_ba.solve_full_ba`) rebuilds and
relinearises the whole map every time, so its cost grows with the map (2.4 s per Levenberg–Marquardt
iteration at 5k keyframes on this machine). Here the optimiser process keeps, per (cloud session,
map), an ``ISAM2`` whose factor graph mirrors the last problem it was given, and each new
:class:`~services.cloud.optimization.full_ba.FullBAProblem` of that map is applied as a difference:

- every term of the problem has a tag — ``("obs", keyframe, point)``, ``("edge", a, b,
  robust)``, ``("imu", a, b)``, ``("bias", keyframe)`` (a chain's first bias),
  ``("att", keyframe)``, ``("prior", keyframe)``, ``("point", point)`` (a weak prior that keeps
  a point seen by one keyframe solvable), ``("hold", point)``; tags of the new problem that the
  graph lacks are added, tags it has that the problem lacks are removed (a keyframe the edge
  culled, an observation the edge re-associated, a stand-in relative-pose term that an IMU
  term replaced), and iSAM2 drops the variables left without factors;
- new keyframes start at their problem pose moved by the correction ``E · P⁻¹`` (estimate
  times inverse problem pose) of the agent's nearest keyframe already in the graph, new points
  by the correction of a keyframe that observes them (the atlas may have moved since the last
  solve: a pose graph after a loop); new velocities come from the preintegrated IMU and the
  poses as in :func:`services.cloud.optimization.inertial.initial_velocities`;
- a new loop edge whose whitened error at the current estimate exceeds
  ``loop_outlier_whitened`` is left out (and not tested again), as in the batch solve;
- then ``update`` and up to ``incremental_max_updates - 1`` more (relinearisation steps)
  while variables still get relinearised, within ``max_seconds``; with a
  ``relinearize_budget``, each update relinearises at most that many variables (those whose
  pending step is largest) and leaves the others for a later one.

The graph is built again from a batch solve (and seeded with its result) when there is none
for the map yet, when the map's agents (a merge), its held keyframe, its prior-map
keyframes or a robot's camera-IMU time offset changed (every IMU term of that robot is then
read anew: a batch solve relinearises them all, where the graph would have kept the terms
read at the old offset), and after iSAM2 fails (an indeterminant system); the optimiser
process dying loses every graph, which costs one batch solve per map. A graph is the same
function of the problem as the batch graph, except for decisions taken once at insertion
(outlier loops, the stand-in terms' measurements) and the linearisation points.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass, field

import gtsam
import numpy as np

from common.geometry import inverse_T, transform_points
from common.preintegration import make_bias
from services.cloud.atlas.map_types import split_key
from services.cloud.config import FullBAConfig, GlobalOptimizationConfig
from services.cloud.optimization.full_ba import (
    FullBAError,
    FullBAProblem,
    FullBAResult,
    gauge_tilt_sigma,
    kernel,
    pose3,
    rms_px,
    solve_full_ba,
)
from services.cloud.optimization.global_optimization import gauge_prior_noise, held_indices
from services.cloud.optimization.inertial import preintegrated

log = logging.getLogger(__name__)

X, V, B, L = (
    gtsam.symbol_shorthand.X,
    gtsam.symbol_shorthand.V,
    gtsam.symbol_shorthand.B,
    gtsam.symbol_shorthand.L,
)
_UNIT_K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
_MAX_SOLVERS = 8  # graphs kept per process (least recently used dropped first)
_RMS_OBSERVATIONS = 200_000  # a result's reprojection RMS samples about this many

Tag = tuple[Hashable, ...]


@dataclass
class _Solver:
    """One map's iSAM2 and how its factors and variables map to the problem's keys."""

    isam: gtsam.ISAM2
    fingerprint: tuple[Hashable, ...]
    slot: dict[int, int] = field(default_factory=dict)  # keyframe key -> X/V/B index
    point_slot: dict[int, int] = field(default_factory=dict)  # point key -> L index
    factors: dict[Tag, int | None] = field(default_factory=dict)  # None: rejected loop
    point_factors: dict[int, list[int]] = field(default_factory=dict)  # point -> its priors
    obs_sig: dict[int, int] = field(default_factory=dict)  # keyframe -> _obs_groups signature
    obs_factors: dict[int, dict[int, int]] = field(default_factory=dict)  # kf -> point -> index
    inertial: set[int] = field(default_factory=set)  # keyframes with V / B
    poses: dict[int, np.ndarray] | None = None  # keyframe key -> its pose in the last result
    imu_noise_scale: float | None = None  # the batch solve's re-weighted IMU noise scale
    next_slot: int = 0
    next_point: int = 0
    updates: int = 0


_SOLVERS: OrderedDict[tuple[str, int], _Solver] = OrderedDict()


def forget(session: str, map_id: int | None = None) -> None:
    """Drop the graphs of ``session`` (one map, or all)."""
    for key in [k for k in _SOLVERS if k[0] == session and map_id in (None, k[1])]:
        del _SOLVERS[key]


def _fingerprint(problem: FullBAProblem) -> tuple[Hashable, ...]:
    held = held_indices(problem.fixed, problem.held)
    keys = problem.keys
    held_pts = () if problem.held_points is None else tuple(problem.held_points.tolist())
    agents = frozenset(split_key(int(k))[0] for k in keys.tolist())
    return (
        int(keys[problem.fixed]),
        tuple(int(keys[i]) for i in held),
        tuple(int(problem.point_keys[j]) for j in held_pts),
        agents,
        problem.imu.agent_offsets if problem.imu is not None else (),
    )


def _corrections(solver: _Solver, problem: FullBAProblem) -> tuple[np.ndarray, np.ndarray]:
    """Per problem keyframe, the start pose (N, 4, 4) in the graph's frame, and the
    correction (N, 4, 4) that takes its problem pose there."""
    keys = problem.keys.tolist()
    n = len(keys)
    C = np.tile(np.eye(4), (n, 1, 1))
    known = np.array([k in solver.slot for k in keys], bool)
    have = np.flatnonzero(known)
    if solver.poses is not None:  # the last result's: the graph has not moved since
        E = np.array([solver.poses[keys[i]] for i in have.tolist()]).reshape(-1, 4, 4)
    else:
        slots = np.array([solver.slot[keys[i]] for i in have.tolist()], np.int64)
        E = _poses(solver.isam.calculateEstimate(), slots)
    C[have] = np.einsum("nij,njk->nik", E, inverse_T(problem.T_world_body[have]))
    agent = np.array([split_key(k)[0] for k in keys], np.int64)
    local = np.array([split_key(k)[1] for k in keys], np.int64)
    for i in np.flatnonzero(~known).tolist():
        same = np.flatnonzero(known & (agent == agent[i]))
        if same.size:
            C[i] = C[same[np.argmin(np.abs(local[same] - local[i]))]]
    return np.einsum("nij,njk->nik", C, problem.T_world_body), C


def _velocity(
    pim: gtsam.PreintegratedCombinedMeasurements,
    T_i: np.ndarray,
    T_j: np.ndarray,
    gravity_mps2: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Velocities (3,) at both ends of a pair that fit its preintegration to the poses
    (:func:`services.cloud.optimization.inertial.initial_velocities`)."""
    g = np.array([0.0, 0.0, -gravity_mps2])
    dt = pim.deltaTij()
    R_i = T_i[:3, :3]
    v_i = (T_j[:3, 3] - T_i[:3, 3] - 0.5 * g * dt**2 - R_i @ np.asarray(pim.deltaPij())) / dt
    return v_i, v_i + g * dt + R_i @ np.asarray(pim.deltaVij())


def _edge_tags(problem: FullBAProblem) -> list[Tag]:
    """``("edge", a, b, robust, n)`` of each edge: its keyframes, kind, and how many edges of
    the same keyframes and kind come before it (a pair can close two loops)."""
    keys = problem.keys.tolist()
    seen: dict[Tag, int] = {}
    out: list[Tag] = []
    for i, j, r in zip(
        problem.edge_i.tolist(), problem.edge_j.tolist(), problem.robust.tolist(), strict=True
    ):
        base = ("edge", keys[i], keys[j], bool(r))
        seen[base] = seen.get(base, -1) + 1
        out.append((*base, seen[base]))
    return out


_MIX = np.uint64(0x9E3779B97F4A7C15)


def _obs_groups(problem: FullBAProblem) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """The observation rows grouped by problem keyframe, ``(rows, start (N + 1,), signature)``:
    keyframe i's rows are ``rows[start[i]:start[i + 1]]`` (the builder groups them already),
    its signature a wrapping sum of its point keys, each mixed (a Fibonacci multiply and an
    xor-shift): it changes when the set of points the keyframe observes does, so unchanged
    keyframes are skipped without a look at their rows."""
    kf = problem.obs_kf
    grouped = kf.size < 2 or bool(np.all(kf[1:] >= kf[:-1]))
    rows = np.arange(kf.size) if grouped else np.argsort(kf, kind="stable")
    start = np.zeros(problem.keys.shape[0] + 1, np.int64)
    np.cumsum(np.bincount(kf, minlength=problem.keys.shape[0]), out=start[1:])
    h = problem.point_keys[problem.obs_point[rows]].astype(np.uint64) * _MIX
    h ^= h >> np.uint64(29)
    total = np.zeros(kf.size + 1, np.uint64)
    np.cumsum(h * _MIX, out=total[1:])
    return rows, start, (total[start[1:]] - total[start[:-1]]).tolist()


def _diff(
    solver: _Solver,
    problem: FullBAProblem,
    config: FullBAConfig,
    graph_config: GlobalOptimizationConfig,
    T0: np.ndarray,
    C: np.ndarray,
    rejected: set[int],
    seed: FullBAResult | None,
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[Tag], list[int], set[int]]:
    """New factors (with their tags), new values and the factor indices to remove that take
    the solver's graph to ``problem``; the new keyframes' slots are assigned. ``T0`` (N, 4, 4)
    start poses, ``C`` their corrections; ``rejected``: loop edges (problem indices) to leave
    out when ``seed`` (a batch result whose values start the graph) is given, else found by
    the outlier test. Returns the keyframes with inertial states."""
    keys = problem.keys.tolist()
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    tags: list[Tag] = []
    want: set[Tag] = set()

    def add(tag: Tag, factor: gtsam.NonlinearFactor) -> None:
        graph.add(factor)
        tags.append(tag)

    present = set(keys)
    remove: list[int] = []
    for k in [k for k in solver.slot if k not in present]:
        del solver.slot[k]
        solver.obs_sig.pop(k, None)
        remove.extend(solver.obs_factors.pop(k, {}).values())
    for i, k in enumerate(keys):
        if k not in solver.slot:
            solver.slot[k] = solver.next_slot
            solver.next_slot += 1
            values.insert(X(solver.next_slot - 1), pose3(T0[i]))
    sx = [X(solver.slot[k]) for k in keys]
    # Points: a weak prior each (``point_prior_sigma_m``), held ones a tight one; a point
    # that left the problem takes its priors along (iSAM2 then drops it).
    pkeys = problem.point_keys.tolist()
    for p in solver.point_slot.keys() - set(pkeys):
        del solver.point_slot[p]
        remove.extend(solver.point_factors.pop(p, ()))
    ref = np.zeros(len(pkeys), np.int64)
    ref[problem.obs_point[::-1]] = problem.obs_kf[::-1]  # a keyframe observing each point
    seed_p = None if seed is None else seed.p_world
    weak = gtsam.noiseModel.Isotropic.Sigma(3, config.point_prior_sigma_m)
    tight = gtsam.noiseModel.Isotropic.Sigma(3, graph_config.prior_sigma)
    held_pts = set() if problem.held_points is None else set(problem.held_points.tolist())
    for j, p in enumerate(pkeys):
        if p in solver.point_slot:
            continue
        solver.point_slot[p] = solver.next_point
        solver.next_point += 1
        if seed_p is not None:
            xyz = np.asarray(seed_p[j], np.float64)
        else:
            xyz = transform_points(C[ref[j]], problem.p_world[j : j + 1])[0]
        values.insert(L(solver.point_slot[p]), xyz)
        add(("point", p), gtsam.PriorFactorPoint3(L(solver.point_slot[p]), xyz, weak))
        if j in held_pts:  # (held points change only with a rebuild: the fingerprint)
            add(("hold", p), gtsam.PriorFactorPoint3(L(solver.point_slot[p]), xyz, tight))
    # Keyframe priors and attitude terms.
    prior = gtsam.noiseModel.Isotropic.Sigma(6, graph_config.prior_sigma)
    tilt = gauge_tilt_sigma(problem, config)
    for i in held_indices(problem.fixed, problem.held):
        free_tilt = i == problem.fixed and tilt > 0
        tag: Tag = ("prior4" if free_tilt else "prior", keys[i])
        want.add(tag)
        if tag not in solver.factors:
            held_noise: gtsam.noiseModel.Base = prior
            if free_tilt:
                held_noise = gauge_prior_noise(T0[i], graph_config.prior_sigma, tilt)
            add(tag, gtsam.PriorFactorPose3(sx[i], pose3(T0[i]), held_noise))
    if problem.up_body is not None and config.attitude_sigma_rad > 0:
        att_noise = gtsam.noiseModel.Isotropic.Sigma(2, config.attitude_sigma_rad)
        z = gtsam.Unit3(np.array([0.0, 0.0, 1.0]))
        for i, k in enumerate(keys):
            tag = ("att", k)
            want.add(tag)
            if tag not in solver.factors:
                up = gtsam.Unit3(np.asarray(problem.up_body[i], np.float64))
                add(tag, gtsam.AttitudeFactorPose3(sx[i], z, att_noise, up))
    # Relative-pose terms and loops.
    loop_kernel = kernel(graph_config.loop_robust_kernel, graph_config.loop_kernel_scale)
    for e, tag in enumerate(_edge_tags(problem)):
        i, j = int(problem.edge_i[e]), int(problem.edge_j[e])
        robust = bool(problem.robust[e])
        want.add(tag)
        if tag in solver.factors:
            continue
        meas = pose3(problem.T_i_j[e])
        noise: gtsam.noiseModel.Base = gtsam.noiseModel.Diagonal.Sigmas(problem.sigmas[e])
        if robust:
            if seed is not None:
                out = e in rejected
            else:
                rel = pose3(T0[i]).between(pose3(T0[j]))
                err = np.asarray(gtsam.Pose3.Logmap(meas.between(rel))) / problem.sigmas[e]
                out = bool(np.linalg.norm(err) > graph_config.loop_outlier_whitened)
            if out:
                solver.factors[tag] = None
                continue
            if loop_kernel is not None:
                noise = gtsam.noiseModel.Robust.Create(loop_kernel, noise)
        add(tag, gtsam.BetweenFactorPose3(sx[i], sx[j], meas, noise))
    # IMU terms: velocity and bias states of the keyframes in a pair.
    inertial: set[int] = set()
    terms = problem.imu
    if terms is not None and terms.n_pairs:
        seed_vb: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        if seed is not None:
            for m, i in enumerate(seed.inertial_index.tolist()):
                seed_vb[i] = (seed.velocity[m], seed.bias_accel[m], seed.bias_gyro[m])
        for m in range(terms.n_pairs):
            inertial.update((keys[int(terms.pair_i[m])], keys[int(terms.pair_j[m])]))
        fresh: dict[int, np.ndarray] = {}
        for m in range(terms.n_pairs):
            i, j = int(terms.pair_i[m]), int(terms.pair_j[m])
            tag = ("imu", keys[i], keys[j])
            want.add(tag)
            if tag in solver.factors:
                continue
            pim = preintegrated(terms, m, config)
            v_i, v_j = _velocity(pim, T0[i], T0[j], config.gravity_mps2)
            fresh.setdefault(i, v_i)
            fresh.setdefault(j, v_j)
            a, b = solver.slot[keys[i]], solver.slot[keys[j]]
            add(tag, gtsam.CombinedImuFactor(X(a), V(a), X(b), V(b), B(a), B(b), pim))
        for i, k in enumerate(keys):
            if k not in inertial or (
                k in solver.inertial and solver.isam.valueExists(V(solver.slot[k]))
            ):
                continue
            if i in seed_vb:
                v, ba, bg = seed_vb[i]
            else:
                v, ba, bg = fresh.get(i, np.zeros(3)), terms.bias_accel[i], terms.bias_gyro[i]
            values.insert(V(solver.slot[k]), np.asarray(v, np.float64))
            values.insert(B(solver.slot[k]), make_bias(ba, bg))
        bias_prior = gtsam.noiseModel.Diagonal.Sigmas(
            np.array([config.bias_prior_accel] * 3 + [config.bias_prior_gyro] * 3)
        )
        for i in terms.first.tolist():
            tag = ("bias", keys[i])
            want.add(tag)
            if tag not in solver.factors:
                bias = make_bias(terms.bias_accel[i], terms.bias_gyro[i])
                add(tag, gtsam.PriorFactorConstantBias(B(solver.slot[keys[i]]), bias, bias_prior))
    # Reprojection terms, keyframe by keyframe (unchanged keyframes are skipped by their
    # signature); they are kept per keyframe (``obs_factors``), not as tags, so an unchanged
    # keyframe costs nothing.
    obs_kernel = kernel(config.robust_kernel, config.kernel_scale)
    noise_of: dict[float, gtsam.noiseModel.Base] = {}
    all_rows, start, sig = _obs_groups(problem)
    for i, k in enumerate(keys):
        if solver.obs_sig.get(k) == sig[i]:
            continue
        solver.obs_sig[k] = sig[i]
        rows = all_rows[start[i] : start[i + 1]]
        pts = problem.point_keys[problem.obs_point[rows]]
        order = np.argsort(pts)
        pts, rows = pts[order], rows[order]
        have = solver.obs_factors.setdefault(k, {})
        kept = set(pts.tolist())
        for p in [p for p in have if p not in kept]:
            remove.append(have.pop(p))
        body_P_cam = pose3(problem.T_body_cam[i])
        for p, r in zip(pts.tolist(), rows.tolist(), strict=True):
            if p in have:
                continue
            s = float(problem.obs_sigma[r])
            obs_noise: gtsam.noiseModel.Base | None = noise_of.get(s)
            if obs_noise is None:
                obs_noise = gtsam.noiseModel.Isotropic.Sigma(2, s)
                if obs_kernel is not None:
                    obs_noise = gtsam.noiseModel.Robust.Create(obs_kernel, obs_noise)
                noise_of[s] = obs_noise
            xy = np.asarray(problem.obs_xy[r], np.float64)
            add(
                ("obs", k, p),
                gtsam.GenericProjectionFactorCal3_S2(
                    xy, obs_noise, sx[i], L(solver.point_slot[p]), _UNIT_K, body_P_cam
                ),
            )
    for tag in [t for t in solver.factors if t not in want]:
        idx = solver.factors.pop(tag)
        if idx is not None:
            remove.append(idx)
    return graph, values, tags, remove, inertial


_DIMS = {ord("x"): 6, ord("v"): 3, ord("b"): 6, ord("l"): 3}


def _held_back(isam: gtsam.ISAM2, config: FullBAConfig) -> gtsam.KeyList | None:
    """The variables kept at their linearisation point this update so that at most
    ``relinearize_budget`` are relinearised (those whose pending step is largest go
    first, the others in a later update); None when within budget or unbounded."""
    if config.relinearize_budget <= 0:
        return None
    keys = np.asarray(isam.getLinearizationPoint().keys(), np.uint64)
    if keys.size <= config.relinearize_budget:
        return None
    dims = np.array([_DIMS[int(c)] for c in (keys >> np.uint64(56)).tolist()], np.int64)
    step = np.abs(isam.getDelta().vector())
    if step.size != int(dims.sum()):  # a variable without a delta yet: no budget this time
        return None
    largest = np.maximum.reduceat(step, np.concatenate([[0], np.cumsum(dims)[:-1]]))
    over = np.flatnonzero(largest >= config.relinearize_threshold)
    if over.size <= config.relinearize_budget:
        return None
    keep = over[np.argsort(-largest[over], kind="stable")[config.relinearize_budget :]]
    out = gtsam.KeyList()
    for k in keys[keep].tolist():
        out.push_back(int(k))
    log.debug("iSAM2: %d of %d variables to relinearise held back", keep.size, over.size)
    return out


def _update(
    solver: _Solver,
    problem: FullBAProblem,
    config: FullBAConfig,
    graph_config: GlobalOptimizationConfig,
    t0: float,
    seed: FullBAResult | None = None,
) -> int:
    """Apply ``problem`` to the solver's graph and relinearise; returns the updates run."""
    if seed is not None:
        T0, C = seed.T_world_body, np.tile(np.eye(4), (problem.keys.shape[0], 1, 1))
        rejected = set(seed.rejected_edges.tolist())
    else:
        T0, C = _corrections(solver, problem)
        rejected = set()
    graph, values, tags, remove, inertial = _diff(
        solver, problem, config, graph_config, T0, C, rejected, seed
    )
    held_back = _held_back(solver.isam, config) if seed is None else None
    result = solver.isam.update(graph, values, remove, noRelinKeys=held_back)
    for tag, idx in zip(tags, result.getNewFactorsIndices(), strict=True):
        if tag[0] == "obs":
            solver.obs_factors[int(tag[1])][int(tag[2])] = int(idx)  # type: ignore[call-overload]
        elif tag[0] in ("point", "hold"):
            solver.point_factors.setdefault(int(tag[1]), []).append(int(idx))  # type: ignore[call-overload]
        else:
            solver.factors[tag] = int(idx)
    solver.inertial = inertial
    updates = 1
    if seed is None:
        while (
            updates < config.incremental_max_updates
            and time.perf_counter() - t0 < config.max_seconds
        ):
            if solver.isam.update().getVariablesRelinearized() == 0:
                break
            updates += 1
    solver.updates += updates
    log.debug(
        "iSAM2: %d new factors, %d removed, %d new values, %d updates; first: %d variables "
        "relinearised, %d re-eliminated",
        len(tags),
        len(remove),
        values.size(),
        updates,
        result.getVariablesRelinearized(),
        result.getVariablesReeliminated(),
    )
    return updates


def _rows(keys: np.ndarray, char: str, slots: np.ndarray) -> np.ndarray:
    """Rows, in the order of ``keys`` (an estimate's: gtsam keeps them sorted) among those of
    ``char``, of the variables ``char``-``slots`` (gtsam's extract functions return them in
    that order)."""
    mine = keys[(keys >> np.uint64(56)) == np.uint64(ord(char))] & np.uint64(2**56 - 1)
    rows = np.searchsorted(mine, slots.astype(np.uint64))
    if slots.size and (rows.max() >= mine.size or np.any(mine[rows] != slots)):
        raise RuntimeError(f"iSAM2 estimate lacks some {char} variables")
    return rows


def _poses(est: gtsam.Values, slots: np.ndarray, keys: np.ndarray | None = None) -> np.ndarray:
    """The X poses of ``slots`` (N,) as (N, 4, 4) in one copy out of ``est`` (``keys``: its
    keys, when known)."""
    keys = np.asarray(est.keys(), np.uint64) if keys is None else keys
    flat = gtsam.utilities.extractPose3(est)[_rows(keys, "x", slots)]  # R row-major, then t
    T = np.tile(np.eye(4), (slots.size, 1, 1))
    T[:, :3, :3] = flat[:, :9].reshape(-1, 3, 3)
    T[:, :3, 3] = flat[:, 9:]
    return T


def _vectors(est: gtsam.Values, keys: np.ndarray, char: str, slots: np.ndarray) -> np.ndarray:
    """The 3-vectors (points, velocities) ``char``-``slots`` (N,) of ``est`` (keys ``keys``)
    as (N, 3)."""
    return np.asarray(gtsam.utilities.extractVectors(est, char), np.float64).reshape(-1, 3)[
        _rows(keys, char, slots)
    ]


def _result(
    solver: _Solver, problem: FullBAProblem, updates: int, t0: float, mode: str
) -> FullBAResult:
    est = solver.isam.calculateEstimate()
    keys, pkeys = problem.keys.tolist(), problem.point_keys.tolist()
    slots = np.array([solver.slot[k] for k in keys], np.int64)
    est_keys = np.asarray(est.keys(), np.uint64)
    T = _poses(est, slots, est_keys)
    p = _vectors(est, est_keys, "l", np.array([solver.point_slot[q] for q in pkeys], np.int64))
    idx = np.array([i for i, k in enumerate(keys) if k in solver.inertial], np.int64)
    vel = _vectors(est, est_keys, "v", slots[idx])
    bias = [est.atConstantBias(B(int(s))) for s in slots[idx].tolist()]
    solver.poses = dict(zip(keys, T.copy(), strict=True))
    rejected = [
        e for e, tag in enumerate(_edge_tags(problem)) if solver.factors.get(tag, 0) is None
    ]
    stride = max(1, problem.n_observations // _RMS_OBSERVATIONS)  # (for the log line)
    rms0 = rms_px(problem, problem.T_world_body, problem.p_world, stride)
    rms1 = rms_px(problem, T, p, stride)
    return FullBAResult(
        keys=problem.keys.copy(),
        T_world_body=T,
        point_keys=problem.point_keys.copy(),
        p_world=p,
        initial_error=float("nan"),
        final_error=float("nan"),
        initial_rms_px=rms0,
        final_rms_px=rms1,
        iterations=updates,
        rejected_edges=np.array(rejected, np.int64),
        seconds=time.perf_counter() - t0,
        inertial_index=idx,
        velocity=vel,
        bias_gyro=np.array([b.gyroscope() for b in bias]).reshape(-1, 3),
        bias_accel=np.array([b.accelerometer() for b in bias]).reshape(-1, 3),
        mode=mode,
        imu_noise_scale=solver.imu_noise_scale or float("nan"),
    )


def _params(config: FullBAConfig) -> gtsam.ISAM2Params:
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(config.relinearize_threshold)
    params.relinearizeSkip = config.relinearize_skip
    params.enablePartialRelinearizationCheck = config.partial_relinearization_check
    return params


def solve_full_ba_incremental(
    problem: FullBAProblem,
    config: FullBAConfig,
    graph_config: GlobalOptimizationConfig,
    session: str,
    map_id: int,
) -> FullBAResult:
    """Solve ``problem`` (map ``map_id`` of cloud ``session``) on the map's iSAM2 graph
    (module docstring); the first time, and whenever the graph is rebuilt, a batch solve;
    a map under ``incremental_min_keyframes`` keyframes only by a batch solve."""
    t0 = time.perf_counter()
    if problem.keys.shape[0] == 0:
        raise FullBAError("empty full-BA problem")
    name = (session, map_id)
    if problem.keys.shape[0] < config.incremental_min_keyframes:  # a batch solve pays
        _SOLVERS.pop(name, None)  # (a graph left behind would be stale when it grows again)
        return solve_full_ba(problem, config, graph_config)
    solver = _SOLVERS.get(name)
    fp = _fingerprint(problem)
    if solver is not None and solver.fingerprint == fp:
        _SOLVERS.move_to_end(name)
        if solver.imu_noise_scale is not None:  # the IMU weighted as the batch solve found
            config = dataclasses.replace(config, imu_noise_scale=solver.imu_noise_scale)
        try:
            updates = _update(solver, problem, config, graph_config, t0)
            out = _result(solver, problem, updates, t0, "isam2")
        except RuntimeError as exc:  # indeterminant system: start the graph again
            log.warning("map %d: iSAM2 update failed (%s); batch solve instead", map_id, exc)
        else:
            log.info(
                "full BA (iSAM2): %d keyframes, %d points, %d observations in %.2f s (%d updates): "
                "reprojection RMS %.2f -> %.2f px",
                problem.keys.shape[0],
                problem.point_keys.shape[0],
                problem.n_observations,
                out.seconds,
                updates,
                out.initial_rms_px,
                out.final_rms_px,
            )
            return out
    _SOLVERS.pop(name, None)
    batch = solve_full_ba(problem, config, graph_config)
    solver = _Solver(gtsam.ISAM2(_params(config)), fp)
    if np.isfinite(batch.imu_noise_scale):
        solver.imu_noise_scale = batch.imu_noise_scale
        config = dataclasses.replace(config, imu_noise_scale=batch.imu_noise_scale)
    seeded = dataclasses.replace(problem, T_world_body=batch.T_world_body, p_world=batch.p_world)
    try:
        _update(solver, seeded, config, graph_config, t0, seed=batch)
    except RuntimeError as exc:
        log.warning("map %d: iSAM2 could not take the batch result (%s)", map_id, exc)
        return dataclasses.replace(batch, seconds=time.perf_counter() - t0)
    _SOLVERS[name] = solver
    while len(_SOLVERS) > _MAX_SOLVERS:
        _SOLVERS.popitem(last=False)
    seconds = time.perf_counter() - t0
    log.info(
        "full BA: map %d graph (re)built for iSAM2, %.2f s with the batch solve", map_id, seconds
    )
    return dataclasses.replace(batch, seconds=seconds, mode="isam2-reset")
