"""``recslam robot`` argument handling: clear errors for malformed configuration."""

from __future__ import annotations

import argparse
import logging

import pytest

from common.errors import RecslamError
from common.protocol.credentials import CredentialsError, load_secret, parse_address
from recslam.commands import robot
from services.robot.server import RobotService
from services.robot.service_config import DEV_SECRET, Rate, RobotConfigError


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    robot.register(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(["robot", *argv])


def test_arguments_build_the_service_config(tmp_path, monkeypatch):
    secret = tmp_path / "secret"
    secret.write_bytes(b"0123456789abcdef-robot\n")
    monkeypatch.delenv("RECSLAM_SECRET", raising=False)
    args = parse(
        [
            "--dataset",
            str(tmp_path),
            "--edge",
            "edge.local:7000",
            "--agent-id",
            "r1",
            "--rate",
            "max",
            "--secret-file",
            str(secret),
            "--backlog-minutes",
            "2",
        ]
    )
    assert args.func is robot.run
    cfg = robot.build_config(args)
    assert (cfg.edge_host, cfg.edge_port, cfg.agent_id) == ("edge.local", 7000, "r1")
    assert cfg.rate is Rate.MAX and cfg.backlog_s == 120.0
    assert cfg.secret.operator == b"0123456789abcdef-robot"  # trailing newline stripped
    assert "0123456789abcdef" not in repr(cfg)


@pytest.mark.parametrize("text", ["localhost", "host:", ":7000", "host:70000", "host:x1"])
def test_malformed_edge_address_is_named(text):
    with pytest.raises(CredentialsError, match="HOST:PORT"):
        parse_address(text)


def test_ipv6_address():
    assert parse_address("[::1]:7000") == ("::1", 7000)


def test_secret_sources(tmp_path, caplog):
    short = tmp_path / "short"
    short.write_bytes(b"abc\n")
    with pytest.raises(CredentialsError, match=f"{short}.*at least 16"):
        load_secret(short, {})
    with pytest.raises(CredentialsError, match="cannot read"):
        load_secret(tmp_path / "missing", {})
    with pytest.raises(CredentialsError, match="RECSLAM_SECRET"):
        load_secret(None, {"RECSLAM_SECRET": "short"})
    with pytest.raises(CredentialsError, match="no shared secret"):
        load_secret(None, {})  # edge and cloud: no development default
    assert load_secret(None, {"RECSLAM_SECRET": "x" * 20}) == b"x" * 20
    with caplog.at_level(logging.WARNING):
        assert load_secret(None, {}, dev_default=DEV_SECRET) == DEV_SECRET
    assert "development secret" in caplog.text


def test_bad_dataset_is_a_clear_error(tmp_path):
    args = parse(["--dataset", str(tmp_path / "nope"), "--edge", "127.0.0.1:1", "--agent-id", "r"])
    cfg = robot.build_config(args)
    with pytest.raises(RobotConfigError, match="nope: dataset folder does not exist"):
        RobotService(cfg)
    (tmp_path / "empty").mkdir()
    cfg = robot.build_config(
        parse(["--dataset", str(tmp_path / "empty"), "--edge", "h:1", "--agent-id", "r"])
    )
    with pytest.raises(RecslamError, match="not an EuRoC sequence"):
        RobotService(cfg)


def test_start_beyond_the_sequence_is_a_clear_error(euroc_micro):
    args = parse(
        ["--dataset", str(euroc_micro), "--edge", "h:1", "--agent-id", "r", "--start", "500"]
    )
    with pytest.raises(RobotConfigError, match="start frame 500 leaves no frames"):
        RobotService(robot.build_config(args))


def test_nonpositive_backlog_is_refused(tmp_path):
    args = parse(
        ["--dataset", str(tmp_path), "--edge", "h:1", "--agent-id", "r", "--backlog-minutes", "0"]
    )
    with pytest.raises(RobotConfigError, match="--backlog-minutes"):
        robot.build_config(args)


def test_environment_supplies_missing_arguments(monkeypatch, tmp_path):
    monkeypatch.setenv("RECSLAM_DATASET", str(tmp_path))
    monkeypatch.setenv("RECSLAM_EDGE", "edge:7001")
    monkeypatch.setenv("RECSLAM_AGENT_ID", "robot-9")
    monkeypatch.setenv("RECSLAM_SECRET", "s" * 16)
    cfg = robot.build_config(parse([]))
    assert (cfg.dataset, cfg.edge_host, cfg.edge_port, cfg.agent_id) == (
        tmp_path,
        "edge",
        7001,
        "robot-9",
    )
    assert cfg.secret.operator == b"s" * 16
    monkeypatch.delenv("RECSLAM_EDGE")
    with pytest.raises(SystemExit):
        parse([])  # --edge is required again


def test_handovers_parse_in_frame_order_and_a_malformed_one_is_named(tmp_path, monkeypatch):
    from services.robot.service_config import Handover

    monkeypatch.setenv("RECSLAM_SECRET", "0123456789abcdef-robot")
    base = ["--dataset", str(tmp_path), "--edge", "a:7000", "--agent-id", "r1"]
    args = parse([*base, "--handover", "100=b:7001", "--handover", "250=[::1]:7002"])
    cfg = robot.build_config(args)
    assert cfg.handovers == (Handover(100, "b", 7001), Handover(250, "::1", 7002))
    with pytest.raises(RobotConfigError, match="FRAME=HOST:PORT"):
        robot.build_config(parse([*base, "--handover", "b:7001"]))
    with pytest.raises(RobotConfigError, match="must increase"):
        robot.build_config(parse([*base, "--handover", "9=b:1", "--handover", "3=c:2"]))


def test_the_ros1_source_needs_a_calibration_and_builds_a_live_config(euroc_micro, monkeypatch):
    from services.robot.ros1.source import Ros1RunConfig

    monkeypatch.delenv("RECSLAM_SECRET", raising=False)
    base = ["--source", "ros1", "--edge", "h:7000", "--agent-id", "r1"]
    topics = ["--image-topic", "/cam0/image_raw", "--imu-topic", "/imu0"]
    with pytest.raises(RobotConfigError, match="needs --calibration"):
        robot.build_config(parse([*base, *topics]))
    args = parse([*base, *topics, "--calibration", str(euroc_micro), "--max-pending-images", "5"])
    cfg = robot.build_config(args)
    assert isinstance(cfg, Ros1RunConfig)
    assert (cfg.ros.image_topic, cfg.ros.imu_topic, cfg.ros.odom_topic) == (
        "/cam0/image_raw",
        "/imu0",
        "odom",
    )
    assert cfg.robot.sensors.camera.width == 752 and cfg.robot.live.max_pending_images == 5
