"""Smooth 6-DoF MAV trajectories with analytic derivatives (the synthetic robots' ground truth).

Each robot flies loops around the room's centre: its body (IMU) position is an ellipse of
slowly modulated radius, with a wandering height and small fast wiggles, and its camera looks
roughly outwards (yaw = loop angle plus a wandering offset, small pitch down, small roll). Every
term is a sinusoid of a warped time ``tau(t)``, so position, velocity, acceleration, attitude
and body rates are all closed-form. ``tau`` starts at rest: ``tau'(t) = 1 - exp(-(t/T)^2)``
with ``T = ramp_s``, so every robot hovers motionless at ``t = 0`` (zero velocity, zero
acceleration) and smoothly speeds up during the first seconds.

Frames: world ``z`` up; the look frame ``L`` is x forward, y left, z up with
``R_world_L = Rz(yaw) Ry(pitch) Rx(roll)`` (pitch > 0 looks down); the camera (x right, y down,
z forward) is rigidly attached to ``L`` and the IMU to the camera by EuRoC's cam0 ``T_BS``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.special import erf

from common.data.synth.scene import Scene
from common.errors import RecslamError


class TrajectoryError(RecslamError):
    """No trajectory satisfying the constraints was found."""


# EuRoC cam0 T_BS (body = IMU frame): maps camera points to the IMU frame.
T_IMU_CAM = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
T_IMU_CAM.setflags(write=False)

# Camera axes expressed in the look frame L: cam x = -L y, cam y = -L z, cam z = L x.
R_L_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class TrajectoryConfig:
    """Limits and style of the generated flights.

    ``ramp_s``: time constant of the start from rest [s]; ``min_clearance_m``: minimum distance
    of the body and the camera from any surface [m]; ``max_speed`` [m/s] and ``max_rate``
    [rad/s]: flights exceeding them are redrawn; ``loop_period_s``: range of the time per loop
    around the room [s] (robot ``k`` of ``n`` gets a period interpolated from slow to fast, so
    some robots are gentle and some aggressive); ``attempts``: redraws before giving up.
    """

    ramp_s: float = 1.5
    min_clearance_m: float = 0.5
    max_speed: float = 1.3
    max_rate: float = 1.3
    loop_period_s: tuple[float, float] = (26.0, 15.0)
    attempts: int = 200


@dataclass(frozen=True)
class Wave:
    """``f(tau) = c + b * tau + sum_i amp_i * sin(freq_i * tau + phase_i)`` (freq in rad/s)."""

    c: float
    b: float
    amp: tuple[float, ...] = ()
    freq: tuple[float, ...] = ()
    phase: tuple[float, ...] = ()

    def __call__(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(f, df/dtau, d2f/dtau2), each shaped like ``tau``."""
        tau = np.asarray(tau, dtype=np.float64)
        f = self.c + self.b * tau
        f1 = np.full_like(tau, self.b)
        f2 = np.zeros_like(tau)
        for a, w, p in zip(self.amp, self.freq, self.phase, strict=True):
            arg = w * tau + p
            s, c = np.sin(arg), np.cos(arg)
            f = f + a * s
            f1 = f1 + a * w * c
            f2 = f2 - a * w * w * s
        return f, f1, f2


@dataclass(frozen=True, eq=False)
class TrajectoryState:
    """Body (IMU) state at times ``t`` (K,) [s]: ``p_world_body``, ``v_world_body``,
    ``a_world_body`` (K, 3) [m, m/s, m/s^2]; ``R_world_body`` (K, 3, 3); ``omega_body`` (K, 3)
    angular rate in the IMU frame [rad/s]."""

    t: np.ndarray
    p_world_body: np.ndarray
    v_world_body: np.ndarray
    a_world_body: np.ndarray
    R_world_body: np.ndarray
    omega_body: np.ndarray

    def T_world_cam(self, T_imu_cam: np.ndarray = T_IMU_CAM) -> np.ndarray:
        """(K, 4, 4) camera-to-world poses."""
        T = np.tile(np.eye(4), (len(self.t), 1, 1))
        T[:, :3, :3] = self.R_world_body @ T_imu_cam[:3, :3]
        T[:, :3, 3] = self.p_world_body + self.R_world_body @ T_imu_cam[:3, 3]
        return T


class Motion(Protocol):
    """A flight: anything whose body state can be evaluated at times ``t`` (K,) [s] (ring
    flights here, the families of :mod:`common.data.synth.flights`, recorded flights of
    :mod:`common.data.synth.recorded`)."""

    def evaluate(self, t: np.ndarray) -> TrajectoryState: ...


Region = tuple[tuple[float, float, float], tuple[float, float, float]]
"""(lo, hi) corners [m] of the box a world's flights are drawn in."""


