"""One module per link: the wire messages of a link and their encoders and decoders.

- ``robot_edge``: RobotFrame, RobotSequenceEnd (robot -> edge), InertialFeedback (edge -> robot);
- ``edge_cloud``: KeyframeUpdate, MapPointUpdate, CullEvent, AgentStatus (edge -> cloud),
  PoseCorrection (cloud -> edge).
"""
