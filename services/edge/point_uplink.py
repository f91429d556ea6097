"""Which map points of one robot map go up to the cloud, and when (sans-I/O).

:class:`SentPoints` is the edge's record of what the cloud holds of one map: the points it
was sent (id, position as the cloud has it, reference keyframe) and the observation rows it
has (sent, or carried by a keyframe's feature -> point ids). For each batch of changed points
from the VIO it selects what is worth sending:

- a point once a robot keyframe observes it (the VIO's own keyframes carry no features and
  stay on the edge, so their observations never count);
- again when it gains observations in robot keyframes (only the new rows), or when it moved
  more than ``resend_m`` from where the cloud has it (each point follows its reference
  keyframe's pose updates at both ends, :meth:`SentPoints.follow`);
- **settling** (``settle_keyframes`` > 0): a new point is held back until that many robot
  keyframes were uplinked after its first robot observer. Local BA moves young points most:
  on the default dataset a point was sent 4.8 times on average, and half of the re-sends
  came within one uplinked keyframe of the first send (82 % within four), so sending a point
  once it has settled replaces most re-sends by one later send. Held points keep their
  newest position and observations, move with the corrections the VIO applies meanwhile
  (:meth:`SentPoints.move_held`, as the VIO moves its points), and :meth:`SentPoints.release`
  sends them all (the robot's sequence ended, or it continues in another map). Keyframe
  messages name only the points the cloud has (:meth:`SentPoints.carried`).
"""

from __future__ import annotations

import numpy as np

from common.geometry import inverse_T
from services.edge.vio.types import MapPointBatch

_KEY = np.int64(2**32)  # (point, keyframe) key: point id * 2**32 + keyframe id

Selection = tuple[np.ndarray, np.ndarray, np.ndarray]
"""``ids`` (P,), ``p_world`` (P, 3) m, observation rows (R, 3) ``[point, keyframe, feature]``."""


