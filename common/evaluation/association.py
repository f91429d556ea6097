"""Timestamp association of an estimate with its reference (evo's ``nearest_time`` sync).

Each pose of the trajectory with fewer poses (the second one when counts are equal, as in
evo's ``sync.associate_trajectories``) is matched to the nearest stamp of the other within
``max_diff_ns``; on a tie the earlier stamp wins. Unlike evo, the result is strictly one-to-one:
when several poses pick the same partner, only the closest pair is kept (ties: the earlier
pose). Whenever evo's result is already one-to-one, both agree index for index.

All stamps are int64 nanoseconds, so no float rounding enters the matching.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from common.evaluation.errors import AssociationError
from common.evaluation.trajectory import Trajectory

log = logging.getLogger(__name__)

DEFAULT_MAX_DIFF_NS = 10_000_000
"""Largest accepted |t_ref - t_est| for a pair: 10 ms, evo's default."""


@dataclass(frozen=True)
class AssociationConfig:
    """How to pair poses by time.

    ``max_diff_ns``: largest accepted stamp difference [ns] (default 10 ms like evo).
    ``offset_ns``: added to the estimate's stamps before matching (evo's ``offset_2``) [ns].
    ``min_pairs``: fewer matched pairs than this is an :class:`AssociationError`.
    """

    max_diff_ns: int = DEFAULT_MAX_DIFF_NS
    offset_ns: int = 0
    min_pairs: int = 1


@dataclass(frozen=True)
class Association:
    """Matched poses: ``ref[i]`` pairs with ``est[i]``; both have the same length.

    ``ref_indices`` / ``est_indices`` (M,) index the original trajectories; ``dt_ns`` (M,) is
    ``t_est + offset - t_ref``.
    """

    ref: Trajectory
    est: Trajectory
    ref_indices: np.ndarray
    est_indices: np.ndarray
    dt_ns: np.ndarray

    def __len__(self) -> int:
        return int(self.ref_indices.shape[0])


def match_timestamps(
    stamps_1: np.ndarray, stamps_2: np.ndarray, max_diff_ns: int = DEFAULT_MAX_DIFF_NS
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one nearest matching of two strictly increasing int64 stamp arrays [ns].

    Iterates over ``stamps_1`` (the caller passes the shorter one) and picks for each stamp the
    nearest of ``stamps_2`` with ``|diff| <= max_diff_ns`` (ties: the earlier); duplicates in
    ``stamps_2`` keep only the closest pair. Returns increasing index arrays ``(i1, i2)``.
    """
    s1 = np.asarray(stamps_1, dtype=np.int64)
    s2 = np.asarray(stamps_2, dtype=np.int64)
    if max_diff_ns < 0:
        raise AssociationError(f"max_diff_ns must be >= 0, got {max_diff_ns}")
    empty = np.zeros(0, dtype=np.int64)
    if s1.size == 0 or s2.size == 0:
        return empty, empty.copy()
    upper = np.minimum(np.searchsorted(s2, s1, side="right"), s2.size - 1)
    lower = upper - 1
    diff_ub = s2[upper] - s1  # may be negative when upper was clamped
    has_lb = lower >= 0
    diff_lb = np.where(has_lb, s1 - s2[np.maximum(lower, 0)], np.iinfo(np.int64).max)
    take_ub = (np.abs(diff_ub) <= max_diff_ns) & (diff_ub < diff_lb)
    take_lb = ~take_ub & has_lb & (diff_lb <= max_diff_ns) & (diff_lb <= diff_ub)
    # A clamped ``upper`` at the end means every s2 <= s1: evo then compares the last two.
    # ``diff_ub < 0`` there, so take_ub needs |diff_ub| and take_lb must defer; handle exactly:
    clamped = diff_ub < 0
    take_ub = np.where(clamped, np.abs(diff_ub) <= max_diff_ns, take_ub)
    take_lb = np.where(clamped, False, take_lb)
    i1 = np.flatnonzero(take_ub | take_lb)
    i2 = np.where(take_ub, upper, lower)[i1]
    dist = np.abs(s2[i2] - s1[i1])
    # Strictly one-to-one: for each i2 keep the closest i1 (stable sort -> earlier on ties).
    order = np.lexsort((i1, dist, i2))
    keep = np.ones(order.size, dtype=bool)
    keep[1:] = i2[order][1:] != i2[order][:-1]
    kept = np.sort(order[keep])
    return i1[kept].astype(np.int64), i2[kept].astype(np.int64)


def associate(
    ref: Trajectory, est: Trajectory, config: AssociationConfig | None = None
) -> Association:
    """Pair ``est`` with ``ref`` by time (see module docstring); raises AssociationError."""
    cfg = config or AssociationConfig()
    est_stamps = est.timestamps_ns + np.int64(cfg.offset_ns)
    if len(est) > len(ref):
        ref_idx, est_idx = match_timestamps(ref.timestamps_ns, est_stamps, cfg.max_diff_ns)
    else:
        est_idx, ref_idx = match_timestamps(est_stamps, ref.timestamps_ns, cfg.max_diff_ns)
    if len(ref_idx) < max(cfg.min_pairs, 1):
        raise AssociationError(_no_overlap_message(ref, est, cfg, len(ref_idx)))
    log.debug(
        "associated %d of max %d poses (%s vs %s, max diff %d ns, offset %d ns)",
        len(ref_idx),
        min(len(ref), len(est)),
        ref.name or "reference",
        est.name or "estimate",
        cfg.max_diff_ns,
        cfg.offset_ns,
    )
    return Association(
        ref=ref.select(ref_idx),
        est=est.select(est_idx),
        ref_indices=ref_idx,
        est_indices=est_idx,
        dt_ns=est_stamps[est_idx] - ref.timestamps_ns[ref_idx],
    )


def _span(traj: Trajectory) -> str:
    if len(traj) == 0:
        return "no poses"
    return (
        f"{len(traj)} poses, {traj.timestamps_ns[0] * 1e-9:.6f}"
        f"..{traj.timestamps_ns[-1] * 1e-9:.6f} s"
    )


def _no_overlap_message(ref: Trajectory, est: Trajectory, cfg: AssociationConfig, n: int) -> str:
    return (
        f"found {n} matching timestamps (need {max(cfg.min_pairs, 1)}) between reference "
        f"{ref.name or ''} ({_span(ref)}) and estimate {est.name or ''} ({_span(est)}) with "
        f"max diff {cfg.max_diff_ns * 1e-6:g} ms and offset {cfg.offset_ns * 1e-6:g} ms"
    )
