"""One module per link: the wire messages of a link and their encoders and decoders.

- ``robot_edge``: RobotSensors, RobotFrame, RobotSequenceEnd (robot -> edge), InertialFeedback
  and InertialFeedbackCoded (edge -> robot; both decode into one FeedbackContent);
- ``edge_cloud``: AgentSensors, KeyframeUpdate, MapPointUpdate, CullEvent, AgentStatus (edge ->
  cloud), PoseCorrection (cloud -> edge); ``edge_cloud_payloads``: the coded payloads they carry
  (keyframe states, map point ids, map points, poses);
- ``sensors``: the sensor description (calibrations) both links carry, and its codec;
- ``wire``: what they share: the wire format (coded or raw) and the codecs' CPU timer.
"""

from __future__ import annotations

# Registers every link's message types with the protocol (importing ``common.links`` is
# enough for a decoder to know them all).
from common.links import edge_cloud, robot_edge
from common.links.wire import CodecTimer, WireFormat, codec_cpu

__all__ = ["CodecTimer", "WireFormat", "codec_cpu", "edge_cloud", "robot_edge"]
