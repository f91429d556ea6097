"""A simulated robot for edge tests and benchmarks: the VIO simulator's tracks, coded.

:func:`code_sequence` turns a :class:`~sim.vio.SimSequence` (tracks and
IMU without images, with ground truth) into the :class:`RobotFrame` messages a real robot
would send: keyframes on ORB's integer level grid with descriptors and continuation links,
non-keyframes as survivors (in the codec's order) plus new tracks on the 1/4 px grid, IMU
through the IMU codec. :func:`play` sends them to an edge over the real transport, after the
robot's sensors (:func:`sim_sensors`).

It stands in for the image-based robot where the EuRoC excerpt has too little motion for the
VIO to initialise (and until rendered synthetic datasets exist).
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass

import numpy as np

from common.codec import (
    CodecConfig,
    FeatureEncoder,
    ImuChunk,
    ImuEncoder,
    KeyframeFeatures,
    NonKeyframeFeatures,
    quantise_uv,
)
from common.links.robot_edge import RobotFrame, RobotSequenceEnd, sensors_message
from common.links.sensors import Sensors
from common.protocol import SessionConfig
from common.protocol.messages import Message
from common.transport import Client, Delivery, TransportConfig
from common.vocabulary import Vocabulary
from sim.vio import SimSequence

logger = logging.getLogger(__name__)


def sim_sensors(seq: SimSequence) -> Sensors:
    """The sensors a robot playing ``seq`` describes when it joins."""
    return Sensors(seq.camera, seq.imu)


def code_sequence(seq: SimSequence, vocabulary: Vocabulary) -> list[RobotFrame]:
    """Every frame of ``seq`` as a coded :class:`RobotFrame` (frame order)."""
    cfg = CodecConfig(image_width=seq.camera.width, image_height=seq.camera.height)
    enc = FeatureEncoder(vocabulary, cfg)
    imu_enc = ImuEncoder()
    prev_ids = np.zeros(0, np.int64)  # codec order of the active tracks (simulator ids)
    out: list[RobotFrame] = []
    for k, (t_imu, gyro, accel, fr) in enumerate(seq.feed()):
        row_of = {int(t): r for r, t in enumerate(prev_ids)}
        if fr.is_keyframe:
            lv = fr.levels.astype(np.int64)
            s = cfg.level_scale(lv)
            kp = np.zeros((len(fr.track_ids), 4), np.int32)
            kp[:, :2] = np.floor(fr.keypoints_px / s[:, None] + 0.5)
            kp[:, 2] = lv
            kp[:, 3] = (fr.track_ids * 7) % cfg.angle_bins
            size = np.array([cfg.level_size(int(v)) for v in lv]).reshape(-1, 2)
            kp[:, 0] = np.clip(kp[:, 0], 0, size[:, 0] - 1)
            kp[:, 1] = np.clip(kp[:, 1], 0, size[:, 1] - 1)
            links = np.array([row_of.get(int(t), -1) for t in fr.track_ids], np.int32)
            assert fr.descriptors is not None
            feats = KeyframeFeatures(kp, fr.descriptors, links)
            order = feats.canonical_order()
            payload = enc.encode_keyframe(feats.canonical())
            prev_ids = fr.track_ids[order]
        else:
            cur = {int(t): r for r, t in enumerate(fr.track_ids)}
            survived = np.array([int(t) in cur for t in prev_ids], bool)
            rows = [cur[int(t)] for t in prev_ids[survived]]
            rows += [r for r, t in enumerate(fr.track_ids) if int(t) not in row_of]
            rows_a = np.array(rows, np.int64)
            uv = quantise_uv(fr.keypoints_px[rows_a], cfg) if len(rows_a) else np.zeros((0, 2))
            kp3 = np.concatenate([uv, fr.levels[rows_a, None].astype(np.float64)], axis=1)
            payload = enc.encode_non_keyframe(NonKeyframeFeatures(survived, kp3))
            prev_ids = fr.track_ids[rows_a]
        imu = imu_enc.encode(ImuChunk(t_imu, gyro, accel))
        out.append(RobotFrame(k, fr.timestamp_ns, fr.is_keyframe, payload, imu))
    return out


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
