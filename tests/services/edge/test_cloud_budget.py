"""The edge's cloud budget: which robot keyframes go up (services/edge/cloud_budget.py) and
how a session applies it (SessionUplink)."""

from __future__ import annotations

import numpy as np
import pytest

from common.codec import KeyframeFeatures
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


def test_the_interval_is_what_the_link_carries_per_keyframe_for_every_robot() -> None:
    b = CloudBudget(CloudBudgetConfig(budget_kbps=100.0, headroom=0.8))  # 12 500 B/s
    assert b.allowance(3) is None  # nothing measured yet: every keyframe goes
    for k in range(4):  # 4 keyframes of 8 kB, and 8 kB of points etc. beside them
        b.on_sent(float(k), 8_000, True)
        b.on_sent(k + 0.5, 2_000, False)
    assert b.bytes_per_keyframe() == pytest.approx(10_000.0)
    a = b.allowance(3)
    assert a == KeyframeAllowance(round(3 * 10_000 / (0.8 * 12_500), 1))  # 3.0 s
    b.on_link(5.0, 12_500 * 4, 0)  # 4 s of backlog > max_delay_s 3 s
    assert b.allowance(3) == KeyframeAllowance(0.0, hold=True)


def test_a_bad_budget_names_itself() -> None:
    assert CloudBudgetConfig.parse("auto").auto
    assert CloudBudgetConfig.parse(None) == CloudBudgetConfig()
    assert CloudBudgetConfig.parse("150").budget_kbps == 150.0
    with pytest.raises(ValueError, match="cloud budget 'fast'"):
        CloudBudgetConfig.parse("fast")
    with pytest.raises(ValueError, match="positive"):
        CloudBudgetConfig.parse("-5")


def _keyframe(session: RobotSession, kf_id: int, t_s: float) -> KeyframeSnapshot:
    """A robot keyframe with 50 features, none on a map point; its features on the session."""
    rng = np.random.default_rng(kf_id)
    t_ns = int(t_s * 1e9)
    xy = rng.integers(10, 400, (50, 2))
    kp = np.column_stack([xy, np.zeros(50, int), rng.integers(0, 30, 50)])
    desc = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    feats = KeyframeFeatures(kp, desc, np.full(50, -1)).canonical()
    session._kf_features[t_ns] = feats
    T = np.eye(4)
    T[0, 3] = t_s
    z = np.zeros(3)
    return KeyframeSnapshot(
        kf_id, 0, t_ns, T, z, z, z, np.arange(50), np.full(50, -1), None, robot_keyframe=True
    )


def test_a_session_uplinks_keyframes_as_far_apart_as_allowed_and_chains_them() -> None:
    session = RobotSession("r", EUROC_CAM0, Vocabulary.load())
    session.cloud_allowance = KeyframeAllowance(1.0)
    sent: list[KeyframeUpdateCoded] = []
    for k in range(10):  # a keyframe every 0.3 s
        upd = MapUpdate(0, True, (_keyframe(session, k, 0.3 * k),), MapPointBatch.of(()), ())
        sent += [m for m in session._uplink(upd) if isinstance(m, KeyframeUpdateCoded)]
    # the map's first goes; then each once 0.95 s of camera time passed: 0, 4, 8 (1.2 s)
    assert [m.keyframe_id for m in sent] == [0, 4, 8]
    assert [m.previous_keyframe_id for m in sent] == [-1, 0, 4]
    assert session.kept_on_edge == {"rate": 7, "backlog": 0}
    assert session.vio_keyframes == 3
    session.cloud_allowance = KeyframeAllowance(0.0, hold=True)
    upd = MapUpdate(0, True, (_keyframe(session, 10, 3.0),), MapPointBatch.of(()), ())
    assert not [m for m in session._uplink(upd) if isinstance(m, KeyframeUpdateCoded)]
    assert session.kept_on_edge["backlog"] == 1
    session.cloud_allowance = None  # no budget: the next goes, chained to the last sent
    upd = MapUpdate(0, True, (_keyframe(session, 11, 3.3),), MapPointBatch.of(()), ())
    (m,) = [m for m in session._uplink(upd) if isinstance(m, KeyframeUpdateCoded)]
    assert (m.keyframe_id, m.previous_keyframe_id) == (11, 8)
