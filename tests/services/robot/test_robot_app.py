"""RobotApp's reaction to the edge's messages: conversion, refusal, map changes."""

from __future__ import annotations

import asyncio
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from common.data.euroc import EurocSequence
from common.links import WireFormat
from common.links.robot_edge import (
    FeedbackContent,
    InertialFeedback,
    decode_feedback,
    encode_feedback,
)
from common.protocol.arrays import pack_array
from common.protocol.messages import Blob
from common.transport import Delivery
from common.vocabulary import Vocabulary
from services.robot.app import RobotApp, content_to_state
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
    content = decode_feedback(feedback(t, n_points=2))
    state = content_to_state(content)
    assert np.array_equal(state.v_world_imu, [0.1, 0.2, 0.3]) and content.reset
    assert content.track_numbers.tolist() == [0, 1] and content.p_world.shape == (2, 3)
    assert not decode_feedback(feedback(t)).reset  # raw without points: keeps the set
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


def coded(ts: int, numbers, p=None, *, map_id: int = 0, reset: bool, forget=()):
    n = len(numbers)
    c = FeedbackContent(
        timestamp_ns=ts,
        map_id=map_id,
        T_world_body=np.eye(4),
        velocity_world=np.zeros(3),
        bias_gyro=np.zeros(3),
        bias_accel=np.zeros(3),
        gravity_world=np.array([0.0, 0.0, -9.81]),
        reset=reset,
        track_numbers=np.asarray(numbers, np.int64),
        p_world=np.ones((n, 3)) if p is None else np.asarray(p, float),
        forget=np.asarray(forget, np.int64),
    )
    return encode_feedback(c, WireFormat.CODED)


def test_coded_feedback_resets_updates_and_forgets():
    seq = EurocSequence(EXCERPT)
    app = RobotApp(FrontEndConfig(), seq.cam0, seq.imu, Vocabulary.load())
    frames = list(seq.frames(0, 3))
    for fr in frames:
        app.process(fr.timestamp_ns, fr.image, fr.imu)
    t = frames[-1].timestamp_ns
    s = app.frame_coder.stream_ids
    tid = dict(zip(s.tolist(), app.frame_coder.track_ids.tolist(), strict=True))

    def landmarks() -> dict[int, list[float]]:
        return {k: v.round(3).tolist() for k, v in app.front_end.predictor._landmarks.items()}

    deliver(app, coded(t, [s[0], s[5], s[9], 10**9], reset=True))  # 10**9: ended, dropped
    assert app.feedback_applied == 1 and app.front_end.vi_initialised
    assert sorted(landmarks()) == sorted(tid[int(k)] for k in s[[0, 5, 9]])
    # update: a new track, a moved one, a forgotten one; the others stay
    deliver(app, coded(t, [s[2], s[5]], [[1, 2, 3], [4, 5, 6]], reset=False, forget=[s[9]]))
    want = {tid[int(s[0])]: [1.0] * 3, tid[int(s[2])]: [1, 2, 3], tid[int(s[5])]: [4, 5, 6]}
    assert landmarks() == want
    # messages that arrive during a frame wait, all of them, and are applied in order
    with app._lock:
        deliver(app, coded(t, [s[1]], reset=False))
        deliver(app, coded(t, [], reset=False, forget=[s[0]]))
    assert app.feedback_applied == 2
    app.apply_pending()
    assert app.feedback_applied == 4 and sorted(landmarks()) == sorted(
        tid[int(k)] for k in s[[1, 2, 5]]
    )
    # refused: a damaged payload (counted, nothing applied); a state too old for the IMU
    # buffer (counted, its landmarks applied: they do not depend on the IMU)
    bad = coded(t, [s[3]], reset=False)
    deliver(app, dataclasses.replace(bad, landmarks=bad.landmarks[:-1]))
    deliver(app, coded(t - 10**10, [s[3]], reset=False))
    assert (app.feedback_rejected, app.feedback_applied) == (2, 4)
    assert tid[int(s[3])] in landmarks()
    # another map: a reset replaces the set; an update of another map drops the old set first
    deliver(app, coded(t, [s[4]], map_id=1, reset=False))
    assert sorted(landmarks()) == [tid[int(s[4])]]
    deliver(app, coded(t, [s[6], s[7]], map_id=1, reset=True))
    assert sorted(landmarks()) == sorted(tid[int(k)] for k in s[[6, 7]])
    decoded = app.codec_timer.snapshot()["decode.InertialFeedbackCoded"]["messages"]
    assert decoded == 7  # all but the damaged one
    fr = next(seq.frames(3, 4))
    app.process(fr.timestamp_ns, fr.image, fr.imu)  # ended tracks' points are dropped
    deliver(app, coded(fr.timestamp_ns, [], map_id=1, reset=False))
    assert set(landmarks()) <= set(app.frame_coder.track_ids.tolist())
