"""The edge's cloud budget: which robot keyframes go up (services/edge/cloud_budget.py) and
how a session applies it (SessionUplink)."""

from __future__ import annotations

import numpy as np
import pytest

from common.codec import KeyframeFeatures, decode_standalone_keyframe
from common.data.synth import EUROC_CAM0
from common.links.edge_cloud import KeyframeUpdateCoded
from common.vocabulary import Vocabulary
from services.edge.cloud_budget import CloudBudget, CloudBudgetConfig, KeyframeAllowance
from services.edge.robot_session import RobotSession
from services.edge.vio.types import KeyframeSnapshot, MapPointBatch, MapUpdate


def test_no_budget_allows_everything() -> None:
    b = CloudBudget()
    b.on_sent(0.0, 30_000, True)
    assert b.allowance(3) is None


def test_a_robots_share_pays_for_features_at_the_links_bytes_per_feature() -> None:
    b = CloudBudget(CloudBudgetConfig(budget_kbps=100.0, headroom=0.8))  # 12 500 B/s
    assert b.allowance(3) is None  # nothing measured yet: every keyframe goes whole
    for k in range(4):  # 4 keyframes of 400 features in 8 kB, and 2 kB of points etc.
        b.on_sent(float(k), 8_000, 400)
        b.on_sent(k + 0.5, 2_000)
    assert b.bytes_per_feature() == pytest.approx(25.0)
    a = b.allowance(3)
    assert a is not None and a.share_Bps == pytest.approx(0.8 * 12_500 / 3)
    assert a.features(3.0) == 400  # 3333 B/s x 3 s / 25 B, in steps of 50
    assert a.features(2.0) == 0  # 266 < 300: it stays on the edge
    b.on_link(5.0, 12_500 * 4, 0)  # 4 s of backlog > max_delay_s 3 s
    held = b.allowance(3)
    assert held is not None and held.hold and held.features(100.0) == 0


def test_a_bad_budget_names_itself() -> None:
    assert CloudBudgetConfig.parse("auto").auto
    assert CloudBudgetConfig.parse(None) == CloudBudgetConfig()
    assert CloudBudgetConfig.parse("150").budget_kbps == 150.0
    with pytest.raises(ValueError, match="cloud budget 'fast'"):
        CloudBudgetConfig.parse("fast")
    with pytest.raises(ValueError, match="positive"):
        CloudBudgetConfig.parse("-5")


def _keyframe(session: RobotSession, kf_id: int, t_s: float) -> KeyframeSnapshot:
    """A robot keyframe with 400 features, the first 100 on map points 1000 + row; its
    features on the session."""
    rng = np.random.default_rng(kf_id)
    t_ns = int(t_s * 1e9)
    xy = rng.integers(10, 400, (400, 2))
    kp = np.column_stack([xy, np.zeros(400, int), rng.integers(0, 30, 400)])
    desc = rng.integers(0, 256, (400, 32), dtype=np.uint8)
    feats = KeyframeFeatures(kp, desc, np.full(400, -1)).canonical()
    session._kf_features[t_ns] = feats
    T = np.eye(4)
    T[0, 3] = t_s
    z = np.zeros(3)
    point_ids = np.full(400, -1)
    point_ids[:100] = 1000 + np.arange(100)
    return KeyframeSnapshot(
        kf_id, 0, t_ns, T, z, z, z, np.arange(400), point_ids, None, robot_keyframe=True
    )


def _sent(session: RobotSession, kf: KeyframeSnapshot) -> list[KeyframeUpdateCoded]:
    upd = MapUpdate(0, True, (kf,), MapPointBatch.of(()), ())
    return [m for m in session._uplink(upd) if isinstance(m, KeyframeUpdateCoded)]


def test_a_session_sends_what_its_share_paid_for_and_keeps_the_rest_on_the_edge() -> None:
    vocab = Vocabulary.load()
    session = RobotSession("r", EUROC_CAM0, vocab)
    session.cloud_allowance = KeyframeAllowance(1000.0, 10.0, 300)  # 100 features a second
    sent: list[KeyframeUpdateCoded] = []
    for k in range(12):  # a keyframe every 0.3 s
        sent += _sent(session, _keyframe(session, k, 0.3 * k))
    # the map's first goes whole; then one once 3 s paid for 300 features: keyframe 10
    assert [m.keyframe_id for m in sent] == [0, 10]
    assert [m.previous_keyframe_id for m in sent] == [-1, 0]
    assert session.kept_on_edge == {"rate": 10, "backlog": 0}
    first, cut = (decode_standalone_keyframe(vocab, m.features, session.codec) for m in sent)
    assert len(first) == 400 and len(cut) == 300
    rows = session._feature_rows[(0, 10)]
    assert (rows[:100] >= 0).all()  # every feature on a map point kept
    assert (rows >= 0).sum() == 300 and (np.sort(rows[rows >= 0]) == np.arange(300)).all()
    # a point observed in keyframe 10 at a kept and a dropped row: renamed, and dropped
    dropped = int(np.flatnonzero(rows < 0)[0])
    batch = MapPointBatch(
        np.array([7, 8]),
        np.zeros((2, 3)),
        np.array([2, 1]),
        np.array([10, 10, 0]),
        np.array([150, dropped, 3]),
    )
    out = session._on_rows_sent(0, batch)
    assert out.counts.tolist() == [1, 1]
    assert out.keyframe_ids.tolist() == [10, 0]
    assert out.feature_indices.tolist() == [int(rows[150]), 3]
    session.cloud_allowance = KeyframeAllowance(hold=True)
    assert not _sent(session, _keyframe(session, 12, 9.0))
    assert session.kept_on_edge["backlog"] == 1
    session.cloud_allowance = None  # no budget: the next goes whole, chained to the last sent
    (m,) = _sent(session, _keyframe(session, 13, 9.3))
    assert (m.keyframe_id, m.previous_keyframe_id) == (13, 10)
    assert len(decode_standalone_keyframe(vocab, m.features, session.codec)) == 400
