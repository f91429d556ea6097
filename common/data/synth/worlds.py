"""Worlds of the generator (``recslam dataset synth --world NAME``): a scene, the region the
flights are drawn in, and the texture resolution.

- ``vicon`` (default): :func:`~common.data.synth.scene.vicon_room`, flights over the whole room.
- ``room-random``: a room of the Vicon room's size whose furniture is drawn per seed: 5-8
  boxes against the walls and in the corners (cabinets, crates, shelves, 0.3-2.4 m tall) and up
  to two low ones (<= 0.8 m) in the middle; the textures (and their posters) are per seed
  anyway, here with more posters.
- ``hall``: a machine-hall-like 20 x 16 x 8 m hall: machines, a tank, a rack, a container,
  pallets and four pillars around a 10 x 8 m flight area in the middle (heights as in the
  Vicon room), with textures twice as coarse per texel as the room's but as rich per metre
  (texel 12 mm on walls and floor, seen from 3-10 m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.data.synth.scene import Box, Scene, vicon_room
from common.data.synth.textures import TextureConfig
from common.data.synth.trajectory import Region, TrajectoryError

WORLDS = ("vicon", "room-random", "hall")


@dataclass(frozen=True)
class World:
    """``scene``; ``region`` (lo, hi) [m] the flights are drawn in; ``textures``."""

    name: str
    scene: Scene
    region: Region
    textures: TextureConfig


def _room_random(seed: int) -> Scene:
    """The Vicon room's walls with furniture drawn from ``seed``."""
    rng = np.random.default_rng([seed, 909])
    lo, hi = np.array([-4.0, -3.5, 0.0]), np.array([4.0, 3.5, 3.5])
    boxes: list[Box] = []

    def free(b_lo: np.ndarray, b_hi: np.ndarray) -> bool:
        return all(
            np.any(b_lo >= np.array(b.hi) + 0.3) or np.any(b_hi <= np.array(b.lo) - 0.3)
            for b in boxes
        )

    want = int(rng.integers(5, 9))
    for _ in range(200):
        if len(boxes) >= want:
            break
        axis = int(rng.integers(2))  # against an x wall (axis 0) or a y wall (axis 1)
        side = int(rng.integers(2))
        depth, width = rng.uniform(0.35, 0.8), rng.uniform(0.5, 1.8)
        height = rng.uniform(0.3, 2.4)
        b_lo, b_hi = lo.copy(), hi.copy()
        if side == 0:
            b_hi[axis] = lo[axis] + depth
        else:
            b_lo[axis] = hi[axis] - depth
        other = 1 - axis
        start = rng.uniform(lo[other], hi[other] - width)
        b_lo[other], b_hi[other] = start, start + width
        b_hi[2] = height
        if free(b_lo, b_hi):
            boxes.append(Box(tuple(b_lo), tuple(b_hi), f"furniture_{len(boxes)}"))
    for i in range(int(rng.integers(0, 3))):
        size = rng.uniform(0.5, 1.2, 2)
        centre = rng.uniform(-0.8, 0.8, 2)
        b_lo = np.array([*(centre - size / 2), 0.0])
        b_hi = np.array([*(centre + size / 2), rng.uniform(0.3, 0.6)])
        if free(b_lo, b_hi):
            boxes.append(Box(tuple(b_lo), tuple(b_hi), f"low_{i}"))
    return Scene(tuple(lo), tuple(hi), tuple(boxes))


def _hall() -> Scene:
    boxes = (
        Box((-10.0, -8.0, 0.0), (-6.5, -5.5, 3.0), "machine_a"),
        Box((6.0, -8.0, 0.0), (10.0, -5.0, 2.2), "machine_b"),
        Box((7.5, 4.0, 0.0), (10.0, 8.0, 5.0), "tank"),
        Box((-10.0, 2.0, 0.0), (-8.8, 7.0, 4.0), "rack"),
        Box((-4.0, 6.2, 0.0), (2.0, 8.0, 2.6), "container"),
        Box((2.5, -8.0, 0.0), (4.5, -6.8, 1.2), "pallets"),
        Box((-9.0, -2.0, 0.0), (-7.5, 0.5, 1.5), "workbench"),
        Box((-0.8, -0.6, 0.0), (0.8, 0.6, 0.5), "crate"),
        Box((-6.3, -4.8, 0.0), (-5.7, -4.2, 8.0), "pillar_a"),
        Box((5.7, -4.8, 0.0), (6.3, -4.2, 8.0), "pillar_b"),
        Box((-6.3, 4.2, 0.0), (-5.7, 4.8, 8.0), "pillar_c"),
        Box((5.7, 4.2, 0.0), (6.3, 4.8, 8.0), "pillar_d"),
    )
    return Scene((-10.0, -8.0, 0.0), (10.0, 8.0, 8.0), boxes)


def make_world(name: str, seed: int) -> World:
    """The world called ``name`` (:data:`WORLDS`) for ``seed``; TrajectoryError if unknown."""
    if name == "vicon":
        scene = vicon_room()
        return World(name, scene, (scene.room_lo, scene.room_hi), TextureConfig())
    if name == "room-random":
        scene = _room_random(seed)
        return World(name, scene, (scene.room_lo, scene.room_hi), TextureConfig(posters_per_m2=0.4))
    if name == "hall":
        textures = TextureConfig(
            texel_m=0.012, box_texel_m=0.008, ceiling_texel_m=0.024, shapes_per_m2=3.0
        )
        return World(name, _hall(), ((-5.0, -4.0, 0.0), (5.0, 4.0, 3.5)), textures)
    raise TrajectoryError(f"--world {name!r}: unknown (known: {', '.join(WORLDS)})")
