"""The robot's uplink budget (sans-I/O): which non-keyframes go, and why the others do not."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest

from common.links.robot_edge import RobotFrame
from services.robot.core import FrameDone, ImageInput, LinkLoad, RobotCore
from services.robot.uplink_budget import UplinkBudget, UplinkBudgetConfig


def test_without_a_budget_every_frame_goes():
    b = UplinkBudget()
    b.on_link(0.0, 10**9, 0)  # however full the link
    assert b.hold_back(0.0) == "" and b.rate_Bps() is None


def test_a_backlog_that_would_not_drain_in_time_leaves_non_keyframes_out():
    b = UplinkBudget(UplinkBudgetConfig(budget_kbps=50.0))  # 6250 B/s
    b.on_link(0.0, 5000, 0)  # 0.8 s of backlog > 0.7 s
    assert b.hold_back(0.0) == "backlog"
    b.on_link(0.1, 4000, 1000)  # 0.64 s: goes
    assert b.hold_back(0.1) == ""


def test_the_non_keyframe_rate_is_what_the_keyframes_leave():
    b = UplinkBudget(UplinkBudgetConfig(budget_kbps=500.0))  # 62.5 kB/s
    for k in range(40):  # 20 Hz of 1 kB non-keyframes, a 10 kB keyframe a second
        b.on_sent(k * 0.05, 10_000 if k % 20 == 0 else 1000, keyframe=k % 20 == 0)
    assert b.hold_back(2.0) == "" and b.rate_hz == 20.0  # 10 + 20 kB/s fit in 50
    tight = UplinkBudget(UplinkBudgetConfig(budget_kbps=240.0))  # 30 kB/s, 24 planned
    for k in range(40):  # (the last non-keyframe at 1.95 s)
        tight.on_sent(k * 0.05, 10_000 if k % 20 == 0 else 1000, keyframe=k % 20 == 0)
    assert tight.hold_back(2.0) == "rate" and tight.rate_hz == 10.0  # 10 + 10 kB/s fit
    assert tight.hold_back(2.06) == ""  # 0.11 s after the last: 10 Hz
    starved = UplinkBudget(UplinkBudgetConfig(budget_kbps=50.0))
    for k in range(40):
        starved.on_sent(k * 0.05, 20_000 if k % 20 == 0 else 1000, keyframe=k % 20 == 0)
    starved.hold_back(2.0)
    assert starved.rate_hz == 5.0  # nothing left beside the keyframes: the lowest rate


def test_the_imu_comes_off_the_non_keyframes():
    """The IMU always goes: what it costs (measured) comes off what the keyframes leave for
    non-keyframes; keyframes keep their share. A vibrating IMU's 1.5 kB/s at 50 kbit/s
    (5 kB/s planned) leaves fewer non-keyframes than a clean one's 0.75 kB/s."""
    clean, noisy = (UplinkBudget(UplinkBudgetConfig(budget_kbps=50.0)) for _ in range(2))
    for k in range(40):  # 5 Hz for 8 s: 300 B of features each, with 150 or 300 B of IMU
        clean.on_sent(k * 0.2, 450, keyframe=False, imu_bytes=150)
        noisy.on_sent(k * 0.2, 600, keyframe=False, imu_bytes=300)
    assert clean.keyframe_plan() == noisy.keyframe_plan()
    for k in (40, 41):  # two 3 kB keyframes: ~0.7 kB/s over the window
        for bud, imu in ((clean, 150), (noisy, 300)):
            bud.on_sent(k * 0.2, 3000 + imu, keyframe=True, features=150, imu_bytes=imu)
    clean.hold_back(9.0)
    noisy.hold_back(9.0)
    assert (clean.rate_hz, noisy.rate_hz) == (10.0, 5.0)  # 3 kB/s fit beside the clean one
    # measured: 42 frames of 150 or 300 B of IMU over the 8.2 s they span
    assert (clean.stats()["imu_kbps"], noisy.stats()["imu_kbps"]) == (6.1, 12.3)
    assert clean.bytes_per_feature() == 20.0  # the keyframes' own bytes, not their IMU's


