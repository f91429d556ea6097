"""The edge's core driven directly with fabricated events, as h11's tests drive a connection:
no sockets, no temporary folders, no asyncio, no decoder and no VIO. The "driver" here is the
test itself: it answers each ``Decode`` with a ``FrameDecoded`` and each ``FeedWorker`` with a
``StepDone``, when it chooses to."""

from __future__ import annotations

import numpy as np
import pytest

from common.calibration import EUROC_IMU
from common.camera import PinholeRadtan
from common.links.edge_cloud import AgentSensors, MapPlacement, encode_pose_correction
from common.links.robot_edge import MapPlacement as RobotMapPlacement
from common.links.robot_edge import RobotFrame, RobotSensors, RobotSequenceEnd, sensors_message
from common.links.sensors import Sensors
from common.links.wire import pack_pose
from common.protocol.link_state import InboundPosition
from common.protocol.messages import Message
from services.edge.config import EdgeConfig
from services.edge.core import EdgeCore
from services.edge.core_events import (
    Action,
    CloseSequence,
    CloudMessage,
    Decode,
    EdgeCoreError,
    FeedbackLost,
    FeedWorker,
    FrameDecoded,
    FrameUndecodable,
    Hold,
    Journal,
    Reject,
    Release,
    RobotMessage,
    RobotSendFailed,
    SendStatus,
    StartRobot,
    StepDone,
    ToCloud,
    ToRobot,
    WorkerResult,
)
from services.edge.vio.types import FrameObservation
from services.edge.worker import WorkItem
from sim.vio import EUROC_CAMERA

SENSORS = Sensors(EUROC_CAMERA, EUROC_IMU)
OTHER = Sensors(
    PinholeRadtan(640, 480, 380.0, 378.5, 315.5, 242.25, -0.22, 0.05, 2e-4, -1e-4).to_calibration(
        EUROC_CAMERA.T_body_cam, 20.0
    ),
    EUROC_IMU,
)
MS = 1_000_000


def item(k: int, t_ms: int, keyframe: bool = False) -> WorkItem:
    """Frame ``k`` at camera time ``t_ms`` with two IMU samples of its own (gyro rows = k)."""
    t = t_ms * MS
    obs = FrameObservation(
        t, np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0, np.uint8), keyframe
    )
    imu_t = np.array([t - 5 * MS, t], np.int64)
    return WorkItem(k, imu_t, np.full((2, 3), float(k)), np.zeros((2, 3)), obs)


def frame(k: int, t_ms: int, keyframe: bool = False) -> RobotFrame:
    return RobotFrame(k, t_ms * MS, keyframe, b"", b"")


def joined(config: EdgeConfig | None = None, journal: bool = False) -> EdgeCore:
    core = EdgeCore(config or EdgeConfig(worker="thread"), journal=journal)
    core.handle(RobotMessage("a", sensors_message(SENSORS), b"s", 1), 0.0)
    return core


def arrive(core: EdgeCore, wi: WorkItem, seq: int = 0, replaying: bool = False) -> list[Action]:
    """A robot frame in: the core asks for its decoding; the decoded ``wi`` goes back."""
    kf = wi.obs is not None and wi.obs.is_keyframe
    t_ms = 0 if wi.obs is None else wi.obs.timestamp_ns // MS
    msg = frame(wi.frame_index, t_ms, kf)
    asked = core.handle(RobotMessage("a", msg, b"s", seq, replaying=replaying), 0.0)
    assert len(asked) == 1 and isinstance(asked[0], Decode) and asked[0].frame is msg
    return core.handle(FrameDecoded("a", wi), 0.0)


def fed(actions: list[Action]) -> list[int]:
    return [a.item.frame_index for a in actions if isinstance(a, FeedWorker)]


# ------------------------------------------------------------------ join and refusals
def test_a_frame_before_sensors_is_refused_with_the_reason() -> None:
    core = EdgeCore()
    (act,) = core.handle(RobotMessage("a", frame(0, 0, True), b"s", 1), 0.0)
    assert isinstance(act, Reject) and act.agent_id == "a"
    assert "robot a: RobotFrame before its RobotSensors" in act.reason
    (act,) = core.handle(RobotMessage("a", RobotSequenceEnd(3), b"s", 2), 0.0)
    assert isinstance(act, Reject) and "before its RobotSensors" in act.reason
    assert core.robots == {}


