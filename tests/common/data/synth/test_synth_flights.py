"""Trajectory families and modifiers: analytic derivatives, smoothness, inside the room, the
speed and rate bounds they claim (measured), hover-then-go, aggressive bursts, overlap of the
robots' places, and each family's shape."""

from __future__ import annotations

import numpy as np
import pytest

from common.data.synth.flights import (
    FAMILIES,
    FlightConfig,
    FlightSpec,
    make_flights,
    parse_flight,
)
from common.data.synth.scene import vicon_room
from common.data.synth.trajectory import TrajectoryError, check_trajectory
from common.data.synth.worlds import make_world

SCENE = vicon_room()
REGION = (SCENE.room_lo, SCENE.room_hi)
SECONDS = 30.0
CFG = FlightConfig()
NAMES = [
    "figure8",
    "lawnmower",
    "inward",
    "vertical",
    "ring+hover",
    "figure8+aggressive",
    "lawnmower+hover+aggressive",
    "inward+aggressive",
    "vertical+aggressive",
]


def _flights(name: str, seed: int = 0):
    return make_flights(SCENE, REGION, parse_flight(name), 3, SECONDS, seed)


def test_parse_flight() -> None:
    assert parse_flight("ring") == FlightSpec()
    assert parse_flight("Figure8+aggressive") == FlightSpec("figure8", aggressive=True)
    assert parse_flight("hover").name == "ring+hover"
    assert parse_flight("lawnmower+aggressive+hover").name == "lawnmower+hover+aggressive"
    for bad in ("spiral", "hover+figure8", "ring+fast"):
        with pytest.raises(TrajectoryError, match="--flight"):
            parse_flight(bad)


@pytest.mark.parametrize("name", NAMES)
def test_family_is_smooth_inside_and_within_its_bounds(name: str) -> None:
    spec = parse_flight(name)
    limits = CFG.check_limits(spec)
    t = np.arange(0.0, SECONDS, 0.005)
    for k, f in enumerate(_flights(name)):
        assert check_trajectory(SCENE, f, SECONDS, limits) is None
        st = f.evaluate(t)
        cam = st.T_world_cam()[:, :3, 3]
        assert min(SCENE.clearance(st.p_world_body).min(), SCENE.clearance(cam).min()) >= 0.5
        speed = np.linalg.norm(st.v_world_body, axis=1)
        rate = np.linalg.norm(st.omega_body, axis=1)
        assert speed.max() <= limits.max_speed and rate.max() <= limits.max_rate
        # Mean speed as configured (robot 0 slow .. robot 2 fast, 0.85-1 of the fast end).
        lo, hi = CFG.mean_speed
        want = lo + (hi - lo) * k / 2
        if not spec.aggressive:
            assert 0.8 * want <= speed.mean() <= 1.05 * want
        # C2 and beyond: acceleration and body rate change boundedly per 5 ms (no steps).
        jerk = np.linalg.norm(np.diff(st.a_world_body, axis=0), axis=1).max() / 0.005
        ang_acc = np.linalg.norm(np.diff(st.omega_body, axis=0), axis=1).max() / 0.005
        assert jerk < (25.0 if spec.aggressive else 10.0) and ang_acc < 8.0, (jerk, ang_acc)
        assert np.all(np.isfinite(st.R_world_body))


@pytest.mark.parametrize("name", ["figure8", "lawnmower+hover", "vertical+aggressive"])
def test_derivatives_match_finite_differences(name: str, derivatives_agree) -> None:
    t = np.linspace(0.3, SECONDS - 1, 29)
    for f in _flights(name):
        derivatives_agree(f, t)


@pytest.mark.parametrize(
    "name", ["figure8+aggressive", "inward+aggressive", "lawnmower+aggressive"]
)
def test_aggressive_flights_reach_about_2_mps_and_2_5_radps(name: str) -> None:
    t = np.arange(0.0, SECONDS, 0.005)
    rates = []
    for f in _flights(name):
        st = f.evaluate(t)
        speed = np.linalg.norm(st.v_world_body, axis=1).max()
        rate = np.linalg.norm(st.omega_body, axis=1).max()
        accel = np.linalg.norm(st.a_world_body, axis=1).max()
        assert speed <= CFG.aggressive_speed and rate <= CFG.aggressive_rate
        assert accel <= CFG.aggressive_accel
        assert speed >= 1.4
        assert len(f.warp.burst_t) >= 3  # bursts every 5-8 s
        rates.append(rate)
    if name == "figure8+aggressive":  # the turning family also reaches the rate limit
        assert max(rates) >= 2.0