def isin_sorted(sorted_values: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``x`` (N,) in ``sorted_values`` (M,, ascending) as a bool mask (N,)."""
    if not len(sorted_values):
        return np.zeros(len(x), bool)
    i = np.searchsorted(sorted_values, x).clip(max=len(sorted_values) - 1)
    return sorted_values[i] == x


def one_point_each(b: MapPointBatch) -> list[MapPointBatch]:
    """``b`` split into one batch per point (in order)."""
    ends = np.cumsum(b.counts)
    return [
        MapPointBatch(
            b.point_ids[i : i + 1],
            b.p_world[i : i + 1],
            b.counts[i : i + 1],
            b.keyframe_ids[e - c : e],
            b.feature_indices[e - c : e],
        )
        for i, (c, e) in enumerate(zip(b.counts.tolist(), ends.tolist(), strict=True))
    ]


def _subset(b: MapPointBatch, keep: np.ndarray) -> MapPointBatch:
    """The points of ``b`` where ``keep`` (P,) bool is set, with their observations."""
    rows = np.repeat(keep, b.counts)
    return MapPointBatch(
        b.point_ids[keep],
        b.p_world[keep],
        b.counts[keep],
        b.keyframe_ids[rows],
        b.feature_indices[rows],
    )


def _newest(old: MapPointBatch, new: MapPointBatch) -> MapPointBatch:
    """``old``'s points that ``new`` does not list, then ``new`` (its entries are newer)."""
    o = _subset(old, ~np.isin(old.point_ids, new.point_ids))
    return MapPointBatch(
        *(
            np.concatenate([a, b])
            for a, b in zip(
                (o.point_ids, o.p_world, o.counts, o.keyframe_ids, o.feature_indices),
                (new.point_ids, new.p_world, new.counts, new.keyframe_ids, new.feature_indices),
                strict=True,
            )
        )
    )


class SentPoints:
    """The points of one map the cloud has, as sorted arrays: ``ids`` (n,) point ids,
    ``p_world`` (n, 3) m the position last sent, ``ref`` (n,) reference keyframe (first
    robot observer), ``keys`` (m,) the observations sent as ``point id * 2**32 + keyframe
    id`` (keyframe ids < 2**32); plus the points held back until they settle (see the module
    docstring)."""

    def __init__(self, settle_keyframes: int = 0) -> None:
        if settle_keyframes < 0:
            raise ValueError(f"settle_keyframes must be >= 0, got {settle_keyframes}")
        self.settle = settle_keyframes
        self.ids = np.zeros(0, np.int64)
        self.p_world = np.zeros((0, 3))
        self.keys = np.zeros(0, np.int64)
        self.ref = np.zeros(0, np.int64)
        self.uplinked = np.zeros(0, np.int64)  # robot keyframe ids uplinked, ascending
        self.held: MapPointBatch | None = None  # new points waiting to settle (newest data)

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def n_held(self) -> int:
        return 0 if self.held is None else len(self.held)

    def add_keys(self, point_ids: np.ndarray, keyframe_id: int) -> None:
        """Record an uplinked robot keyframe and the observations the cloud got with it."""
        if not len(self.uplinked) or keyframe_id > self.uplinked[-1]:
            self.uplinked = np.append(self.uplinked, np.int64(keyframe_id))
        elif not isin_sorted(self.uplinked, np.array([keyframe_id]))[0]:
            self.uplinked = np.sort(np.append(self.uplinked, np.int64(keyframe_id)))
        k = np.unique(np.asarray(point_ids, np.int64) * _KEY + keyframe_id)
        k = k[~isin_sorted(self.keys, k)]
        self.keys = np.insert(self.keys, np.searchsorted(self.keys, k), k)

    def carried(self, point_ids: np.ndarray, keyframe_id: int) -> np.ndarray:
        """The feature -> point ids (N,) a keyframe message names: -1 for the points the cloud
        does not have (held, or never sent), whose rows in this keyframe then go with the
        point (their keys are forgotten); the cloud thus never hears of a point without its
        position."""
        ids = np.array(point_ids, np.int64)
        unsent = (ids >= 0) & ~isin_sorted(self.ids, ids)
        if unsent.any():
            gone = np.sort(ids[unsent] * _KEY + keyframe_id)
            self.keys = self.keys[~isin_sorted(gone, self.keys)]
            ids[unsent] = -1
        return ids

    def follow(self, keyframe_id: int, T_old: np.ndarray, T_new: np.ndarray) -> None:
        """Move the points whose reference keyframe moved from ``T_old`` to ``T_new`` (4, 4),
        as the cloud does when it gets the keyframe's new pose."""
        sel = self.ref == keyframe_id
        if sel.any():
            corr = T_new @ inverse_T(T_old)
            self.p_world[sel] = self.p_world[sel] @ corr[:3, :3].T + corr[:3, 3]

    def move_held(self, corrections: dict[int, np.ndarray]) -> None:
        """Move the held points as the VIO moved its points with a correction: each with the
        ``(4, 4)`` correction of its first observer (``{keyframe id: correction}``), so that a
        held point goes up where the VIO has it, not where it was before the correction."""
        b = self.held
        if b is None or not len(b) or not corrections:
            return
        owner = np.repeat(np.arange(len(b)), b.counts)
        first = np.full(len(b), np.iinfo(np.int64).max)
        np.minimum.at(first, owner, b.keyframe_ids)
        p = b.p_world.copy()
        for i, kf in enumerate(first.tolist()):
            T = corrections.get(kf)
            if T is not None:
                p[i] = T[:3, :3] @ p[i] + T[:3, 3]
        self.held = MapPointBatch(b.point_ids, p, b.counts, b.keyframe_ids, b.feature_indices)

    def select(self, b: MapPointBatch, own_sorted: np.ndarray, resend_m: float) -> Selection | None:
        """What of ``b`` (distinct point ids) and of the held points to send now, recorded as
        sent; ``own_sorted``: the VIO's own keyframe ids, ascending."""
        if self.held is not None:
            b, self.held = _newest(self.held, b), None
        return self._select(b, own_sorted, resend_m, self.settle)

    def release(self, own_sorted: np.ndarray, resend_m: float) -> Selection | None:
        """Every held point, settled or not (the map gets no more keyframes)."""
        if self.held is None:
            return None
        b, self.held = self.held, None
        return self._select(b, own_sorted, resend_m, 0)

    def _select(
        self, b: MapPointBatch, own_sorted: np.ndarray, resend_m: float, settle: int
    ) -> Selection | None:
        ids, p_world, kf_ids = b.point_ids, b.p_world, b.keyframe_ids
        n = len(ids)
        owner = np.repeat(np.arange(n), b.counts)  # (O,) point index of each observation
        robot = ~isin_sorted(own_sorted, kf_ids)  # (O,) observation in a robot kf
        slot = np.searchsorted(self.ids, ids)
        known = slot < len(self.ids)
        known[known] = self.ids[slot[known]] == ids[known]
        keys = ids[owner] * _KEY + kf_ids
        new = robot & ~isin_sorted(self.keys, keys)  # keys: rows sent, or carried by a keyframe
        d = p_world[known] - self.p_world[slot[known]]
        moved = np.zeros(n, bool)
        moved[known] = (d * d).sum(axis=1) > resend_m**2
        seen = np.bincount(owner[robot], minlength=n) > 0
        first = np.full(n, np.iinfo(np.int64).max)  # first robot observer
        np.minimum.at(first, owner[robot], kf_ids[robot])
        if settle > 0:
            ordinal = np.searchsorted(self.uplinked, first, side="right") - 1
            hold = seen & ~known & (len(self.uplinked) - 1 - ordinal < settle)
            if hold.any():
                self.held = _subset(b, hold)
                seen &= ~hold
                new &= ~hold[owner]
        go = seen & (~known | moved | (np.bincount(owner[new], minlength=n) > 0))
        if not go.any():
            return None
        self.p_world[slot[go & known]] = p_world[go & known]
        fresh = go & ~known
        if fresh.any():  # inserted in id order (np.insert keeps the given order at one slot)
            i = np.flatnonzero(fresh)[np.argsort(ids[fresh], kind="stable")]
            self.ids = np.insert(self.ids, slot[i], ids[i])
            self.p_world = np.insert(self.p_world, slot[i], p_world[i], axis=0)
            self.ref = np.insert(self.ref, slot[i], first[i])
        if new.any():
            k = np.sort(keys[new])
            self.keys = np.insert(self.keys, np.searchsorted(self.keys, k), k)
        rows = np.stack([ids[owner[new]], kf_ids[new], b.feature_indices[new]], axis=1)
        return ids[go], p_world[go], rows

    def remove(self, point_ids: np.ndarray) -> np.ndarray:
        """Forget ``point_ids`` (R,) (held ones too); the ones that were sent, in order (each
        once)."""
        first = np.sort(np.unique(point_ids, return_index=True)[1])
        point_ids = point_ids[first]
        if self.held is not None:
            self.held = _subset(self.held, ~np.isin(self.held.point_ids, point_ids))
        hit = isin_sorted(self.ids, point_ids)
        gone = point_ids[hit]
        if len(gone):
            keep = ~isin_sorted(np.sort(gone), self.ids)
            self.ids, self.p_world, self.ref = self.ids[keep], self.p_world[keep], self.ref[keep]
            lo = np.searchsorted(self.keys, gone * _KEY)
            hi = np.searchsorted(self.keys, (gone + 1) * _KEY)
            drop = np.zeros(len(self.keys) + 1, np.int64)
            np.add.at(drop, lo, 1)
            np.add.at(drop, hi, -1)
            self.keys = self.keys[np.cumsum(drop[:-1]) == 0]
        return gone
