"""Timestamp association: agreement with evo's sync, one-to-one, clear errors."""

from __future__ import annotations

import numpy as np
import pytest
from evo.core import sync
from hypothesis import given, settings
from hypothesis import strategies as st

from common.evaluation.association import AssociationConfig, associate, match_timestamps
from common.evaluation.errors import AssociationError, EvaluationError
from common.evaluation.trajectory import Trajectory


def _jittered(tools, ref: Trajectory, rng, step: int, jitter_ns: int, offset_ns: int):
    """Every ``step``-th reference pose with jittered, offset stamps (like camera vs GT)."""
    sub = ref.select(np.arange(0, len(ref), step))
    ts = sub.timestamps_ns + offset_ns + rng.integers(-jitter_ns, jitter_ns + 1, size=len(sub))
    return Trajectory(ts, sub.p_world_body, sub.q_wxyz, "est")


def _evo_indices(tools, ref, est, max_diff_ns, offset_ns):
    """Indices evo's associate_trajectories keeps, recovered from the stamps it returns."""
    ref_e, est_e = sync.associate_trajectories(
        tools.to_evo(ref), tools.to_evo(est), max_diff=max_diff_ns * 1e-9, offset_2=offset_ns * 1e-9
    )
    ref_s = ref.timestamps_ns.astype(np.float64) * 1e-9
    est_s = est.timestamps_ns.astype(np.float64) * 1e-9
    return np.searchsorted(ref_s, ref_e.timestamps), np.searchsorted(est_s, est_e.timestamps)


@pytest.mark.parametrize(
    ("step", "jitter_ms", "offset_ms", "max_diff_ms"),
    [(10, 3, 0, 10), (10, 4, 7, 10), (1, 2, 0, 10), (4, 1, -3, 2), (10, 6, 25, 10)],
)
def test_matches_evo_associate_trajectories(tools, rng, step, jitter_ms, offset_ms, max_diff_ms):
    ref = tools.smooth(rng, n=800)
    est = _jittered(tools, ref, rng, step, jitter_ms * 1_000_000, offset_ms * 1_000_000)
    cfg = AssociationConfig(max_diff_ns=max_diff_ms * 1_000_000, offset_ns=offset_ms * 1_000_000)
    ours = associate(ref, est, cfg)
    evo_ref, evo_est = _evo_indices(tools, ref, est, cfg.max_diff_ns, cfg.offset_ns)
    assert len(ours) > 10
    np.testing.assert_array_equal(ours.ref_indices, evo_ref)
    np.testing.assert_array_equal(ours.est_indices, evo_est)
    assert np.all(np.abs(ours.dt_ns) <= cfg.max_diff_ns)
    np.testing.assert_array_equal(ours.ref.timestamps_ns, ref.timestamps_ns[ours.ref_indices])


def test_matches_evo_when_estimate_is_longer(tools, rng):
    ref = _jittered(tools, tools.smooth(rng, n=800), rng, 10, 3_000_000, 0)
    est = tools.smooth(rng, n=800)  # 200 Hz estimate against 20 Hz reference
    ours = associate(ref, est)
    evo_ref, evo_est = _evo_indices(tools, ref, est, 10_000_000, 0)
    np.testing.assert_array_equal(ours.ref_indices, evo_ref)
    np.testing.assert_array_equal(ours.est_indices, evo_est)


def test_strictly_one_to_one_where_evo_is_not():
    # Two short-side stamps share the same nearest partner: evo keeps both, we keep the closer.
    s1 = np.array([0, 4, 100], dtype=np.int64)
    s2 = np.array([5, 101, 300], dtype=np.int64)
    i1, i2 = match_timestamps(s1, s2, max_diff_ns=10)
    np.testing.assert_array_equal(i1, [1, 2])
    np.testing.assert_array_equal(i2, [0, 1])


def test_ties_pick_the_earlier_stamp_and_boundaries_are_inclusive():
    i1, i2 = match_timestamps(np.array([10], np.int64), np.array([5, 15], np.int64), 5)
    np.testing.assert_array_equal(i2, [0])
    i1, i2 = match_timestamps(np.array([10, 40], np.int64), np.array([20, 30], np.int64), 10)
    np.testing.assert_array_equal(i1, [0, 1])
    np.testing.assert_array_equal(i2, [0, 1])
    i1, _ = match_timestamps(np.array([10, 40], np.int64), np.array([21, 30], np.int64), 10)
    np.testing.assert_array_equal(i1, [1])


def test_no_overlap_in_time_raises_clear_evaluation_error(tools, rng):
    ref = tools.smooth(rng, n=100, name="gt")
    later = tools.smooth(rng, n=100, t0_ns=tools.T0_NS + 60_000_000_000, name="est")
    with pytest.raises(EvaluationError, match=r"found 0 matching timestamps.*gt.*est"):
        associate(ref, later)
    with pytest.raises(AssociationError, match="need 5"):
        associate(ref, ref.select([0, 1, 2]), AssociationConfig(min_pairs=5))


def test_offset_shifts_the_matching(tools, rng):
    ref = tools.smooth(rng, n=200)
    shifted = Trajectory(ref.timestamps_ns - 50_000_000, ref.p_world_body, ref.q_wxyz)
    plain = associate(ref, shifted, AssociationConfig(max_diff_ns=1_000))
    assert len(plain) == len(ref) - 10  # 50 ms at 200 Hz: 10 poses fall off
    fixed = associate(ref, shifted, AssociationConfig(max_diff_ns=1_000, offset_ns=50_000_000))
    np.testing.assert_array_equal(fixed.ref_indices, fixed.est_indices)
    assert len(fixed) == len(ref)
    assert np.all(fixed.dt_ns == 0)


@settings(max_examples=300, deadline=None)
@given(
    a=st.lists(st.integers(0, 2_000), min_size=0, max_size=40, unique=True),
    b=st.lists(st.integers(0, 2_000), min_size=1, max_size=40, unique=True),
    max_diff=st.integers(0, 60),
)
def test_match_timestamps_is_evo_made_one_to_one(a, b, max_diff):
    s1 = np.array(sorted(a), dtype=np.int64)
    s2 = np.array(sorted(b), dtype=np.int64)
    i1, i2 = match_timestamps(s1, s2, max_diff)
    # evo's matcher is unit-agnostic; integer-valued floats keep ties exact.
    e1, e2 = sync.matching_time_indices(s1.astype(float), s2.astype(float), float(max_diff))
    e1, e2 = np.asarray(e1, dtype=np.int64), np.asarray(e2, dtype=np.int64)
    assert len(np.unique(i2)) == len(i2)  # one-to-one
    assert np.all(np.abs(s1[i1] - s2[i2]) <= max_diff)
    expected = {}
    for j1, j2 in zip(e1.tolist(), e2.tolist(), strict=True):
        d = abs(int(s1[j1]) - int(s2[j2]))
        if j2 not in expected or d < expected[j2][1]:
            expected[j2] = (j1, d)
    want = sorted((j1, j2) for j2, (j1, _) in expected.items())
    assert list(zip(i1.tolist(), i2.tolist(), strict=True)) == want
