"""Visual-inertial initialisation: inertial-only MAP estimate (ORB-SLAM3, Campos et al. 2020).

The up-to-scale visual keyframe poses are held fixed; scale ``s``, gravity direction ``R_world_v``
(2 DoF: yaw is unobservable), one velocity per keyframe and a constant gyro/accel bias are
estimated from the IMU preintegration residuals of paper Eq. 13 between consecutive keyframes,
weighted by the preintegration covariance, with Gaussian bias priors. A linear solve (gravity
from the summed velocity increments, then scale and velocities by least squares) provides the
starting point; scipy's Levenberg–Marquardt solves the MAP problem. The caller then applies
the similarity to the map and runs a joint visual-inertial bundle adjustment.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import gtsam
import numpy as np
from scipy.optimize import least_squares

from common.geometry import so3_exp, so3_log
from common.imu import concat_segments
from common.preintegration import make_bias, preintegrate
from services.edge.vio.state import Keyframe

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class ViInitResult:
    """``R_world_v`` (3, 3) and ``scale``: ``p_world = scale * R_world_v @ p_v``;
    ``velocities`` (N, 3) in the world frame; biases (3,); ``cost`` final whitened cost."""

    scale: float
    R_world_v: np.ndarray
    velocities: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray
    cost: float
    cost_per_residual: float  # whitened; about 1 or below when IMU and poses agree
    # 1-sigma of log(scale) from the Gauss-Newton covariance at the solution: how well this
    # stretch of motion observes the scale (small accelerations leave it weakly observed).
    scale_sigma_rel: float = float("nan")


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector ``a`` onto unit vector ``b``."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    c = float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.cross(a, [0.0, 1.0, 0.0])
        return so3_exp(np.pi * perp / np.linalg.norm(perp))
    return so3_exp(axis / s * np.arctan2(s, c))


class _Problem:
    """Vectorised residuals of the inertial-only problem."""

    def __init__(
        self,
        keyframes: list[Keyframe],
        params: gtsam.PreintegrationCombinedParams,
        bias_accel: np.ndarray,
        bias_gyro: np.ndarray,
        gravity: float,
    ) -> None:
        self.params = params
        self.n = len(keyframes)
        self.R_v = np.stack([kf.T_world_body[:3, :3] for kf in keyframes])
        self.p_v = np.stack([kf.T_world_body[:3, 3] for kf in keyframes])
        self.pims = []
        for kf in keyframes[1:]:
            assert kf.imu_from_previous is not None
            self.pims.append(preintegrate(params, kf.imu_from_previous, bias_accel, bias_gyro))
        self.dt = np.array([p.deltaTij() for p in self.pims])
        self.g = np.array([0.0, 0.0, -gravity])
        self.W = np.zeros((len(self.pims), 9, 9))
        self.set_weights(0.0, 0.0)
        self._cache_key: tuple | None = None
        self._deltas: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._rR = np.zeros((0, 3))

    def set_weights(self, sigma_pos_metric: float, sigma_rot: float) -> None:
        """Whitening from the preintegration covariance plus the noise of the fixed visual
        poses: position ``sigma_pos_metric`` [m] and rotation ``sigma_rot`` [rad] per pose."""
        g = abs(self.g[2])
        for k, (p, dt) in enumerate(zip(self.pims, self.dt, strict=True)):
            cov = p.preintMeasCov()[:9, :9].copy()
            extra_p = 2.0 * sigma_pos_metric**2 + (0.5 * g * dt**2 * sigma_rot) ** 2
            extra = [2.0 * sigma_rot**2] * 3 + [extra_p] * 3 + [(g * dt * sigma_rot) ** 2] * 3
            cov += np.diag(extra)
            self.W[k] = np.linalg.inv(np.linalg.cholesky(cov + 1e-12 * np.eye(9)))

    def deltas(self, ba: np.ndarray, bg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bias-corrected (ΔR (M,3,3), Δv (M,3), Δp (M,3)) via gtsam's first-order update."""
        key = (*ba.tolist(), *bg.tolist())
        if key != self._cache_key:
            bias = make_bias(ba, bg)
            dR, dv, dp = [], [], []
            start = gtsam.NavState()
            for p, dt in zip(self.pims, self.dt, strict=True):
                out = p.predict(start, bias)  # includes gravity from rest at identity
                dR.append(out.attitude().matrix())
                dv.append(np.asarray(out.velocity()) - self.g * dt)
                dp.append(np.asarray(out.position()) - 0.5 * self.g * dt**2)
            dRs = np.stack(dR)
            RiTRj = np.swapaxes(self.R_v[:-1], 1, 2) @ self.R_v[1:]  # gravity rotation cancels
            E = np.swapaxes(dRs, 1, 2) @ RiTRj
            self._rR = np.stack([so3_log_batch(e) for e in E])
            self._deltas = (dRs, np.stack(dv), np.stack(dp))
            self._cache_key = key
        assert self._deltas is not None
        return self._deltas

    def residuals(
        self, R_wv: np.ndarray, s: float, v: np.ndarray, ba: np.ndarray, bg: np.ndarray
    ) -> np.ndarray:
        _, dv, dp = self.deltas(ba, bg)
        rR = self._rR
        R = R_wv @ self.R_v  # (N, 3, 3)
        p = s * self.p_v @ R_wv.T
        RiT = np.swapaxes(R[:-1], 1, 2)
        dt = self.dt[:, None]
        rv = np.einsum("mij,mj->mi", RiT, v[1:] - v[:-1] - self.g * dt) - dv
        rp = np.einsum("mij,mj->mi", RiT, p[1:] - p[:-1] - v[:-1] * dt - 0.5 * self.g * dt**2) - dp
        r = np.concatenate([rR, rp, rv], axis=1)  # gtsam order: theta, position, velocity
        return np.einsum("mij,mj->mi", self.W, r).reshape(-1)


