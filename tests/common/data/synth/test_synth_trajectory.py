"""Flights: analytic derivatives, room constraints, start at rest, loops and overlaps."""

from __future__ import annotations

import numpy as np
import pytest

from common.data.synth.scene import vicon_room
from common.data.synth.trajectory import (
    TrajectoryConfig,
    check_trajectory,
    make_trajectories,
)

SCENE = vicon_room()


@pytest.fixture(scope="module")
def flights():
    return make_trajectories(SCENE, 3, 60.0, seed=0)


def test_derivatives_match_finite_differences(flights, derivatives_agree) -> None:
    t = np.linspace(0.3, 59.0, 37)
    for traj in flights:
        derivatives_agree(traj, t)


def test_rotations_are_proper(flights) -> None:
    R = flights[0].evaluate(np.linspace(0, 60, 50)).R_world_body
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.tile(np.eye(3), (50, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


def test_inside_room_away_from_surfaces_and_within_limits(flights) -> None:
    cfg = TrajectoryConfig()
    t = np.arange(0.0, 60.0, 0.01)
    for traj in flights:
        assert check_trajectory(SCENE, traj, 60.0, cfg) is None
        st = traj.evaluate(t)
        assert SCENE.clearance(st.p_world_body).min() >= 0.5
        assert SCENE.clearance(st.T_world_cam()[:, :3, 3]).min() >= 0.5
        assert np.linalg.norm(st.v_world_body, axis=1).max() <= cfg.max_speed
        assert np.linalg.norm(st.omega_body, axis=1).max() <= cfg.max_rate


def test_robots_start_at_rest_and_then_move(flights) -> None:
    for traj in flights:
        st = traj.evaluate(np.array([0.0, 10.0]))
        assert np.linalg.norm(st.v_world_body[0]) < 1e-12
        assert np.linalg.norm(st.a_world_body[0]) < 1e-12
        assert np.linalg.norm(st.omega_body[0]) < 1e-12
        assert np.linalg.norm(st.v_world_body[1]) > 0.1


def test_speeds_differ_between_robots(flights) -> None:
    t = np.arange(0.0, 60.0, 0.05)
    means = [np.linalg.norm(tr.evaluate(t).v_world_body, axis=1).mean() for tr in flights]
    assert max(means) > 1.4 * min(means)


def _poses(traj, t):
    st = traj.evaluate(t)
    T = st.T_world_cam()
    return T[:, :3, 3], T[:, :3, 2]


def test_own_places_revisited_and_other_robots_places_overlap(flights) -> None:
    t = np.arange(0.0, 60.0, 0.25)
    poses = [_poses(tr, t) for tr in flights]
    # Intra-robot loops: same place and viewing direction again more than 10 s later.
    for p, f in poses:
        d = np.linalg.norm(p[:, None] - p[None], axis=2)
        cos = f @ f.T
        later = np.abs(t[:, None] - t[None]) > 10.0
        assert np.any((d < 0.4) & (cos > 0.95) & later)
    # Inter-robot: every pair sees the same place from a similar viewpoint at some times.
    for i in range(3):
        for j in range(i + 1, 3):
            (pi, fi), (pj, fj) = poses[i], poses[j]
            d = np.linalg.norm(pi[:, None] - pj[None], axis=2)
            assert np.any((d < 0.4) & (fi @ fj.T > 0.95)), (i, j)


def test_deterministic_and_seed_dependent() -> None:
    a = make_trajectories(SCENE, 2, 20.0, seed=5)
    b = make_trajectories(SCENE, 2, 20.0, seed=5)
    c = make_trajectories(SCENE, 2, 20.0, seed=6)
    assert a == b
    assert a != c
