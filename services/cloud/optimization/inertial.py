"""Inertial terms of the cloud's global bundle adjustment (paper Eq. 20, ``e_imu``).

The edges forward, with every new keyframe, the IMU samples since the robot's previous
uplinked keyframe (``KeyframeUpdate(Coded).imu``). :class:`ImuStore` keeps them per atlas
agent in one :class:`common.imu.ImuBuffer` each (IMU frame = the body frame of the edge's VIO,
which re-expresses its camera extrinsic in the IMU frame); merges do not touch them, since a
merge only re-expresses the map frame. Merged maps keep z along gravity (their alignment is
yaw + translation, ``AlignmentMode.YAW_TRANSLATION``), so gravity is ``-g`` along the map's z
in every map.

:func:`build_imu_terms` (on the service's worker, with the atlas) picks, per agent of a map,
consecutive keyframes in time order (keyframes MBP or the edge removed simply lengthen an
interval), slices the IMU between their timestamps and keeps the pieces as plain arrays
(:class:`ImuTerms`, picklable for the optimiser process). :func:`add_imu_factors` (in the
solver) preintegrates each interval around the keyframe's forwarded bias with
:mod:`common.preintegration` and adds a ``CombinedImuFactor`` (pose, velocity and bias of both
keyframes, bias random walk included), a prior on the first bias of each agent's chain, and
initial velocities computed from the current poses and the preintegrated IMU (the stored
velocities are not rotated by pose-graph corrections, the poses are).

The IMU is not persisted: after a cloud restart, intervals without IMU fall back to the full
BA's relative-pose terms.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from common.calibration import ImuCalibration
from common.imu import ImuBuffer, ImuDataError, ImuSegment, with_measured_noise
from common.preintegration import make_bias, make_preintegration_params, preintegrate
from services.cloud.atlas.atlas import Atlas
from services.cloud.config import FullBAConfig

log = logging.getLogger(__name__)

ImuOf = Callable[[int], ImuCalibration]
"""Atlas agent id -> its robot's IMU calibration."""


class ImuStore:
    """Every IMU sample the edges forwarded, per atlas agent (timestamps ns on the IMU's
    clock, IMU frame), and each agent's camera-IMU time offset."""

    def __init__(self) -> None:
        self._buffers: dict[int, ImuBuffer] = {}
        self._offsets: dict[int, int] = {}

    def set_time_offset(self, agent_id: int, offset_ns: int) -> None:
        """``agent_id``'s camera-IMU time offset (``t_imu = t_cam + offset``, ns; the edge's
        estimate): its IMU between two keyframes is read at their times plus it."""
        self._offsets[agent_id] = int(offset_ns)

    def time_offset_ns(self, agent_id: int) -> int:
        return self._offsets.get(agent_id, 0)

    def add(
        self, agent_id: int, timestamps_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray
    ) -> None:
        """Append ``agent_id``'s samples (K,), (K, 3), (K, 3); samples not newer than the
        newest held are ignored (a re-sent or overlapping batch); a malformed batch is logged
        and dropped."""
        if len(timestamps_ns) == 0:
            return
        buf = self._buffers.setdefault(agent_id, ImuBuffer())
        try:
            buf.append(timestamps_ns, gyro, accel)
        except ImuDataError as exc:
            log.warning("agent %d: IMU batch dropped: %s", agent_id, exc)

    def buffer(self, agent_id: int) -> ImuBuffer | None:
        return self._buffers.get(agent_id)

    def n_samples(self, agent_id: int | None = None) -> int:
        if agent_id is not None:
            b = self._buffers.get(agent_id)
            return 0 if b is None else len(b)
        return sum(len(b) for b in self._buffers.values())


@dataclass(frozen=True, eq=False)
class ImuTerms:
    """Plain IMU terms of a map (indices into the problem's keyframes).

    pair_i, pair_j (K,): consecutive keyframes of one agent; offsets (K + 1,): pair k's
    samples (an :class:`common.imu.ImuSegment`, ends interpolated at the keyframes'
    timestamps) are rows ``offsets[k]:offsets[k + 1]`` of timestamps_ns (S,), gyro (S, 3)
    rad/s and accel (S, 3) m/s²; noise (K, 4) the
    robot's gyro noise density, gyro random walk, accel noise density, accel random walk;
    bias_gyro, bias_accel (N, 3) the forwarded biases of every keyframe; first (A,) the first
    keyframe of each agent's chain (where the bias prior sits); agent_offsets: (agent, its
    camera-IMU time offset in ns) of the agents read, the offset the samples were read at."""

    pair_i: np.ndarray
    pair_j: np.ndarray
    offsets: np.ndarray
    timestamps_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    noise: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray
    first: np.ndarray
    agent_offsets: tuple[tuple[int, int], ...] = ()

    @property
    def n_pairs(self) -> int:
        return int(self.pair_i.shape[0])

    def segment(self, k: int) -> ImuSegment:
        s = slice(int(self.offsets[k]), int(self.offsets[k + 1]))
        return ImuSegment(self.timestamps_ns[s], self.gyro[s], self.accel[s])

    def interval_s(self, k: int) -> float:
        return self.segment(k).duration_s


