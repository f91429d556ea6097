"""Camera-IMU time offset from the tracked frames' rotations and the gyro.

A camera not triggered by its IMU stamps its frames on another clock: at one instant the IMU
clock reads ``t_imu = t_cam + offset`` (OpenVINS' ``calib_camimu_dt``, Kalibr's
``timeshift_cam_imu`` with the sign flipped). An offset of 15 ms on a MAV turning at 2 rad/s
puts every preintegration 30 mrad out of step with the images.

The rotation between two tracked frames is known from vision alone (up to noise, and without
scale); the gyro integrates the same rotation over the same interval read on the IMU clock.
:func:`estimate_time_offset` finds the offset at which they agree best: for each candidate
offset it integrates the bias-corrected gyro once into an orientation track, reads the
relative rotation of each frame pair (gaps of 1, 2 and 4 frames) between ``t_a + offset`` and
``t_b + offset``, and solves the residual gyro bias linearly (the rotation error of a pair
grows as ``bias * dt``); a Huber cost over a 1 ms grid, then a parabola through the finest
samples, gives the offset; its standard deviation comes from a delete-a-block jackknife over
stretches of time (neighbouring residuals are correlated, so the curvature alone overstates the
certainty). The offset
is only observable while the angular velocity changes, so a flight hovering or turning at a
constant rate gives a large sigma, and the caller keeps its previous value.

Pure numpy/scipy, no state: :class:`~services.edge.vio.manager.VioManager` calls it on its
recent frames.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class TimeOffsetConfig:
    """``max_offset_ms``: the search range (±); ``grid_step_ms``: its coarse grid;
    ``baselines``: the frame gaps compared; ``max_pair_s``: the longest pair interval [s];
    ``huber_rad``: the residual [rad] beyond which a pair counts linearly (a tracking glitch
    must not pull the offset); ``min_pairs``: fewer pairs is no estimate;
    ``max_sigma_ms``: a wider estimate, or one over frames spanning less than ``min_span_s``
    (too few stretches for the jackknife to see the errors that last), is reported but not
    confident. Online
    (:class:`TimeOffsetTracker`): the newest ``window_s`` of tracked frames, every ``every_s``
    of frame time until a confident estimate (each unconfident one waits ``backoff`` times
    longer for the next, up to ``max_every_s``: a flight that hardly turns must not pay an
    estimate every few seconds for its whole life), then every ``confident_every_s`` within
    ``track_range_ms`` of it; a change below ``min_change_ms`` is not applied; a forced
    estimate (before a VI initialisation) runs at most once per ``every_s``."""

    max_offset_ms: float = 50.0
    grid_step_ms: float = 1.0
    baselines: tuple[int, ...] = (1, 2, 4, 8, 16)
    max_pair_s: float = 1.0
    huber_rad: float = 0.01
    min_pairs: int = 40
    max_sigma_ms: float = 1.0
    window_s: float = 60.0
    every_s: float = 3.0
    backoff: float = 1.5
    max_every_s: float = 30.0
    confident_every_s: float = 10.0
    track_range_ms: float = 10.0
    min_change_ms: float = 0.3
    jackknife_blocks: int = 8
    min_span_s: float = 5.0


@dataclass(frozen=True)
class TimeOffsetEstimate:
    """``offset_ns``: ``t_imu = t_cam + offset``; ``sigma_ms`` its standard deviation from
    the cost's curvature; ``pairs`` frame pairs used; ``rms_rad`` their residual rotation;
    ``bias_gyro`` (3,) rad/s the gyro bias that goes with it (the given one plus the residual
    solved here); ``confident``: sigma within ``max_sigma_ms``."""

    offset_ns: int
    sigma_ms: float
    pairs: int
    rms_rad: float
    bias_gyro: np.ndarray
    confident: bool

    def __str__(self) -> str:
        return (
            f"{self.offset_ns * 1e-6:+.2f} ms (sigma {self.sigma_ms:.2f} ms, {self.pairs} pairs, "
            f"rms {1e3 * self.rms_rad:.2f} mrad)"
        )


def _quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton products ``p q`` of (N, 4) scalar-last quaternions."""
    px, py, pz, pw = p.T
    qx, qy, qz, qw = q.T
    return np.stack(
        [
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
            pw * qw - px * qx - py * qy - pz * qz,
        ],
        axis=1,
    )


