"""ATE and RPE against evo on the same trajectories; identities; joint vs per-agent ATE."""

from __future__ import annotations

import numpy as np
import pytest
from evo.core import metrics, sync
from evo.core.trajectory import PosePath3D

from common.evaluation.alignment import AlignMode, SimilarityTransform, align, umeyama
from common.evaluation.association import AssociationConfig, associate
from common.evaluation.errors import AlignmentError, EvaluationError, MetricsError
from common.evaluation.metrics import (
    AteConfig,
    DeltaUnit,
    ErrorStats,
    RpeConfig,
    compute_ate,
    compute_joint_ate,
    compute_rpe,
)
from common.evaluation.trajectory import Trajectory

REL = 1e-9
STATS = ("rmse", "mean", "median", "std", "min", "max", "sse")


def _estimate(tools, rng, ref: Trajectory, sim: SimilarityTransform, noise=0.02, step=10):
    """Noisy, jittered 20 Hz estimate of ``ref`` in a frame related by ``sim`` (est -> ref)."""
    sub = tools.perturbed(rng, ref.select(np.arange(0, len(ref), step)), noise, noise / 2)
    inv_R = sim.R_ref_est.T
    est = sub.transformed(inv_R, -inv_R @ sim.t_ref_est / sim.scale, 1.0 / sim.scale)
    ts = est.timestamps_ns + rng.integers(-3_000_000, 3_000_001, size=len(est))
    return Trajectory(ts, est.p_world_body, est.q_wxyz, "est")


def _sim(tools, rng, scale=1.0) -> SimilarityTransform:
    return SimilarityTransform(tools.random_rotation(rng), rng.normal(size=3) * 5.0, scale)


def _assert_stats_close(ours: ErrorStats, evo_stats: dict[str, float]):
    for key in STATS:
        assert getattr(ours, key) == pytest.approx(evo_stats[key], rel=REL, abs=1e-14), key


@pytest.mark.parametrize(
    ("mode", "scale", "n_align"),
    [
        (AlignMode.SE3, 1.0, None),
        (AlignMode.SIM3, 1.7, None),
        (AlignMode.SIM3, 0.6, 20),
        (AlignMode.SE3, 1.0, 15),
        (AlignMode.SCALE, 1.3, None),
        (AlignMode.NONE, 1.0, None),
        (AlignMode.ORIGIN, 1.0, None),
    ],
)
def test_ate_matches_evo_ape(tools, rng, mode, scale, n_align):
    ref = tools.smooth(rng, n=1200)
    est = _estimate(tools, rng, ref, _sim(tools, rng, scale))
    ours = compute_ate(ref, est, AteConfig(align=mode, n_align=n_align))

    ref_e, est_e = sync.associate_trajectories(tools.to_evo(ref), tools.to_evo(est))
    if mode is AlignMode.ORIGIN:
        est_e.align_origin(ref_e)
    elif mode is not AlignMode.NONE:
        r, t, s = est_e.align(
            ref_e,
            correct_scale=mode is AlignMode.SIM3,
            correct_only_scale=mode is AlignMode.SCALE,
            n=-1 if n_align is None else n_align,
        )
        if mode is not AlignMode.SCALE:
            np.testing.assert_allclose(ours.transform.R_ref_est, r, rtol=0, atol=1e-10)
            np.testing.assert_allclose(ours.transform.t_ref_est, t, rtol=REL, atol=1e-10)
        assert ours.transform.scale == pytest.approx(s, rel=REL)
    trans = metrics.APE(metrics.PoseRelation.translation_part)
    trans.process_data((ref_e, est_e))
    rot = metrics.APE(metrics.PoseRelation.rotation_angle_deg)
    rot.process_data((ref_e, est_e))

    assert ours.stats.count == ref_e.num_poses == 120
    np.testing.assert_allclose(ours.errors_m, trans.error, rtol=REL, atol=1e-12)
    _assert_stats_close(ours.stats, trans.get_all_statistics())
    np.testing.assert_allclose(ours.rot_errors_deg, rot.error, rtol=REL, atol=1e-10)
    assert ours.rot_stats.rmse == pytest.approx(rot.get_statistic(metrics.StatisticsType.rmse))
    assert ours.n_ref == len(ref) and ours.n_est == len(est)
    if mode is AlignMode.NONE:
        assert ours.stats.rmse > 1.0  # unaligned frames: large error
    elif n_align is None and mode is not AlignMode.SCALE:
        assert ours.stats.rmse < 0.06