def so3_log_batch(R: np.ndarray) -> np.ndarray:
    """so3_log tolerant of tiny numerical non-orthogonality (re-orthonormalised by SVD)."""
    U, _, Vt = np.linalg.svd(R)
    Rn = U @ Vt
    if np.linalg.det(Rn) < 0:
        Rn = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return so3_log(Rn)


def subsample_keyframes(keyframes: list[Keyframe], min_interval_s: float) -> list[Keyframe]:
    """Copies of ``keyframes`` at least ``min_interval_s`` apart, their IMU segments joined, so
    that each interval carries enough acceleration signal against the visual pose noise."""
    out = [keyframes[0]]
    seg = None
    for kf in keyframes[1:]:
        assert kf.imu_from_previous is not None
        seg = kf.imu_from_previous if seg is None else concat_segments(seg, kf.imu_from_previous)
        if (kf.timestamp_ns - out[-1].timestamp_ns) * 1e-9 >= min_interval_s or kf is keyframes[-1]:
            out.append(replace(kf, imu_from_previous=seg, previous_id=out[-1].id))
            seg = None
    return out


def inertial_only_map(
    keyframes: list[Keyframe],
    params: gtsam.PreintegrationCombinedParams,
    gravity: float,
    bias_accel: np.ndarray,
    bias_gyro: np.ndarray,
    sigma_bias_accel: float,
    sigma_bias_gyro: float,
    sigma_pos_visual: float = 0.0,
    sigma_rot_visual: float = 0.0,
) -> tuple[ViInitResult | None, str]:
    """Solve the inertial-only problem over consecutive ``keyframes`` (each after the first
    carrying ``imu_from_previous``). Poses are read as fixed, up-to-scale visual poses whose
    noise (``sigma_pos_visual`` in map units, ``sigma_rot_visual`` rad) widens the IMU residual
    covariance; without it the MAP estimate collapses the scale on noisy poses.
    Returns (result, "") or (None, reason); ``velocities`` are per given keyframe."""
    if len(keyframes) < 3:
        return None, f"{len(keyframes)} keyframes (< 3)"
    if any(kf.imu_from_previous is None for kf in keyframes[1:]):
        return None, "IMU missing between keyframes"
    prob = _Problem(keyframes, params, bias_accel, bias_gyro, gravity)
    n, m = prob.n, prob.n - 1
    _dR, dv, dp = prob.deltas(bias_accel, bias_gyro)
    # Gravity direction in the visual frame: sum of rotated velocity increments.
    dir_g_v = -np.einsum("mij,mj->i", prob.R_v[:-1], dv)
    if np.linalg.norm(dir_g_v) < 1e-9:
        return None, "no velocity increment: IMU data degenerate"
    R_wv0 = _rotation_between(dir_g_v, np.array([0.0, 0.0, -1.0]))
    # Linear least squares for scale and velocities (world frame) at that gravity.
    A = np.zeros((6 * m, 1 + 3 * n))
    b = np.zeros(6 * m)
    Rw = R_wv0 @ prob.R_v
    pw = prob.p_v @ R_wv0.T
    for k in range(m):
        dt = prob.dt[k]
        r0 = 6 * k
        A[r0 : r0 + 3, 1 + 3 * (k + 1) : 1 + 3 * (k + 2)] = np.eye(3)
        A[r0 : r0 + 3, 1 + 3 * k : 1 + 3 * (k + 1)] = -np.eye(3)
        b[r0 : r0 + 3] = prob.g * dt + Rw[k] @ dv[k]
        A[r0 + 3 : r0 + 6, 0] = pw[k + 1] - pw[k]
        A[r0 + 3 : r0 + 6, 1 + 3 * k : 1 + 3 * (k + 1)] = -dt * np.eye(3)
        b[r0 + 3 : r0 + 6] = 0.5 * prob.g * dt**2 + Rw[k] @ dp[k]
    x_lin, *_ = np.linalg.lstsq(A, b, rcond=None)
    s0 = float(x_lin[0])
    if not np.isfinite(s0) or s0 <= 0:
        logger.debug("linear VI init gave scale %.4g; starting from 1", s0)
        s0 = 1.0
    v0 = x_lin[1:].reshape(n, 3) if x_lin[0] > 0 else np.zeros((n, 3))

    def unpack(x: np.ndarray) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
        R_wv = so3_exp(np.array([x[1], x[2], 0.0])) @ R_wv0
        return R_wv, float(np.exp(x[0])), x[3 : 3 + 3 * n].reshape(n, 3), x[-3:], x[-6:-3]

    def fun(x: np.ndarray) -> np.ndarray:
        R_wv, s, v, ba, bg = unpack(x)
        r = prob.residuals(R_wv, s, v, ba, bg)
        pri = np.concatenate(
            [(bg - bias_gyro) / sigma_bias_gyro, (ba - bias_accel) / sigma_bias_accel]
        )
        return np.concatenate([r, pri])

    x = np.concatenate([[np.log(s0), 0.0, 0.0], v0.reshape(-1), bias_gyro, bias_accel])
    sol = None
    for _ in range(3):  # re-weight: the visual position noise in metres depends on the scale
        prob.set_weights(float(np.exp(x[0])) * sigma_pos_visual, sigma_rot_visual)
        try:
            sol = least_squares(fun, x, method="lm", x_scale="jac")
        except (ValueError, np.linalg.LinAlgError) as exc:
            return None, f"inertial-only optimisation failed: {exc}"
        x = sol.x
    assert sol is not None
    R_wv, s, v, ba, bg = unpack(x)
    cost = float(2.0 * sol.cost)
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac)
        sigma_log_s = float(np.sqrt(max(cov[0, 0], 0.0)))
    except np.linalg.LinAlgError:
        sigma_log_s = float("inf")
    return ViInitResult(s, R_wv, v, bg, ba, cost, cost / (9 * m), sigma_log_s), ""
