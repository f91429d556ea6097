"""The robot's own pose as the edge sends it back: latency, the live TUM file (sans-I/O core).

The edge sends a :class:`~common.links.robot_edge.FramePose` for every frame its VIO
finished. :class:`PoseTrack` matches each with the moment the robot captured that frame
(:meth:`PoseTrack.captured`, on the same monotonic clock), so the latency it keeps is what a
user of the pose feels: camera frame taken -> its pose on the robot, through the uplink, the
edge's queue and VIO, and the downlink. :func:`tum_line` renders a pose as a TUM line
(``recslam robot --pose-out FILE.tum``: the robot's own map frame, as the cloud's corrections
moved it; frames without a metric pose are not written).

The cloud also says where the robot's map sits in its global map
(:class:`~common.links.robot_edge.MapPlacement`, ``T_global_map``, forwarded by the edge when it
changes; ROS' ``map -> odom``): :meth:`PoseTrack.on_placement` keeps the latest per map, and
each pose of a placed map also gets ``T_global_body = T_global_map T_map_body``
(``--global-pose-out``). The own-map pose is continuous; the global one jumps when a merge or
an optimisation moves the map.
"""

from __future__ import annotations

import logging
from collections import OrderedDict, deque
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from common.geometry import R_to_quat_wxyz
from common.links.robot_edge import (
    FramePose,
    MapPlacement,
    decode_map_placement,
    decode_pose,
    pose_status,
)
from common.protocol.errors import RemoteProtocolError

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class ReceivedPose:
    """One pose from the edge: the frame's camera time (ns), the edge map, the VIO's status
    (``FramePose.status``), ``T_map_body`` (4, 4) or None without a metric pose, and the
    latency [s] from the frame's capture to now (None if the capture is not known here); the
    global map its map is placed in and ``T_global_body`` (4, 4) (None until the cloud placed
    the map, or without a metric pose); and what the robot's input did to that frame
    (``flags``, see :data:`services.robot.core.FLAGS`: e.g. ``"imu_gap"`` when its IMU interval
    had a hole; empty when the input was clean)."""

    timestamp_ns: int
    map_id: int
    status: str
    T_map_body: np.ndarray | None
    latency_s: float | None
    global_map: int | None = None
    T_global_body: np.ndarray | None = None
    flags: frozenset[str] = frozenset()