def _ns(timestamp_s: float) -> int:
    return round(timestamp_s * 1e9)


def build_imu_terms(
    atlas: Atlas,
    map_id: int,
    keys: list[int],
    store: ImuStore,
    imu_of: ImuOf,
    config: FullBAConfig,
) -> ImuTerms:
    """The IMU terms between consecutive keyframes (time order) of every agent of ``map_id``;
    ``keys`` the problem's keyframes (indices refer to it). An interval is left out when it
    is longer than ``config.imu_max_interval_s``, the agent's IMU does not cover it, or two
    samples inside are more than ``config.imu_max_gap_s`` apart."""
    index = {k: i for i, k in enumerate(keys)}
    pi: list[int] = []
    pj: list[int] = []
    offsets = [0]
    stamps: list[np.ndarray] = []
    gyros: list[np.ndarray] = []
    accels: list[np.ndarray] = []
    noise: list[tuple[float, float, float, float]] = []
    first: list[int] = []
    agent_offsets: list[tuple[int, int]] = []
    skipped = 0
    for agent in atlas.agents_in_map(map_id):
        buf = store.buffer(agent)
        ak = [k for k in atlas.keyframe_keys(map_id=map_id, agent_id=agent) if k in index]
        if buf is None or len(ak) < 2:
            continue
        ak.sort(key=lambda k: atlas.keyframe(k).timestamp)
        calib = imu_of(agent)
        if config.imu_noise_from_data:
            measured = buf.noise_density(config.imu_noise_window_samples)
            calib = with_measured_noise(calib, *measured)
        n_before = len(pi)
        td = store.time_offset_ns(agent)
        agent_offsets.append((agent, td))
        for a, b in itertools.pairwise(ak):
            t0, t1 = _ns(atlas.keyframe(a).timestamp), _ns(atlas.keyframe(b).timestamp)
            seg = None
            if 0 < (t1 - t0) * 1e-9 <= config.imu_max_interval_s:
                seg = buf.segment(t0 + td, t1 + td)
            if seg is None:
                skipped += 1
                continue
            if float(np.diff(seg.timestamps_ns).max()) * 1e-9 > config.imu_max_gap_s:
                skipped += 1
                continue
            if len(pi) == n_before or pj[-1] != index[a]:
                first.append(index[a])
            pi.append(index[a])
            pj.append(index[b])
            stamps.append(seg.timestamps_ns)
            gyros.append(seg.gyro)
            accels.append(seg.accel)
            offsets.append(offsets[-1] + seg.timestamps_ns.size)
            noise.append(
                (
                    calib.gyro_noise_density,
                    calib.gyro_random_walk,
                    calib.accel_noise_density,
                    calib.accel_random_walk,
                )
            )
    if skipped:
        log.debug("map %d: %d keyframe intervals without usable IMU", map_id, skipped)
    views = [atlas.keyframe(k) for k in keys]
    return ImuTerms(
        pair_i=np.array(pi, np.int64),
        pair_j=np.array(pj, np.int64),
        offsets=np.array(offsets, np.int64),
        timestamps_ns=np.concatenate(stamps) if stamps else np.zeros(0, np.int64),
        gyro=np.concatenate(gyros) if gyros else np.zeros((0, 3)),
        accel=np.concatenate(accels) if accels else np.zeros((0, 3)),
        noise=np.array(noise, np.float64).reshape(-1, 4),
        bias_gyro=np.array([v.bias_gyro for v in views], np.float64).reshape(-1, 3),
        bias_accel=np.array([v.bias_accel for v in views], np.float64).reshape(-1, 3),
        first=np.array(first, np.int64),
        agent_offsets=tuple(agent_offsets),
    )


def preintegrated(
    terms: ImuTerms, k: int, config: FullBAConfig
) -> gtsam.PreintegratedCombinedMeasurements:
    """Pair ``k``'s IMU preintegrated around keyframe ``pair_i[k]``'s forwarded bias (noise
    densities times ``config.imu_noise_scale``)."""
    gn, gw, an, aw = (config.imu_noise_scale * terms.noise[k]).tolist()
    params = make_preintegration_params(
        ImuCalibration(gn, gw, an, aw), config.gravity_mps2, config.imu_integration_sigma
    )
    i = int(terms.pair_i[k])
    return preintegrate(params, terms.segment(k), terms.bias_accel[i], terms.bias_gyro[i])


