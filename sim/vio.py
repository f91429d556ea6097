"""Built-in simulator for the VIO (OpenVINS-style): tracks and IMU without images.

A room of random landmarks (walls, floor, ceiling), a smooth trajectory with analytic
derivatives, a camera through :func:`common.camera.camera_model` (default :data:`EUROC_CAMERA`,
the generator's EuRoC cam0 preset), persistent track ids with robot-like keyframes
(new tracks start only on keyframes, as ORB runs only there), and 200 Hz IMU with EuRoC
ADIS16448 white noise and bias random walk. Deterministic per seed.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from common.calibration import EUROC_IMU, CameraCalibration, ImuCalibration
from common.camera import camera_model
from common.data.synth.cameras import camera_preset
from common.geometry import inverse_T, umeyama_alignment
from services.edge.vio.types import FrameObservation, FrameResult

if TYPE_CHECKING:
    from services.edge.vio.manager import VioManager
    from services.edge.vio.state import PinholeUndistorter, VioMap

EUROC_CAMERA = camera_preset("euroc").calibration(20.0)
"""EuRoC cam0 at 20 Hz: the synthetic generator's preset (:mod:`common.data.synth.cameras`:
intrinsics, distortion and EuRoC's ``T_body_cam``, body = IMU frame)."""


@dataclass(frozen=True)
class SimConfig:
    """Synthetic sequence parameters (defaults: a 20 s EuRoC-like hand-held/MAV motion)."""

    duration_s: float = 20.0
    camera_rate_hz: float = 20.0
    imu_rate_hz: float = 200.0
    n_landmarks: int = 3000
    room_half_size_m: float = 5.0
    room_height_m: float = 3.5
    max_features: int = 150
    keyframe_interval_s: float = 0.25  # robot keyframe at least this often
    keyframe_track_ratio: float = 0.6  # or when fewer of the last keyframe's tracks survive
    track_drop_prob: float = 0.01  # per frame, LK failure
    pixel_noise_px: float = 0.5
    outlier_ratio: float = 0.0  # share of observations per frame displaced by 5–30 px (bad LK)
    motion_amplitude_m: tuple[float, float, float] = (1.2, 0.9, 0.3)
    motion_freq_rad_s: tuple[float, float, float] = (0.6, 0.8, 1.1)
    yaw_rate_rad_s: float = 0.15
    attitude_swing: float = 1.0  # scales the yaw, pitch and roll oscillations (a MAV: ~4)
    bias_gyro: tuple[float, float, float] = (0.003, -0.002, 0.004)
    bias_accel: tuple[float, float, float] = (0.02, -0.015, 0.03)
    seed: int = 0


@dataclass(frozen=True, eq=False)
class SimSequence:
    """Frames (time order), IMU ``imu_timestamps_ns`` (K,), ``gyro``/``accel`` (K, 3), and
    ground truth at frame times: ``T_world_body`` (N, 4, 4), ``v_world`` (N, 3)."""

    frames: tuple[FrameObservation, ...]
    imu_timestamps_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    gt_timestamps_ns: np.ndarray
    gt_T_world_body: np.ndarray
    gt_v_world: np.ndarray
    landmarks_world: np.ndarray
    camera: CameraCalibration
    imu: ImuCalibration

    def feed(self) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, FrameObservation]]:
        """Yield ``(imu_t, gyro, accel, frame)``: the IMU samples up to each frame, then it."""
        j = 0
        for fr in self.frames:
            k = int(np.searchsorted(self.imu_timestamps_ns, fr.timestamp_ns, side="right"))
            yield self.imu_timestamps_ns[j:k], self.gyro[j:k], self.accel[j:k], fr
            j = k


def _rot(axis: int, a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((*np.shape(a), 3, 3))
    i, j = [(1, 2), (0, 2), (0, 1)][axis]
    R[..., axis, axis] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s if axis != 1 else s
    R[..., j, i] = s if axis != 1 else -s
    return R


_R0 = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])  # body x up, body z fwd