def test_a_damaged_description_is_refused() -> None:
    damaged = bytearray(sensors_message(SENSORS).sensors)
    damaged[10] ^= 1
    (act,) = EdgeCore().handle(RobotMessage("a", RobotSensors(bytes(damaged))), 0.0)
    assert isinstance(act, Reject) and "robot a: invalid sensor description" in act.reason


def test_a_rejoin_with_another_calibration_is_refused_the_same_one_taken() -> None:
    core = EdgeCore()
    start, up = core.handle(RobotMessage("a", sensors_message(SENSORS), b"s", 1), 0.0)
    assert isinstance(start, StartRobot) and start.sensors.same_as(SENSORS)
    assert isinstance(up, ToCloud) and isinstance(up.message, AgentSensors)
    assert core.handle(RobotMessage("a", sensors_message(SENSORS), b"t", 1), 0.0) == []
    (act,) = core.handle(RobotMessage("a", sensors_message(OTHER), b"t", 2), 0.0)
    assert isinstance(act, Reject) and "robot a re-joined with other sensors" in act.reason
    assert core.robots["a"].sensors.same_as(SENSORS)
    # another robot may join with those sensors
    assert isinstance(core.handle(RobotMessage("b", sensors_message(OTHER)), 0.0)[0], StartRobot)


def test_an_undecodable_frame_is_refused_and_the_next_one_taken() -> None:
    core = joined()
    assert isinstance(core.handle(RobotMessage("a", frame(0, 0, True)), 0.0)[0], Decode)
    (act,) = core.handle(FrameUndecodable("a", 0, "bad bits"), 0.0)
    assert isinstance(act, Reject) and act.reason == "robot a: frame 0 does not decode: bad bits"
    assert fed(arrive(core, item(0, 0, True))) == [0]
    with pytest.raises(EdgeCoreError):  # a decoded frame the core did not ask for
        core.handle(FrameDecoded("a", item(1, 50)), 0.0)


# ------------------------------------------------------------------ journal
def test_live_messages_are_journaled_once_queued_and_duplicates_dropped() -> None:
    core = EdgeCore(journal=True)
    acts = core.handle(RobotMessage("a", sensors_message(SENSORS), b"s", 1), 0.0)
    assert [type(a) for a in acts] == [StartRobot, ToCloud, Journal]
    acts = arrive(core, item(0, 0, True), seq=2)
    assert [type(a) for a in acts] == [Journal, FeedWorker]
    assert isinstance(acts[0], Journal) and (acts[0].stream_id, acts[0].seq) == (b"s", 2)
    last = InboundPosition(b"s", 2)  # the driver's journal says so (a restart)
    assert core.handle(RobotMessage("a", frame(0, 0, True), b"s", 2, last), 0.0) == []
    assert core.handle(RobotMessage("a", frame(1, 50), b"s", 3, last), 0.0) != []
    # replayed messages are never journaled again; without a journal nothing is
    replay = EdgeCore(journal=True)
    acts = replay.handle(RobotMessage("a", sensors_message(SENSORS), replaying=True), 0.0)
    assert not any(isinstance(a, Journal) for a in acts)
    assert not any(isinstance(a, Journal) for a in arrive(joined(), item(0, 0, True)))


# ------------------------------------------------------------------ queue and back-pressure
def test_a_full_queue_holds_the_handler_until_the_runner_makes_room() -> None:
    core = joined(EdgeConfig(worker="thread", max_queued_frames=2), journal=True)
    assert fed(arrive(core, item(0, 0, True), 1)) == [0]  # the runner waited: fed at once
    assert fed(arrive(core, item(1, 50), 2)) == []  # its only step is being finished: queued
    assert fed(arrive(core, item(2, 100), 3)) == []
    assert arrive(core, item(3, 150), 4) == [Hold("a")]  # the queue is full: not journaled
    assert not core.idle("a") and core.stats("a")["queued"] == 2
    acts = core.handle(StepDone("a"), 0.0)  # step 0 done: 1 and 2 go, 3 takes their room
    assert fed(acts) == [1, 2]
    journal = [a for a in acts if isinstance(a, Journal)]
    assert [j.seq for j in journal] == [4] and acts[-1] == Release("a")
    assert core.stats("a")["queued"] == 1
    assert fed(core.handle(StepDone("a"), 0.0)) == [3]
    for _ in range(2):
        assert not core.idle("a")
        assert core.handle(StepDone("a"), 0.0) == []
    assert core.idle("a")
    with pytest.raises(EdgeCoreError):
        core.handle(StepDone("a"), 0.0)