class _GyroTrack:
    """The bias-corrected gyro integrated into one orientation track: ``at(tau)`` the
    rotations (N,) at times ``tau`` [s] on the IMU clock (piecewise-constant rate between
    samples, the mean of the two ends)."""

    def __init__(self, s: np.ndarray, gyro: np.ndarray) -> None:
        self.s = s
        self.w = 0.5 * (gyro[1:] + gyro[:-1])  # (K-1, 3) rad/s on [s_j, s_j+1]
        steps = Rotation.from_rotvec(self.w * np.diff(s)[:, None]).as_quat()  # (x, y, z, w)
        quats = np.concatenate([[[0.0, 0.0, 0.0, 1.0]], steps])
        # Inclusive prefix product q_0 q_1 ... q_j by doubling (log2 K vectorised passes).
        shift = 1
        while shift < len(quats):
            quats[shift:] = _quat_mul(quats[:-shift], quats[shift:])
            shift *= 2
        self.R = Rotation.from_quat(quats)

    def at(self, tau: np.ndarray) -> Rotation:
        j = np.clip(np.searchsorted(self.s, tau, side="right") - 1, 0, len(self.w) - 1)
        return self.R[j] * Rotation.from_rotvec(self.w[j] * (tau - self.s[j])[:, None])


def _pairs(t: np.ndarray, baselines: tuple[int, ...], max_pair_s: float) -> np.ndarray:
    out = []
    for m in baselines:
        a = np.arange(len(t) - m)
        b = a + m
        ok = (t[b] - t[a]) <= max_pair_s
        out.append(np.stack([a[ok], b[ok]], axis=1))
    return np.concatenate(out) if out else np.zeros((0, 2), np.int64)


def _jackknife_sigma(
    residuals: Callable[[float], tuple[np.ndarray, np.ndarray]],
    offset: float,
    t_pair: np.ndarray,
    e: np.ndarray,
    o: TimeOffsetConfig,
) -> float:
    """Standard deviation [s] of the offset by the delete-a-block jackknife over
    ``o.jackknife_blocks`` contiguous stretches of time: the residuals of neighbouring frames
    are not independent (tracking errors and vibration last longer than a frame), so the cost's
    curvature alone overstates the certainty. One Gauss-Newton step from ``offset`` per
    left-out block, with the residuals' derivative by central differences (``t_pair`` (P,) s
    the start of each pair, ``e`` (P,) its residual norm at ``offset``)."""
    h = 0.5e-3
    r0 = residuals(offset)[0]
    J = (residuals(offset + h)[0] - residuals(offset - h)[0]) / (2 * h)  # (P, 3) rad/s
    w = np.minimum(1.0, o.huber_rad / np.maximum(e, 1e-12))
    n = o.jackknife_blocks
    block = np.minimum((t_pair / max(float(t_pair.max()), 1e-9) * n).astype(int), n - 1)
    jr = np.bincount(block, w * (J * r0).sum(1), n)
    jj = np.bincount(block, w * (J * J).sum(1), n)
    if (jj.sum() - jj <= 0).any():
        return float("inf")
    loo = offset - (jr.sum() - jr) / (jj.sum() - jj)
    return float(np.sqrt((n - 1) / n * np.sum((loo - loo.mean()) ** 2)))


