"""What every camera model shares: the error, the :class:`CameraModel` interface, and the
pinhole pixel maths around a model's distortion (intrinsics, pixel grid).

Conventions (OpenCV's): pixel ``(u, v)`` has its centre at integer coordinates, ``u`` to the
right, ``v`` down; the camera frame has ``x`` right, ``y`` down, ``z`` forward. Normalised
points are ``(x, y) = (X / Z, Y / Z)``; a model's distortion maps them to distorted normalised
points ``xy_d``, and pixels are ``(fx * x_d + cx, fy * y_d + cy)``.
"""

from __future__ import annotations

from typing import ClassVar, Protocol, Self

import numpy as np

from common.calibration import CAMERA_MODELS, CameraCalibration
from common.errors import RecslamError


class CameraModelError(RecslamError):
    """Invalid camera parameters or point arrays of the wrong shape."""


def as_points(a: np.ndarray, dim: int, what: str) -> np.ndarray:
    """``a`` as float64 (N, dim), else :class:`CameraModelError`."""
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise CameraModelError(f"{what} must be (N, {dim}), got shape {arr.shape}")
    return arr


def check_intrinsics(width: int, height: int, fx: float, fy: float, coeffs: tuple) -> None:
    """Raise :class:`CameraModelError` unless size and focal lengths are positive and every
    coefficient is finite."""
    if width <= 0 or height <= 0:
        raise CameraModelError(f"image size must be positive, got {width}x{height}")
    if not (fx > 0 and fy > 0):
        raise CameraModelError(f"focal lengths must be positive, got {fx}, {fy}")
    if not np.all(np.isfinite(coeffs)):
        raise CameraModelError(f"distortion coefficients must be finite, got {coeffs}")


def intrinsic_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(3, 3) pinhole intrinsic matrix [px]."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def to_pixels(fx: float, fy: float, cx: float, cy: float, xy_d: np.ndarray) -> np.ndarray:
    """Distorted normalised points (N, 2) -> pixels (N, 2)."""
    return np.stack([fx * xy_d[:, 0] + cx, fy * xy_d[:, 1] + cy], axis=1)


