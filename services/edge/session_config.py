"""Options of one robot's session on the edge (:class:`~services.edge.robot_session.RobotSession`
and its cloud half :class:`~services.edge.session_uplink.SessionUplink`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from common.links import WireFormat
from services.edge.feedback import FeedbackPolicy


@dataclass(frozen=True)
class EdgeSessionConfig:
    """Per-robot output options: feedback policy, status period (frames), features kept for
    the keyframe uplink (robot keyframes, newest), IMU history kept (s), and the map-point
    uplink threshold: a point already sent is sent again only when it moved more than
    ``point_resend_m`` (m) or gained observations in robot keyframes, and then with only the
    new observations (local BA nudges every window point a little, and resending all of them
    with every observation dominated the edge->cloud link)."""

    feedback: FeedbackPolicy = field(default_factory=FeedbackPolicy)
    status_every_frames: int = 20
    keyframes_kept: int = 300
    imu_history_s: float = 120.0
    point_resend_m: float = 0.01
    wire: WireFormat = WireFormat.CODED
    """Encoding of the messages to the robot and to the cloud (``raw``: the schema-1 baseline)."""
    frame_poses_every: int = 20
    """Coded wire only: the tracked frames' poses relative to the newest uplinked keyframe go
    to the cloud (``FramePoses``, 44 B a frame) in batches of this many frames (and when the
    map changes, and at the end), so that it writes a trajectory of every frame."""
    pose_resend_m: float = 1e-3
    """Coded wire only: a keyframe the cloud has gets a new state (``KeyframePoses``) when its
    position moved more than this (m) since last sent, its rotation more than
    ``pose_resend_rad``, its velocity more than ``velocity_resend_mps`` or a bias more than
    ``bias_resend``; each point then follows its reference keyframe at both ends, and is
    re-sent when it moved more than ``point_resend_m`` from where it followed to."""
    pose_resend_rad: float = 1e-3
    velocity_resend_mps: float = 0.01
    bias_resend: float = 1e-3
    point_settle_keyframes: int = 0
    """Coded wire only: a new map point goes up once this many robot keyframes were uplinked
    after its first robot observer (``services.edge.point_uplink``; 0: at once, as the raw
    wire does). Off by default: 3 cut the map-point bytes by ~45 % (edge->cloud 1237 -> 1020
    / 1034 kbit/s at camera rate, default dataset) but joint ATE was 2.7 / 3.0 cm against 2.5
    at 0 (single runs; ``benchmarks/results/link_budget_sweep.md``). A likely cause: a held
    point kept the position it had before a cloud correction the edge applied meanwhile (the
    VIO moves its points without re-sending them), so it reached the cloud off its corrected
    keyframes; held points now move with those corrections (``SentPoints.move_held``), not
    yet measured on the whole job."""
