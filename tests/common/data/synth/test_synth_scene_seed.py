"""``scene_seed``: datasets of one scene seed and different seeds fly through one room (the
room's look comes from the scene seed, the flights and noise from the seed)."""

from __future__ import annotations

import pytest

from common.data.synth import generate
from common.data.synth.generate import SynthConfig, generate_dataset


class _StopError(Exception):
    pass


def test_the_rooms_look_follows_the_scene_seed(monkeypatch, tmp_path):
    seen: list[tuple[str, int]] = []
    real_world = generate.make_world

    def world(name, seed):
        seen.append(("world", seed))
        return real_world(name, seed)

    def atlas(scene, seed, cfg):
        seen.append(("textures", seed))
        raise _StopError

    monkeypatch.setattr(generate, "make_world", world)
    monkeypatch.setattr(generate, "build_atlas", atlas)
    configs = [SynthConfig(seed=2, scene_seed=1), SynthConfig(seed=1), SynthConfig(seed=2)]
    for i, config in enumerate(configs):
        with pytest.raises(_StopError):
            generate_dataset(tmp_path / str(i), config)
    assert seen == [("world", 1), ("textures", 1)] * 2 + [("world", 2), ("textures", 2)]
    assert [c.room_seed for c in configs] == [1, 1, 2]
