"""Map state of one robot's VIO: keyframes, map points and their observations.

A map point is born from one robot track, so its id is that track id (unique within a map).
Observations are stored as undistorted normalised image coordinates ``xy = (X/Z, Y/Z)`` of the
camera frame, with the pixel noise sigma converted to those units.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from common.calibration import CameraCalibration
from common.camera import camera_model
from common.geometry import inverse_T
from common.imu import ImuSegment
from services.edge.vio.types import KeyframeSnapshot, MapPointBatch


class PinholeUndistorter:
    """Distorted pixels -> undistorted normalised coordinates through the calibration's camera
    model (:func:`common.camera.camera_model`, any distortion model), plus the extrinsic."""

    def __init__(self, camera: CameraCalibration) -> None:
        self.camera = camera
        self.model = camera_model(camera)
        self.K = camera.K
        self.focal = 0.5 * (camera.fx + camera.fy)
        self.T_body_cam = np.array(camera.T_body_cam)
        self.T_cam_body = inverse_T(self.T_body_cam)

    def normalise(self, keypoints_px: np.ndarray) -> np.ndarray:
        """(N, 2) distorted px -> (N, 2) undistorted normalised coordinates (NaN for pixels
        whose ray is not in front of the camera, possible with a fisheye)."""
        if len(keypoints_px) == 0:
            return np.zeros((0, 2))
        return self.model.pixels_to_normalized(np.asarray(keypoints_px, dtype=np.float64))


def _scatter(values: np.ndarray, rows: np.ndarray, n: int, fill: int) -> np.ndarray:
    """(n,) int64 array holding ``values`` (K,) at ``rows`` (K,) and ``fill`` elsewhere."""
    out = np.full(n, fill, np.int64)
    out[rows] = values
    return out


def project(
    T_world_body: np.ndarray, T_body_cam: np.ndarray, p_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) -> normalised coordinates (N, 2) and camera depths (N,)."""
    T_cam_world = inverse_T(T_world_body @ T_body_cam)
    p_cam = p_world @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    z = p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = p_cam[:, :2] / z[:, None]
    return xy, z


@dataclass(eq=False)
class Keyframe:
    """A keyframe: state (``T_world_body`` (4, 4), ``v_world`` (3,), biases (3,)) and features.

    ``xy`` (N, 2) normalised undistorted; ``sigma`` (N,) noise in normalised units;
    ``imu_from_previous`` covers ``[previous.timestamp, timestamp]``. ``robot_rows`` (N,): the
    row of each feature in the robot's keyframe when the VIO left some out (a fisheye's
    features at 90 degrees or more off axis), None when it kept all in order;
    ``n_robot_rows`` the robot keyframe's feature count then. Rows that leave the VIO (the
    snapshot's ``point_ids``, a point batch's ``feature_indices``) are the robot's rows.
    """

    id: int
    timestamp_ns: int
    T_world_body: np.ndarray
    track_ids: np.ndarray
    xy: np.ndarray
    sigma: np.ndarray
    keypoints_px: np.ndarray
    levels: np.ndarray
    descriptors: np.ndarray | None
    previous_id: int | None
    imu_from_previous: ImuSegment | None
    v_world: np.ndarray = field(default_factory=lambda: np.zeros(3))
    bias_gyro: np.ndarray = field(default_factory=lambda: np.zeros(3))
    bias_accel: np.ndarray = field(default_factory=lambda: np.zeros(3))
    row_of: dict[int, int] = field(default_factory=dict)
    robot_rows: np.ndarray | None = None
    n_robot_rows: int = 0

    def __post_init__(self) -> None:
        self.row_of = {int(t): i for i, t in enumerate(self.track_ids)}

    def robot_row(self, row: int) -> int:
        """The robot's row of this keyframe's feature ``row``."""
        return row if self.robot_rows is None else int(self.robot_rows[row])


@dataclass(eq=False)
class MapPoint:
    """``p_world`` (3,); ``observations`` keyframe id -> feature row in that keyframe;
    ``descriptor`` (32,) uint8 ORB of its first keyframe observation with one; ``tracks`` the
    robot track ids bound to it (its birth track, plus tracks matched to it later)."""

    id: int
    p_world: np.ndarray
    observations: dict[int, int] = field(default_factory=dict)
    descriptor: np.ndarray | None = None
    tracks: set[int] = field(default_factory=set)


