"""Chunked point bookkeeping, keyframe tracks, live ATE and bandwidth binning."""

from __future__ import annotations

import dataclasses

import numpy as np

from common.map_view import (
    BandwidthSample,
    Direction,
    GroundTruth,
    KeyframeSet,
    PointSet,
)
from dashboard.map_state import KeyframeTracks, PointChunks, live_ate_rmse
from dashboard.panels import (
    agents_markdown,
    bandwidth_series,
    counts_markdown,
    edge_rates,
    edges_markdown,
)
from dashboard.scene import frustum_segments


def _pts(ids, agent, z=0.0, pruned=False):
    ids = np.asarray(ids)
    p = np.zeros((ids.size, 3))
    p[:, 0] = ids
    p[:, 2] = z
    return PointSet(ids, p, np.full(ids.size, agent), np.full(ids.size, pruned))


def _none():
    return np.zeros(0, np.int64)


def test_new_points_go_to_new_chunks_and_consolidate():
    pc = PointChunks(chunk_points=100)
    pc.apply(_pts(range(60), agent=0), _none())
    ops = pc.take_ops()
    assert [len(u.p_world) for u in ops.upserts] == [60] and not ops.removals
    pc.apply(_pts(range(60, 90), agent=0), _none())
    ops = pc.take_ops()
    assert [len(u.p_world) for u in ops.upserts] == [30]  # only the new points are sent
    pc.apply(_pts(range(90, 130), agent=0), _none())
    ops = pc.take_ops()
    # 130 loose points >= 100: consolidated into one sealed chunk of 100 and one of 30
    assert sorted(len(u.p_world) for u in ops.upserts) == [30, 100]
    assert len(ops.removals) == 2  # the earlier two fragments (the third was never sent)
    assert len(pc) == 130 and pc.n_nodes == 2
    assert not pc.take_ops().upserts


def test_moved_point_dirties_only_its_chunk_and_removal_drops_it():
    pc = PointChunks(chunk_points=50)
    pc.apply(_pts(range(50), agent=0), _none())
    pc.apply(_pts(range(100, 150), agent=1), _none())
    pc.take_ops()
    pc.apply(_pts([7], agent=0, z=3.0, pruned=True), np.array([120]))
    ops = pc.take_ops()
    by_agent = {u.agent: u for u in ops.upserts}
    assert sorted(by_agent) == [0, 1]
    assert by_agent[0].p_world[7, 2] == 3.0 and by_agent[0].pruned[7]
    assert len(by_agent[1].p_world) == 49
    assert len(pc) == 99


def test_owner_change_and_max_points():
    pc = PointChunks(chunk_points=10, max_points=15)
    pc.apply(_pts(range(10), agent=0), _none())
    pc.apply(_pts([3], agent=2), _none())
    assert len(pc) == 10
    ops = pc.take_ops()
    assert {u.agent for u in ops.upserts} == {0, 2}
    pc.apply(_pts(range(20, 40), agent=1), _none())
    assert len(pc) == 15


def _kfs(ids, agent, t, x, pruned=None):
    n = len(ids)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = x
    return KeyframeSet(
        ids, np.full(n, agent), t, T, np.zeros(n, bool) if pruned is None else pruned
    )


