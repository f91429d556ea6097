"""Pinhole camera with radial-tangential distortion (EuRoC's ``pinhole`` + ``radial-tangential``).

Conventions (OpenCV's): pixel ``(u, v)`` has its centre at integer coordinates, ``u`` to the
right, ``v`` down; the camera frame has ``x`` right, ``y`` down, ``z`` forward. Normalised
points are ``(x, y) = (X / Z, Y / Z)``; distortion maps undistorted normalised points to
distorted ones (k1, k2 radial; p1, p2 tangential), exactly as ``cv2.projectPoints`` does with a
4-element distortion vector.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from common.calibration import CameraCalibration
from common.errors import RecslamError


class CameraModelError(RecslamError):
    """Invalid camera parameters or point arrays of the wrong shape."""


def _as_points(a: np.ndarray, dim: int, what: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise CameraModelError(f"{what} must be (N, {dim}), got shape {arr.shape}")
    return arr


class CameraModel(Protocol):
    """What every consumer of a camera uses (tracker, keypoint codec, ORB, VIO, the cloud's
    verification, the synthetic renderer): pixels <-> undistorted normalised points <-> rays.
    Build one with :func:`camera_model`."""

    @property
    def width(self) -> int: ...

    @property
    def height(self) -> int: ...

    @property
    def fx(self) -> float: ...

    @property
    def fy(self) -> float: ...

    @property
    def cx(self) -> float: ...

    @property
    def cy(self) -> float: ...

    @property
    def K(self) -> np.ndarray: ...

    def project(self, p_cam: np.ndarray) -> np.ndarray: ...

    def normalized_to_pixels(self, xy: np.ndarray) -> np.ndarray: ...

    def pixels_to_normalized(self, uv: np.ndarray) -> np.ndarray: ...

    def unproject(self, uv: np.ndarray) -> np.ndarray: ...

    def pixel_grid(self) -> np.ndarray: ...

    def pixel_rays(self) -> np.ndarray: ...


def camera_model(calib: CameraCalibration) -> CameraModel:
    """The projection model ``calib.model`` names, with ``calib``'s parameters."""
    if calib.model == "radtan":
        return PinholeRadtan.from_calibration(calib)
    raise CameraModelError(f"camera model {calib.model!r} is not implemented")


@dataclass(frozen=True)
class PinholeRadtan:
    """Pinhole intrinsics [px] plus radial-tangential distortion ``(k1, k2, p1, p2)``."""

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
        if self.width <= 0 or self.height <= 0:
            raise CameraModelError(f"image size must be positive, got {self.width}x{self.height}")
        if self.fx <= 0 or self.fy <= 0:
            raise CameraModelError(f"focal lengths must be positive, got {self.fx}, {self.fy}")

    @classmethod
    def from_calibration(cls, calib: CameraCalibration) -> PinholeRadtan:
        k1, k2, p1, p2 = calib.distortion
        return cls(
            calib.width, calib.height, calib.fx, calib.fy, calib.cx, calib.cy, k1, k2, p1, p2
        )

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """(4,) OpenCV distortion vector ``(k1, k2, p1, p2)``."""
        return np.array([self.k1, self.k2, self.p1, self.p2])

    # ------------------------------------------------------------------ normalised plane

    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Undistorted normalised points (N, 2) -> distorted normalised points (N, 2)."""
        xy = _as_points(xy, 2, "xy")
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

    def undistort(self, xy_distorted: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Distorted normalised points (N, 2) -> undistorted normalised points (N, 2).

        OpenCV's fixed-point iteration (as ``cv2.undistortPoints``) followed by three
        Gauss-Newton steps, so ``distort(undistort(p)) == p`` to ~1e-12 inside the image.
        """
        xy_d = _as_points(xy_distorted, 2, "xy_distorted")
        xd, yd = xy_d[:, 0], xy_d[:, 1]
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            icdist = 1.0 / (1.0 + r2 * (self.k1 + self.k2 * r2))
            dx = 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
            dy = self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
            x = (xd - dx) * icdist
            y = (yd - dy) * icdist
        for _ in range(3):
            ex, ey = (self.distort(np.stack([x, y], axis=1)) - xy_d).T
            a, b, c, d = self._distort_jacobian(x, y)
            det = a * d - b * c
            x = x - (d * ex - b * ey) / det
            y = y - (-c * ex + a * ey) / det
        return np.stack([x, y], axis=1)

    # ------------------------------------------------------------------ pixels

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) [m] -> distorted pixels (N, 2). Points with ``z <= 0``
        give NaN."""
        p_cam = _as_points(p_cam, 3, "p_cam")
        z = p_cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p_cam[:, :2] / np.where(z > 0, z, np.nan)[:, None]
        return self.normalized_to_pixels(xy)

    def normalized_to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """Undistorted normalised points (N, 2) -> distorted pixels (N, 2)."""
        xy_d = self.distort(xy)
        return np.stack([self.fx * xy_d[:, 0] + self.cx, self.fy * xy_d[:, 1] + self.cy], axis=1)

    def pixels_to_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N, 2) -> undistorted normalised points (N, 2)."""
        uv = _as_points(uv, 2, "uv")
        xy_d = np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], axis=1)
        return self.undistort(xy_d)

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N, 2) -> unit ray directions in the camera frame (N, 3)."""
        xy = self.pixels_to_normalized(uv)
        rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def pixel_grid(self) -> np.ndarray:
        """All pixel centres (H * W, 2) in row-major order (``u`` fastest)."""
        u, v = np.meshgrid(np.arange(self.width), np.arange(self.height))
        return np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)

    def pixel_rays(self) -> np.ndarray:
        """(H, W, 3) unit rays of every pixel: pixel ``(u, v)`` of a distorted image shows the
        scene along ``pixel_rays()[v, u]``."""
        return self.unproject(self.pixel_grid()).reshape(self.height, self.width, 3)

    def scaled(self, factor: float) -> PinholeRadtan:
        """Same optics at ``factor`` times the resolution (pixel centres stay consistent:
        ``u' + 0.5 = factor * (u + 0.5)``). Distortion coefficients are unchanged."""
        w, h = round(self.width * factor), round(self.height * factor)
        return PinholeRadtan(
            w,
            h,
            self.fx * factor,
            self.fy * factor,
            (self.cx + 0.5) * factor - 0.5,
            (self.cy + 0.5) * factor - 0.5,
            self.k1,
            self.k2,
            self.p1,
            self.p2,
        )

    def to_calibration(self, T_body_cam: np.ndarray, rate_hz: float) -> CameraCalibration:
        return CameraCalibration(
            width=self.width,
            height=self.height,
            fx=self.fx,
            fy=self.fy,
            cx=self.cx,
            cy=self.cy,
            distortion=(self.k1, self.k2, self.p1, self.p2),
            T_body_cam=T_body_cam,
            rate_hz=rate_hz,
        )