def initial_velocities(
    terms: ImuTerms,
    pims: list[gtsam.PreintegratedCombinedMeasurements],
    T_world_body: np.ndarray,
    gravity_mps2: float,
) -> dict[int, np.ndarray]:
    """Velocity (3,) m/s, map frame, of every keyframe in a pair: the one that makes pair
    k's preintegrated position delta fit the current poses (``p_j = p_i + v_i Δt + ½ g Δt²
    + R_i Δp``); a chain's last keyframe gets ``v_i + g Δt + R_i Δv`` of its last pair."""
    g = np.array([0.0, 0.0, -gravity_mps2])
    out: dict[int, np.ndarray] = {}
    for k, pim in enumerate(pims):
        i, j = int(terms.pair_i[k]), int(terms.pair_j[k])
        dt = pim.deltaTij()
        Ri, pi_, pj_ = T_world_body[i, :3, :3], T_world_body[i, :3, 3], T_world_body[j, :3, 3]
        vi = (pj_ - pi_ - 0.5 * g * dt**2 - Ri @ np.asarray(pim.deltaPij())) / dt
        out[i] = vi
        if j not in out:
            out[j] = vi + g * dt + Ri @ np.asarray(pim.deltaVij())
    return out


def add_imu_factors(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    terms: ImuTerms,
    T_world_body: np.ndarray,
    config: FullBAConfig,
) -> int:
    """Add velocity and bias states, a ``CombinedImuFactor`` per pair and a bias prior per
    chain to ``graph`` / ``values`` (poses are ``X(i)``, velocities ``V(i)``, biases
    ``B(i)``); returns the factors added."""
    X, V, B = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B
    pims = [preintegrated(terms, k, config) for k in range(terms.n_pairs)]
    velocities = initial_velocities(terms, pims, T_world_body, config.gravity_mps2)
    for i, v in velocities.items():
        values.insert(V(i), np.asarray(v, np.float64))
        values.insert(B(i), make_bias(terms.bias_accel[i], terms.bias_gyro[i]))
    for k, pim in enumerate(pims):
        i, j = int(terms.pair_i[k]), int(terms.pair_j[k])
        graph.add(gtsam.CombinedImuFactor(X(i), V(i), X(j), V(j), B(i), B(j), pim))
    prior = gtsam.noiseModel.Diagonal.Sigmas(
        np.array([config.bias_prior_accel] * 3 + [config.bias_prior_gyro] * 3)
    )
    for i in terms.first.tolist():
        bias = make_bias(terms.bias_accel[i], terms.bias_gyro[i])
        graph.add(gtsam.PriorFactorConstantBias(B(i), bias, prior))
    return len(pims) + int(terms.first.shape[0])


def imu_variance_factor(
    graph: gtsam.NonlinearFactorGraph, first: int, count: int, values: gtsam.Values, terms: ImuTerms
) -> float:
    """The IMU's variance factor at a solution (variance component estimation, Förstner 1979):
    the whitened squared residuals of the ``count`` IMU factors from index ``first`` of
    ``graph`` (those :func:`add_imu_factors` added) over their redundancy, ``15 K + 6 C - 9 M``
    (K pairs, C bias priors, M keyframes with velocity and bias; the poses counted as fixed
    by the images). Near 1 when the assumed noise fits; 0.1 when the IMU agrees with the map
    ten times better in variance than assumed. NaN when the redundancy is not positive."""
    n_states = np.unique(np.concatenate([terms.pair_i, terms.pair_j])).size
    redundancy = 15 * terms.n_pairs + 6 * int(terms.first.shape[0]) - 9 * n_states
    if redundancy <= 0:
        return float("nan")
    chi2 = 2.0 * sum(graph.at(first + k).error(values) for k in range(count))
    return float(chi2 / redundancy)


def inertial_states(
    values: gtsam.Values, terms: ImuTerms
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The optimised ``(index (M,), velocity (M, 3), bias_gyro (M, 3), bias_accel (M, 3))``
    of every keyframe with inertial states."""
    V, B = gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B
    idx = np.unique(np.concatenate([terms.pair_i, terms.pair_j])).astype(np.int64)
    vel = np.array([values.atVector(V(int(i))) for i in idx]).reshape(-1, 3)
    biases = [values.atConstantBias(B(int(i))) for i in idx]
    bg = np.array([b.gyroscope() for b in biases]).reshape(-1, 3)
    ba = np.array([b.accelerometer() for b in biases]).reshape(-1, 3)
    return idx, vel, bg, ba