class VioMap:
    """One map of one robot (a new one starts after tracking loss)."""

    def __init__(self, map_id: int) -> None:
        self.map_id = map_id
        self.keyframes: dict[int, Keyframe] = {}  # insertion order = time order
        self.points: dict[int, MapPoint] = {}
        self.vi_initialized = False
        self.vi_init_runs = 0
        self.last_vi_attempt_ns: int | None = None
        self.vi_time_offset_ns = 0  # camera-IMU offset of its last VI initialisation / refinement
        self.banned_tracks: set[int] = set()
        self.track_point: dict[int, int] = {}  # robot track id -> map point id
        self._dirty_keyframes: set[int] = set()
        self._dirty_points: set[int] = set()
        self._removed_points: set[int] = set()

    # ------------------------------------------------------------------ access
    @property
    def first_timestamp_ns(self) -> int:
        return next(iter(self.keyframes.values())).timestamp_ns

    def keyframe_list(self) -> list[Keyframe]:
        return list(self.keyframes.values())

    def point_of(self, track_id: int) -> MapPoint | None:
        """The map point a track is bound to, if any."""
        pid = self.track_point.get(int(track_id))
        return None if pid is None else self.points.get(pid)

    def last_keyframe(self) -> Keyframe | None:
        return next(reversed(self.keyframes.values())) if self.keyframes else None

    # ------------------------------------------------------------------ edits
    def add_keyframe(self, kf: Keyframe) -> None:
        self.keyframes[kf.id] = kf
        self._dirty_keyframes.add(kf.id)

    def add_point(self, point: MapPoint) -> None:
        """Add a point born from track ``point.id``."""
        self.points[point.id] = point
        point.tracks.add(point.id)
        self.track_point[point.id] = point.id
        self._dirty_points.add(point.id)
        self._removed_points.discard(point.id)

    def bind_track(self, track_id: int, point_id: int) -> None:
        """Bind another track (e.g. a re-detection matched by descriptor) to a point."""
        self.track_point[int(track_id)] = point_id
        self.points[point_id].tracks.add(int(track_id))
        self._dirty_points.add(point_id)

    def remove_point(self, point_id: int, ban: bool = False) -> None:
        mp = self.points.pop(point_id, None)
        if mp is not None:
            for t in mp.tracks:
                if self.track_point.get(t) == point_id:
                    del self.track_point[t]
            self._removed_points.add(point_id)
            self._dirty_points.discard(point_id)
        if ban:
            self.banned_tracks.add(point_id)

    def remove_observation(self, point_id: int, keyframe_id: int) -> None:
        mp = self.points.get(point_id)
        if mp is not None:
            mp.observations.pop(keyframe_id, None)
            self._dirty_points.add(point_id)

    def mark_dirty(
        self, keyframe_ids: list[int] | None = None, point_ids: list[int] | None = None
    ) -> None:
        self._dirty_keyframes.update(keyframe_ids or [])
        self._dirty_points.update(pid for pid in (point_ids or []) if pid in self.points)

    def mark_all_dirty(self) -> None:
        self.mark_dirty(list(self.keyframes), list(self.points))

    def transform(self, T_new_old: np.ndarray, scale: float) -> None:
        """Apply ``p_new = scale * R p_old + t`` to the whole map (VI initialisation)."""
        R, t = T_new_old[:3, :3], T_new_old[:3, 3]
        for kf in self.keyframes.values():
            T = kf.T_world_body.copy()
            T[:3, :3] = R @ T[:3, :3]
            T[:3, 3] = scale * (R @ T[:3, 3]) + t
            kf.T_world_body = T
            kf.v_world = scale * (R @ kf.v_world)
        for mp in self.points.values():
            mp.p_world = scale * (R @ mp.p_world) + t
        self.mark_all_dirty()

    # ------------------------------------------------------------------ snapshots
    def keyframe_snapshot(self, kf: Keyframe) -> KeyframeSnapshot:
        ids = []
        for t in kf.track_ids.tolist():
            mp = self.point_of(t)
            ids.append(mp.id if mp is not None and kf.id in mp.observations else -1)
        point_ids = np.array(ids, dtype=np.int64)
        track_ids = kf.track_ids.copy()
        if kf.robot_rows is not None:  # in the robot's rows: -1 where the VIO left one out
            point_ids = _scatter(point_ids, kf.robot_rows, kf.n_robot_rows, -1)
            track_ids = _scatter(track_ids, kf.robot_rows, kf.n_robot_rows, -1)
        return KeyframeSnapshot(
            keyframe_id=kf.id,
            map_id=self.map_id,
            timestamp_ns=kf.timestamp_ns,
            T_world_body=kf.T_world_body.copy(),
            v_world=kf.v_world.copy(),
            bias_gyro=kf.bias_gyro.copy(),
            bias_accel=kf.bias_accel.copy(),
            track_ids=track_ids,
            point_ids=point_ids,
            previous_keyframe_id=kf.previous_id,
            robot_keyframe=kf.descriptors is not None,
        )

    def point_batch(self, point_ids: list[int]) -> MapPointBatch:
        """These points (in order) as one flat :class:`MapPointBatch`."""
        pts = [self.points[p] for p in point_ids]
        n = len(pts)
        counts = np.fromiter((len(mp.observations) for mp in pts), np.int64, n)
        m = int(counts.sum())
        return MapPointBatch(
            point_ids=np.fromiter((mp.id for mp in pts), np.int64, n),
            p_world=np.array([mp.p_world for mp in pts], np.float64).reshape(n, 3),
            counts=counts,
            keyframe_ids=np.fromiter((k for mp in pts for k in mp.observations), np.int64, m),
            feature_indices=np.fromiter(
                (
                    self.keyframes[k].robot_row(r) if k in self.keyframes else r
                    for mp in pts
                    for k, r in mp.observations.items()
                ),
                np.int64,
                m,
            ),
        )

    def pop_changes(self) -> tuple[list[int], list[int], list[int]]:
        """(dirty keyframe ids, dirty point ids, removed point ids) since the last call."""
        kfs = [k for k in self._dirty_keyframes if k in self.keyframes]
        pts = [p for p in self._dirty_points if p in self.points]
        removed = sorted(self._removed_points)
        self._dirty_keyframes.clear()
        self._dirty_points.clear()
        self._removed_points.clear()
        return sorted(kfs), sorted(pts), removed
