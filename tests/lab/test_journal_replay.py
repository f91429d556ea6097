"""A robot's edge journal replayed in process (lab.journal_replay): a freshly rendered 10 s
synthetic robot through the robot's front end and codecs, journaled as an edge journals it,
then replayed through the edge's decoding, VIO and cloud uplink."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from common.data.euroc import EurocSequence
from common.data.synth import SynthConfig, generate_dataset
from common.links.edge_cloud import KeyframeUpdateCoded
from common.links.robot_edge import RobotSequenceEnd, sensors_message
from common.links.sensors import Sensors
from common.protocol.messages import Message, encode_payload
from common.vocabulary import Vocabulary
from lab.journal_replay import cloud_bytes, point_sends, replay_journal
from services.edge.journal import JournalRecord, JournalStore
from services.edge.session_config import EdgeSessionConfig
from services.edge.vio.types import TrackingStatus
from services.robot.app import RobotApp
from services.robot.config import FrontEndConfig


@pytest.fixture(scope="module")
def journaled(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int]:
    """An edge state folder holding robot0's journal of a rendered 10 s flight; its frames."""
    root = tmp_path_factory.mktemp("journal")
    cfg = SynthConfig(robots=1, seconds=10.0, seed=7, progress=False, contact_sheet=False)
    generate_dataset(root / "synth", cfg)
    seq = EurocSequence(root / "synth" / "robot0")
    app = RobotApp(FrontEndConfig(), seq.cam0, seq.imu, Vocabulary.load())
    msgs: list[Message] = [sensors_message(Sensors(seq.cam0, seq.imu))]
    for fr in seq.frames(0, len(seq)):
        assert fr.image is not None
        msgs.append(app.process(fr.timestamp_ns, fr.image, fr.imu))
    msgs.append(RobotSequenceEnd(len(seq)))
    store = JournalStore(root / "state", fsync_interval_s=0.0)
    store.register("robot0")
    journal = store.journal("robot0")
    for seq_no, m in enumerate(msgs, start=1):
        journal.append(JournalRecord(b"s", seq_no, type(m).TYPE_ID, encode_payload(m)))
    store.close()
    return root / "state", len(seq)


@pytest.mark.slow
def test_replay_gives_every_frame_and_the_cloud_uplink(journaled):
    state, n = journaled
    rep = replay_journal(state, "robot0")
    assert len(rep.frames) == n and rep.runs == 1
    assert sum(f.robot_keyframe for f in rep.frames) == len(rep.keyframe_tracks) > 0
    tracked = [f for f in rep.frames if f.status is TrackingStatus.TRACKING]
    assert len(tracked) > n // 2  # VI-initialised within the first half
    assert all(f.map_id == tracked[0].map_id for f in tracked)  # one map
    sizes = cloud_bytes(rep.cloud)
    assert sizes["KeyframeUpdateCoded"] > 0 and sizes["MapPointUpdateCoded"] > 0
    ps = point_sends(rep.cloud)
    assert ps.distinct > 100 and ps.sends >= ps.distinct and len(ps.moves_m) > 0
    # every keyframe message names a robot keyframe whose track numbers were kept
    for m in rep.cloud:
        if isinstance(m, KeyframeUpdateCoded):
            assert int(m.timestamp_ns) in rep.keyframe_tracks


@pytest.mark.slow
def test_replay_is_deterministic_and_session_options_change_only_the_uplink(journaled):
    state, _ = journaled
    a = replay_journal(state, "robot0")
    b = replay_journal(
        state, "robot0", session=replace(EdgeSessionConfig(), point_settle_keyframes=3)
    )
    # the same VIO outcome frame by frame
    assert [(f.status, f.map_id, f.n_inliers) for f in a.frames] == [
        (f.status, f.map_id, f.n_inliers) for f in b.frames
    ]
    pa, pb = point_sends(a.cloud), point_sends(b.cloud)
    # points held until 3 keyframes settle them are sent fewer times each, none lost
    assert pb.sends / pb.distinct < pa.sends / pa.distinct
    assert pb.distinct >= 0.9 * pa.distinct
    again = replay_journal(state, "robot0")
    assert cloud_bytes(again.cloud) == cloud_bytes(a.cloud)
    np.testing.assert_array_equal(again.frames[-1].timestamp_ns, a.frames[-1].timestamp_ns)