def test_auto_measures_the_rate_only_while_the_link_has_a_backlog():
    b = UplinkBudget(UplinkBudgetConfig(auto=True))
    assert b.rate_Bps() is None and b.hold_back(0.0) == ""  # nothing measured yet: all go
    b.on_link(0.0, 9000, 0)
    b.on_link(0.6, 9000, 0)
    b.on_link(1.2, 9000, 0)  # a backlog and no ack for 1.2 s: a stall, not a zero rate
    assert b.rate_Bps() is None and b.hold_back(1.2) == ""
    b = UplinkBudget(UplinkBudgetConfig(auto=True))
    b.on_link(0.0, 0, 0)
    b.on_link(1.0, 0, 50_000)  # idle link at the end: says nothing of its capacity
    assert b.rate_Bps() is None
    b.on_link(2.0, 20_000, 50_000)
    b.on_link(2.5, 20_000, 50_000)  # a big message's ack has not come yet ...
    b.on_link(3.0, 15_000, 56_250)  # ... now: 6250 B/s over the backlogged second, not 12500
    assert b.rate_Bps() == pytest.approx(6250.0)
    assert b.hold_back(3.0) == "backlog"  # 15 kB at 6.25 kB/s: 2.4 s
    b.on_link(20.0, 100, 70_000)  # the samples age out: the last estimate holds (an outage
    assert b.rate_Bps() == pytest.approx(6250.0)  # must not turn the budget off)
    b.on_link(20.5, 5000, 70_000)
    b.on_link(21.0, 2000, 72_000)
    b.on_link(21.5, 2000, 75_000)  # a new second of samples replaces it
    assert b.rate_Bps() == pytest.approx(5000 / 1.5)  # 5 kB acknowledged in 1.5 s of backlog


def test_parse_names_what_is_wrong():
    assert UplinkBudgetConfig.parse(None) == UplinkBudgetConfig()
    assert UplinkBudgetConfig.parse("unlimited") == UplinkBudgetConfig()
    assert UplinkBudgetConfig.parse("auto").auto
    assert UplinkBudgetConfig.parse("50").budget_kbps == 50.0
    with pytest.raises(ValueError, match="kbit/s"):
        UplinkBudgetConfig.parse("fast")
    with pytest.raises(ValueError, match="positive"):
        UplinkBudgetConfig.parse("-5")


def test_the_core_counts_a_frame_left_out_and_expects_no_pose_for_it():
    core = RobotCore(8, 6, uplink=UplinkBudget(UplinkBudgetConfig(budget_kbps=50.0)))
    core.handle(LinkLoad(10_000, 0), 0.0)
    core.handle(ImageInput(1_000, np.zeros((6, 8), np.uint8)), 0.0)
    job = core.next_job(1.0)  # (no IMU: tracked after the wait)
    assert job is not None and job.hold_back == "backlog"
    assert core.handle(FrameDone(None, 1_000, job.hold_back), 1.1) == []
    assert core.frames_left_out == 1 and core.uplink.left_out["backlog"] == 1
    assert core.poses.pending == 0  # no pose is owed for it
    sent = RobotFrame(1, 2_000, True, b"x" * 100, b"y" * 10)
    assert len(core.handle(FrameDone(sent, 2_000), 1.2)) == 1
    assert core.uplink.sent_keyframes == 1
    assert core.stats()["uplink"]["left_out"] == {"rate": 0, "backlog": 1, "outage": 0}