class PoseTrack:
    """Capture times in, poses out, with their latencies (one robot, all its edge sessions).

    ``keep``: capture times remembered (the oldest are forgotten: a pose that comes later
    than that many frames has no latency); ``window``: the latencies the summary is over (the
    newest; a robot that runs for hours keeps a bounded history)."""

    def __init__(self, keep: int = 20_000, window: int = 100_000) -> None:
        self.keep = keep
        self.latest: ReceivedPose | None = None
        self.received = 0  # FramePose messages taken
        self.with_pose = 0  # ... that carried a metric pose
        self.rejected = 0  # malformed ones (logged, not retried)
        self.with_global = 0  # metric poses placed in the global map
        self.predicted = 0  # poses the robot predicted itself (frames the budget left out)
        self.placements: dict[int, tuple[int, np.ndarray]] = {}  # map -> (global map, T)
        self.latencies_s: deque[float] = deque(maxlen=window)
        # (camera time [ns], latency [s]) of the newest poses: recovery after an outage
        self.series: deque[tuple[int, float]] = deque(maxlen=min(window, 20_000))
        self._captured: OrderedDict[int, float] = OrderedDict()

    @property
    def pending(self) -> int:
        """Frames captured whose pose has not come back (of the ``keep`` newest)."""
        return len(self._captured)

    def captured(self, timestamp_ns: int, now_s: float) -> None:
        """The frame at camera time ``timestamp_ns`` was taken at ``now_s`` (monotonic s)."""
        self._captured[int(timestamp_ns)] = now_s
        while len(self._captured) > self.keep:
            self._captured.popitem(last=False)

    def forget(self, timestamp_ns: int) -> None:
        """The frame at ``timestamp_ns`` will not be sent (dropped): no pose will come back."""
        self._captured.pop(int(timestamp_ns), None)

    def on_pose(self, msg: FramePose, now_s: float) -> ReceivedPose | None:
        """The edge's pose of one frame, received at ``now_s``; None (logged, counted) if the
        message is malformed."""
        try:
            T = decode_pose(msg)
        except RemoteProtocolError as exc:
            self.rejected += 1
            logger.warning("pose of frame %d refused: %s", msg.timestamp_ns, exc)
            return None
        t_cap = self._captured.pop(int(msg.timestamp_ns), None)
        latency = None if t_cap is None else now_s - t_cap
        placed = self.placements.get(int(msg.map_id))
        global_map = T_global = None
        if placed is not None and T is not None:
            global_map, T_global = placed[0], placed[1] @ T
        pose = ReceivedPose(
            int(msg.timestamp_ns),
            int(msg.map_id),
            pose_status(msg),
            T,
            latency,
            global_map,
            T_global,
        )
        self.received += 1
        self.with_pose += T is not None
        self.with_global += T_global is not None
        if latency is not None:
            self.latencies_s.append(latency)
            self.series.append((int(msg.timestamp_ns), latency))
        self.latest = pose
        return pose

    def on_predicted(
        self, timestamp_ns: int, map_id: int, T_map_body: np.ndarray, now_s: float
    ) -> ReceivedPose:
        """The robot's own pose of a frame the edge will not see (the uplink budget left it
        out): its tracker's IMU propagation from the edge's last state, status
        ``"predicted"``; its latency is not the edge's (not in :meth:`summary`'s)."""
        t_cap = self._captured.pop(int(timestamp_ns), None)
        placed = self.placements.get(int(map_id))
        global_map, T_global = (
            (None, None) if placed is None else (placed[0], placed[1] @ T_map_body)
        )
        self.predicted += 1
        latency = None if t_cap is None else now_s - t_cap
        return ReceivedPose(
            int(timestamp_ns), int(map_id), "predicted", T_map_body, latency, global_map, T_global
        )

    def on_placement(self, msg: MapPlacement) -> bool:
        """Where the robot's map ``msg.map_id`` now sits in the global map; False (logged,
        counted) if the message is malformed."""
        try:
            T_global_map = decode_map_placement(msg)
        except RemoteProtocolError as exc:
            self.rejected += 1
            logger.warning("placement of map %d refused: %s", msg.map_id, exc)
            return False
        self.placements[int(msg.map_id)] = (int(msg.global_map), T_global_map)
        return True

    def summary(self) -> dict[str, float | int]:
        """Counts and the latency's median, 95th percentile and maximum [s] (NaN if none)."""
        lat = np.asarray(self.latencies_s, np.float64)
        stats = {"median_s": np.nan, "p95_s": np.nan, "max_s": np.nan}
        if lat.size:
            stats = {
                "median_s": float(np.median(lat)),
                "p95_s": float(np.percentile(lat, 95)),
                "max_s": float(lat.max()),
            }
        return {
            "received": self.received,
            "with_pose": self.with_pose,
            "with_global": self.with_global,
            "rejected": self.rejected,
            "predicted": self.predicted,
            **stats,
        }


def open_tum(path: Path | None) -> TextIO | None:
    """A TUM file opened for line-buffered writing, with its header (None: no file)."""
    if path is None:
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    file = path.open("w", buffering=1, encoding="utf-8")
    file.write("# timestamp tx ty tz qx qy qz qw\n")
    return file


def tum_line(pose: ReceivedPose, global_frame: bool = False) -> str | None:
    """``t tx ty tz qx qy qz qw`` (TUM: seconds, position m, Hamilton quaternion xyzw) of a
    pose in its own map (or, ``global_frame``, the global map), None without one, and None for
    a predicted pose (the files hold the edge's poses in camera-time order; a predicted one
    comes out before the edge's of earlier frames)."""
    T = pose.T_global_body if global_frame else pose.T_map_body
    if T is None or pose.status == "predicted":
        return None
    w, x, y, z = R_to_quat_wxyz(T[:3, :3])
    p = T[:3, 3]
    return (
        f"{pose.timestamp_ns // 1_000_000_000}.{pose.timestamp_ns % 1_000_000_000:09d} "
        f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {x:.9f} {y:.9f} {z:.9f} {w:.9f}"
    )