@pytest.mark.parametrize("mode", [AlignMode.SE3, AlignMode.SIM3])
def test_aligning_a_transformed_copy_recovers_the_transform(tools, rng, mode):
    ref = tools.smooth(rng, n=400)
    sim = _sim(tools, rng, 2.5 if mode is AlignMode.SIM3 else 1.0)
    inv_R = sim.R_ref_est.T
    est = ref.transformed(inv_R, -inv_R @ sim.t_ref_est / sim.scale, 1.0 / sim.scale)
    res = compute_ate(ref, est, AteConfig(align=mode))
    assert res.stats.rmse < 1e-9
    assert res.stats.count == len(ref)
    assert res.rot_stats.max < 1e-6
    np.testing.assert_allclose(res.transform.R_ref_est, sim.R_ref_est, atol=1e-10)
    np.testing.assert_allclose(res.transform.t_ref_est, sim.t_ref_est, atol=1e-9)
    assert res.transform.scale == pytest.approx(sim.scale, rel=1e-12)
    assert res.scale_error == pytest.approx(sim.scale - 1.0, abs=1e-12)
    np.testing.assert_allclose(
        res.transform.apply_points(est.p_world_body), ref.p_world_body, atol=1e-9
    )
    M = res.transform.matrix
    np.testing.assert_allclose(M[:3, :3], sim.scale * sim.R_ref_est, atol=1e-9)


def test_se3_on_scaled_copy_leaves_error_and_sim3_removes_it(tools, rng):
    ref = tools.smooth(rng, n=400)
    est = ref.transformed(np.eye(3), np.zeros(3), 0.8)
    se3 = compute_ate(ref, est, AteConfig(align=AlignMode.SE3))
    sim3 = compute_ate(ref, est, AteConfig(align=AlignMode.SIM3))
    assert se3.stats.rmse > 0.05
    assert se3.scale_error == 0.0
    assert sim3.stats.rmse < 1e-9
    assert sim3.scale_error == pytest.approx(1 / 0.8 - 1, rel=1e-12)


def test_umeyama_matches_evo_and_rejects_degenerate_input(rng):
    from evo.core.geometry import umeyama_alignment

    x = rng.normal(size=(50, 3))
    y = rng.normal(size=(50, 3)) + x @ np.diag([1, 2, 3])
    for with_scale in (False, True):
        ours = umeyama(x, y, with_scale)
        r, t, c = umeyama_alignment(x.T, y.T, with_scale)
        np.testing.assert_allclose(ours.R_ref_est, r, atol=1e-12)
        np.testing.assert_allclose(ours.t_ref_est, t, atol=1e-12)
        assert ours.scale == pytest.approx(c, rel=1e-12)
    line = np.outer(np.arange(10.0), [1.0, 2.0, 3.0])
    with pytest.raises(AlignmentError, match="collinear"):
        umeyama(line, line)
    with pytest.raises(AlignmentError, match="at least 3"):
        umeyama(x[:2], y[:2])


def _evo_rpe(tools, ref, est, relation, delta, unit, all_pairs, scale_first=False):
    ref_e, est_e = sync.associate_trajectories(tools.to_evo(ref), tools.to_evo(est))
    if scale_first:
        est_e.align(ref_e, correct_only_scale=True)
    rpe = metrics.RPE(relation, delta=delta, delta_unit=unit, all_pairs=all_pairs)
    rpe.process_data((ref_e, est_e))
    return rpe


