"""Map view records, recordings and the static / progressive replay source."""

from __future__ import annotations

import numpy as np
import pytest

from common.map_view import (
    KeyframeSet,
    MapDelta,
    MapSource,
    MapViewError,
    PointSet,
    StaticMapSource,
    load_recording,
    save_recording,
)
from dashboard.demo import DemoConfig, make_demo_map


@pytest.fixture(scope="module")
def demo():
    return make_demo_map(DemoConfig(n_points=3000, keyframes_per_agent=20))


def test_point_set_rejects_bad_shape_and_is_read_only():
    with pytest.raises(MapViewError, match="p_world"):
        PointSet(np.arange(3), np.zeros((3, 2)), np.zeros(3), np.zeros(3, bool))
    ps = PointSet(np.arange(2), np.ones((2, 3)), [0, 1], [False, True])
    assert ps.p_world.dtype == np.float32
    with pytest.raises(ValueError):
        ps.p_world[0, 0] = 5.0


def test_keyframe_set_rejects_bad_pose_shape():
    with pytest.raises(MapViewError, match="T_world_body"):
        KeyframeSet([1], [0], [0.0], np.zeros((1, 3, 4)), [False])


def test_recording_round_trip(tmp_path, demo):
    delta, stats = demo
    path = tmp_path / "map.npz"
    save_recording(path, delta, stats)
    d2, s2 = load_recording(path)
    assert d2.full
    np.testing.assert_array_equal(d2.points.ids, delta.points.ids)
    np.testing.assert_array_equal(d2.points.pruned, delta.points.pruned)
    np.testing.assert_allclose(d2.keyframes.T_world_body, delta.keyframes.T_world_body)
    np.testing.assert_array_equal(d2.loops, delta.loops)
    assert sorted(d2.current_pose) == [0, 1, 2]
    assert [g.agent_id for g in d2.ground_truth] == [0, 1, 2]
    assert s2.agents == stats.agents
    assert s2.bandwidth == stats.bandwidth
    assert s2.counts == stats.counts


def test_recording_errors_name_the_file(tmp_path, demo):
    bad = tmp_path / "junk.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(MapViewError, match=r"junk\.npz"):
        load_recording(bad)
    partial = tmp_path / "partial.npz"
    np.savez(partial, meta=np.frombuffer(b'{"format": "recslam-map-recording/1"}', np.uint8))
    with pytest.raises(MapViewError, match=r"partial.npz: malformed.*KeyError"):
        load_recording(partial)
    with pytest.raises(MapViewError, match="full delta"):
        save_recording(tmp_path / "x.npz", MapDelta(2, 1, False), demo[1])


def test_static_source_full_then_nothing(demo):
    src = StaticMapSource(*demo)
    assert isinstance(src, MapSource)
    first = src.snapshot(-1)
    assert first.full and len(first.points) == 3000 and len(first.keyframes) == 60
    again = src.snapshot(first.version)
    assert again.empty and again.version == first.version
    assert src.stats().counts.map_points == 3000


def test_progressive_reveal_delivers_each_item_once(demo):
    delta, stats = demo
    now = [0.0]
    src = StaticMapSource(delta, stats, reveal_seconds=10.0, reveal_steps=10, clock=lambda: now[0])
    seen_pts, seen_kfs, version, sizes = [], [], -1, []
    for t in (0.0, 2.5, 2.6, 7.0, 9.99, 10.0, 30.0):
        now[0] = t
        d = src.snapshot(version)
        seen_pts.extend(d.points.ids.tolist())
        seen_kfs.extend(d.keyframes.ids.tolist())
        sizes.append(len(d.points))
        assert d.full == (version < 0)
        version = d.version
    assert sorted(seen_pts) == sorted(delta.points.ids.tolist())
    assert sorted(seen_kfs) == sorted(delta.keyframes.ids.tolist())
    assert 0 < sizes[0] < 3000 and sizes[-1] == 0
    assert len(src.snapshot(version).loops) == 3
    now[0] = 5.0
    mid = StaticMapSource(delta, stats, reveal_seconds=10.0, clock=lambda: now[0])
    now[0] = 10.0
    s = mid.stats()
    assert 0 < s.counts.map_points < 3000
    assert max(b.time for b in s.bandwidth) < max(b.time for b in stats.bandwidth)