def trajectory(
    t: np.ndarray, o: SimConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Analytic state at times ``t`` (K,) s: R_world_body (K,3,3), p (K,3), v (K,3),
    a_world (K,3), omega_body (K,3)."""
    A = np.array(o.motion_amplitude_m)
    w = np.array(o.motion_freq_rad_s)
    phi = np.array([0.0, 0.7, 1.9])
    arg = t[:, None] * w + phi
    p = np.array([0.0, 0.0, 1.5]) + A * np.sin(arg)
    v = A * w * np.cos(arg)
    acc = -A * w**2 * np.sin(arg)
    k = o.attitude_swing
    yaw = o.yaw_rate_rad_s * t + k * 0.6 * np.sin(0.35 * t)
    dyaw = o.yaw_rate_rad_s + k * 0.6 * 0.35 * np.cos(0.35 * t)
    pitch = k * 0.08 * np.sin(1.7 * t)
    dpitch = k * 0.08 * 1.7 * np.cos(1.7 * t)
    roll = k * 0.1 * np.sin(1.3 * t)
    droll = k * 0.1 * 1.3 * np.cos(1.3 * t)
    Rz, Ry, Rx = _rot(2, yaw), _rot(1, pitch), _rot(0, roll)
    R = Rz @ Ry @ Rx @ _R0
    ez, ey, ex = np.eye(3)[2], np.eye(3)[1], np.eye(3)[0]
    w_world = (
        dyaw[:, None] * ez
        + np.einsum("kij,j->ki", Rz, ey) * dpitch[:, None]
        + np.einsum("kij,j->ki", Rz @ Ry, ex) * droll[:, None]
    )
    w_body = np.einsum("kji,kj->ki", R, w_world)
    return R, p, v, acc, w_body


def _landmarks(o: SimConfig, rng: np.random.Generator) -> np.ndarray:
    n = o.n_landmarks
    h, H = o.room_half_size_m, o.room_height_m
    n_walls = int(0.75 * n)
    side = rng.integers(0, 4, n_walls)
    u = rng.uniform(-h, h, n_walls)
    z = rng.uniform(0.0, H, n_walls)
    walls = np.zeros((n_walls, 3))
    walls[:, 2] = z
    walls[side == 0, 0], walls[side == 0, 1] = h, u[side == 0]
    walls[side == 1, 0], walls[side == 1, 1] = -h, u[side == 1]
    walls[side == 2, 1], walls[side == 2, 0] = h, u[side == 2]
    walls[side == 3, 1], walls[side == 3, 0] = -h, u[side == 3]
    walls[:, :2] += rng.normal(0, 0.1, (n_walls, 2))  # some relief
    n_fc = n - n_walls
    fc = np.c_[rng.uniform(-h, h, (n_fc, 2)), np.where(rng.random(n_fc) < 0.5, 0.0, H)]
    return np.vstack([walls, fc])


def simulate(
    options: SimConfig | None = None,
    camera: CameraCalibration = EUROC_CAMERA,
    imu: ImuCalibration = EUROC_IMU,
) -> SimSequence:
    """Generate one synthetic sequence (deterministic per ``options.seed``)."""
    o = options or SimConfig()
    # One stream per component: a shorter sequence is a prefix of a longer one (same seed).
    rng_lm, rng_g, rng_a, rng_bg, rng_ba, rng = (
        np.random.default_rng([o.seed, k]) for k in range(6)
    )
    lm = _landmarks(o, rng_lm)
    # ---------------------------------------------------------------- IMU
    dt_imu = 1.0 / o.imu_rate_hz
    t_imu = np.arange(0.0, o.duration_s + 0.1, dt_imu)
    R, _, _, acc, w_body = trajectory(t_imu, o)
    g = np.array([0.0, 0.0, -9.81])
    f_body = np.einsum("kji,kj->ki", R, acc - g)
    sq = np.sqrt(o.imu_rate_hz)
    k = len(t_imu)
    bg = np.array(o.bias_gyro) + np.cumsum(
        rng_bg.normal(0, imu.gyro_random_walk * np.sqrt(dt_imu), (k, 3)), axis=0
    )
    ba = np.array(o.bias_accel) + np.cumsum(
        rng_ba.normal(0, imu.accel_random_walk * np.sqrt(dt_imu), (k, 3)), axis=0
    )
    gyro = w_body + bg + rng_g.normal(0, imu.gyro_noise_density * sq, (k, 3))
    accel = f_body + ba + rng_a.normal(0, imu.accel_noise_density * sq, (k, 3))
    imu_ns = np.round(t_imu * 1e9).astype(np.int64)
    # ---------------------------------------------------------------- frames
    t_cam = np.arange(0.05, o.duration_s, 1.0 / o.camera_rate_hz)
    Rc, pc, vc, _, _ = trajectory(t_cam, o)
    T_wb = np.tile(np.eye(4), (len(t_cam), 1, 1))
    T_wb[:, :3, :3] = Rc
    T_wb[:, :3, 3] = pc
    T_bc = np.array(camera.T_body_cam)
    level_of = rng.choice(4, size=len(lm), p=[0.5, 0.25, 0.15, 0.1]).astype(np.uint8)
    desc_of = rng.integers(0, 256, (len(lm), 32), dtype=np.uint8)
    active: dict[int, int] = {}  # landmark -> track id
    next_track = 0
    last_kf_t = -1e9
    last_kf_tracks: set[int] = set()
    frames = []
    margin = 10.0
    model = camera_model(camera)
    for i, t in enumerate(t_cam):
        T_cw = inverse_T(T_wb[i] @ T_bc)
        p_c = lm @ T_cw[:3, :3].T + T_cw[:3, 3]
        z = p_c[:, 2]
        uv = model.project(p_c)
        vis = (
            (z > 0.2)
            & (uv[:, 0] > margin)
            & (uv[:, 0] < camera.width - margin)
            & (uv[:, 1] > margin)
            & (uv[:, 1] < camera.height - margin)
        )
        for li in list(active):
            if not vis[li] or rng.random() < o.track_drop_prob:
                del active[li]
        surviving = len(last_kf_tracks & set(active.values()))
        is_kf = (t - last_kf_t >= o.keyframe_interval_s - 1e-9) or (
            surviving < o.keyframe_track_ratio * max(len(last_kf_tracks), 1)
        )
        if is_kf:
            free = np.flatnonzero(vis & ~np.isin(np.arange(len(lm)), list(active)))
            need = o.max_features - len(active)
            if need > 0 and len(free):
                for li in rng.choice(free, size=min(need, len(free)), replace=False):
                    active[int(li)] = next_track
                    next_track += 1
            last_kf_t = t
            last_kf_tracks = set(active.values())
        lms = np.array(sorted(active), dtype=np.int64)
        levels = level_of[lms]
        noise = rng.normal(0, 1, (len(lms), 2)) * (o.pixel_noise_px * 1.2 ** levels[:, None])
        if o.outlier_ratio > 0:
            bad = rng.random(len(lms)) < o.outlier_ratio
            ang = rng.uniform(0, 2 * np.pi, bad.sum())
            mag = rng.uniform(5.0, 30.0, bad.sum())
            noise[bad] += np.c_[np.cos(ang), np.sin(ang)] * mag[:, None]
        frames.append(
            FrameObservation(
                timestamp_ns=round(t * 1e9),
                track_ids=np.array([active[int(li)] for li in lms], dtype=np.int64),
                keypoints_px=uv[lms] + noise,
                levels=levels,
                is_keyframe=bool(is_kf),
                descriptors=desc_of[lms] if is_kf else None,
            )
        )
    return SimSequence(
        frames=tuple(frames),
        imu_timestamps_ns=imu_ns,
        gyro=gyro,
        accel=accel,
        gt_timestamps_ns=np.round(t_cam * 1e9).astype(np.int64),
        gt_T_world_body=T_wb,
        gt_v_world=vc,
        landmarks_world=lm,
        camera=camera,
        imu=imu,
    )


def ate_rmse(est: np.ndarray, gt: np.ndarray, with_scale: bool = False) -> tuple[float, float]:
    """ATE RMSE [m] of positions (N, 3) after SE(3) (or Sim(3)) alignment, and the Sim(3)
    scale factor (1 + scale error)."""
    R, t, s = umeyama_alignment(est, gt, with_scale)
    err = gt - (s * est @ R.T + t)
    _, _, s_sim = umeyama_alignment(est, gt, True)
    return float(np.sqrt((err**2).sum(1).mean())), s_sim


def ground_truth_map(
    seq: SimSequence, max_keyframes: int, bias_from_options: SimConfig
) -> tuple[VioMap, PinholeUndistorter]:
    """A :class:`VioMap` built from the sequence's robot keyframes at their true states
    (poses, velocities, initial biases), points triangulated from the noisy tracks.
    For tests of the back end in isolation."""
    from common.imu import ImuBuffer
    from services.edge.vio.local_mapping import associate_keyframe, triangulate_new_points
    from services.edge.vio.state import Keyframe, PinholeUndistorter, VioMap
    from services.edge.vio.types import MappingConfig

    cam = PinholeUndistorter(seq.camera)
    buf = ImuBuffer()
    buf.append(seq.imu_timestamps_ns, seq.gyro, seq.accel)
    vmap = VioMap(0)
    mopt = MappingConfig()
    prev = None
    kf_frames = [i for i, f in enumerate(seq.frames) if f.is_keyframe][:max_keyframes]
    for k, i in enumerate(kf_frames):
        f = seq.frames[i]
        seg = None if prev is None else buf.segment(prev.timestamp_ns, f.timestamp_ns)
        kf = Keyframe(
            id=k,
            timestamp_ns=f.timestamp_ns,
            T_world_body=seq.gt_T_world_body[i].copy(),
            track_ids=f.track_ids,
            xy=cam.normalise(f.keypoints_px),
            sigma=1.2 ** f.levels.astype(float) / cam.focal,
            keypoints_px=f.keypoints_px,
            levels=f.levels,
            descriptors=f.descriptors,
            previous_id=None if prev is None else prev.id,
            imu_from_previous=seg,
        )
        kf.v_world = seq.gt_v_world[i].copy()
        kf.bias_accel = np.array(bias_from_options.bias_accel)
        kf.bias_gyro = np.array(bias_from_options.bias_gyro)
        vmap.add_keyframe(kf)
        associate_keyframe(vmap, kf, cam, mopt)
        triangulate_new_points(vmap, kf, cam, mopt)
        prev = kf
    return vmap, cam


@dataclass(frozen=True)
class RunMetrics:
    """Accuracy of one run on a synthetic sequence (the latest map only).

    ``ate_frames_m``: real-time per-frame poses of TRACKING frames, SE(3)-aligned;
    ``ate_keyframes_m``: final keyframe poses after all optimisation, SE(3)-aligned;
    ``scale_*``: Sim(3) scale factor (1 = perfect metric scale)."""

    n_frames: int
    n_tracking: int
    n_maps: int
    ate_frames_m: float
    scale_frames: float
    ate_keyframes_m: float
    scale_keyframes: float


def run_sequence(manager: VioManager, seq: SimSequence) -> list[FrameResult]:
    """Feed a sequence to a VioManager; returns its FrameResults."""
    out = []
    for t, gyro, accel, frame in seq.feed():
        manager.feed_imu(t, gyro, accel)
        out.append(manager.feed_frame(frame))
    return out


def evaluate_run(manager: VioManager, results: list[FrameResult], seq: SimSequence) -> RunMetrics:
    """ATE and scale of a finished run against the sequence's ground truth."""
    from services.edge.vio.types import TrackingStatus

    last_map = results[-1].map_id
    idx = [
        i
        for i, r in enumerate(results)
        if r.status == TrackingStatus.TRACKING and r.map_id == last_map
    ]
    nan = float("nan")
    ate_f, s_f = nan, nan
    if len(idx) >= 3:
        est = np.array([results[i].T_world_body[:3, 3] for i in idx])
        ate_f, s_f = ate_rmse(est, seq.gt_T_world_body[idx, :3, 3])
    ate_k, s_k = nan, nan
    vmap = manager.current_map
    if vmap is not None and vmap.vi_initialized:
        row = {int(t): i for i, t in enumerate(seq.gt_timestamps_ns)}
        kfs = vmap.keyframe_list()
        est = np.array([kf.T_world_body[:3, 3] for kf in kfs])
        ate_k, s_k = ate_rmse(est, seq.gt_T_world_body[[row[k.timestamp_ns] for k in kfs], :3, 3])
    return RunMetrics(
        n_frames=len(results),
        n_tracking=len(idx),
        n_maps=len({r.map_id for r in results}),
        ate_frames_m=ate_f,
        scale_frames=s_f,
        ate_keyframes_m=ate_k,
        scale_keyframes=s_k,
    )
