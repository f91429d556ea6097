"""RobotApp's reaction to the edge's messages: conversion, refusal, map changes."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from common.data.euroc import EurocSequence
from common.links.robot_edge import InertialFeedback
from common.protocol.arrays import pack_array
from common.protocol.messages import Blob
from common.transport import Delivery
from common.vocabulary import Vocabulary
from services.robot.app import RobotApp, feedback_to_state
from services.robot.config import FrontEndConfig

EXCERPT = Path(__file__).resolve().parents[3].parent / "shared/datasets/euroc-micro-V1_01"
pytestmark = pytest.mark.skipif(not EXCERPT.exists(), reason="EuRoC excerpt not available")


def feedback(ts: int, map_id: int = 0, n_points: int = 0, **over) -> InertialFeedback:
    fields = dict(
        timestamp_ns=ts,
        map_id=map_id,
        T_world_body=pack_array(np.eye(4), "<f8"),
        velocity_world=pack_array([0.1, 0.2, 0.3], "<f8"),
        bias_gyro=pack_array([0.01, 0.02, 0.03], "<f8"),
        bias_accel=pack_array([0.0, 0.0, 0.1], "<f8"),
        gravity_world=pack_array([0.0, 0.0, -9.81], "<f8"),
        track_ids=pack_array(np.arange(n_points), "<i8"),
        p_world=pack_array(np.ones((n_points, 3)), "<f8"),
    )
    fields.update(over)
    return InertialFeedback(**fields)


def deliver(app: RobotApp, msg) -> None:
    asyncio.run(app.on_message(Delivery("edge", "edge", msg, 1, b"s" * 16)))


def test_feedback_conversion_and_refusals():
    seq = EurocSequence(EXCERPT)
    app = RobotApp(FrontEndConfig(), seq.cam0, seq.imu, Vocabulary.load())
    frames = list(seq.frames(0, 3))
    for fr in frames:
        app.process(fr.timestamp_ns, fr.image, fr.imu)
    t = frames[-1].timestamp_ns
    state, ids, pts = feedback_to_state(feedback(t, n_points=2))
    assert np.array_equal(state.v_world_imu, [0.1, 0.2, 0.3]) and ids.tolist() == [0, 1]
    assert pts.shape == (2, 3)
    # Malformed arrays, a non-rotation, a state older than the IMU buffer: refused, counted.
    deliver(app, feedback(t, velocity_world=b"\x00" * 5))
    deliver(app, feedback(t, T_world_body=pack_array(2 * np.eye(4), "<f8")))
    deliver(app, feedback(t - 10**10))
    deliver(app, feedback(t, track_ids=pack_array([1, 2, 3], "<i8")))
    assert (app.feedback_rejected, app.feedback_applied) == (4, 0)
    assert not app.front_end.vi_initialised
    deliver(app, Blob(0, b"x"))  # not for the robot: ignored
    # Points named by stream track numbers (the edge's naming); an ended track is dropped.
    numbers = app.frame_coder.stream_ids[[0, 5, 9]]
    msg = feedback(t, n_points=4, track_ids=pack_array([*numbers, 10**9], "<i8"))
    deliver(app, msg)
    assert app.feedback_applied == 1 and app.front_end.vi_initialised
    want = set(app.frame_coder.track_ids[[0, 5, 9]].tolist())
    assert set(app.front_end.predictor._landmarks) == want
    deliver(app, feedback(t, map_id=1))  # another map, no points: the old ones are dropped
    assert app.feedback_applied == 2 and len(app.front_end.predictor._landmarks) == 0
    fr = next(seq.frames(3, 4))
    app.process(fr.timestamp_ns, fr.image, fr.imu)
    assert app.frames == 4
