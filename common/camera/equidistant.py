"""Pinhole camera with Kannala-Brandt equidistant distortion (OpenCV's ``cv2.fisheye``, Kalibr's
and TUM-VI's ``equidistant``).

A camera-frame point at angle ``theta`` from the optical axis lands at distorted normalised
radius ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)`` in the
direction of its ``(X, Y)``; on the normalised plane ``theta = atan(r)`` and
``xy_d = (theta_d / r) xy``, exactly as ``cv2.fisheye.projectPoints``. Unlike a pinhole, the
model sees beyond 90 degrees: :meth:`PinholeEquidistant.project` and ``unproject`` work on rays
up to :attr:`PinholeEquidistant.theta_max` (where ``theta_d(theta)`` stops increasing, at most
pi), while normalised coordinates exist only in front (``theta < pi / 2``). Frame and pixel
conventions: :mod:`common.camera.base`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import ClassVar

import numpy as np

from common.camera.base import (
    CameraModelError,
    Pinhole,
    as_points,
    from_pixels,
    to_pixels,
)

_NEWTON_ITERATIONS = 30
_SMALL = 1e-12


@dataclass(frozen=True)
class PinholeEquidistant(Pinhole):
    """Pinhole intrinsics [px] plus equidistant distortion ``(k1, k2, k3, k4)``."""

    MODEL: ClassVar[str] = "equidistant"

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0

    def __post_init__(self) -> None:
        self._check()
        if not self.theta_max > 0.1:
            raise CameraModelError(
                f"equidistant coefficients {self.dist_coeffs.tolist()} fold over at "
                f"theta = {self.theta_max:.3g} rad: no usable field of view"
            )

    # ------------------------------------------------------------------ angle <-> radius

    def _theta_d(self, theta: np.ndarray) -> np.ndarray:
        t2 = theta * theta
        return theta * (1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4))))

    def _dtheta_d(self, theta: np.ndarray) -> np.ndarray:
        t2 = theta * theta
        k1, k2, k3, k4 = self.k1, self.k2, self.k3, self.k4
        return 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))

    @cached_property
    def theta_max(self) -> float:
        """Largest valid angle from the optical axis [rad]: where ``theta_d`` stops increasing
        (the model folds over beyond), at most pi."""
        theta = np.linspace(0.0, np.pi, 257)
        bad = np.flatnonzero(self._dtheta_d(theta) <= 0.0)
        if not len(bad):
            return float(np.pi)
        lo, hi = float(theta[bad[0] - 1]), float(theta[bad[0]])  # bisect the first fold
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if self._dtheta_d(np.array(mid)) > 0.0 else (lo, mid)
        return lo

    @cached_property
    def theta_d_max(self) -> float:
        """Distorted normalised radius of :attr:`theta_max`."""
        return float(self._theta_d(np.array([self.theta_max]))[0])

    def _solve_theta(self, theta_d: np.ndarray) -> np.ndarray:
        """Angles (N,) with ``_theta_d(theta) == theta_d`` (Newton, clamped to the valid
        range); NaN for radii beyond :attr:`theta_d_max`."""
        theta = np.clip(theta_d, 0.0, self.theta_max)
        for _ in range(_NEWTON_ITERATIONS):
            step = (self._theta_d(theta) - theta_d) / self._dtheta_d(theta)
            theta = np.clip(theta - step, 0.0, self.theta_max)
            if not np.any(np.abs(step) > 1e-15):
                break
        return np.where(theta_d <= self.theta_d_max * (1.0 + 1e-12), theta, np.nan)

    # ------------------------------------------------------------------ normalised plane

    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Undistorted normalised points (N, 2) -> distorted normalised points (N, 2)."""
        xy = as_points(xy, 2, "xy")
        r = np.hypot(xy[:, 0], xy[:, 1])
        theta = np.arctan(r)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            scale = np.where(r > 1e-8, self._theta_d(theta) / r, 1.0)
        scale = np.where(theta <= self.theta_max, scale, np.nan)
        return xy * scale[:, None]

    def undistort(self, xy_distorted: np.ndarray) -> np.ndarray:
        """Distorted normalised points (N, 2) -> undistorted normalised points (N, 2) (Newton
        on theta); NaN where the ray is not in front of the camera or beyond the model."""
        xy_d = as_points(xy_distorted, 2, "xy_distorted")
        theta_d = np.hypot(xy_d[:, 0], xy_d[:, 1])
        theta = self._solve_theta(theta_d)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            scale = np.where(theta_d > _SMALL, np.tan(theta) / theta_d, 1.0)
        scale = np.where(theta < np.pi / 2, scale, np.nan)
        return xy_d * scale[:, None]

    # ------------------------------------------------------------------ pixels

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) [m] -> distorted pixels (N, 2), also behind the image
        plane; NaN beyond :attr:`theta_max` (and straight back or at the origin)."""
        p_cam = as_points(p_cam, 3, "p_cam")
        X, Y, Z = p_cam.T
        rho = np.hypot(X, Y)
        theta = np.arctan2(rho, Z)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            scale = np.where(rho > _SMALL * np.abs(Z), self._theta_d(theta) / rho, 1.0 / Z)
        on_axis = rho <= _SMALL * np.abs(Z)
        ok = (theta <= self.theta_max) & ~(on_axis & (Z <= 0))  # straight back: no direction
        xy_d = p_cam[:, :2] * np.where(ok, scale, np.nan)[:, None]
        return to_pixels(self.fx, self.fy, self.cx, self.cy, xy_d)

    def project_jacobian(self, p_cam: np.ndarray) -> np.ndarray:
        """d pixel / d p_cam (N, 2, 3) [px/m] at camera-frame points (N, 3) [m]; NaN beyond
        :attr:`theta_max`. With ``rho = |(X, Y)|``, ``m = (X, Y) / rho``, ``R² = rho² + Z²``:
        ``d xy_d = theta_d'(theta) m dtheta + theta_d / rho (I - m mᵀ) d(X, Y)``."""
        p_cam = as_points(p_cam, 3, "p_cam")
        X, Y, Z = p_cam.T
        rho = np.hypot(X, Y)
        R2 = rho * rho + Z * Z
        theta = np.arctan2(rho, Z)
        on_axis = rho <= _SMALL * np.abs(Z)
        safe = np.where(on_axis, 1.0, rho)
        m = np.stack([X, Y], axis=1) / safe[:, None]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            dtheta = np.concatenate([m * (Z / R2)[:, None], (-rho / R2)[:, None]], axis=1)
            g = np.where(on_axis, 1.0 / Z, self._theta_d(theta) / safe)
        J = self._dtheta_d(theta)[:, None, None] * m[:, :, None] * dtheta[:, None, :]
        J[:, :, :2] += g[:, None, None] * (np.eye(2)[None] - m[:, :, None] * m[:, None, :])
        J[on_axis] = 0.0
        J[on_axis, 0, 0] = J[on_axis, 1, 1] = 1.0 / Z[on_axis]
        J[(theta > self.theta_max) | (on_axis & (Z <= 0))] = np.nan
        return J * np.array([self.fx, self.fy])[None, :, None]

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N, 2) -> unit ray directions in the camera frame (N, 3), also
        beyond 90 degrees; NaN beyond :attr:`theta_max`."""
        xy_d = from_pixels(self.fx, self.fy, self.cx, self.cy, uv)
        theta_d = np.hypot(xy_d[:, 0], xy_d[:, 1])
        theta = self._solve_theta(theta_d)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            m = np.where((theta_d > _SMALL)[:, None], xy_d / theta_d[:, None], 0.0)
        return np.concatenate([m * np.sin(theta)[:, None], np.cos(theta)[:, None]], axis=1)