def test_keyframes_are_planned_to_fit_the_budget(euroc_micro):
    """At 50 kbit/s a 1000-feature keyframe (~21 kB) takes 3.4 s: the plan keeps 300 features
    about 2 s apart; at 1 Mbit/s the configured keyframes fit; without a budget, no plan. The
    front end applies it (and goes back to its configuration)."""
    from common.data.euroc import EurocSequence
    from services.robot.config import FrontEndConfig
    from services.robot.tracker import FrontEnd

    assert UplinkBudget().keyframe_plan() is None
    slow = UplinkBudget(UplinkBudgetConfig(budget_kbps=50.0)).keyframe_plan()
    assert slow is not None and slow.n_features == 300
    assert slow.n_features * 21 / slow.min_interval_s <= 0.6 * 0.8 * 6250 * 1.05
    assert 1.5 < slow.min_interval_s < 3.0
    # lost tracking: a keyframe no sooner than the link carries one (6.3 kB at 5 kB/s)
    assert slow.lost_min_interval_s == pytest.approx(300 * 21 / 5000, abs=0.05)
    behind = UplinkBudget(UplinkBudgetConfig(budget_kbps=50.0))
    behind.on_link(0.0, 50_000, 0)  # 8 s of backlog (an outage): only keyframes tracking needs
    held = behind.keyframe_plan()
    assert held is not None and held.min_interval_s == float("inf")
    mid = UplinkBudget(UplinkBudgetConfig(budget_kbps=200.0)).keyframe_plan()
    assert mid is not None and mid.n_features == 650  # 0.7 s of the link: 13.7 kB
    fast = UplinkBudget(UplinkBudgetConfig(budget_kbps=1000.0)).keyframe_plan()
    assert fast is not None and fast.n_features == 1000 and fast.min_interval_s < 0.5
    # What the keyframes sent cost is measured: cheaper features (continued tracks carry
    # their descriptor) buy more of them, or the same sooner.
    cheap = UplinkBudget(UplinkBudgetConfig(budget_kbps=200.0))
    cheap.on_sent(0.0, 10_500, True, 1000)
    assert cheap.bytes_per_feature() == 10.5
    plan = cheap.keyframe_plan()
    assert plan is not None and plan.n_features == 1000  # 0.7 s of the link: 13.7 kB
    cheap.on_sent(11.0, 4_200, True, 200)  # the older keyframe leaves the 10 s window
    assert cheap.bytes_per_feature() == 21.0
    assert cheap.stats()["bytes_per_feature"] == 21.0
    seq = EurocSequence(euroc_micro)
    fe = FrontEnd(FrontEndConfig(), seq.cam0, seq.imu)
    fe.set_keyframe_plan(slow)
    assert fe.orb.n_features == 300 and fe.config.keyframe.min_interval_s == slow.min_interval_s
    assert fe.config.keyframe.max_interval_s == 2 * slow.min_interval_s
    assert fe.config.keyframe.min_tracked == 45  # 150 of 1000 features -> of 300
    first = fe.process(next(seq.frames(0, 1)).image, next(seq.frames(0, 1)).timestamp_ns)
    assert first.is_keyframe and 250 <= len(first) <= 300
    fe.set_keyframe_plan(None)
    assert fe.orb.n_features == 1000 and fe.config == FrontEndConfig()


def test_a_frame_left_out_gets_the_robots_own_predicted_pose():
    """Once the edge's state came, a frame the budget left out still has a pose on the robot:
    the IMU propagation, status "predicted", placed in the global map like the edge's; it is
    not written to the TUM files (they keep the edge's poses in camera-time order)."""
    from services.robot.poses import tum_line

    core = RobotCore(8, 6)
    core.poses.captured(5_000, 1.0)
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    (out,) = core.handle(FrameDone(None, 5_000, "rate", (7, T)), 1.05)
    pose = out.pose
    assert pose.status == "predicted" and pose.map_id == 7
    assert np.allclose(pose.T_map_body, T) and pose.latency_s == pytest.approx(0.05)
    assert core.poses.summary()["predicted"] == 1 and core.poses.pending == 0
    assert core.poses.latencies_s == deque() or len(core.poses.latencies_s) == 0
    assert tum_line(pose) is None


def test_an_outage_is_data_waiting_and_nothing_acknowledged_for_two_seconds():
    b = UplinkBudget(UplinkBudgetConfig(budget_kbps=100.0))
    b.on_link(0.0, 3000, 0)
    b.on_link(1.0, 3000, 0)
    assert b.hold_back(1.0) == ""  # 0.24 s of backlog, 1 s without an ack: not yet
    b.on_link(2.1, 9000, 0)
    assert b.outage(2.1) and b.hold_back(2.1) == "outage"
    b.on_link(2.3, 8000, 1000)  # the link is back
    assert not b.outage(2.3) and b.hold_back(2.3) == ""
    idle = UplinkBudget(UplinkBudgetConfig(budget_kbps=100.0))
    idle.on_link(0.0, 0, 0)
    idle.on_link(5.0, 0, 0)  # nothing waits: no outage however long
    assert not idle.outage(5.0)
    assert not UplinkBudget().outage(100.0)  # no budget: the recorder never leaves out