@pytest.mark.parametrize(
    ("delta", "unit", "all_pairs"),
    [
        (1, DeltaUnit.FRAMES, False),
        (7, DeltaUnit.FRAMES, False),
        (5, DeltaUnit.FRAMES, True),
        (1.0, DeltaUnit.METERS, False),
        (0.5, DeltaUnit.METERS, True),
    ],
)
def test_rpe_matches_evo(tools, rng, delta, unit, all_pairs):
    ref = tools.smooth(rng, n=1200)
    est = _estimate(tools, rng, ref, _sim(tools, rng), noise=0.01)
    ours = compute_rpe(ref, est, RpeConfig(delta=delta, unit=unit, all_pairs=all_pairs))
    evo_unit = metrics.Unit.frames if unit is DeltaUnit.FRAMES else metrics.Unit.meters
    trans = _evo_rpe(
        tools, ref, est, metrics.PoseRelation.translation_part, delta, evo_unit, all_pairs
    )
    rot = _evo_rpe(
        tools, ref, est, metrics.PoseRelation.rotation_angle_deg, delta, evo_unit, all_pairs
    )
    assert ours.pairs.shape[0] == len(trans.error) > 5
    np.testing.assert_array_equal(ours.pairs[:, 1], trans.delta_ids)
    np.testing.assert_allclose(ours.trans_errors_m, trans.error, rtol=REL, atol=1e-12)
    _assert_stats_close(ours.trans_stats, trans.get_all_statistics())
    np.testing.assert_allclose(ours.rot_errors_deg, rot.error, rtol=REL, atol=1e-10)


def test_rpe_with_scale_alignment_matches_evo(tools, rng):
    ref = tools.smooth(rng, n=800)
    est = _estimate(tools, rng, ref, _sim(tools, rng, 0.7), noise=0.01)
    ours = compute_rpe(ref, est, RpeConfig(delta=3, align=AlignMode.SCALE))
    unscaled = compute_rpe(ref, est, RpeConfig(delta=3))
    evo = _evo_rpe(
        tools,
        ref,
        est,
        metrics.PoseRelation.translation_part,
        3,
        metrics.Unit.frames,
        False,
        scale_first=True,
    )
    np.testing.assert_allclose(ours.trans_errors_m, evo.error, rtol=REL, atol=1e-12)
    assert unscaled.trans_stats.rmse > 2 * ours.trans_stats.rmse


def test_rpe_of_exact_copy_is_zero_and_bad_delta_raises(tools, rng):
    ref = tools.smooth(rng, n=300)
    sim = _sim(tools, rng)
    est = ref.transformed(sim.R_ref_est, sim.t_ref_est)  # rigid motion cancels in RPE
    res = compute_rpe(ref, est, RpeConfig(delta=10))
    assert res.trans_stats.max < 1e-9
    assert res.rot_stats.max < 1e-5
    with pytest.raises(MetricsError, match="no pose pairs"):
        compute_rpe(ref, est, RpeConfig(delta=1000.0, unit=DeltaUnit.METERS))
    with pytest.raises(MetricsError, match="integer"):
        compute_rpe(ref, est, RpeConfig(delta=1.5))


def _agents(tools, rng, n_agents=3):
    """Ground truths of several agents in one world and their estimates in one map frame."""
    sim = _sim(tools, rng)
    refs, ests = {}, {}
    for k in range(n_agents):
        name = f"agent{k}"
        ref = tools.smooth(rng, n=800, t0_ns=tools.T0_NS + k * 1_000_000_000, name=name)
        ref = ref.transformed(np.eye(3), rng.normal(size=3) * 2.0)  # agents start apart
        refs[name] = ref
        ests[name] = _estimate(tools, rng, ref, sim, noise=0.01).renamed(name)
    return refs, ests, sim


