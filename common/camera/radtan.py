"""Pinhole camera with radial-tangential distortion (EuRoC's ``pinhole`` + ``radial-tangential``).

Distortion maps undistorted normalised points to distorted ones (k1, k2 radial; p1, p2
tangential), exactly as ``cv2.projectPoints`` does with a 4-element distortion vector. Frame
and pixel conventions: :mod:`common.camera.base`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np

from common.camera.base import (
    Pinhole,
    as_points,
)

_EYE3 = np.eye(3)


@dataclass(frozen=True)
class PinholeRadtan(Pinhole):
    """Pinhole intrinsics [px] plus radial-tangential distortion ``(k1, k2, p1, p2)``."""

    MODEL: ClassVar[str] = "radtan"

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def __post_init__(self) -> None:
        self._check()

    # ------------------------------------------------------------------ normalised plane

    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Undistorted normalised points (N, 2) -> distorted normalised points (N, 2)."""
        xy = as_points(xy, 2, "xy")
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + self.k2 * r2)
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return np.stack([xd, yd], axis=1)

    def _distort_jacobian(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
        """Partial derivatives (dxd/dx, dxd/dy, dyd/dx, dyd/dy), each (N,)."""
        k1, k2, p1, p2 = self.k1, self.k2, self.p1, self.p2
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + k2 * r2)
        dradial = 2.0 * (k1 + 2.0 * k2 * r2)  # d radial / d(x or y) = dradial * (x or y)
        a = radial + x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        b = x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        c = x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        d = radial + y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
        return a, b, c, d

    def _newton_step(
        self, x: np.ndarray, y: np.ndarray, xd: np.ndarray, yd: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """One Newton step of ``distort(x, y) = (xd, yd)`` (distortion and its Jacobian fused:
        the robot undistorts every tracked point several times per frame)."""
        k1, k2, p1, p2 = self.k1, self.k2, self.p1, self.p2
        xx, yy, xy = x * x, y * y, x * y
        r2 = xx + yy
        radial = 1.0 + r2 * (k1 + k2 * r2)
        dradial = 2.0 * (k1 + 2.0 * k2 * r2)
        ex = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx) - xd
        ey = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy - yd
        a = radial + xx * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        b = xy * dradial + 2.0 * p1 * x + 2.0 * p2 * y  # = dyd/dx
        d = radial + yy * dradial + 6.0 * p1 * y + 2.0 * p2 * x
        det = a * d - b * b
        return x - (d * ex - b * ey) / det, y - (a * ey - b * ex) / det

    def undistort(self, xy_distorted: np.ndarray, iterations: int = 5) -> np.ndarray:
        """Distorted normalised points (N, 2) -> undistorted normalised points (N, 2).

        OpenCV's fixed-point iteration (``cv2.undistortPoints``, ``iterations`` steps: its
        default) followed by two Newton steps, so ``distort(undistort(p)) == p`` to ~1e-14
        inside the image (cv2's five steps alone leave up to 0.6 px at EuRoC cam0's corners).
        """
        xy_d = as_points(xy_distorted, 2, "xy_distorted")
        if len(xy_d) == 0:
            return np.zeros((0, 2))
        start = cv2.undistortPoints(
            np.ascontiguousarray(xy_d).reshape(-1, 1, 2),
            _EYE3,
            self.dist_coeffs,
            None,
            None,
            None,
            (cv2.TERM_CRITERIA_COUNT, iterations, 0.0),
        ).reshape(-1, 2)
        x, y = start[:, 0], start[:, 1]
        xd, yd = xy_d[:, 0], xy_d[:, 1]
        for _ in range(2):  # quadratic convergence from cv2's start
            x, y = self._newton_step(x, y, xd, yd)
        return np.stack([x, y], axis=1)

    # ------------------------------------------------------------------ pixels

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) [m] -> distorted pixels (N, 2). Points with ``z <= 0``
        give NaN."""
        p_cam = as_points(p_cam, 3, "p_cam")
        z = p_cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p_cam[:, :2] / np.where(z > 0, z, np.nan)[:, None]
        return self.normalized_to_pixels(xy)

    def project_jacobian(self, p_cam: np.ndarray) -> np.ndarray:
        """d pixel / d p_cam (N, 2, 3) [px/m] at camera-frame points (N, 3) [m]; NaN where
        ``z <= 0``."""
        p_cam = as_points(p_cam, 3, "p_cam")
        X, Y = p_cam[:, 0], p_cam[:, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = 1.0 / np.where(p_cam[:, 2] > 0, p_cam[:, 2], np.nan)
        x, y = X * iz, Y * iz
        a, b, c, d = self._distort_jacobian(x, y)
        J_xy = np.zeros((len(p_cam), 2, 3))  # d (x, y) / d p_cam
        J_xy[:, 0, 0] = iz
        J_xy[:, 0, 2] = -x * iz
        J_xy[:, 1, 1] = iz
        J_xy[:, 1, 2] = -y * iz
        J_d = np.stack([np.stack([a, b], axis=1), np.stack([c, d], axis=1)], axis=1)
        J_d *= np.array([self.fx, self.fy])[None, :, None]
        return J_d @ J_xy

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N, 2) -> unit ray directions in the camera frame (N, 3)."""
        xy = self.pixels_to_normalized(uv)
        rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)
