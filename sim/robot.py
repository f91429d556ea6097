"""A simulated robot for edge tests and benchmarks: the VIO simulator's tracks, coded.

:func:`code_sequence` turns a :class:`~sim.vio.SimSequence` (tracks and IMU without images,
with ground truth) into the :class:`RobotFrame` messages a real robot would send: each frame
becomes the front end's :class:`~services.robot.tracker.TrackedFrame` (keyframe keypoints on
ORB's integer level grid, non-keyframe keypoints on the codec's sub-pixel grid, survivors first
in the previous frame's order) and goes through the robot's own
:class:`~services.robot.coding.FrameCoder` and :class:`~services.robot.coding.ImuCoder`.
:func:`play` sends them to an edge over the real transport, after the robot's sensors
(:func:`sim_sensors`).

It stands in for the image-based robot where the EuRoC excerpt has too little motion for the
VIO to initialise (and until rendered synthetic datasets exist).
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass

import numpy as np

from common.codec import CodecConfig, ImuChunk, quantise_uv
from common.codec.keypoints import kf_track_q
from common.links.robot_edge import RobotFrame, RobotSequenceEnd, sensors_message
from common.links.sensors import Sensors
from common.protocol import SessionConfig
from common.protocol.messages import Message
from common.transport import Client, Delivery, TransportConfig
from common.vocabulary import Vocabulary
from services.edge.vio.types import FrameObservation
from services.robot.coding import FrameCoder, ImuCoder
from services.robot.keyframe_decision import KeyframeReason
from services.robot.tracker import TrackedFrame, TrackingStats
from sim.vio import SimSequence

logger = logging.getLogger(__name__)


def sim_sensors(seq: SimSequence) -> Sensors:
    """The sensors a robot playing ``seq`` describes when it joins."""
    return Sensors(seq.camera, seq.imu)


def code_sequence(seq: SimSequence, vocabulary: Vocabulary) -> list[RobotFrame]:
    """Every frame of ``seq`` as a coded :class:`RobotFrame` (frame order)."""
    cfg = CodecConfig(image_width=seq.camera.width, image_height=seq.camera.height)
    coder = FrameCoder(vocabulary, cfg)
    imu_coder = ImuCoder()
    tracks = _Tracks(cfg)
    out: list[RobotFrame] = []
    for k, (t_imu, gyro, accel, fr) in enumerate(seq.feed()):
        payload = coder.encode(tracks.frame(k, fr)).payload
        imu = imu_coder.encode(ImuChunk(t_imu, gyro, accel))
        out.append(RobotFrame(k, fr.timestamp_ns, fr.is_keyframe, payload, imu))
    return out


class _Tracks:
    """The simulator's frames as the front end would hand them to the coder: the rows, grids
    and orientations of the :class:`TrackedFrame` contract (``services.robot.tracker``)."""

    def __init__(self, config: CodecConfig) -> None:
        self.config = config
        self.previous = np.zeros(0, np.int64)  # the previous frame's track ids, row order
        self.keyframe_id = -1
        self.keyframe_rows: dict[int, int] = {}  # track id -> row of the last keyframe

    def frame(self, index: int, fr: FrameObservation) -> TrackedFrame:
        """Frame ``index`` of the sequence, ``fr``, as a :class:`TrackedFrame`."""
        cfg = self.config
        survived = np.isin(self.previous, fr.track_ids)
        angles = None
        if fr.is_keyframe:
            # A keyframe's rows in the simulator's (extraction) order, on ORB's level grid;
            # orientations at the centre of a bin drawn from the track id.
            rows = np.arange(len(fr.track_ids))
            levels = fr.levels.astype(np.int64)
            kp = np.zeros((len(rows), 4), np.int32)
            kp[:, :2] = np.floor(fr.keypoints_px / cfg.level_scale(levels)[:, None] + 0.5)
            kp[:, 2] = levels
            size = np.array([cfg.level_size(int(v)) for v in levels]).reshape(-1, 2)
            kp[:, 0] = np.clip(kp[:, 0], 0, size[:, 0] - 1)
            kp[:, 1] = np.clip(kp[:, 1], 0, size[:, 1] - 1)
            keypoints = kf_track_q(kp, cfg) / cfg.subpixel
            bins = (fr.track_ids * 7) % cfg.angle_bins
            angles = ((bins + 0.5) * (360.0 / cfg.angle_bins)).astype(np.float32)
            self.keyframe_id += 1
            self.keyframe_rows = {int(t): r for r, t in enumerate(fr.track_ids)}
            kf_index = rows.astype(np.int32)
            # (The simulator does not say which of its rules made the keyframe; the coder reads
            # no reason.)
            reason = KeyframeReason.FIRST_FRAME if index == 0 else KeyframeReason.MAX_INTERVAL
        else:
            # Survivors first, in the previous frame's order, then new tracks.
            row_of = {int(t): r for r, t in enumerate(fr.track_ids)}
            old = [row_of[int(t)] for t in self.previous[survived]]
            prev = set(self.previous.tolist())
            rows = np.array(
                old + [r for r, t in enumerate(fr.track_ids) if int(t) not in prev], np.int64
            )
            keypoints = quantise_uv(fr.keypoints_px[rows].reshape(-1, 2), cfg)
            kf_index = np.array(
                [self.keyframe_rows.get(int(t), -1) for t in fr.track_ids[rows]], np.int32
            )
            reason = KeyframeReason.NOT_KEYFRAME
        track_ids = fr.track_ids[rows].astype(np.int64)
        self.previous = track_ids
        return TrackedFrame(
            frame_index=index,
            timestamp_ns=fr.timestamp_ns,
            is_keyframe=fr.is_keyframe,
            keyframe_reason=reason,
            keyframe_id=self.keyframe_id,
            track_ids=track_ids,
            keyframe_feature_index=kf_index,
            keypoints=keypoints,
            levels=fr.levels[rows].astype(np.uint8),
            survived_mask_vs_previous=survived,
            descriptors=fr.descriptors,
            angles=angles,
            stats=TrackingStats(n_previous=len(survived), n_features=len(rows)),
        )


@dataclass
class PlayResult:
    """What a simulated robot saw: frames sent, feedback messages received, wall time [s]."""

    frames: int
    feedback: list[Message]
    wall_s: float
    counters: dict


async def play(
    frames: list[RobotFrame],
    host: str,
    port: int,
    agent_id: str,
    secret: bytes,
    sensors: Sensors,
    rate_hz: float | None = None,
    transport: TransportConfig | None = None,
    flush_timeout_s: float = 120.0,
    linger: asyncio.Event | None = None,
    retransmit_timeout_s: float = 5.0,
) -> PlayResult:
    """Send ``sensors``, ``frames`` then :class:`RobotSequenceEnd` to the edge at
    ``host:port`` (as fast as the link allows, or at ``rate_hz``); wait until the edge
    delivered everything, then (to receive late feedback) until ``linger`` is set."""
    feedback: list[Message] = []

    async def on_message(d: Delivery) -> None:
        feedback.append(d.message)

    cfg = SessionConfig(
        "robot",
        agent_id,
        secret,
        heartbeat_interval=0.5,
        idle_timeout=5.0,
        retransmit_timeout=retransmit_timeout_s,
    )
    client = Client(cfg, on_message, host, port, transport=transport, server_name="edge")
    await client.start()
    t0 = time.monotonic()
    try:
        await client.send(sensors_message(sensors))
        for k, fr in enumerate(frames):
            if rate_hz:
                await asyncio.sleep(max(0.0, t0 + k / rate_hz - time.monotonic()))
            await client.send(fr)
        await client.send(RobotSequenceEnd(len(frames)))
        await asyncio.wait_for(client.flush(), flush_timeout_s)
        wall = time.monotonic() - t0
        if linger is not None:
            await asyncio.wait_for(linger.wait(), flush_timeout_s)
        counters = client.counters()
    finally:
        await client.close()
    return PlayResult(len(frames), feedback, wall, counters)