def test_keyframe_tracks_sorted_by_time_and_dirty_agents():
    kt = KeyframeTracks()
    kt.apply(_kfs([3, 1, 2], 0, [3.0, 1.0, 2.0], [30.0, 10.0, 20.0]), _none())
    kt.apply(_kfs([9], 1, [0.5], [90.0]), _none())
    assert kt.take_dirty() == [0, 1]
    t, T, _ = kt.track(0)
    np.testing.assert_array_equal(t, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(T[:, 0, 3], [10.0, 20.0, 30.0])
    kt.apply(KeyframeSet.empty(), np.array([2]))
    assert kt.take_dirty() == [0]
    assert kt.position(2) is None and kt.position(9)[0] == 90.0


def test_live_ate_is_zero_after_rigid_motion_and_positive_with_noise():
    rng = np.random.default_rng(1)
    t = np.linspace(0, 10, 50)
    p_gt = np.stack([np.cos(t), np.sin(t), 0.1 * t], axis=1)
    gt = GroundTruth(0, t, p_gt)
    c, s = np.cos(0.4), np.sin(0.4)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    p_est = p_gt @ R.T + [1.0, 2.0, 3.0]
    assert live_ate_rmse(t, p_est, gt) < 1e-9
    noisy = p_est + rng.normal(0, 0.05, p_est.shape)
    assert 0.03 < live_ate_rmse(t, noisy, gt) < 0.08
    assert live_ate_rmse(t[:2], p_est[:2], gt) is None
    assert live_ate_rmse(t + 100.0, p_est, gt) is None


def test_bandwidth_series_bins_kbit_per_second():
    up, down = Direction.UP, Direction.DOWN
    samples = (
        BandwidthSample(0.5, "edge→cloud", up, "keyframe", 1000),
        BandwidthSample(9.5, "edge→cloud", up, "keyframe", 2000),
        BandwidthSample(9.6, "edge→cloud", up, "keyframe", 500),
        BandwidthSample(9.0, "robot0→edge", down, "ack", 125),
    )
    out = bandwidth_series(samples, window_s=5.0, bin_s=1.0)
    assert [s.link for s in out] == ["robot0→edge", "edge→cloud"]
    cloud = out[1]
    np.testing.assert_array_equal(cloud.t_s, [-4, -3, -2, -1, 0])
    np.testing.assert_allclose(cloud.kbit_s["keyframe ↑"], [0, 0, 0, 0, 20.0])  # 2500 B in 1 s
    np.testing.assert_allclose(out[0].kbit_s["ack ↓"], [0, 0, 0, 0, 1.0])  # (8.6, 9.6]


def test_frustum_segments_geometry():
    T = np.eye(4)[None].repeat(2, axis=0)
    T[1, :3, 3] = [5, 0, 0]
    seg = frustum_segments(T, scale=1.0)
    assert seg.shape == (16, 2, 3)
    np.testing.assert_allclose(seg[0, 0], [0, 0, 0])
    assert np.allclose(seg[:4, 1, 2], 1.0)  # corners at depth 1 along +z
    np.testing.assert_allclose(seg[8, 0], [5, 0, 0])


def test_edges_show_their_robots_and_link_rates():
    """Two sites: each edge lists the robots of the agents it serves (a robot that moved is on
    both) and the kbit/s of its robot links and its cloud link over the recent window."""
    from common.map_view import AgentRecord, AgentState, MapCounts, StatsSnapshot

    up, down = Direction.UP, Direction.DOWN
    agents = tuple(
        AgentRecord(i, AgentState.TRACKING, 10, 2, 9.0, 0, name=n, edge=e)
        for i, (n, e) in enumerate([("r0", "a"), ("r1", "a"), ("r1", "b"), ("r2", "b")])
    )
    samples = (
        BandwidthSample(1.0, "r0→a", up, "frame", 10_000),  # outside the 5 s window
        BandwidthSample(6.0, "r0→a", up, "frame", 1000),
        BandwidthSample(7.0, "r1→a", up, "frame", 1500),
        BandwidthSample(8.0, "r1→a", down, "ack", 250),
        BandwidthSample(9.0, "r2→b", up, "frame", 625),
        BandwidthSample(9.0, "a→cloud", up, "keyframe", 5000),
        BandwidthSample(9.5, "b→cloud", down, "correction", 1250),
    )
    stats = StatsSnapshot(10.0, agents, MapCounts(0, 0, 0, 0, 0, 0), samples)
    a, b = edge_rates(stats, window_s=5.0)
    assert (a.edge, a.robots, b.edge, b.robots) == ("a", ("r0", "r1"), "b", ("r1", "r2"))
    assert (a.robots_up, a.robots_down, a.cloud_up, a.cloud_down) == (4.0, 0.4, 8.0, 0.0)
    assert (b.robots_up, b.cloud_down) == (1.0, 2.0)
    text = edges_markdown(stats, window_s=5.0)
    assert "| a | r0, r1 | 4.0 / 0.4 | 8.0 / 0.0 |" in text
    assert "| r1 | b |" in agents_markdown(stats, {})


def test_agents_say_why_with_the_edges_numbers():
    """A robot that cannot initialise says why under the agents table, with the numbers the
    edge sent (the VI initialisation's refusal, the camera-IMU offset); one that says
    nothing adds no line."""
    from common.map_view import AgentRecord, AgentState, MapCounts, StatsSnapshot

    why = (
        "visual-only map (arbitrary scale); VI initialisation pending (VI init rejected: "
        "4 keyframes (< 10) over 1.2 s); camera-IMU offset +14.9 ± 0.4 ms"
    )
    agents = (
        AgentRecord(0, AgentState.INITIALISING, 30, 1, 9.0, 0, name="r0", detail=why),
        AgentRecord(1, AgentState.TRACKING, 30, 5, 9.0, 1, name="r1"),
    )
    text = agents_markdown(StatsSnapshot(10.0, agents, MapCounts(0, 0, 0, 0, 0, 0), ()), {})
    assert f"- **r0**: {why}" in text
    assert "**r1**" not in text


def test_counts_say_the_sources_status_when_it_has_one():
    from common.map_view import MapCounts, StatsSnapshot

    stats = StatsSnapshot(1.0, (), MapCounts(10, 6, 500, 300, 2, 1))
    assert "| Keyframes | 10 | 6 |" in counts_markdown(stats) and "Cloud" not in counts_markdown(
        stats
    )
    text = counts_markdown(dataclasses.replace(stats, status="overloaded for 12 s"))
    assert "**Cloud:** overloaded for 12 s" in text


def test_a_link_silent_for_the_whole_window_keeps_its_plot_at_zero():
    """Once one link's samples have all left the window (its edge finished, another goes on),
    its plot drops to zero instead of failing the panel's update on every poll."""
    import socket

    import viser

    from common.map_view import MapCounts, StatsSnapshot
    from dashboard.panels import Panels

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    try:
        panels = Panels(server, window_s=5.0)
        up = Direction.UP
        counts = MapCounts(0, 0, 0, 0, 0, 0)
        early = (
            BandwidthSample(1.0, "a→cloud", up, "keyframe", 1000),
            BandwidthSample(1.0, "b→cloud", up, "keyframe", 1000),
        )
        panels.update(StatsSnapshot(1.0, (), counts, early), {})
        late = (*early, BandwidthSample(20.0, "b→cloud", up, "keyframe", 500))
        panels.update(StatsSnapshot(20.0, (), counts, late), {})  # a: nothing in (15, 20]
        a_data, b_data = (panels._plots[k][1].data for k in ("a→cloud", "b→cloud"))
        assert not np.asarray(a_data[1]).any() and np.asarray(b_data[1]).any()
    finally:
        server.stop()
