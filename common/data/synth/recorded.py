"""Recorded flights: fly a ground truth from a file (``recslam dataset synth --trajectory FILE``).

Input: TUM (``t x y z qx qy qz qw``, seconds, whitespace separated) or EuRoC
``state_groundtruth_estimate0/data.csv`` (``t[ns], p, q_wxyz, ...``, comma separated),
detected from the first data line (a comma means EuRoC); a malformed file raises
:class:`~common.data.synth.trajectory.TrajectoryError` naming the file and line. The poses are
taken as the body (IMU) frame in a world with z up (gravity along -z), as EuRoC's are.

Smoothing (the method): each position coordinate and each quaternion component (signs made
continuous first) is fitted by a quintic smoothing spline (FITPACK ``UnivariateSpline``,
``k = 5``) with smoothing factor ``s = N * sigma^2`` (``sigma_p`` = 5 mm, ``sigma_q`` = 0.002),
so the fit stays within about sigma of the samples while recorder noise is not differentiated
into the IMU. Flown with the IMU recorded on the flight (``--imu``), nothing is differentiated
and the images must show the measured motion: ``sigma_p`` = 0.5 mm, ``sigma_q`` = 0.0002.
Position, velocity and acceleration are the spline and its derivatives (C4); the attitude is
the normalised quaternion spline and the body rate ``omega = 2 Im(q* dq/dt)`` of that
normalised curve, so the IMU derived from the smoothed motion integrates back to the smoothed
ground truth (which is what the dataset's ground truth then holds).

Placement: all files of one dataset share one shift (so recordings made in one frame keep
their overlap): the centre of their positions' bounding box goes to the centre of the world's
flight region (per axis; to the room's centre along an axis where they are larger than the
region); a flight that does not fit (extent, or clearance from walls and boxes) is refused
with the reason.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.interpolate import UnivariateSpline

from common.data.synth.scene import Scene
from common.data.synth.trajectory import (
    T_IMU_CAM,
    Region,
    TrajectoryConfig,
    TrajectoryError,
    TrajectoryState,
    check_trajectory,
    continuous_quaternions,
)
from common.errors import RecslamError
from common.geometry import quat_wxyz_to_R

logger = logging.getLogger(__name__)

SIGMA_P_M = 0.005
SIGMA_Q = 0.002
# With the IMU recorded on the flight the images must show the motion that IMU measured: the
# smoothing above takes out real motion (V2_01: the accelerometer's 0.5 s velocity changes
# are 16 % larger than the 5 mm spline's; the gyro disagrees with the 0.002 attitude spline
# by 10.5 mrad rms per frame pair, with the recording itself by 1-2.4 mrad). Smooth at the
# recorder's own noise instead (Vicon: sub-millimetre, ~0.5 mrad): 0.5 mm, 0.0002.
SIGMA_P_RECORDED_IMU_M = 0.0005
SIGMA_Q_RECORDED_IMU = 0.0002


def smoothing(sigma_p: float, sigma_q: float) -> str:
    """The smoothing's description in ``dataset.json``."""
    return (
        f"quintic smoothing spline per coordinate and quaternion component (FITPACK, k=5, "
        f"s=N*sigma^2, sigma_p={sigma_p} m, sigma_q={sigma_q})"
    )


SMOOTHING = smoothing(SIGMA_P_M, SIGMA_Q)

RECORDED_LIMITS = TrajectoryConfig(max_speed=4.0, max_rate=6.0)
"""Limits a recorded flight is checked against: the clearance of the default flights, and
speeds and rates far above EuRoC's (about 2.3 m/s and 2.7 rad/s) so only nonsense fails."""


@dataclass(frozen=True)
class Recording:
    """Poses read from ``source`` (format ``"tum"`` or ``"euroc"``): ``t`` (N,) [s] from the
    first pose, ``p`` (N, 3) [m], ``q_wxyz`` (N, 4) unit, signs continuous."""

    source: str
    format: str
    t: np.ndarray = field(repr=False)
    p: np.ndarray = field(repr=False)
    q_wxyz: np.ndarray = field(repr=False)


