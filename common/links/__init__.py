"""One module per link: the wire messages of a link and their encoders and decoders.

- ``robot_edge``: RobotFrame, RobotSequenceEnd (robot -> edge), InertialFeedback (edge -> robot);
- ``edge_cloud``: KeyframeUpdate, MapPointUpdate, CullEvent, AgentStatus (edge -> cloud),
  PoseCorrection (cloud -> edge).
"""

from __future__ import annotations

import enum


class WireFormat(enum.Enum):
    """How a service encodes the messages it sends (receivers accept both)."""

    CODED = "coded"
    """Entropy-coded and quantised at stated precisions (the default)."""
    RAW = "raw"
    """Schema-1 messages: float64 / int64 arrays as they were before the links were coded,
    kept as the baseline of ``recslam experiment links``."""