def estimate_time_offset(
    t_cam_ns: np.ndarray,
    R_world_body: np.ndarray,
    imu_t_ns: np.ndarray,
    gyro: np.ndarray,
    bias_gyro: np.ndarray,
    options: TimeOffsetConfig | None = None,
    around_ns: int = 0,
    range_ms: float | None = None,
) -> TimeOffsetEstimate | str:
    """The camera-IMU time offset from frames and gyro samples, or why there is none.

    ``t_cam_ns`` (N,) int64 camera times of tracked frames (ascending) and ``R_world_body``
    (N, 3, 3) their rotations (body = IMU frame; one map, any scale); ``imu_t_ns`` (K,) int64
    IMU-clock sample times and ``gyro`` (K, 3) rad/s; ``bias_gyro`` (3,) rad/s the current
    gyro bias estimate (zeros before initialisation). The search covers ``around_ns ±
    range_ms`` (default ``options.max_offset_ms``).
    """
    o = options or TimeOffsetConfig()
    t_cam_ns = np.asarray(t_cam_ns, np.int64)
    imu_t_ns = np.asarray(imu_t_ns, np.int64)
    if len(imu_t_ns) < 3 or len(t_cam_ns) < 3:
        return f"too few samples ({len(t_cam_ns)} frames, {len(imu_t_ns)} IMU samples)"
    ref = int(imu_t_ns[0])
    s = (imu_t_ns - ref) * 1e-9
    t = (t_cam_ns - ref) * 1e-9
    centre = around_ns * 1e-9
    span = (o.max_offset_ms if range_ms is None else range_ms) * 1e-3
    inside = (t + centre - span >= s[0]) & (t + centre + span <= s[-1])
    t, Rv = t[inside], Rotation.from_matrix(np.asarray(R_world_body)[inside])
    pairs = _pairs(t, o.baselines, o.max_pair_s)
    if len(pairs) < o.min_pairs:
        return f"{len(pairs)} frame pairs inside the IMU's span (< {o.min_pairs})"
    gyro = np.asarray(gyro, np.float64)
    bias = np.asarray(bias_gyro, np.float64).copy()
    track = _GyroTrack(s, gyro - bias)
    a, b = pairs[:, 0], pairs[:, 1]
    dR_vis_inv = (Rv[a].inv() * Rv[b]).inv()
    dt = (t[b] - t[a])[:, None]

    def residuals(offset_s: float) -> tuple[np.ndarray, np.ndarray]:
        R = track.at(t + offset_s)
        r = (dR_vis_inv * (R[a].inv() * R[b])).as_rotvec()
        # r ≈ r0 - δb dt: the residual bias, by (robust) least squares.
        w = np.ones(len(r))
        for _ in range(3):
            db = (w[:, None] * r * dt).sum(0) / max(float((w[:, None] * dt**2).sum()), 1e-12)
            e = np.linalg.norm(r - db * dt, axis=1)
            w = np.minimum(1.0, o.huber_rad / np.maximum(e, 1e-12))
        return r - db * dt, db

    def cost(offset_s: float) -> float:
        e = np.linalg.norm(residuals(offset_s)[0], axis=1)
        h = o.huber_rad
        return float(np.where(e <= h, 0.5 * e**2, h * (e - 0.5 * h)).sum())

    step = o.grid_step_ms * 1e-3
    grid = centre + np.arange(-span, span + 0.5 * step, step)
    best = float(grid[int(np.argmin([cost(x) for x in grid]))])
    # The bias model (r ≈ r0 - δb dt) is first order: over a long pair that turns far, a large
    # residual bias (the VIO's is 0 before its initialisation; a real MAV's ~0.08 rad/s) no
    # longer adds up along one axis. Integrate again with the bias found and search near.
    bias += residuals(best)[1]
    track = _GyroTrack(s, gyro - bias)
    near = best + step * np.arange(-3, 4)
    best = float(near[int(np.argmin([cost(x) for x in near]))])
    fine = best + np.linspace(-step, step, 9)
    fine_costs = np.array([cost(x) for x in fine])
    a2, a1, _ = np.polyfit(fine - best, fine_costs, 2)
    offset = best + (-a1 / (2 * a2) if a2 > 0 else 0.0)
    offset = float(np.clip(offset, best - step, best + step))
    r, db = residuals(offset)
    e = np.linalg.norm(r, axis=1)
    inl = e <= 3 * o.huber_rad
    sigma = _jackknife_sigma(residuals, offset, t[a] - t[0], e, o)
    est = TimeOffsetEstimate(
        offset_ns=round(offset * 1e9),
        sigma_ms=float(sigma * 1e3),
        pairs=len(pairs),
        rms_rad=float(np.sqrt(np.mean(e[inl] ** 2))) if inl.any() else float("nan"),
        bias_gyro=bias + db,
        confident=bool(
            sigma * 1e3 <= o.max_sigma_ms
            and abs(offset - centre) < span - step
            and t[-1] - t[0] >= o.min_span_s
        ),
    )
    logger.debug("time offset: %s", est)
    return est


