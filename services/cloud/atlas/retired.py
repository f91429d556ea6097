"""Retired keyframes: the keyframes MBP removed, kept as poses relative to kept ones.

ORB-SLAM reports a culled keyframe through its parent (the relative pose at culling time), so
its trajectory still holds every keyframe. :class:`RetiredKeyframes` does the same for the
cloud's atlas: each record holds ``T_anchor_body`` to a live keyframe of the same agent, and
``T_map_body = T_map_anchor @ T_anchor_body`` follows every later correction of the anchor.
When an anchor goes too, its records move to an heir with the composed relative pose. A record
may also hold the kept keyframe on its other side in time (``other``): its pose is then the
blend of what both say (:func:`retired_pose`); on the live replays of
``benchmarks/results/mbp_midrun.md`` the removed keyframes were where MBP while running lost its
accuracy, not the kept ones. Owned and mutated by :class:`~services.cloud.atlas.atlas.Atlas` only.
"""

from __future__ import annotations

from collections.abc import Container, Iterable
from dataclasses import replace

import numpy as np

from common.geometry import inverse_T, so3_exp, so3_log
from services.cloud.atlas.atlas_records import KeyframeRecord
from services.cloud.atlas.map_types import RetiredKeyframe, ro


class RetiredKeyframes:
    """The retired keyframes of an atlas by key."""

    def __init__(self, records: Iterable[RetiredKeyframe] = ()) -> None:
        self._by_key = {r.key: r for r in records}

    @classmethod
    def of_live(cls, records: Iterable[RetiredKeyframe], live: Container[int]) -> RetiredKeyframes:
        """``records`` whose anchor is ``live`` (keys), without a blend whose other is not."""
        return cls(
            r if r.other is None or r.other in live else _unblended(r)
            for r in records
            if r.anchor in live
        )

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

    def drop_other(self, key: int) -> None:
        """``key`` goes: the records that blend with it keep their anchor alone."""
        for r in [r for r in self._by_key.values() if r.other == key]:
            self._by_key[r.key] = _unblended(r)

    def of_agent(self, agent_id: int) -> list[RetiredKeyframe]:
        return [r for r in self._by_key.values() if r.agent_id == agent_id]

    def records(self) -> tuple[RetiredKeyframe, ...]:
        return tuple(self._by_key.values())


def _unblended(r: RetiredKeyframe) -> RetiredKeyframe:
    return replace(r, other=None, T_other_body=None, w_other=0.0)


def retired_pose(
    r: RetiredKeyframe, T_map_anchor: np.ndarray, T_map_other: np.ndarray | None
) -> np.ndarray:
    """``r``'s pose (4, 4) from its anchor's current pose and, when it blends with ``other``,
    that one's (``T_map_other``): position interpolated, rotation along the geodesic."""
    A = T_map_anchor @ r.T_anchor_body
    if r.T_other_body is None or T_map_other is None:
        return A
    B = T_map_other @ r.T_other_body
    w = float(min(r.w_other, 1.0))
    T = np.eye(4)
    T[:3, :3] = A[:3, :3] @ so3_exp(w * so3_log(A[:3, :3].T @ B[:3, :3]))
    T[:3, 3] = (1.0 - w) * A[:3, 3] + w * B[:3, 3]
    return T


def retirement(
    k: KeyframeRecord, anchor: KeyframeRecord, other: KeyframeRecord | None
) -> RetiredKeyframe:
    """The record of ``k`` retired on ``anchor`` (and blended with ``other``: its weight is
    how far ``k`` lies from ``anchor`` towards ``other`` in time), from their current poses."""
    T_anchor_body = ro(inverse_T(anchor.T_map_body) @ k.T_map_body)
    r = RetiredKeyframe(k.key, k.agent_id, k.timestamp, anchor.key, T_anchor_body)
    if other is None:
        return r
    span = abs(k.timestamp - anchor.timestamp) + abs(other.timestamp - k.timestamp)
    w = abs(k.timestamp - anchor.timestamp) / span if span > 0 else 0.0
    T_other_body = ro(inverse_T(other.T_map_body) @ k.T_map_body)
    return replace(r, other=other.key, T_other_body=T_other_body, w_other=float(w))
