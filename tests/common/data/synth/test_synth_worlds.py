"""Worlds: the random room differs per seed and keeps its furniture apart, the hall is
hall-sized, and both render with enough texture to track (ORB features per frame)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.data.synth.cameras import EUROC_CAM0
from common.data.synth.flights import make_flights, parse_flight
from common.data.synth.render import Renderer
from common.data.synth.textures import build_atlas
from common.data.synth.trajectory import TrajectoryError
from common.data.synth.worlds import make_world


def test_random_rooms_differ_per_seed_and_are_deterministic() -> None:
    a, b, c = (make_world("room-random", s).scene for s in (0, 0, 1))
    assert a == b and a.boxes != c.boxes
    for scene in (a, c):
        assert 5 <= len(scene.boxes) <= 10
        assert scene.room_lo == (-4.0, -3.5, 0.0) and scene.room_hi == (4.0, 3.5, 3.5)
        for i, p in enumerate(scene.boxes):  # 0.3 m apart at least
            for q in scene.boxes[i + 1 :]:
                gap = np.maximum(np.array(p.lo) - q.hi, np.array(q.lo) - p.hi).max()
                assert gap >= 0.3 - 1e-9, (p.name, q.name)


def test_hall_is_hall_sized_with_a_free_flight_area() -> None:
    hall = make_world("hall", 0)
    assert tuple(hall.scene.size) == (20.0, 16.0, 8.0)
    lo, hi = np.array(hall.region[0]), np.array(hall.region[1])
    grid = np.stack(np.meshgrid(*[np.linspace(lo[k], hi[k], 9) for k in range(3)]), -1)
    inner = grid.reshape(-1, 3)
    inner = inner[(inner[:, 2] >= 1.0) & (inner[:, 2] <= 2.5)]
    assert hall.scene.clearance(inner).min() > 0.5  # no obstacle in the flight area


def test_unknown_world_is_refused() -> None:
    with pytest.raises(TrajectoryError, match="--world 'moon'"):
        make_world("moon", 0)


@pytest.mark.slow
@pytest.mark.parametrize(("world", "flight"), [("hall", "ring"), ("room-random", "figure8")])
def test_worlds_render_with_enough_texture_to_track(world: str, flight: str) -> None:
    w = make_world(world, 2)
    renderer = Renderer(w.scene, build_atlas(w.scene, 2, w.textures), EUROC_CAM0)
    orb = cv2.ORB_create(nfeatures=1000)
    counts = []
    for f in make_flights(w.scene, w.region, parse_flight(flight), 2, 20.0, 2):
        T = f.evaluate(np.array([3.0, 9.0, 15.0])).T_world_cam()
        for k in range(3):
            img = renderer.render(T[k], 0.0, np.random.default_rng(k))
            assert 40 < img.mean() < 210 and img.std() > 25
            counts.append(len(orb.detect(img, None)))
    assert min(counts) >= 300, counts
