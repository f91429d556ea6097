"""Every frame's trajectory: the edges' relative frame poses placed on the final keyframes.

The edges send, in :class:`~common.links.edge_cloud.FramePoses`, each tracked frame's pose
relative to an uplinked keyframe (``T_kf_frame``, the VIO's motion since that keyframe).
:class:`FrameTrack` keeps them per robot; :meth:`FrameTrack.trajectories` places each frame on
its keyframe's pose in the robot's keyframe trajectory (:func:`services.cloud.store.output.
robot_trajectories`: after the merges, loops and full BA, and through the anchors of the
keyframes MBP removed), ``T_map_frame = T_map_kf @ T_kf_frame``, and adds the keyframes
themselves: the trajectory at camera rate that ``recslam eval`` measures beside the keyframe
one (``RESULT_DIR/frames/``). Frames whose keyframe is not in the trajectory (a map that did
not merge with the robot's main one) are left out.

Kept in memory, like the forwarded IMU: after a cloud restart the frames before it are gone
from this trajectory (the keyframe trajectory is not).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from common.evaluation.trajectory import Trajectory

MATCH_NS = 1000
"""A keyframe's stamp in the trajectory (seconds as float, rounded) matches the edge's
nanoseconds within this."""


class FrameTrack:
    """Relative frame poses per robot name: ``{t_frame: (t_kf, T_kf_frame)}``."""

    def __init__(self) -> None:
        self._frames: dict[str, dict[int, tuple[int, np.ndarray]]] = {}

    def add(
        self, robot: str, t_ns: np.ndarray, t_kf_ns: np.ndarray, T_kf_frame: np.ndarray
    ) -> None:
        """Frames (N,) of ``robot`` relative to its keyframes at ``t_kf_ns`` (N,),
        ``T_kf_frame`` (N, 4, 4); a frame sent again (an edge's replay) replaces itself."""
        rows = self._frames.setdefault(robot, {})
        for t, tk, T in zip(t_ns.tolist(), t_kf_ns.tolist(), T_kf_frame, strict=True):
            rows[int(t)] = (int(tk), np.array(T))

    def count(self, robot: str | None = None) -> int:
        if robot is not None:
            return len(self._frames.get(robot, {}))
        return sum(len(v) for v in self._frames.values())

    def trajectories(self, keyframes: Mapping[str, Trajectory]) -> dict[str, Trajectory]:
        """Per robot of ``keyframes`` with frames here: its frames placed on its keyframes'
        poses, and the keyframes, in time order (a frame at a keyframe's time: the keyframe)."""
        out: dict[str, Trajectory] = {}
        for robot, kf_traj in keyframes.items():
            rows = self._frames.get(robot)
            if not rows or len(kf_traj) == 0:
                continue
            t_kf = kf_traj.timestamps_ns
            T_kf = kf_traj.T_world_body
            t = np.fromiter(rows, np.int64, len(rows))
            ref = np.array([tk for tk, _ in rows.values()], np.int64)
            rel = np.array([T for _, T in rows.values()])
            j, near = _nearest(t_kf, ref)  # each frame's keyframe in the trajectory
            keep = near & ~_nearest(t_kf, t)[1]  # (a frame at a keyframe's time: the keyframe)
            stamps = np.concatenate([t_kf, t[keep]])
            poses = np.concatenate([T_kf, T_kf[j[keep]] @ rel[keep]])
            order = np.argsort(stamps, kind="stable")
            out[robot] = Trajectory.from_poses(stamps[order], poses[order], robot)
        return out


def _nearest(sorted_ns: np.ndarray, query_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each query stamp (Q,): the index of the nearest of ``sorted_ns`` (N,), N >= 1, and
    whether it is within :data:`MATCH_NS`."""
    i = np.searchsorted(sorted_ns, query_ns)
    lo = np.clip(i - 1, 0, len(sorted_ns) - 1)
    hi = np.clip(i, 0, len(sorted_ns) - 1)
    j = np.where(np.abs(sorted_ns[lo] - query_ns) <= np.abs(sorted_ns[hi] - query_ns), lo, hi)
    return j, np.abs(sorted_ns[j] - query_ns) <= MATCH_NS
