"""The robot <-> edge link acknowledges within one camera period, so that acknowledgements ride
on the frames and poses both ends send anyway instead of costing Ack frames of their own."""

from __future__ import annotations

import pytest

from common.vocabulary import Vocabulary
from services.edge.app import EdgeConfig
from services.edge.server import EdgeServer, EdgeServiceConfig
from services.robot.server import RobotService
from services.robot.service_config import RobotServiceConfig

SECRET = b"edge-ack-test-secret-0123456789"


def test_edge_acknowledges_robots_within_a_camera_period() -> None:
    vocab = Vocabulary.load()
    edge = EdgeServer(SECRET, vocab, EdgeConfig(worker="thread"), EdgeServiceConfig())
    assert edge.robot_session.ack_delay == pytest.approx(0.05)
    slow = EdgeServer(
        SECRET, vocab, EdgeConfig(worker="thread"), EdgeServiceConfig(robot_ack_delay_s=0.1)
    )
    assert slow.robot_session.ack_delay == pytest.approx(0.1)
    with pytest.raises(ValueError, match="robot_ack_delay_s"):
        EdgeServiceConfig(robot_ack_delay_s=0.0)


def test_robot_acknowledges_the_edge_with_its_next_frame(euroc_micro) -> None:
    robot = RobotService(
        RobotServiceConfig(
            dataset=euroc_micro,
            edge_host="127.0.0.1",
            edge_port=1,
            agent_id="robot-1",
            secret=SECRET,
        )
    )
    rate = float(robot.sequence.summary()["camera_rate_hz"])
    assert rate == pytest.approx(20.0)
    assert robot.session_config().ack_delay == pytest.approx(1.0 / rate)