def test_replayed_frames_are_never_held() -> None:
    core = joined(EdgeConfig(worker="thread", max_queued_frames=1))
    for k in range(5):
        assert Hold("a") not in arrive(core, item(k, 50 * k, k == 0), replaying=True)
    assert core.stats("a")["queued"] == 4


def test_a_message_given_up_by_the_driver_does_not_block_the_next() -> None:
    """A handler that failed after Decode (the transport retries it) or was cancelled while
    held: the next message of the robot is taken as if the first never came."""
    core = joined(EdgeConfig(worker="thread", max_queued_frames=1))
    assert isinstance(core.handle(RobotMessage("a", frame(0, 0, True)), 0.0)[0], Decode)
    assert fed(arrive(core, item(0, 0, True))) == [0]
    assert fed(arrive(core, item(1, 50))) == []
    assert arrive(core, item(2, 100)) == [Hold("a")]
    assert fed(arrive(core, item(2, 100))) == []  # the retry is held again, not doubled
    assert fed(core.handle(StepDone("a"), 0.0)) == [1]


# ------------------------------------------------------------------ fresh before complete
def _late_robot(config: EdgeConfig, replaying: bool = False) -> tuple[EdgeCore, list[Action]]:
    """Frames every 50 ms, the VIO busy with frame 0 while 1..8 (2 a keyframe) queue up;
    then the driver finishes steps one by one. Returns the core and every FeedWorker."""
    core = joined(config)
    feeds = arrive(core, item(0, 0, True), replaying=replaying)
    for k in range(1, 9):
        feeds += arrive(core, item(k, 50 * k, k == 2), replaying=replaying)
    for _ in range(12):
        if core.idle("a"):
            break
        feeds += core.handle(StepDone("a"), 0.0)
    return core, [a for a in feeds if isinstance(a, FeedWorker)]


def test_stale_non_keyframes_are_skipped_and_their_imu_goes_with_the_next_frame() -> None:
    core, feeds = _late_robot(EdgeConfig(worker="thread", max_vio_lag_s=0.1))
    # newest 400 ms: 1 (50 ms) is stale, the keyframe 2 (100 ms) goes anyway with 1's IMU;
    # then 3, 4, 5 (150..250 ms) are stale and 6 (300 ms, 100 ms behind) goes with their IMU
    assert [a.item.frame_index for a in feeds] == [0, 2, 6, 7, 8]
    assert core.stats("a")["frames_skipped_stale"] == 4
    by = {a.item.frame_index: a.item for a in feeds}
    assert by[2].gyro[:, 0].tolist() == [1, 1, 2, 2]
    assert by[6].gyro[:, 0].tolist() == [3, 3, 4, 4, 5, 5, 6, 6]
    assert np.all(np.diff(by[6].imu_t_ns) > 0)  # in time order
    assert by[7].gyro[:, 0].tolist() == [7, 7]  # the carry went once
    assert by[6].obs is not None and by[6].obs.timestamp_ns == 300 * MS


def test_nothing_is_skipped_without_a_lag_or_while_replaying() -> None:
    for config, replaying in [
        (EdgeConfig(worker="thread"), False),
        (EdgeConfig(worker="thread", max_vio_lag_s=0.1), True),
    ]:
        core, feeds = _late_robot(config, replaying)
        assert [a.item.frame_index for a in feeds] == list(range(9))
        assert core.stats("a")["frames_skipped_stale"] == 0
        assert all(a.replaying == replaying for a in feeds)