def from_pixels(fx: float, fy: float, cx: float, cy: float, uv: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) -> distorted normalised points (N, 2)."""
    uv = as_points(uv, 2, "uv")
    return np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy], axis=1)


def pixel_grid(width: int, height: int) -> np.ndarray:
    """All pixel centres (H * W, 2) in row-major order (``u`` fastest)."""
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    return np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)


def scaled_intrinsics(
    width: int, height: int, fx: float, fy: float, cx: float, cy: float, factor: float
) -> tuple[int, int, float, float, float, float]:
    """Size and intrinsics at ``factor`` times the resolution, pixel centres consistent
    (``u' + 0.5 = factor * (u + 0.5)``)."""
    return (
        round(width * factor),
        round(height * factor),
        fx * factor,
        fy * factor,
        (cx + 0.5) * factor - 0.5,
        (cy + 0.5) * factor - 0.5,
    )


class Pinhole:
    """The pinhole half every model shares, for frozen dataclasses with the fields ``width,
    height, fx, fy, cx, cy`` followed by the coefficients :data:`CAMERA_MODELS` names for
    :attr:`MODEL`; the model supplies ``distort`` / ``undistort`` on the normalised plane."""

    MODEL: ClassVar[str]
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def distort(self, xy: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def undistort(self, xy_distorted: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    @property
    def coefficients(self) -> tuple[float, ...]:
        """The distortion coefficients, in :data:`CAMERA_MODELS` order."""
        return tuple(getattr(self, name) for name in CAMERA_MODELS[self.MODEL])

    def _check(self) -> None:
        check_intrinsics(self.width, self.height, self.fx, self.fy, self.coefficients)

    @classmethod
    def from_calibration(cls, calib: CameraCalibration) -> Self:
        if calib.model != cls.MODEL:
            raise CameraModelError(
                f"{cls.__name__} needs a calibration of model {cls.MODEL!r}, got {calib.model!r}"
            )
        return cls(  # type: ignore[call-arg]  # the dataclass fields, in order
            calib.width, calib.height, calib.fx, calib.fy, calib.cx, calib.cy, *calib.distortion
        )

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix."""
        return intrinsic_matrix(self.fx, self.fy, self.cx, self.cy)

    @property
    def dist_coeffs(self) -> np.ndarray:
        """(4,) OpenCV distortion vector of the model (``cv2`` for radtan, ``cv2.fisheye``
        for equidistant)."""
        return np.array(self.coefficients)

    def normalized_to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """Undistorted normalised points (N, 2) -> distorted pixels (N, 2)."""
        return to_pixels(self.fx, self.fy, self.cx, self.cy, self.distort(xy))

    def pixels_to_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N, 2) -> undistorted normalised points (N, 2); NaN for pixels
        whose ray is not in front of the camera (possible with a fisheye)."""
        return self.undistort(from_pixels(self.fx, self.fy, self.cx, self.cy, uv))

    def pixel_grid(self) -> np.ndarray:
        """All pixel centres (H * W, 2) in row-major order (``u`` fastest)."""
        return pixel_grid(self.width, self.height)

    def pixel_rays(self) -> np.ndarray:
        """(H, W, 3) unit rays of every pixel: pixel ``(u, v)`` of a distorted image shows the
        scene along ``pixel_rays()[v, u]`` (NaN outside the model's field of view)."""
        return self.unproject(self.pixel_grid()).reshape(self.height, self.width, 3)

    def scaled(self, factor: float) -> Self:
        """Same optics at ``factor`` times the resolution (pixel centres stay consistent:
        ``u' + 0.5 = factor * (u + 0.5)``). Distortion coefficients are unchanged."""
        size = scaled_intrinsics(
            self.width, self.height, self.fx, self.fy, self.cx, self.cy, factor
        )
        return type(self)(*size, *self.coefficients)  # type: ignore[call-arg]

    def to_calibration(self, T_body_cam: np.ndarray, rate_hz: float) -> CameraCalibration:
        """This camera as a :class:`CameraCalibration` with that extrinsic and rate."""
        return CameraCalibration(
            width=self.width,
            height=self.height,
            fx=self.fx,
            fy=self.fy,
            cx=self.cx,
            cy=self.cy,
            distortion=self.coefficients,
            T_body_cam=T_body_cam,
            rate_hz=rate_hz,
            model=self.MODEL,
        )


class CameraModel(Protocol):
    """What every consumer of a camera uses (tracker, keypoint codec, ORB, VIO, the cloud's
    verification, the synthetic renderer): pixels <-> undistorted normalised points <-> rays.
    Build one with :func:`common.camera.camera_model`.

    Points outside a model's field of view (behind a pinhole camera; beyond a fisheye's
    largest valid angle) project to NaN; pixels whose ray is not in front of the camera
    (``z <= 0``, possible with a fisheye) have NaN normalised coordinates, but
    :meth:`unproject` still gives their ray."""

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

    @property
    def dist_coeffs(self) -> np.ndarray: ...

    def distort(self, xy: np.ndarray) -> np.ndarray: ...

    def undistort(self, xy_distorted: np.ndarray) -> np.ndarray: ...

    def project(self, p_cam: np.ndarray) -> np.ndarray: ...

    def project_jacobian(self, p_cam: np.ndarray) -> np.ndarray: ...

    def normalized_to_pixels(self, xy: np.ndarray) -> np.ndarray: ...

    def pixels_to_normalized(self, uv: np.ndarray) -> np.ndarray: ...

    def unproject(self, uv: np.ndarray) -> np.ndarray: ...

    def pixel_grid(self) -> np.ndarray: ...

    def pixel_rays(self) -> np.ndarray: ...

    def scaled(self, factor: float) -> CameraModel: ...

    def to_calibration(self, T_body_cam: np.ndarray, rate_hz: float) -> CameraCalibration: ...
