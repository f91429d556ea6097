"""Every frame's pose, both ways (sans-I/O): to the robot at once, to the cloud in batches.

:func:`frame_pose` is the :class:`~common.links.robot_edge.FramePose` the robot gets for each
frame the VIO finished (its pose in the robot's own map, none while the VIO has no metric
pose). :class:`FramePoseBatcher` keeps each tracked frame's pose relative to the newest
keyframe the cloud has and sends them as :class:`~common.links.edge_cloud.FramePoses`, one per
map every ``every`` frames, so that the cloud can write a trajectory of every frame.
"""

from __future__ import annotations

import numpy as np

from common.links.edge_cloud import FramePoses, pack_frame_poses
from common.links.robot_edge import FramePose, encode_pose, frame_pose_message
from services.edge.vio.types import FrameResult, TrackingStatus


def frame_pose(result: FrameResult | None, timestamp_ns: int, map_id: int) -> FramePose:
    """The robot's pose at a frame: ``result`` (None: the VIO failed on the frame at
    ``timestamp_ns`` of map ``map_id`` and starts over, "lost")."""
    if result is None:
        return frame_pose_message(timestamp_ns, map_id, "lost", b"")
    metric = result.status is TrackingStatus.TRACKING
    pose = encode_pose(result.T_world_body) if metric else b""
    return frame_pose_message(result.timestamp_ns, result.map_id, result.status.value, pose)


class FramePoseBatcher:
    """Tracked frames' poses relative to uplinked keyframes, batched per map (``every``
    frames; a frame of another map sends the batch first)."""

    def __init__(self, agent_id: str, every: int) -> None:
        self.agent_id = agent_id
        self.every = every
        self._rows: dict[int, list[tuple[int, int, np.ndarray]]] = {}

    def add(self, map_id: int, t_ns: int, t_kf_ns: int, T_kf_frame: np.ndarray) -> list[FramePoses]:
        """The frame at ``t_ns`` is ``T_kf_frame`` (4, 4) from the keyframe at ``t_kf_ns``;
        the batches due now."""
        out = self.release() if any(m != map_id for m in self._rows) else []
        rows = self._rows.setdefault(map_id, [])
        rows.append((int(t_ns), int(t_kf_ns), np.asarray(T_kf_frame, np.float64)))
        if len(rows) >= self.every:
            out += self.release()
        return out

    def release(self) -> list[FramePoses]:
        """Everything kept, one message per map."""
        msgs = []
        for map_id, rows in sorted(self._rows.items()):
            t, t_kf, T = zip(*rows, strict=True)
            msgs.append(pack_frame_poses(self.agent_id, map_id, np.array(t), np.array(t_kf), T))
        self._rows.clear()
        return msgs
