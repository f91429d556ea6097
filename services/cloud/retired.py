"""Retired keyframes: the keyframes MBP removed, kept as poses relative to kept ones.

ORB-SLAM reports a culled keyframe through its parent (the relative pose at culling time), so
its trajectory still holds every keyframe. :class:`RetiredKeyframes` does the same for the
cloud's atlas: each record holds ``T_anchor_body`` to a live keyframe of the same agent, and
``T_map_body = T_map_anchor @ T_anchor_body`` follows every later correction of the anchor.
When an anchor goes too, its records move to an heir with the composed relative pose.
Owned and mutated by :class:`~services.cloud.atlas.Atlas` only.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import replace

import numpy as np

from services.cloud.map_types import RetiredKeyframe, ro


class RetiredKeyframes:
    """The retired keyframes of an atlas by key."""

    def __init__(self, records: Iterable[RetiredKeyframe] = ()) -> None:
        self._by_key = {r.key: r for r in records}

    def add(self, record: RetiredKeyframe) -> None:
        self._by_key[record.key] = record

    def get(self, key: int) -> RetiredKeyframe | None:
        return self._by_key.get(key)

    def anchored_on(self, key: int) -> bool:
        return any(r.anchor == key for r in self._by_key.values())

    def pass_on(self, key: int, heir: int | None, T_heir_key: np.ndarray | None) -> None:
        """Move the records anchored on ``key`` to ``heir`` (``T_heir_key`` (4, 4): ``key``'s
        pose in the heir's body frame); ``heir`` None drops them."""
        for r in [r for r in self._by_key.values() if r.anchor == key]:
            if heir is None or T_heir_key is None:
                del self._by_key[r.key]
                continue
            T = ro(np.asarray(T_heir_key) @ r.T_anchor_body)
            self._by_key[r.key] = replace(r, anchor=heir, T_anchor_body=T)

    def of_agent(self, agent_id: int) -> list[RetiredKeyframe]:
        return [r for r in self._by_key.values() if r.agent_id == agent_id]

    def records(self) -> tuple[RetiredKeyframe, ...]:
        return tuple(self._by_key.values())
