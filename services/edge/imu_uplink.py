"""The IMU a robot's uplinked keyframes carry to the cloud (sans-I/O, one per robot session).

:class:`ImuUplink` holds the robot's newest IMU samples (as the robot sent them, stamped on
the IMU's clock) and cuts, for each uplinked keyframe, the samples since its predecessor's:
up to the keyframe's camera time plus the camera-IMU time offset, from where the
predecessor's window ended. The cloud reads the samples at its keyframes' times plus the
offset the robot's status reports, so an offset found late still applies to the keyframes
sent before it; and since each window starts where the previous one ended, an offset that
moves (found 0 -> 15 ms, refined to 14.6 ms) neither skips nor repeats samples.
"""

from __future__ import annotations

import numpy as np

from common.codec import ImuChunk, ImuEncoder

Key = tuple[int, int]
"""(edge map id, keyframe id)"""


class ImuUplink:
    """The IMU history of one robot and the windows of its uplinked keyframes.

    ``history_s``: seconds of samples kept behind the newest (a keyframe uplinked later than
    that after its predecessor gets what is left)."""

    def __init__(self, history_s: float) -> None:
        self.history_s = history_s
        self._chunks: list[tuple[np.ndarray, np.ndarray]] = []  # (t_ns (K,), (K, 6))
        self._end: dict[Key, int] = {}  # keyframe -> where its window ended (IMU clock, ns)

    def add(self, timestamps_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """One frame's samples (K,), (K, 3) rad/s, (K, 3) m/s² (IMU clock, IMU frame)."""
        if not len(timestamps_ns):
            return
        self._chunks.append((timestamps_ns, np.concatenate([gyro, accel], axis=1)))
        horizon = int(timestamps_ns[-1]) - int(self.history_s * 1e9)
        while self._chunks and self._chunks[0][0][-1] < horizon:
            self._chunks.pop(0)

    def window(
        self, prev: Key | None, prev_time_ns: int | None, key: Key, t_ns: int, offset_ns: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """The samples of keyframe ``key`` at camera time ``t_ns``: after where the window of
        its predecessor ``prev`` ended (else after ``prev_time_ns + offset_ns``; everything
        held if neither is known) up to ``t_ns + offset_ns`` on the IMU clock. Returns
        ``t_ns`` (M,) int64 IMU-clock stamps and ``[gyro, accel]`` (M, 6)."""
        end = t_ns + offset_ns
        start = None if prev is None else self._end.get(prev)
        if start is None and prev_time_ns is not None:
            start = prev_time_ns + offset_ns
        self._end[key] = end if start is None else max(start, end)
        if not self._chunks:
            return np.zeros(0, np.int64), np.zeros((0, 6))
        t = np.concatenate([c[0] for c in self._chunks])
        v = np.concatenate([c[1] for c in self._chunks])
        keep = t <= end
        if start is not None:
            keep &= t > start
        return t[keep], v[keep]

    def raw(
        self, prev: Key | None, prev_time_ns: int | None, key: Key, t_ns: int, offset_ns: int
    ) -> np.ndarray:
        """:meth:`window` as rows "<f8 (M, 7)" ``[t_s, gyro, accel]`` (the raw wire)."""
        t, v = self.window(prev, prev_time_ns, key, t_ns, offset_ns)
        return np.concatenate([t[:, None] * 1e-9, v], axis=1)

    def coded(
        self, prev: Key | None, prev_time_ns: int | None, key: Key, t_ns: int, offset_ns: int
    ) -> bytes:
        """:meth:`window` coded by a fresh ``ImuEncoder`` (the coded wire; ``b""`` if empty)."""
        t, v = self.window(prev, prev_time_ns, key, t_ns, offset_ns)
        if not len(t):
            return b""
        return ImuEncoder().encode(ImuChunk(t, v[:, :3], v[:, 3:]))