def test_aggressive_vertical_sweeps_are_bounded_by_acceleration() -> None:
    t = np.arange(0.0, SECONDS, 0.005)
    calm, fast = _flights("vertical"), _flights("vertical+aggressive")
    for a, b in zip(calm, fast, strict=True):
        sa, sb = a.evaluate(t), b.evaluate(t)
        accel = np.linalg.norm(sb.a_world_body, axis=1).max()
        assert accel <= CFG.aggressive_accel
        top_a = np.linalg.norm(sa.v_world_body, axis=1).max()
        assert np.linalg.norm(sb.v_world_body, axis=1).max() > 1.1 * top_a


def test_hover_then_go_is_nearly_still_first_then_moves() -> None:
    t = np.arange(0.0, SECONDS, 0.005)
    for f in _flights("figure8+hover"):
        go = f.warp.go_s
        assert CFG.hover_s[0] <= go <= CFG.hover_s[1]
        st = f.evaluate(t)
        speed = np.linalg.norm(st.v_world_body, axis=1)
        rate = np.linalg.norm(st.omega_body, axis=1)
        still = t < go - 2.0 * CFG.hover_ramp_s
        assert still[:200].all()  # at least the first second
        assert speed[still].max() < 0.005 and rate[still].max() < 0.005
        assert speed[t > go + 3.0].mean() > 0.3


def test_every_robot_shares_places_with_another_robot() -> None:
    t = np.arange(0.0, SECONDS, 0.25)
    for name in ("figure8", "lawnmower", "inward", "vertical", "figure8+aggressive"):
        poses = []
        for f in _flights(name):
            T = f.evaluate(t).T_world_cam()
            poses.append((T[:, :3, 3], T[:, :3, 2]))
        for i, (pi, fi) in enumerate(poses):
            shared = 0
            for j, (pj, fj) in enumerate(poses):
                if i != j:
                    d = np.linalg.norm(pi[:, None] - pj[None], axis=2)
                    shared += int(((d < 0.4) & (fi @ fj.T > 0.95)).sum())
            assert shared >= 20, (name, i)


def test_family_shapes() -> None:
    t = np.arange(0.0, SECONDS, 0.05)
    centre = np.array([0.0, 0.0])
    # inward: the camera looks towards the room's centre.
    for f in _flights("inward"):
        T = f.evaluate(t).T_world_cam()
        to_c = centre - T[:, :2, 3]
        fwd = T[:, :2, 2]
        cos = (to_c * fwd).sum(1) / np.linalg.norm(to_c, axis=1) / np.linalg.norm(fwd, axis=1)
        assert np.median(cos) > 0.85
    # vertical: large up-and-down sweeps.
    for f in _flights("vertical"):
        z = f.evaluate(t).p_world_body[:, 2]
        assert z.max() - z.min() > 1.4
    # lawnmower: long rows along x, yaw nearly fixed.
    for f in _flights("lawnmower"):
        st = f.evaluate(t)
        assert np.ptp(st.p_world_body[:, 0]) > 0.5 * (REGION[1][0] - REGION[0][0])
        assert np.linalg.norm(st.omega_body, axis=1).max() < 0.5
    # figure8: y oscillates twice per x oscillation (y crosses its mean twice as often).
    for f in _flights("figure8"):
        p = f.evaluate(np.arange(0.0, SECONDS, 0.01)).p_world_body
        cx = np.count_nonzero(np.diff(np.sign(p[:, 0] - p[:, 0].mean())))
        cy = np.count_nonzero(np.diff(np.sign(p[:, 1] - p[:, 1].mean())))
        assert cx >= 2 and 1.5 * cx <= cy <= 2.6 * cx, (cx, cy)


def test_families_fly_in_the_hall_and_are_deterministic() -> None:
    hall = make_world("hall", 0)
    for name in FAMILIES:
        spec = parse_flight(f"{name}+aggressive")
        fs = make_flights(hall.scene, hall.region, spec, 2, 20.0, 4)
        for f in fs:
            assert check_trajectory(hall.scene, f, 20.0, CFG.check_limits(spec)) is None
        assert fs == make_flights(hall.scene, hall.region, spec, 2, 20.0, 4)
        assert fs != make_flights(hall.scene, hall.region, spec, 2, 20.0, 5)