def _rot_zyx(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """(K,) angles -> (K, 3, 3) ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    R = np.empty((len(yaw), 3, 3))
    R[:, 0, 0] = cy * cp
    R[:, 0, 1] = cy * sp * sr - sy * cr
    R[:, 0, 2] = cy * sp * cr + sy * sr
    R[:, 1, 0] = sy * cp
    R[:, 1, 1] = sy * sp * sr + cy * cr
    R[:, 1, 2] = sy * sp * cr - cy * sr
    R[:, 2, 0] = -sp
    R[:, 2, 1] = cp * sr
    R[:, 2, 2] = cp * cr
    return R


@dataclass(frozen=True)
class LoopTrajectory:
    """One robot's flight (see the module docstring). Angles in rad, lengths in m."""

    centre: tuple[float, float]
    radius: tuple[float, float]  # ellipse semi-axes along x, y
    radius_mod: Wave  # multiplies both semi-axes
    angle: Wave  # loop angle
    height: Wave
    jitter_x: Wave
    jitter_y: Wave
    yaw_offset: Wave
    pitch: Wave
    roll: Wave
    ramp_s: float
    T_imu_cam: tuple[tuple[float, ...], ...] = tuple(map(tuple, T_IMU_CAM))

    def warp(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Warped time (tau, dtau/dt, d2tau/dt2) at ``t`` (K,) [s]."""
        t = np.asarray(t, dtype=np.float64)
        T = self.ramp_s
        if T <= 0:
            return t, np.ones_like(t), np.zeros_like(t)
        e = np.exp(-((t / T) ** 2))
        tau = t - T * np.sqrt(np.pi) / 2.0 * erf(t / T)
        return tau, 1.0 - e, 2.0 * t / T**2 * e

    def evaluate(self, t: np.ndarray) -> TrajectoryState:
        """Closed-form state at times ``t`` (K,) [s]."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        tau, w1, w2 = self.warp(t)
        m, m1, m2 = self.radius_mod(tau)
        th, th1, th2 = self.angle(tau)
        c, s = np.cos(th), np.sin(th)
        rx, ry = self.radius
        jx, jx1, jx2 = self.jitter_x(tau)
        jy, jy1, jy2 = self.jitter_y(tau)
        z, z1, z2 = self.height(tau)
        # Derivatives with respect to tau.
        x = self.centre[0] + rx * m * c + jx
        y = self.centre[1] + ry * m * s + jy
        x1 = rx * (m1 * c - m * s * th1) + jx1
        y1 = ry * (m1 * s + m * c * th1) + jy1
        x2 = rx * (m2 * c - 2 * m1 * s * th1 - m * c * th1**2 - m * s * th2) + jx2
        y2 = ry * (m2 * s + 2 * m1 * c * th1 - m * s * th1**2 + m * c * th2) + jy2
        p = np.stack([x, y, z], axis=1)
        d1 = np.stack([x1, y1, z1], axis=1)
        d2 = np.stack([x2, y2, z2], axis=1)
        v = d1 * w1[:, None]
        a = d2 * (w1**2)[:, None] + d1 * w2[:, None]
        # Attitude of the look frame and its body rates (ZYX Euler kinematics).
        yo, yo1, _ = self.yaw_offset(tau)
        pt, pt1, _ = self.pitch(tau)
        rl, rl1, _ = self.roll(tau)
        yaw, yaw_d = th + yo, (th1 + yo1) * w1
        R_world_body, omega_body = look_attitude(
            yaw, yaw_d, pt, pt1 * w1, rl, rl1 * w1, np.asarray(self.T_imu_cam)
        )
        return TrajectoryState(t, p, v, a, R_world_body, omega_body)


def look_attitude(
    yaw: np.ndarray,
    yaw_d: np.ndarray,
    pitch: np.ndarray,
    pitch_d: np.ndarray,
    roll: np.ndarray,
    roll_d: np.ndarray,
    T_imu_cam: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Body attitude ``R_world_body`` (K, 3, 3) and body rates ``omega_body`` (K, 3) [rad/s]
    of a look frame with ZYX angles (K,) [rad] and their time derivatives (K,) [rad/s]
    (ZYX Euler kinematics), the camera mounted on the body by ``T_imu_cam`` (4, 4)."""
    R_world_L = _rot_zyx(yaw, pitch, roll)
    omega_L = np.stack(
        [
            roll_d - yaw_d * np.sin(pitch),
            pitch_d * np.cos(roll) + yaw_d * np.cos(pitch) * np.sin(roll),
            -pitch_d * np.sin(roll) + yaw_d * np.cos(pitch) * np.cos(roll),
        ],
        axis=1,
    )
    R_imu_cam = T_imu_cam[:3, :3]
    R_L_imu = R_L_CAM @ R_imu_cam.T
    R_world_body = R_world_L @ R_L_imu
    omega_body = omega_L @ R_L_imu  # R_L_imu^T omega_L, row-wise
    return R_world_body, omega_body


def _random_wave(
    rng: np.random.Generator,
    c: float,
    amps: list[tuple[float, float]],
    freqs: list[tuple[float, float]],
    b: float = 0.0,
) -> Wave:
    amp = tuple(float(rng.uniform(*r)) for r in amps)
    freq = tuple(float(rng.uniform(*r)) for r in freqs)
    phase = tuple(float(rng.uniform(0, 2 * np.pi)) for _ in amps)
    return Wave(float(c), float(b), amp, freq, phase)


def _draw(
    region: Region, k: int, n: int, rng: np.random.Generator, cfg: TrajectoryConfig
) -> LoopTrajectory:
    """Random flight for robot ``k`` of ``n`` in ``region`` (aggressiveness grows with ``k``)."""
    lo, hi = np.array(region[0]), np.array(region[1])
    centre = (lo[:2] + hi[:2]) / 2.0
    half = (hi[:2] - lo[:2]) / 2.0
    frac = k / max(n - 1, 1)
    slow, fast = cfg.loop_period_s
    period = slow + (fast - slow) * frac * rng.uniform(0.85, 1.0)
    direction = 1.0 if (k % 2 == 0) else -1.0
    omega = direction * 2 * np.pi / period
    agg = 0.4 + 0.6 * frac  # 0.4 gentle .. 1.0 aggressive
    radius = (float(rng.uniform(0.42, 0.62) * half[0]), float(rng.uniform(0.4, 0.6) * half[1]))
    radius_mod = _random_wave(rng, 1.0, [(0.04, 0.12)], [(0.15, 0.45)])
    angle = _random_wave(rng, rng.uniform(0, 2 * np.pi), [(0.05, 0.2)], [(0.2, 0.5)], b=omega)
    z_mid = (lo[2] + hi[2]) / 2.0
    height = _random_wave(
        rng,
        z_mid + rng.uniform(-0.4, 0.1),
        [(0.15, 0.4), (0.0, 0.06 * agg)],
        [(0.15, 0.4), (1.5, 3.0)],
    )
    jitter_x = _random_wave(rng, 0.0, [(0.03 * agg, 0.1 * agg)], [(1.0, 2.5 + agg)])
    jitter_y = _random_wave(rng, 0.0, [(0.03 * agg, 0.1 * agg)], [(1.0, 2.5 + agg)])
    yaw_offset = _random_wave(
        rng,
        rng.uniform(-0.35, 0.35),
        [(0.15, 0.2 + 0.4 * agg), (0.0, 0.08 * agg)],
        [(0.3 + 0.3 * agg, 0.5 + 0.7 * agg), (1.0, 2.0)],
    )
    pitch = _random_wave(
        rng, rng.uniform(0.08, 0.25), [(0.04, 0.1), (0.0, 0.03 * agg)], [(0.2, 0.6), (1.0, 3.0)]
    )
    roll = _random_wave(rng, 0.0, [(0.03, 0.08), (0.0, 0.04 * agg)], [(0.2, 0.6), (1.0, 3.0)])
    return LoopTrajectory(
        (float(centre[0]), float(centre[1])),
        radius,
        radius_mod,
        angle,
        height,
        jitter_x,
        jitter_y,
        yaw_offset,
        pitch,
        roll,
        cfg.ramp_s,
    )


def check_trajectory(
    scene: Scene, traj: Motion, seconds: float, cfg: TrajectoryConfig
) -> str | None:
    """Reason why ``traj`` violates the constraints over ``[0, seconds]``, or None."""
    st = traj.evaluate(np.arange(0.0, seconds + 1e-9, 0.02))
    cam = st.T_world_cam()[:, :3, 3]
    clear = min(scene.clearance(st.p_world_body).min(), scene.clearance(cam).min())
    if clear < cfg.min_clearance_m:
        return f"clearance {clear:.2f} m < {cfg.min_clearance_m} m"
    speed = np.linalg.norm(st.v_world_body, axis=1).max()
    if speed > cfg.max_speed:
        return f"speed {speed:.2f} m/s > {cfg.max_speed}"
    rate = np.linalg.norm(st.omega_body, axis=1).max()
    if rate > cfg.max_rate:
        return f"angular rate {rate:.2f} rad/s > {cfg.max_rate}"
    return None


def make_trajectories(
    scene: Scene,
    robots: int,
    seconds: float,
    seed: int,
    cfg: TrajectoryConfig = TrajectoryConfig(),
    region: Region | None = None,
) -> list[LoopTrajectory]:
    """One valid ring flight per robot, deterministic in ``seed``, drawn in ``region``
    (default the whole room)."""
    area = (scene.room_lo, scene.room_hi) if region is None else region
    out = []
    for k in range(robots):
        rng = np.random.default_rng([seed, 101, k])
        reason = ""
        for _ in range(cfg.attempts):
            traj = _draw(area, k, robots, rng, cfg)
            why = check_trajectory(scene, traj, seconds, cfg)
            if why is None:
                out.append(traj)
                break
            reason = why
        else:
            raise TrajectoryError(f"robot {k}: no valid flight in {cfg.attempts} draws ({reason})")
    return out


def continuous_quaternions(q: np.ndarray) -> np.ndarray:
    """Quaternions (K, 4) with signs flipped so that neighbours never jump to ``-q``."""
    flips = np.concatenate([[False], np.einsum("ij,ij->i", q[1:], q[:-1]) < 0])
    sign = np.where(np.cumsum(flips) % 2 == 1, -1.0, 1.0)
    return q * sign[:, None]