# ------------------------------------------------------------------ the cloud's messages
def test_a_correction_goes_with_the_next_frame_fed() -> None:
    core = joined()
    assert fed(arrive(core, item(0, 0, True))) == [0]
    T = np.tile(np.eye(4), (2, 1, 1))
    T[1, 0, 3] = 0.5
    msg = encode_pose_correction("a", 3, np.array([4, 9]), T)
    assert core.handle(CloudMessage(msg), 0.0) == []
    assert fed(arrive(core, item(1, 50))) == []  # queued behind step 0
    (feed,) = core.handle(StepDone("a"), 0.0)
    assert isinstance(feed, FeedWorker) and feed.item.frame_index == 1
    ((map_id, poses),) = feed.item.corrections
    assert map_id == 3 and sorted(poses) == [4, 9]
    assert np.allclose(poses[9], T[1], atol=1e-4)
    core.handle(StepDone("a"), 0.0)
    (feed,) = arrive(core, item(2, 100))
    assert isinstance(feed, FeedWorker) and feed.item.corrections == ()
    # for a robot the edge does not serve: ignored
    stranger = encode_pose_correction("z", 3, np.array([4]), T[:1])
    assert core.handle(CloudMessage(stranger), 0.0) == []


def test_a_placement_goes_to_the_robot_only_when_it_changed() -> None:
    core = joined()
    here, there = pack_pose(np.eye(4)), pack_pose(np.diag([1.0, -1.0, -1.0, 1.0]))
    (act,) = core.handle(CloudMessage(MapPlacement("a", 1, 7, here)), 0.0)
    assert isinstance(act, ToRobot) and act.agent_id == "a"
    assert act.message == RobotMapPlacement(1, 7, here)
    assert core.handle(CloudMessage(MapPlacement("a", 1, 7, here)), 0.0) == []
    (act,) = core.handle(CloudMessage(MapPlacement("a", 1, 7, there)), 0.0)
    assert isinstance(act, ToRobot) and act.message == RobotMapPlacement(1, 7, there)
    # that one did not reach the robot: the next copy of it goes again, the old one does not
    assert core.handle(RobotSendFailed("a", act.message), 0.0) == []
    assert core.handle(CloudMessage(MapPlacement("a", 1, 7, here)), 0.0) == []
    (act,) = core.handle(CloudMessage(MapPlacement("a", 1, 7, there)), 0.0)
    assert isinstance(act, ToRobot)
    assert core.handle(CloudMessage(MapPlacement("a", 1, 7, bytes(20))), 0.0) == []  # malformed
    assert core.handle(CloudMessage(MapPlacement("z", 1, 7, here)), 0.0) == []  # unknown robot


# ------------------------------------------------------------------ results and the end
def test_results_go_out_and_a_lost_feedback_makes_the_next_a_reset() -> None:
    core = joined()
    arrive(core, item(0, 0, True))
    robot: tuple[Message, ...] = (RobotMapPlacement(0, 0, pack_pose(np.eye(4))),)
    up: tuple[Message, ...] = (AgentSensors("a", b""),)
    acts = core.handle(WorkerResult("a", robot, up, status_due=True), 0.0)
    assert [type(a) for a in acts] == [ToRobot, ToCloud, SendStatus]
    feedback = RobotSequenceEnd(0)  # any message the session made for the robot
    assert core.handle(RobotSendFailed("a", feedback), 0.0) == [FeedbackLost("a")]


def test_the_sequence_end_closes_after_every_step_before_it() -> None:
    core = joined(EdgeConfig(worker="thread", max_queued_frames=1))
    arrive(core, item(0, 0, True))
    arrive(core, item(1, 50))
    assert core.handle(RobotMessage("a", RobotSequenceEnd(2)), 0.0) == [Hold("a")]
    assert core.stats("a")["expected_frames"] == 2
    acts = core.handle(StepDone("a"), 0.0)
    assert fed(acts) == [1] and acts[-1] == Release("a")
    assert arrive(core, item(0, 1000, True)) == [Hold("a")]  # a new stream's first frame
    # step 1 done: the end closes, the new frame takes its room but waits for the close
    assert core.handle(StepDone("a"), 0.0) == [CloseSequence("a"), Release("a")]
    assert not core.idle("a")
    assert fed(core.handle(StepDone("a"), 0.0)) == [0]  # after the close, the new stream
    core.handle(StepDone("a"), 0.0)
    assert core.idle("a")
