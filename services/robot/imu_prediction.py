"""IMU prediction of keypoint positions for LK (Algorithm 1, first half).

Before visual-inertial initialisation the rotation between two frames comes from the mean
angular velocity over the IMU samples between them (the paper's uniform-motion model,
equation 2): ``R_imu0_imu1 = Exp((ω_mean − b_g) Δt)``. It is carried into the camera frame with
the extrinsic ``R_imu_cam`` and applied to the keypoints' rays (the infinite homography
``K R_cur_prev K⁻¹`` of a pinhole camera; rays also serve a fisheye's view beyond 90 degrees);
the camera model (:func:`common.camera.camera_model`) projects them back into pixels.

After initialisation the edge sends an :class:`InertialState` (pose, velocity, biases,
gravity) for some past frame; it is propagated through the buffered IMU samples (on-manifold
integration with the bias-corrected measurements, as preintegration does) to the previous
and the current frame. Tracks with a 3D point from the edge are predicted by reprojection;
the rest by the rotation of the propagated states.

Frames: ``R_a_b`` rotates vectors from ``b`` into ``a``; ``T_a_b`` maps points from ``b`` to
``a``; ``imu`` is the IMU sensor frame, ``cam`` the camera frame, ``world`` the edge's world.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from common.calibration import CameraCalibration, ImuCalibration
from common.camera import camera_model
from common.errors import RecslamError
from common.geometry import inverse_T, so3_exp
from common.imu import ImuBuffer, ImuDataError

logger = logging.getLogger(__name__)

GRAVITY_WORLD = (0.0, 0.0, -9.81)


class ImuPredictionError(RecslamError):
    """Invalid IMU data or inertial state given to the predictor."""


def _vec3(a: Sequence[float] | np.ndarray, name: str) -> np.ndarray:
    arr = np.array(a, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ImuPredictionError(f"{name} must be 3 finite numbers, got {a!r}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class InertialState:
    """IMU state at ``timestamp_ns`` as the edge estimates it after VI initialisation.

    ``R_world_imu`` (3, 3) and ``p_world_imu`` (3,) [m]: pose of the IMU frame in the world;
    ``v_world_imu`` (3,) [m/s]; ``bias_gyro`` (3,) [rad/s]; ``bias_accel`` (3,) [m/s²];
    ``gravity_world`` (3,) [m/s²], the gravity vector in the world frame.
    """

    timestamp_ns: int
    R_world_imu: np.ndarray
    p_world_imu: np.ndarray
    v_world_imu: np.ndarray
    bias_gyro: np.ndarray = field(default_factory=lambda: np.zeros(3))
    bias_accel: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gravity_world: np.ndarray = field(default_factory=lambda: np.array(GRAVITY_WORLD))

    def __post_init__(self) -> None:
        R = np.array(self.R_world_imu, dtype=np.float64)
        if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-5):
            raise ImuPredictionError("InertialState.R_world_imu is not a (3, 3) rotation")
        R.setflags(write=False)
        object.__setattr__(self, "R_world_imu", R)
        for name in ("p_world_imu", "v_world_imu", "bias_gyro", "bias_accel", "gravity_world"):
            object.__setattr__(self, name, _vec3(getattr(self, name), f"InertialState.{name}"))
        object.__setattr__(self, "timestamp_ns", int(self.timestamp_ns))


def mean_angular_velocity(buffer: ImuBuffer, t0_ns: int, t1_ns: int) -> np.ndarray:
    """Time-weighted mean gyro reading (3,) [rad/s] over ``[t0, t1]`` (the paper's eq. 2)."""
    dt, gyro, _ = buffer.held_segment(t0_ns, t1_ns).midpoints()
    total = float(dt.sum())
    if total <= 0.0:
        return gyro.mean(axis=0) if len(gyro) else np.zeros(3)
    return (dt[:, None] * gyro).sum(axis=0) / total


def gyro_rotation(
    buffer: ImuBuffer, t0_ns: int, t1_ns: int, bias_gyro: np.ndarray | None = None
) -> np.ndarray:
    """``R_imu0_imu1`` (3, 3): rotation of the IMU frame at ``t1`` seen from ``t0``, from the
    mean angular velocity (uniform-motion model): ``Exp((ω_mean − b_g) Δt)``."""
    w = mean_angular_velocity(buffer, t0_ns, t1_ns)
    if bias_gyro is not None:
        w = w - np.asarray(bias_gyro, dtype=np.float64)
    return so3_exp(w * (t1_ns - t0_ns) * 1e-9)


def propagate(state: InertialState, buffer: ImuBuffer, t1_ns: int) -> InertialState:
    """Integrate ``state`` forward to ``t1_ns`` with the buffered IMU (bias-corrected, midpoint
    samples, exact rotation per piece). Biases and gravity are kept."""
    if t1_ns == state.timestamp_ns:
        return state
    dt, gyro, accel = buffer.held_segment(state.timestamp_ns, t1_ns).midpoints()
    R = state.R_world_imu.copy()
    p = state.p_world_imu.copy()
    v = state.v_world_imu.copy()
    g = state.gravity_world
    for h, w, a in zip(dt, gyro - state.bias_gyro, accel - state.bias_accel, strict=True):
        acc_world = R @ a + g
        p = p + v * h + 0.5 * acc_world * h * h
        v = v + acc_world * h
        R = R @ so3_exp(w * h)
    return InertialState(t1_ns, R, p, v, state.bias_gyro, state.bias_accel, g)


# ---------------------------------------------------------------------------- camera model


def R_imu_cam_from(camera: CameraCalibration, imu: ImuCalibration) -> np.ndarray:
    """Extrinsic rotation ``R_imu_cam`` (3, 3) from the two body-frame calibrations."""
    return T_imu_cam_from(camera, imu)[:3, :3]


def T_imu_cam_from(camera: CameraCalibration, imu: ImuCalibration) -> np.ndarray:
    """Extrinsic ``T_imu_cam`` (4, 4) = ``T_body_imu⁻¹ T_body_cam``."""
    return inverse_T(imu.T_body_imu) @ camera.T_body_cam


def undistort_normalised(camera: CameraCalibration, pts_px: np.ndarray) -> np.ndarray:
    """Distorted pixels (N, 2) -> undistorted normalised image coordinates (N, 2) (NaN for
    pixels whose ray is not in front of the camera, possible with a fisheye)."""
    pts = np.asarray(pts_px, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return np.zeros((0, 2))
    return camera_model(camera).pixels_to_normalized(pts)


def project_points(camera: CameraCalibration, p_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (N, 3) -> distorted pixels (N, 2) and a mask (N,) of points the
    camera sees (in front of a pinhole camera; within a fisheye's field of view, which may
    reach behind); pixels of the others are NaN."""
    p_cam = np.asarray(p_cam, dtype=np.float64).reshape(-1, 3)
    if len(p_cam) == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)
    out = camera_model(camera).project(p_cam)
    return out, np.isfinite(out).all(axis=1)


def predict_rotation(
    camera: CameraCalibration, pts_px: np.ndarray, R_cur_prev: np.ndarray
) -> np.ndarray:
    """Infinite-homography prediction: distorted pixels (N, 2) of the previous frame -> their
    positions (N, 2) in the current one under the camera rotation ``R_cur_prev`` (vectors of
    the previous camera frame into the current). Points turning out of view keep their
    previous position."""
    pts_px = np.asarray(pts_px, dtype=np.float64).reshape(-1, 2)
    if len(pts_px) == 0:
        return np.zeros((0, 2))
    rays = camera_model(camera).unproject(pts_px) @ np.asarray(R_cur_prev).T
    out, front = project_points(camera, rays)
    out[~front] = pts_px[~front]
    return out


# ---------------------------------------------------------------------------- predictor


class StaticGyroBias:
    """Running mean of gyro readings over standstill intervals (bias before VI init)."""

    def __init__(self, min_frames: int) -> None:
        self.min_frames = min_frames
        self.n_frames = 0
        self._sum = np.zeros(3)
        self._seconds = 0.0

    def add_standstill(self, buffer: ImuBuffer, t0_ns: int, t1_ns: int) -> None:
        """Count ``[t0, t1]`` as standstill: its mean gyro reading is bias."""
        dt, gyro, _ = buffer.held_segment(t0_ns, t1_ns).midpoints()
        self._sum += (dt[:, None] * gyro).sum(axis=0)
        self._seconds += float(dt.sum())
        self.n_frames += 1

    @property
    def bias(self) -> np.ndarray | None:
        """Learnt gyro bias (3,) [rad/s], or None before ``min_frames`` standstill frames."""
        if self.n_frames < self.min_frames or self._seconds <= 0.0:
            return None
        return self._sum / self._seconds


@dataclass(frozen=True, eq=False)
class MotionPrediction:
    """Relative camera motion between the previous and the current frame.

    ``R_cur_prev`` (3, 3) rotates vectors of the previous camera frame into the current one;
    ``T_cam_world`` (4, 4) is the current camera pose (world -> camera) when an inertial state
    is available, else None; ``source`` is ``"gyro"`` or ``"preintegration"``.
    """

    R_cur_prev: np.ndarray
    T_cam_world: np.ndarray | None
    source: str


class MotionPredictor:
    """Keeps the IMU buffer and the edge's inertial feedback; predicts frame-to-frame motion."""

    def __init__(
        self,
        camera: CameraCalibration,
        imu: ImuCalibration,
        buffer_horizon_s: float = 2.0,
        static_min_frames: int = 5,
    ) -> None:
        self.camera = camera
        self.static_bias = StaticGyroBias(static_min_frames)
        self.T_imu_cam = T_imu_cam_from(camera, imu)
        self.T_cam_imu = inverse_T(self.T_imu_cam)
        self.R_imu_cam = self.T_imu_cam[:3, :3]
        self.buffer = ImuBuffer(buffer_horizon_s)
        self._base: InertialState | None = None
        self._at_prev: InertialState | None = None
        self._landmarks: dict[int, np.ndarray] = {}
        self.time_offset_ns = 0  # t_imu = t_cam + offset: frame times read on the IMU clock

    @property
    def initialised(self) -> bool:
        """True once an inertial state from the edge has been applied."""
        return self._base is not None

    def add_imu(self, timestamps_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Buffer IMU samples (IMU frame); ImuPredictionError on malformed samples."""
        try:
            self.buffer.append(timestamps_ns, gyro, accel)
        except ImuDataError as exc:
            raise ImuPredictionError(str(exc)) from exc

    def set_time_offset(self, offset_ns: int) -> None:
        """The camera-IMU time offset (``t_imu = t_cam + offset``, ns, the edge's estimate):
        frame times and the edge's states are read on the IMU clock from now on."""
        delta = int(offset_ns) - self.time_offset_ns
        self.time_offset_ns = int(offset_ns)
        if self._base is not None and delta:
            self._base = replace(self._base, timestamp_ns=self._base.timestamp_ns + delta)
        self._at_prev = None

    def set_inertial_state(
        self,
        state: InertialState,
        track_ids: np.ndarray | None = None,
        p_world: np.ndarray | None = None,
    ) -> None:
        """Apply the edge's state (at a camera time); optionally 3D points (M, 3) [m, world] of
        tracks (M,), which replace the previous set (``None`` keeps it: points live in the
        world frame)."""
        state = replace(state, timestamp_ns=state.timestamp_ns + self.time_offset_ns)
        if len(self.buffer) and state.timestamp_ns < self.buffer.timestamps_ns[0]:
            raise ImuPredictionError(
                f"inertial state at {state.timestamp_ns} ns is older than the IMU buffer "
                f"(starts {int(self.buffer.timestamps_ns[0])} ns); raise imu_buffer_s"
            )
        if track_ids is not None and p_world is not None:
            self.update_landmarks(track_ids, p_world, replace=True)
        self._base = state
        self._at_prev = None

    def update_landmarks(
        self,
        track_ids: np.ndarray,
        p_world: np.ndarray,
        *,
        replace: bool = False,
        forget: np.ndarray | None = None,
        active: np.ndarray | None = None,
    ) -> None:
        """Points (M, 3) [m, world] of tracks (M,) (tracker ids): the new set (``replace``) or
        merged into it (a track's point is overwritten); then the tracks in ``forget`` (K,) are
        dropped and, if ``active`` (A,) is given, every track not in it (tracks that ended)."""
        ids = np.asarray(track_ids, dtype=np.int64).reshape(-1)
        pts = np.asarray(p_world, dtype=np.float64).reshape(-1, 3)
        if len(ids) != len(pts):
            raise ImuPredictionError(f"{len(ids)} track ids but {len(pts)} points")
        if not np.isfinite(pts).all():
            raise ImuPredictionError("landmark points must be finite")
        if replace:
            self._landmarks = {}
        self._landmarks.update(zip(ids.tolist(), pts, strict=True))
        if forget is not None:
            for i in np.asarray(forget, dtype=np.int64).reshape(-1).tolist():
                self._landmarks.pop(i, None)
        if active is not None and self._landmarks:
            keep = set(np.asarray(active, dtype=np.int64).reshape(-1).tolist())
            self._landmarks = {i: p for i, p in self._landmarks.items() if i in keep}

    @property
    def landmark_ids(self) -> np.ndarray:
        """Tracks (M,) ascending with a 3D point from the edge."""
        return np.array(sorted(self._landmarks), dtype=np.int64)

    def state_at(self, t_ns: int) -> InertialState | None:
        """The edge's state propagated to camera time ``t_ns`` (None before VI
        initialisation); its ``timestamp_ns`` is on the IMU clock."""
        if self._base is None:
            return None
        t_ns = int(t_ns) + self.time_offset_ns
        start = self._base
        if self._at_prev is not None and self._at_prev.timestamp_ns <= t_ns:
            start = self._at_prev
        return propagate(start, self.buffer, t_ns)

    def predict_motion(self, t_prev_ns: int, t_cur_ns: int) -> MotionPrediction:
        """Camera motion from camera time ``t_prev`` to ``t_cur`` (IMU samples must be
        buffered)."""
        td = self.time_offset_ns
        if self._base is None or self._base.timestamp_ns > t_prev_ns + td:
            # Before VI init; or the edge's state is newer than the previous frame (it cannot be
            # propagated backwards): rotation from the gyro, with the best bias known.
            bias = self.static_bias.bias if self._base is None else self._base.bias_gyro
            R_imu0_imu1 = gyro_rotation(self.buffer, t_prev_ns + td, t_cur_ns + td, bias)
            R_cam0_cam1 = self.R_imu_cam.T @ R_imu0_imu1 @ self.R_imu_cam
            return MotionPrediction(R_cam0_cam1.T, None, "gyro")
        prev = self.state_at(t_prev_ns)
        cur = self.state_at(t_cur_ns)
        assert prev is not None and cur is not None
        self._at_prev = cur
        R_imu1_imu0 = cur.R_world_imu.T @ prev.R_world_imu
        R_cur_prev = self.R_imu_cam.T @ R_imu1_imu0 @ self.R_imu_cam
        T_world_imu = np.eye(4)
        T_world_imu[:3, :3] = cur.R_world_imu
        T_world_imu[:3, 3] = cur.p_world_imu
        T_cam_world = self.T_cam_imu @ inverse_T(T_world_imu)
        return MotionPrediction(R_cur_prev, T_cam_world, "preintegration")

    def predict_points(
        self, motion: MotionPrediction, pts_px: np.ndarray, track_ids: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Predicted pixels (N, 2) of tracks at ``pts_px`` (N, 2) in the previous frame, and a
        mask (N,) of the tracks predicted by reprojecting their 3D point."""
        pred = predict_rotation(self.camera, pts_px, motion.R_cur_prev)
        by_point = np.zeros(len(pred), dtype=bool)
        if motion.T_cam_world is not None and self._landmarks:
            rows = [i for i, t in enumerate(np.asarray(track_ids)) if int(t) in self._landmarks]
            if rows:
                p_world = np.stack([self._landmarks[int(track_ids[i])] for i in rows])
                p_cam = p_world @ motion.T_cam_world[:3, :3].T + motion.T_cam_world[:3, 3]
                px, front = project_points(self.camera, p_cam)
                idx = np.asarray(rows)[front]
                pred[idx] = px[front]
                by_point[idx] = True
        return pred, by_point


def warp_by_rotation(
    camera: CameraCalibration,
    image: np.ndarray,
    R_cur_prev: np.ndarray,
    out_camera: CameraCalibration | None = None,
) -> np.ndarray:
    """Render what a camera rotated by ``R_cur_prev`` sees: each output pixel's ray ``x_cur``
    (through ``out_camera``, default ``camera``) is looked up at ``R_cur_prev⁻¹ x_cur`` in
    ``image`` taken by ``camera`` (bilinear, black outside). Used to test and benchmark the
    rotation prediction on real images; an ``out_camera`` with a longer focal length renders a
    narrower view that stays inside the source image (no black borders)."""
    out = camera if out_camera is None else out_camera
    h, w = out.height, out.width
    rays = camera_model(out).pixel_rays().reshape(-1, 3) @ np.asarray(R_cur_prev)
    src, front = project_points(camera, rays)
    src[~front] = -1.0
    map_x = src[:, 0].reshape(h, w).astype(np.float32)
    map_y = src[:, 1].reshape(h, w).astype(np.float32)
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