def detect_format(path: Path) -> str:
    """``"euroc"`` when the first data line holds a comma, else ``"tum"``."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise TrajectoryError(f"--trajectory {path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise TrajectoryError(f"--trajectory {path}: cannot read it ({exc})") from None
    for line in text.splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            return "euroc" if "," in line else "tum"
    raise TrajectoryError(f"--trajectory {path}: no poses (empty or only comments)")


def read_recording(path: Path | str) -> Recording:
    """Read a TUM or EuRoC ground-truth file (see the module docstring)."""
    from common.data.euroc import read_groundtruth
    from common.evaluation.tum import read_tum

    p = Path(path)
    fmt = detect_format(p)
    try:
        if fmt == "euroc":
            gt = read_groundtruth(p)
            ts, pos, q = gt.timestamps_ns, gt.p_world_body, gt.q_world_body_wxyz
        else:
            tr = read_tum(p)
            ts, pos, q = tr.timestamps_ns, tr.p_world_body, tr.q_wxyz
    except RecslamError as exc:
        raise TrajectoryError(f"--trajectory: {exc}") from None
    if len(ts) < 8:
        raise TrajectoryError(f"--trajectory {p}: {len(ts)} poses; a flight needs at least 8")
    q = np.asarray(q, float)
    q = continuous_quaternions(q / np.linalg.norm(q, axis=1, keepdims=True))
    t = (np.asarray(ts, np.int64) - int(ts[0])) * 1e-9
    return Recording(str(p), fmt, t, np.asarray(pos, float), q)


def _fit(t: np.ndarray, y: np.ndarray, sigma: float) -> UnivariateSpline:
    return UnivariateSpline(t, y, k=5, s=len(t) * sigma**2)


@dataclass(frozen=True, eq=False)
class RecordedFlight:
    """A smoothed recording shifted by ``offset`` [m] (see the module docstring)."""

    source: str
    format: str
    duration_s: float
    offset: tuple[float, float, float]
    _pos: tuple[UnivariateSpline, ...] = field(repr=False)
    _quat: tuple[UnivariateSpline, ...] = field(repr=False)
    T_imu_cam: tuple[tuple[float, ...], ...] = tuple(map(tuple, T_IMU_CAM))
    smoothing: str = SMOOTHING

    @classmethod
    def fit(
        cls,
        rec: Recording,
        offset: np.ndarray,
        sigma_p: float = SIGMA_P_M,
        sigma_q: float = SIGMA_Q,
    ) -> RecordedFlight:
        pos = tuple(_fit(rec.t, rec.p[:, i], sigma_p) for i in range(3))
        quat = tuple(_fit(rec.t, rec.q_wxyz[:, i], sigma_q) for i in range(4))
        off = (float(offset[0]), float(offset[1]), float(offset[2]))
        how = smoothing(sigma_p, sigma_q)
        return cls(rec.source, rec.format, float(rec.t[-1]), off, pos, quat, smoothing=how)

    def evaluate(self, t: np.ndarray) -> TrajectoryState:
        """State of the smoothed flight at ``t`` (K,) [s] (time 0 = the file's first pose)."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        p = np.stack([s(t) for s in self._pos], axis=1) + np.asarray(self.offset)
        v = np.stack([s(t, 1) for s in self._pos], axis=1)
        a = np.stack([s(t, 2) for s in self._pos], axis=1)
        q = np.stack([s(t) for s in self._quat], axis=1)
        dq = np.stack([s(t, 1) for s in self._quat], axis=1)
        n = np.linalg.norm(q, axis=1, keepdims=True)
        qn = q / n
        dqn = dq / n - qn * np.einsum("ij,ij->i", qn, dq)[:, None] / n
        # omega_body = 2 Im(conj(qn) * dqn) for q_world_body (Hamilton, wxyz).
        w, xyz = qn[:, :1], qn[:, 1:]
        dw, dxyz = dqn[:, :1], dqn[:, 1:]
        omega = 2.0 * (w * dxyz - dw * xyz - np.cross(xyz, dxyz))
        return TrajectoryState(t, p, v, a, quat_wxyz_to_R(qn), omega)

    def describe(self) -> dict[str, Any]:
        """What ``dataset.json`` records of this flight."""
        return {
            "family": "recorded",
            "source": self.source,
            "format": self.format,
            "duration_s": self.duration_s,
            "offset": list(self.offset),
            "smoothing": self.smoothing,
        }


def _clearest_offset(
    scene: Scene,
    recs: list[Recording],
    seconds: float,
    centred: np.ndarray,
    limits: TrajectoryConfig,
    reach_m: float = 1.0,
    step_m: float = 0.1,
) -> np.ndarray:
    """``centred`` when the flights keep ``limits.min_clearance_m`` (plus 5 cm for the
    smoothing) there, else the shift within ``reach_m`` of it (grid of ``step_m``, the
    room's floor and ceiling bounding z) that keeps the largest clearance from walls and
    furniture: a room of the right size whose table sits under one flight's low pass still
    takes the flights, moved aside, as a real team would fly around it."""
    samples = []
    for rec in recs:
        sel = rec.t <= seconds + 1e-6
        sel[sel] = np.arange(int(sel.sum())) % 10 == 0  # 20 Hz of a 200 Hz ground truth
        R = quat_wxyz_to_R(rec.q_wxyz[sel])
        samples += [rec.p[sel], rec.p[sel] + R @ T_IMU_CAM[:3, 3]]
    pts = np.concatenate(samples)

    def clearance(offsets: np.ndarray, p: np.ndarray) -> np.ndarray:
        return np.array([scene.clearance(p + o).min() for o in offsets])

    want = limits.min_clearance_m + 0.05
    if clearance(centred[None], pts)[0] >= want:
        return centred
    g = np.arange(-reach_m, reach_m + 1e-9, step_m)
    dz = np.arange(-0.3, 0.3 + 1e-9, step_m)
    grid = np.stack(np.meshgrid(g, g, dz, indexing="ij"), axis=-1).reshape(-1, 3) + centred
    grid = grid[np.argsort(np.linalg.norm(grid - centred, axis=1), kind="stable")]
    # A coarse pass on the poses every second, then the best few on all of them.
    best = grid[np.argsort(-clearance(grid, pts[::20]), kind="stable")[:20]]
    return best[int(np.argmax(clearance(best, pts)))]


def recorded_flights(
    scene: Scene,
    region: Region,
    files: tuple[str, ...],
    seconds: float,
    world: str,
    limits: TrajectoryConfig = RECORDED_LIMITS,
    recorded_imu: bool = False,
) -> list[RecordedFlight]:
    """The recordings in ``files`` (one per robot), smoothed (at the recorder's noise with
    ``recorded_imu``: the images then show the motion the recorded IMU measured), shifted into
    ``region`` by one common offset and checked over ``[0, seconds]``; TrajectoryError says
    why one cannot fly."""
    recs = [read_recording(f) for f in files]
    for rec in recs:
        if rec.t[-1] < seconds - 1e-6:
            raise TrajectoryError(
                f"--trajectory {rec.source}: lasts {rec.t[-1]:.2f} s, less than --seconds "
                f"{seconds:g}: fly it shorter"
            )
    inside = [rec.p[rec.t <= seconds + 1e-6] for rec in recs]
    lo = np.min([p.min(axis=0) for p in inside], axis=0)
    hi = np.max([p.max(axis=0) for p in inside], axis=0)
    r_lo, r_hi = np.array(region[0], float), np.array(region[1], float)
    room_lo, room_hi = np.array(scene.room_lo, float), np.array(scene.room_hi, float)
    need = hi - lo + 2.0 * limits.min_clearance_m
    if np.any(need > room_hi - room_lo):
        span = np.round(hi - lo, 2).tolist()
        raise TrajectoryError(
            f"--trajectory {', '.join(files)}: the flights span {span} m; with "
            f"{limits.min_clearance_m} m clearance they do not fit the {world} world "
            f"({np.round(room_hi - room_lo, 2).tolist()} m): try --world hall"
        )
    # Per axis: the flight region's centre where the flights fit it, else the room's.
    fits = need + 0.25 <= r_hi - r_lo  # 0.25 m: the camera sits off the body, splines overshoot
    target = np.where(fits, (r_lo + r_hi) / 2.0, (room_lo + room_hi) / 2.0)
    offset = _clearest_offset(scene, recs, seconds, target - (lo + hi) / 2.0, limits)
    sigmas = (
        (SIGMA_P_RECORDED_IMU_M, SIGMA_Q_RECORDED_IMU) if recorded_imu else (SIGMA_P_M, SIGMA_Q)
    )
    flights = [RecordedFlight.fit(rec, offset, *sigmas) for rec in recs]
    for f in flights:
        why = check_trajectory(scene, f, seconds, limits)
        if why is not None:
            raise TrajectoryError(
                f"--trajectory {f.source}: recentred by {np.round(offset, 2).tolist()} m, the "
                f"flight does not fit the {world} world: {why}"
                + ("" if world == "hall" else "; the hall world fits it (--world hall)")
            )
        logger.info("recorded flight %s (%s) shifted by %s m", f.source, f.format, offset)
    return flights