def test_joint_ate_equals_evo_on_stacked_agents(tools, rng):
    refs, ests, _ = _agents(tools, rng)
    ours = compute_joint_ate(refs, ests, AteConfig(align=AlignMode.SIM3))
    pairs = [
        sync.associate_trajectories(tools.to_evo(refs[a]), tools.to_evo(ests[a])) for a in refs
    ]
    stacked_ref = PosePath3D(poses_se3=[p for r, _ in pairs for p in r.poses_se3])
    stacked_est = PosePath3D(poses_se3=[p for _, e in pairs for p in e.poses_se3])
    _, _, s = stacked_est.align(stacked_ref, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((stacked_ref, stacked_est))
    _assert_stats_close(ours.stats, ape.get_all_statistics())
    np.testing.assert_allclose(ours.errors_m, ape.error, rtol=REL, atol=1e-12)
    assert ours.transform.scale == pytest.approx(s, rel=REL)
    assert set(ours.under_joint) == set(ours.individual) == set(refs)
    assert all(r.transform is ours.transform for r in ours.under_joint.values())
    assert ours.stats.rmse < 0.03


def test_joint_ate_reveals_a_map_merge_error_that_per_agent_ate_hides(tools, rng):
    refs, ests, _ = _agents(tools, rng)
    bad = ests["agent1"]
    yaw = np.deg2rad(8.0)
    R_off = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    ests["agent1"] = bad.transformed(R_off, np.array([0.8, -0.5, 0.3]))  # merged ~1 m off
    good = compute_joint_ate(refs, {a: e for a, e in ests.items() if a != "agent1"})
    res = compute_joint_ate(refs, ests)
    per_agent = [r.stats.rmse for r in res.individual.values()]
    assert max(per_agent) < 0.03  # each agent alone aligns well
    assert res.stats.rmse > 0.3  # one transform for all cannot fix the offset
    assert good.stats.rmse < 0.03
    assert res.under_joint["agent1"].stats.rmse > 0.3
    # individual results equal a plain per-agent compute_ate
    alone = compute_ate(refs["agent1"], ests["agent1"])
    assert res.individual["agent1"].stats.rmse == pytest.approx(alone.stats.rmse, rel=1e-12)


def test_joint_ate_errors_name_the_problem(tools, rng):
    refs, ests, _ = _agents(tools, rng, n_agents=2)
    with pytest.raises(MetricsError, match="no reference for agent"):
        compute_joint_ate({"agent0": refs["agent0"]}, ests)
    shifted = ests["agent1"]
    far = Trajectory(
        shifted.timestamps_ns + 3600 * 10**9, shifted.p_world_body, shifted.q_wxyz, "agent1"
    )
    with pytest.raises(EvaluationError, match="agent1"):
        compute_joint_ate(refs, {"agent0": ests["agent0"], "agent1": far})


def test_align_rejects_mismatched_lengths(tools, rng):
    ref = tools.smooth(rng, n=50)
    with pytest.raises(AlignmentError, match="equal length"):
        align(ref, ref.select(np.arange(10)), AlignMode.SE3)


def test_error_stats_and_association_config_feed_through(tools, rng):
    stats = ErrorStats.from_errors(np.array([3.0, 4.0]))
    assert stats.rmse == pytest.approx(np.sqrt(12.5))
    assert stats.median == 3.5 and stats.std == 0.5 and stats.sse == 25.0
    with pytest.raises(MetricsError, match="empty"):
        ErrorStats.from_errors(np.zeros(0))
    ref = tools.smooth(rng, n=200)
    tight = AteConfig(association=AssociationConfig(max_diff_ns=0))
    est = Trajectory(ref.timestamps_ns + 1, ref.p_world_body, ref.q_wxyz)
    with pytest.raises(EvaluationError, match="found 0 matching"):
        compute_ate(ref, est, tight)
    assert len(associate(ref, est)) == len(ref)
