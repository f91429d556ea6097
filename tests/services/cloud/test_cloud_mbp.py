"""Map backbone profiling: fewer keyframes, a connected covisibility graph, folded observations."""

from __future__ import annotations

import numpy as np
import pytest

from services.cloud.atlas import Atlas, make_key
from services.cloud.config import MbpConfig
from services.cloud.mbp import connected_dominating_set, covisibility_components, run_mbp
from services.cloud.simulation import circle_poses, default_camera, make_session, make_world

CAM = default_camera()


@pytest.fixture(scope="module")
def dense():
    world = make_world(31, n_points=3000)
    return make_session(
        world, CAM, 0, circle_poses(90, turns=1.0), np.eye(4), seed=6, dt=0.2, track_gap=200
    )


def _atlas(kfs, mps):
    atlas = Atlas()
    for k in kfs:
        atlas.add_keyframe(k)
    for m in mps:
        atlas.add_map_point(m)
    return atlas


def test_connected_dominating_set_on_a_path():
    # Path 0-1-2-...-9: a CDS is the interior run of nodes; every node is dominated.
    adj = {i: {} for i in range(10)}
    for i in range(9):
        adj[i][i + 1] = adj[i + 1][i] = 1.0
    cds = connected_dominating_set(adj)
    assert all(v in cds or any(u in cds for u in adj[v]) for v in adj)
    s = sorted(cds)
    assert s == list(range(s[0], s[-1] + 1))  # connected
    assert len(cds) <= 8


def test_mbp_removes_40_percent_keeps_graph_connected_and_folds_observations(dense):
    kfs, mps = dense
    atlas = _atlas(kfs, mps)
    report = run_mbp(atlas, 0, CAM, MbpConfig())
    assert report.keyframes_before == 90
    assert report.keyframes_after <= 0.6 * report.keyframes_before
    assert report.connected_before and report.connected_after
    assert covisibility_components(atlas, atlas.keyframe_keys()) == 1
    assert report.virtual_observations > 0
    assert report.map_points_after <= report.map_points_before
    assert atlas.has_keyframe(make_key(0, 0))  # the anchor is protected
    for key in report.removed_keyframes:
        assert not atlas.has_keyframe(key)
    # Every surviving map point keeps at least two observations.
    for mk in atlas.map_point_keys():
        assert len(atlas.map_point_observations(mk)) >= 2
    # Virtual observations project to where the point is: check one folded keyframe.
    kept = [atlas.keyframe(k) for k in atlas.keyframe_keys()]
    virt = next(k for k in kept if k.virtual.any())
    i = int(np.flatnonzero(virt.virtual)[0])
    assert virt.map_point_keys[i] >= 0


def test_mbp_disabled_changes_nothing(dense):
    kfs, mps = dense
    atlas = _atlas(kfs, mps)
    report = run_mbp(atlas, 0, CAM, MbpConfig(enabled=False))
    assert report.keyframes_after == report.keyframes_before == atlas.n_keyframes()
    assert report.removed_keyframes == ()
