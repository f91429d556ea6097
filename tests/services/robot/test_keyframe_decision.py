"""Keyframe decision (paper Fig. 4): truth table over count, fraction and time."""

from __future__ import annotations

import pytest

from services.robot.config import KeyframeDecisionConfig
from services.robot.keyframe_decision import (
    KeyframeDecisionError,
    KeyframeReason,
    decide_keyframe,
)

CFG = KeyframeDecisionConfig(
    min_tracked=100,
    min_tracked_fraction=0.5,
    max_interval_s=1.0,
    min_interval_s=0.2,
    lost_tracked=20,
)


@pytest.mark.parametrize(
    ("n_tracked", "n_kf", "dt", "expected", "reason"),
    [
        (500, None, None, True, KeyframeReason.FIRST_FRAME),
        (500, 1000, 0.5, False, KeyframeReason.NOT_KEYFRAME),  # plenty tracked, recent
        (501, 1000, 0.5, False, KeyframeReason.NOT_KEYFRAME),
        (499, 1000, 0.5, True, KeyframeReason.LOW_FRACTION),  # fraction below 0.5
        (99, 150, 0.5, True, KeyframeReason.FEW_TRACKED),  # count below 100
        (100, 150, 0.5, False, KeyframeReason.NOT_KEYFRAME),  # exactly at the floor
        (900, 1000, 1.01, True, KeyframeReason.MAX_INTERVAL),  # too long since the KF
        (900, 1000, 1.0, False, KeyframeReason.NOT_KEYFRAME),  # bound is strict
        (50, 1000, 0.1, False, KeyframeReason.NOT_KEYFRAME),  # too soon, not lost
        (19, 1000, 0.1, True, KeyframeReason.TRACKING_LOST),  # lost overrides too soon
        (0, 0, 0.5, True, KeyframeReason.TRACKING_LOST),
    ],
)
def test_truth_table(n_tracked, n_kf, dt, expected, reason) -> None:
    decision = decide_keyframe(CFG, n_tracked, n_kf, dt)
    assert decision.is_keyframe is expected
    assert decision.reason is reason


def test_every_frame_baseline() -> None:
    cfg = KeyframeDecisionConfig(every_frame=True)
    decision = decide_keyframe(cfg, 1000, 1000, 0.05)
    assert decision.is_keyframe and decision.reason is KeyframeReason.EVERY_FRAME


def test_fraction_relative_to_keyframe_features() -> None:
    cfg = KeyframeDecisionConfig(min_tracked=10, min_tracked_fraction=0.8, lost_tracked=0)
    assert not decide_keyframe(cfg, 80, 100, 0.1).is_keyframe
    assert decide_keyframe(cfg, 79, 100, 0.1).reason is KeyframeReason.LOW_FRACTION


def test_lost_tracking_waits_for_its_own_minimum_interval() -> None:
    """Under an uplink budget a keyframe for lost tracking waits until the link has carried
    the last one (``lost_min_interval_s``); the frames between are not keyframes."""
    cfg = KeyframeDecisionConfig(min_interval_s=2.0, lost_tracked=30, lost_min_interval_s=1.2)
    assert decide_keyframe(cfg, 0, 300, 0.1).reason is KeyframeReason.NOT_KEYFRAME
    assert decide_keyframe(cfg, 29, 300, 1.19).reason is KeyframeReason.NOT_KEYFRAME
    assert decide_keyframe(cfg, 29, 300, 1.2).reason is KeyframeReason.TRACKING_LOST
    assert decide_keyframe(cfg, 30, 300, 1.5).reason is KeyframeReason.NOT_KEYFRAME


@pytest.mark.parametrize(("n", "n_kf", "dt"), [(-1, 10, 0.1), (5, -1, 0.1), (5, 10, -0.1)])
def test_rejects_invalid_input(n, n_kf, dt) -> None:
    with pytest.raises(KeyframeDecisionError):
        decide_keyframe(CFG, n, n_kf, dt)