class TimeOffsetTracker:
    """The online estimate of one robot's VIO: tracked frames' rotations in, the offset out.

    :meth:`add_frame` keeps the frames of the current map (a new map starts a new history);
    :meth:`update` runs :func:`estimate_time_offset` when due (or forced) on the newest
    ``window_s`` and returns the new offset when a confident estimate moves it. ``offset_ns``
    starts at the given value (the calibration's) and is only changed by ``update``.
    """

    def __init__(self, options: TimeOffsetConfig, offset_ns: int = 0, enabled: bool = True):
        self.options = options
        self.offset_ns = int(offset_ns)
        self.enabled = enabled
        self.last: TimeOffsetEstimate | None = None
        self.confident = False
        self.updates = 0
        self.runs = 0  # estimates made
        self._map_id: int | None = None
        self._t: list[int] = []
        self._R: list[np.ndarray] = []
        self._next_ns: int | None = None
        self._last_ns: int | None = None
        self._every_s = options.every_s

    def add_frame(self, t_cam_ns: int, R_world_body: np.ndarray, map_id: int) -> None:
        """A frame tracked in map ``map_id`` at camera time ``t_cam_ns``, rotation (3, 3)."""
        if not self.enabled:
            return
        if map_id != self._map_id:
            self._map_id, self._t, self._R = map_id, [], []
        self._t.append(int(t_cam_ns))
        self._R.append(np.array(R_world_body[:3, :3], dtype=np.float64))
        cut = self._t[-1] - int(self.options.window_s * 1e9)
        while self._t[0] < cut:
            self._t.pop(0)
            self._R.pop(0)

    def update(
        self,
        imu_t_ns: np.ndarray,
        gyro: np.ndarray,
        bias_gyro: np.ndarray,
        force: bool = False,
        now_only: bool = False,
    ) -> int | None:
        """Estimate when due (or ``force``: at most once per ``every_s``; ``now_only``: now,
        unless the newest frame was estimated already); the new ``offset_ns`` if it changed,
        else None."""
        if not self.enabled or len(self._t) < 3:
            return None
        now = self._t[-1]
        o = self.options
        if self._next_ns is not None and now < self._next_ns:
            assert self._last_ns is not None
            if now_only:
                if now == self._last_ns:
                    return None
            elif not force or now - self._last_ns < o.every_s * 1e9:
                return None
        every = o.confident_every_s if self.confident else self._every_s
        self._next_ns, self._last_ns = now + int(every * 1e9), now
        self.runs += 1
        est = estimate_time_offset(
            np.array(self._t),
            np.stack(self._R),
            imu_t_ns,
            gyro,
            bias_gyro,
            o,
            around_ns=self.offset_ns if self.confident else 0,
            range_ms=o.track_range_ms if self.confident else None,
        )
        if isinstance(est, str):
            logger.debug("time offset not estimated: %s", est)
            return None
        self.last = est
        if not est.confident:
            self._every_s = min(self._every_s * o.backoff, o.max_every_s)
            return None
        self.confident = True
        if abs(est.offset_ns - self.offset_ns) < o.min_change_ms * 1e6:
            return None
        logger.info("camera-IMU time offset %+.2f ms -> %s", self.offset_ns * 1e-6, est)
        self.offset_ns = est.offset_ns
        self.updates += 1
        return self.offset_ns

    def adopt_last(self, k_sigmas: float, min_move_ms: float) -> int | None:
        """Take the last estimate although it is not confident, when its sigma is within
        ``max_sigma_ms`` (it lacks only the span) and the offset in use lies more than
        ``k_sigmas`` of its sigmas and ``min_move_ms`` from it: the data rejects the
        calibration's value (15 ms off, estimated at 16.1 ± 0.1 ms over 3 s of frames). Over so
        short a span the sigma understates the error (a few ms on real flights), hence the
        floor. For the moment the IMU is first used (a VI initialisation) when no confident
        estimate came in time. The new ``offset_ns``, else None."""
        est = self.last
        if not self.enabled or self.confident or est is None or k_sigmas <= 0:
            return None
        if not est.sigma_ms <= self.options.max_sigma_ms:
            return None  # also a non-finite sigma
        if abs(est.offset_ns - self.offset_ns) * 1e-6 <= max(k_sigmas * est.sigma_ms, min_move_ms):
            return None
        logger.info(
            "camera-IMU time offset %+.2f ms -> %s (not confident)", self.offset_ns * 1e-6, est
        )
        self.offset_ns = est.offset_ns
        self.updates += 1
        return self.offset_ns
