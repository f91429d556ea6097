"""The edge application's options (one object, built once and handed down)."""

from __future__ import annotations

from dataclasses import dataclass, field

from services.edge.cloud_budget import CloudBudgetConfig
from services.edge.session_config import EdgeSessionConfig
from services.edge.vio.types import VioConfig


@dataclass(frozen=True)
class EdgeConfig:
    """Options of the edge application.

    worker: "process" (one spawned VIO process per robot, default) or "thread".
    max_queued_frames: decoded frames waiting for a robot's VIO before the handler waits
        (200 = 10 s at 20 Hz).
    max_vio_lag_s: fresh before complete at the edge (``recslam edge --max-vio-lag``): a
        non-keyframe whose camera time is more than this behind the robot's newest decoded
        frame is not given to the VIO (its IMU goes with the next frame, which the VIO
        integrates across the gap; counted per robot as ``frames_skipped_stale``); keyframes
        always go. 0 (default): every frame, however late (the lossless recorder).
    cloud_budget: which robot keyframes go up to the cloud (``recslam edge --cloud-budget``,
        ``services/edge/cloud_budget.py``); default: every one.
    vio: the VIO's options; session: feedback / status / uplink options.
    """

    worker: str = "process"
    max_queued_frames: int = 200
    max_vio_lag_s: float = 0.0
    cloud_budget: CloudBudgetConfig = field(default_factory=CloudBudgetConfig)
    vio: VioConfig = field(default_factory=VioConfig)
    session: EdgeSessionConfig = field(default_factory=EdgeSessionConfig)
