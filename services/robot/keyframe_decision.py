"""Keyframe decision (the paper's Fig. 4): tracked count, tracked fraction and time.

Pure code: the caller states how many of the last keyframe's features are still tracked and
how long ago that keyframe was; the decision and its reason come back.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from common.errors import RecslamError
from services.robot.config import KeyframeDecisionConfig


class KeyframeDecisionError(RecslamError):
    """Invalid input to the keyframe decision."""


class KeyframeReason(enum.Enum):
    """Why a frame is (or is not) a keyframe."""

    NOT_KEYFRAME = "not_keyframe"
    FIRST_FRAME = "first_frame"
    EVERY_FRAME = "every_frame"
    TRACKING_LOST = "tracking_lost"
    FEW_TRACKED = "few_tracked"
    LOW_FRACTION = "low_fraction"
    MAX_INTERVAL = "max_interval"


@dataclass(frozen=True)
class KeyframeDecision:
    """Outcome: ``is_keyframe`` and the first rule that fired (``reason``)."""

    is_keyframe: bool
    reason: KeyframeReason


def decide_keyframe(
    config: KeyframeDecisionConfig,
    n_tracked: int,
    n_keyframe_features: int | None,
    dt_since_keyframe_s: float | None,
) -> KeyframeDecision:
    """Decide whether the current frame is a keyframe.

    ``n_tracked``: tracks in this frame that continue a feature of the last keyframe.
    ``n_keyframe_features``: how many features that keyframe had (None: no keyframe yet).
    ``dt_since_keyframe_s``: seconds since that keyframe (None: no keyframe yet).
    """
    if n_tracked < 0:
        raise KeyframeDecisionError(f"n_tracked must be >= 0, got {n_tracked}")
    if n_keyframe_features is None or dt_since_keyframe_s is None:
        return KeyframeDecision(True, KeyframeReason.FIRST_FRAME)
    if n_keyframe_features < 0:
        raise KeyframeDecisionError(f"n_keyframe_features must be >= 0, got {n_keyframe_features}")
    if dt_since_keyframe_s < 0:
        raise KeyframeDecisionError(
            f"time since keyframe must be >= 0 s, got {dt_since_keyframe_s}"
        )
    if config.every_frame:
        return KeyframeDecision(True, KeyframeReason.EVERY_FRAME)
    if n_tracked < config.lost_tracked and dt_since_keyframe_s >= config.lost_min_interval_s:
        return KeyframeDecision(True, KeyframeReason.TRACKING_LOST)
    if dt_since_keyframe_s < config.min_interval_s:
        return KeyframeDecision(False, KeyframeReason.NOT_KEYFRAME)
    if n_tracked < config.min_tracked:
        return KeyframeDecision(True, KeyframeReason.FEW_TRACKED)
    if n_keyframe_features > 0 and n_tracked < config.min_tracked_fraction * n_keyframe_features:
        return KeyframeDecision(True, KeyframeReason.LOW_FRACTION)
    if dt_since_keyframe_s > config.max_interval_s:
        return KeyframeDecision(True, KeyframeReason.MAX_INTERVAL)
    return KeyframeDecision(False, KeyframeReason.NOT_KEYFRAME)
