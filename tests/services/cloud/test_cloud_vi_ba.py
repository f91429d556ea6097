"""Visual-inertial global BA at the cloud: IMU terms from the forwarded IMU, metric scale, and
the switch."""

from __future__ import annotations

import dataclasses
import pickle
import uuid

import numpy as np
import pytest

from common.calibration import EUROC_IMU
from common.codec.imu import ImuEncoder
from common.codec.types import ImuChunk
from common.geometry import make_T, so3_exp
from common.links.edge_cloud import KeyframeUpdateCoded
from common.links.edge_cloud_payloads import KeyframeStates, encode_point_ids, encode_states
from common.protocol.arrays import pack_array
from common.vocabulary import Vocabulary
from services.cloud.app import open_app
from services.cloud.atlas.atlas import KeyframeInput, make_key
from services.cloud.config import FullBAConfig, GlobalOptimizationConfig, MbpConfig
from services.cloud.core import CloudCore
from services.cloud.core_actions import SendCorrections, SolveRequest, solve
from services.cloud.fusion.uplink import UplinkError, decode_keyframe_update
from services.cloud.optimization.full_ba import (
    FullBAProblem,
    _build_graph,
    build_full_ba,
    reweighted_noise_scale,
    solve_full_ba,
)
from services.cloud.optimization.incremental_ba import forget, solve_full_ba_incremental
from services.cloud.optimization.inertial import ImuStore, build_imu_terms, imu_variance_factor
from services.cloud.service_config import CloudServiceConfig, OptimizationScheduleConfig
from sim.cloud import (
    default_camera,
    encode_keyframe_update,
    encode_session,
    make_session,
    make_world,
    map_scale,
    vi_circle_atlas,
    wavy_circle,
)

ON = FullBAConfig()  # IMU factors on by default
OFF = dataclasses.replace(FullBAConfig(), imu_factors=False)
GRAPH = GlobalOptimizationConfig()


def _imu_of(_agent: int):
    return EUROC_IMU


def test_vi_ba_recovers_the_metric_scale_the_relative_pose_terms_keep_wrong():
    scales = {}
    for name, cfg in (("on", ON), ("off", OFF)):
        atlas, store, truth = vi_circle_atlas(60, scale=1.05)
        problem = build_full_ba(atlas, 0, default_camera(), cfg, GRAPH, store, _imu_of)
        res = solve_full_ba(problem, cfg, GRAPH)
        assert map_scale(problem.T_world_body, truth.T_world_body) == pytest.approx(1.05, abs=2e-3)
        scales[name] = map_scale(res.T_world_body, truth.T_world_body)
        if name == "on":
            v_err = np.abs(res.velocity - truth.velocity[res.inertial_index]).max()
            assert v_err < 0.03  # m/s; true speed 1.0 m/s horizontally, 0.6 m/s vertically
            assert res.inertial_index.size == 60
    assert abs(scales["on"] - 1.0) < 0.01
    assert abs(scales["off"] - 1.0) > 0.03


def test_imu_terms_pair_consecutive_keyframes_over_their_timestamps():
    atlas, store, _ = vi_circle_atlas(30, n_landmarks=300, pose_noise=0.0)
    keys = atlas.keyframe_keys()
    terms = build_imu_terms(atlas, 0, keys, store, _imu_of, ON)
    assert terms.n_pairs == 29
    assert terms.pair_i.tolist() == list(range(29))
    assert terms.pair_j.tolist() == list(range(1, 30))
    assert np.diff(terms.offsets).tolist() == [51] * 29  # 0.25 s at 200 Hz, both ends
    assert all(terms.interval_s(k) == pytest.approx(0.25) for k in range(29))
    assert terms.first.tolist() == [0]
    # A keyframe gone (MBP, the edge's culling): its neighbours' interval spans it.
    atlas.remove_keyframe(make_key(0, 10))
    keys = atlas.keyframe_keys()
    terms = build_imu_terms(atlas, 0, keys, store, _imu_of, ON)
    assert terms.n_pairs == 28
    k = terms.pair_i.tolist().index(keys.index(make_key(0, 9)))
    assert terms.interval_s(k) == pytest.approx(0.5)
    assert np.diff(terms.offsets)[k] == 101


def test_an_agents_time_offset_reads_its_imu_at_keyframe_times_plus_the_offset():
    """An IMU on a clock 15 ms ahead, read with the agent's offset, gives the synchronised
    terms; read without it, the same samples give other ones."""
    atlas, sync, _ = vi_circle_atlas(30, n_landmarks=300, pose_noise=0.0)
    buf = sync.buffer(0)
    assert buf is not None
    late = ImuStore()
    late.add(0, buf.timestamps_ns + 15_000_000, buf.gyro, buf.accel)
    keys = atlas.keyframe_keys()
    blind = build_imu_terms(atlas, 0, keys, late, _imu_of, ON)
    late.set_time_offset(0, 15_000_000)
    told = build_imu_terms(atlas, 0, keys, late, _imu_of, ON)
    want = build_imu_terms(atlas, 0, keys, sync, _imu_of, ON)
    assert told.n_pairs == want.n_pairs == 29
    np.testing.assert_array_equal(told.gyro, want.gyro)
    np.testing.assert_array_equal(told.timestamps_ns - 15_000_000, want.timestamps_ns)
    # Blind, the first interval is not covered (it starts before the first sample) and the
    # others read the accelerometer 15 ms early.
    assert blind.n_pairs == 28
    k = want.pair_i.tolist().index(5)
    j = blind.pair_i.tolist().index(5)
    assert np.abs(blind.segment(j).accel - want.segment(k).accel).max() > 1e-3


def test_the_incremental_graph_is_rebuilt_when_a_robots_offset_moves():
    """iSAM2 keeps the terms it has: when a robot's camera-IMU offset moves, every IMU term of
    that robot is read anew, and the graph is built again from a batch solve of the corrected
    terms (not patched, not left with the terms read at the old offset)."""
    atlas, sync, _ = vi_circle_atlas(30, n_landmarks=300, pose_noise=0.0)
    buf = sync.buffer(0)
    assert buf is not None
    late = ImuStore()
    late.add(0, buf.timestamps_ns + 15_000_000, buf.gyro, buf.accel)
    cfg = dataclasses.replace(ON, incremental=True, incremental_min_keyframes=0)
    session = uuid.uuid4().hex
    try:
        blind = build_full_ba(atlas, 0, default_camera(), cfg, GRAPH, late, _imu_of)
        solve_full_ba_incremental(blind, cfg, GRAPH, session, 0)
        again = solve_full_ba_incremental(blind, cfg, GRAPH, session, 0)
        late.set_time_offset(0, 15_000_000)
        told = build_full_ba(atlas, 0, default_camera(), cfg, GRAPH, late, _imu_of)
        res = solve_full_ba_incremental(told, cfg, GRAPH, session, 0)
    finally:
        forget(session)
    assert blind.imu is not None and told.imu is not None
    assert blind.imu.agent_offsets == ((0, 0),) and told.imu.agent_offsets == ((0, 15_000_000),)
    assert again.mode == "isam2" and res.mode != "isam2"  # rebuilt by a batch solve
    batch = solve_full_ba(
        build_full_ba(atlas, 0, default_camera(), ON, GRAPH, sync, _imu_of), ON, GRAPH
    )
    np.testing.assert_allclose(res.T_world_body[:, :3, 3], batch.T_world_body[:, :3, 3], atol=2e-3)


def test_imu_gaps_and_long_intervals_get_no_factor_and_break_the_chain():
    atlas, full, _ = vi_circle_atlas(30, n_landmarks=300, pose_noise=0.0)
    buf = full.buffer(0)
    assert buf is not None
    t, g, a = buf.timestamps_ns, buf.gyro, buf.accel
    hole = (t > 2_600_000_000) & (t < 2_700_000_000)  # 0.1 s missing inside (2.5, 2.75)
    store = ImuStore()
    store.add(0, t[~hole], g[~hole], a[~hole])
    keys = atlas.keyframe_keys()
    terms = build_imu_terms(atlas, 0, keys, store, _imu_of, ON)
    assert terms.n_pairs == 28
    assert 10 not in terms.pair_i.tolist()  # the interval 2.5 -> 2.75 s
    assert terms.first.tolist() == [0, 11]
    short = dataclasses.replace(ON, imu_max_interval_s=0.2)
    assert build_imu_terms(atlas, 0, keys, store, _imu_of, short).n_pairs == 0


def test_switch_off_reproduces_the_relative_pose_full_ba():
    atlas, store, _ = vi_circle_atlas(40, n_landmarks=400)
    cam = default_camera()
    assert ON.imu_factors
    old = build_full_ba(atlas, 0, cam, OFF, GRAPH)  # the call as before IMU factors existed
    new = build_full_ba(atlas, 0, cam, OFF, GRAPH, store, _imu_of)
    assert new.imu is None
    assert np.array_equal(old.T_i_j, new.T_i_j) and np.array_equal(old.edge_i, new.edge_i)
    a, b = solve_full_ba(old, OFF, GRAPH), solve_full_ba(new, OFF, GRAPH)
    assert np.array_equal(a.T_world_body, b.T_world_body)
    assert np.array_equal(a.p_world, b.p_world)
    assert a.velocity.size == 0
    # On, the odometry terms between keyframes with IMU are replaced.
    on = build_full_ba(atlas, 0, cam, ON, GRAPH, store, _imu_of)
    assert on.imu is not None and on.imu.n_pairs == 39
    assert on.edge_i.size == old.edge_i.size - 39


@pytest.fixture(scope="module")
def vocab() -> Vocabulary:
    return Vocabulary.load()


def test_uplink_decodes_the_forwarded_imu_raw_and_coded(vocab):
    atlas, _, _ = vi_circle_atlas(2, n_landmarks=300, pose_noise=0.0)
    kf = atlas.keyframe(make_key(0, 1))
    inp = KeyframeInput(
        agent_id=0,
        keyframe_id=1,
        timestamp=kf.timestamp,
        T_world_body=np.array(kf.T_map_body),
        keypoints=np.array(kf.keypoints),
        levels=np.array(kf.levels),
        descriptors=np.array(kf.descriptors),
        word_ids=np.array(kf.word_ids),
        map_point_ids=np.full(kf.keypoints.shape[0], -1, np.int64),
    )
    t_ns = np.arange(5_000_000, 250_000_001, 5_000_000, dtype=np.int64)
    _, _, gyro, accel = wavy_circle(t_ns * 1e-9, 2.0, 0.5, 1.5, 0.3, 2.0)
    msg, _ = encode_keyframe_update(inp, "r0", vocab, previous_keyframe_id=0)
    rows = np.concatenate([t_ns[:, None] * 1e-9, gyro, accel], axis=1)
    d = decode_keyframe_update(dataclasses.replace(msg, imu=pack_array(rows, "<f8")), 0, vocab)
    assert d.imu is not None
    assert np.array_equal(d.imu.timestamps_ns, t_ns)
    assert np.array_equal(d.imu.accel, accel)
    with pytest.raises(UplinkError):
        decode_keyframe_update(dataclasses.replace(msg, imu=b"\0" * 13), 0, vocab)
    coded = KeyframeUpdateCoded(
        agent_id="r0",
        map_id=0,
        keyframe_id=1,
        previous_keyframe_id=0,
        timestamp_ns=msg.timestamp_ns,
        state=encode_states_of(inp),
        features=msg.features,
        map_point_ids=encode_point_ids(np.full(inp.keypoints.shape[0], -1, np.int64)),
        imu=ImuEncoder().encode(ImuChunk(t_ns, gyro, accel)),
    )
    dc = decode_keyframe_update(coded, 0, vocab)
    assert dc.imu is not None and dc.imu.equals(ImuChunk(t_ns, gyro, accel))


def encode_states_of(kf: KeyframeInput) -> bytes:
    return encode_states(
        KeyframeStates(
            np.array([kf.keyframe_id], np.int64),
            np.array([kf.T_world_body]),
            np.array([kf.velocity]),
            np.array([kf.bias_gyro]),
            np.array([kf.bias_accel]),
        )
    )


def test_the_service_core_runs_a_vi_full_ba_from_forwarded_imu(tmp_path, vocab):
    """Keyframe messages carrying their IMU (as the edge sends them) through the app and the
    core: the full BA request holds one IMU factor per keyframe interval, survives pickling
    (the optimiser process), and its result goes back to the edge as corrections."""
    cam = default_camera()
    n, dt = 16, 0.25
    t_kf = dt * np.arange(n)
    poses, _, _, _ = wavy_circle(t_kf, 2.0, 0.5, 1.5, 0.3, 2.0)
    kfs, mps = make_session(make_world(3, n_points=800), cam, 0, poses, np.eye(4), seed=4, dt=dt)
    t_imu = np.arange(0, round(t_kf[-1] * 1e9) + 1, 5_000_000, dtype=np.int64)
    _, _, gyro, accel = wavy_circle(t_imu * 1e-9, 2.0, 0.5, 1.5, 0.3, 2.0)
    rows = np.concatenate([t_imu[:, None] * 1e-9, gyro, accel], axis=1)
    base = CloudServiceConfig()
    full = dataclasses.replace(base.domain.full_ba, imu_factors=True, max_iterations=3)
    domain = dataclasses.replace(base.domain, full_ba=full, mbp=MbpConfig(enabled=False))
    cfg = dataclasses.replace(
        base, domain=domain, schedule=OptimizationScheduleConfig(every_keyframes=1000)
    )
    app = open_app(tmp_path / "state", cam, vocab, cfg)
    try:
        core = CloudCore(app)
        seq = 0
        prev_ns = None
        for kf, msgs in zip(kfs, encode_session(kfs, mps, "r0", vocab), strict=True):
            t_ns = round(kf.timestamp * 1e9)
            keep = (t_imu <= t_ns) if prev_ns is None else (t_imu > prev_ns) & (t_imu <= t_ns)
            prev_ns = t_ns
            msgs[0] = dataclasses.replace(msgs[0], imu=pack_array(rows[keep], "<f8"))
            for m in msgs:
                seq += 1
                core.handle("edge", m, b"s", seq, float(seq))
        [req] = [a for a in core.full_ba(0, 100.0) if isinstance(a, SolveRequest)]
        assert isinstance(req.problem, FullBAProblem) and req.problem.imu is not None
        assert req.problem.imu.n_pairs == n - 1
        result = solve(pickle.loads(pickle.dumps(req)))  # as in the optimiser process
        assert result.inertial_index.size == n
        actions = core.solved(req, result, 101.0)
        assert core.full_bas == 1
        sends = [a for a in actions if isinstance(a, SendCorrections)]
        assert len(sends) == 1 and sends[0].corrections[0].edge_id == "edge"
    finally:
        app.close()


def _tilted_circle(tilt_rad: float):
    """A 60-keyframe visual-inertial map whose whole frame is tilted by ``tilt_rad`` about x
    at its first keyframe (poses and points), as a map started from an edge's slightly wrong
    gravity estimate: its IMU still measures gravity along the true vertical."""
    atlas, store, truth = vi_circle_atlas(60, pose_noise=0.0)
    keys = atlas.keyframe_keys()
    p0 = atlas.T_map_body(keys[0])[:3, 3].copy()
    R = so3_exp(np.array([tilt_rad, 0.0, 0.0]))
    A = make_T(R, p0 - R @ p0)
    atlas.set_keyframe_poses({k: A @ atlas.T_map_body(k) for k in keys})
    pk = np.array(atlas.map_point_keys(), np.int64)
    P = (atlas.map_point_positions(pk) - p0) @ R.T + p0
    atlas.set_map_point_positions(dict(zip(pk.tolist(), P, strict=True)))
    return atlas, store, truth


def _tilt_deg(T_world_body: np.ndarray, truth: np.ndarray) -> float:
    """Angle between the estimated and the true up direction in the first body frame."""
    up_est, up_true = T_world_body[0, 2, :3], truth[0, 2, :3]  # rows: world z in body
    return float(np.degrees(np.arccos(np.clip(up_est @ up_true, -1.0, 1.0))))


@pytest.mark.parametrize("incremental", [False, True], ids=["batch", "isam2"])
def test_a_free_gauge_tilt_lets_gravity_level_a_tilted_map(incremental):
    tilt = np.radians(1.0)
    cfg = dataclasses.replace(ON, incremental=incremental, incremental_min_keyframes=0)
    out = {}
    for name, sigma in (("held", 0.0), ("free", 0.05)):
        atlas, store, truth = _tilted_circle(tilt)
        c = dataclasses.replace(cfg, gauge_tilt_sigma_rad=sigma)
        problem = build_full_ba(atlas, 0, default_camera(), c, GRAPH, store, _imu_of)
        assert _tilt_deg(problem.T_world_body, truth.T_world_body) == pytest.approx(1.0, abs=1e-6)
        if incremental:
            session = uuid.uuid4().hex
            try:
                res = solve_full_ba_incremental(problem, c, GRAPH, session, 0)
            finally:
                forget(session)
        else:
            res = solve_full_ba(problem, c, GRAPH)
        first = res.T_world_body[0]
        out[name] = _tilt_deg(res.T_world_body, truth.T_world_body)
        # The gauge's position and yaw stay where they were.
        assert np.abs(first[:3, 3] - problem.T_world_body[0, :3, 3]).max() < 1e-4
        fwd, fwd0 = first[:3, 0], problem.T_world_body[0, :3, 0]
        yaw = np.arctan2(fwd[1], fwd[0]) - np.arctan2(fwd0[1], fwd0[0])
        assert abs(yaw) < 1e-3
    assert out["held"] == pytest.approx(1.0, abs=0.01)  # the prior holds the wrong tilt
    assert out["free"] < 0.15, out  # gravity levels the map (0.085° here)


def _noisy_store(store: ImuStore, density: float, seed: int = 3) -> ImuStore:
    """``store``'s agent-0 samples with white noise of ``density`` (accel, m/s²/√Hz; the gyro
    a twelfth of it, as the ADIS16448's datasheet) added."""
    buf = store.buffer(0)
    assert buf is not None
    t, gyro, accel = buf.timestamps_ns, buf.gyro, buf.accel
    rng = np.random.default_rng(seed)
    sd = density / np.sqrt(0.005)  # per 200 Hz sample
    out = ImuStore()
    out.add(
        0,
        t,
        gyro + rng.normal(0.0, sd / 12.0, gyro.shape),
        accel + rng.normal(0.0, sd, accel.shape),
    )
    return out


def test_the_imu_variance_factor_scales_inversely_with_the_assumed_variance():
    atlas, store, _ = vi_circle_atlas(40, n_landmarks=300)
    store = _noisy_store(store, 0.02)
    cfg = dataclasses.replace(ON, imu_reweight_rounds=0)
    problem = build_full_ba(atlas, 0, default_camera(), cfg, GRAPH, store, _imu_of)
    res = solve_full_ba(problem, cfg, GRAPH)
    assert problem.imu is not None
    factors = []
    for scale in (1.0, 2.0):
        c = dataclasses.replace(cfg, imu_noise_scale=scale)
        built = _build_graph(problem, res.T_world_body, res.p_world, c, GRAPH)
        values = built.values  # at the solution's poses; velocities fitted to them
        factors.append(
            imu_variance_factor(built.graph, built.imu_first, built.n_imu, values, problem.imu)
        )
    assert factors[0] > 0
    # Bias priors' share aside, four times the variance: a quarter of the factor.
    assert factors[1] == pytest.approx(factors[0] / 4, rel=0.05)


def test_reweighting_lowers_an_overstated_imu_noise_and_recovers_the_scale():
    atlas, store, truth = vi_circle_atlas(60, scale=1.05)
    store = _noisy_store(store, 0.02)
    over = dataclasses.replace(ON, imu_noise_scale=30.0, imu_noise_scale_max=30.0)
    problem = build_full_ba(atlas, 0, default_camera(), over, GRAPH, store, _imu_of)
    fixed = solve_full_ba(problem, dataclasses.replace(over, imu_reweight_rounds=0), GRAPH)
    fitted = solve_full_ba(problem, over, GRAPH)
    assert fixed.imu_noise_scale == 30.0
    assert fitted.imu_noise_scale < 10.0  # the measured noise is the sensor's: ~1x fits
    err_fixed = abs(map_scale(fixed.T_world_body, truth.T_world_body) - 1.0)
    err_fitted = abs(map_scale(fitted.T_world_body, truth.T_world_body) - 1.0)
    assert err_fitted < 0.5 * err_fixed


def test_reweighted_noise_scale_bounds_each_step_and_the_result():
    cfg = dataclasses.replace(
        ON, imu_reweight_max_step=4.0, imu_noise_scale_min=0.5, imu_noise_scale_max=8.0
    )
    assert reweighted_noise_scale(3.0, 0.25, cfg) == pytest.approx(1.5)  # sqrt: sigma
    assert reweighted_noise_scale(3.0, 1e-6, cfg) == pytest.approx(0.75)  # step at most 4x
    assert reweighted_noise_scale(1.0, 1e-6, cfg) == pytest.approx(0.5)  # floor
    assert reweighted_noise_scale(3.0, 100.0, cfg) == pytest.approx(8.0)  # ceiling
    assert reweighted_noise_scale(3.0, float("nan"), cfg) == 3.0
    assert reweighted_noise_scale(3.0, 0.0, cfg) == 3.0


def test_the_incremental_graph_keeps_the_noise_its_batch_solve_fitted():
    atlas, store, _ = vi_circle_atlas(40, n_landmarks=300)
    store = _noisy_store(store, 0.02)
    cfg = dataclasses.replace(
        ON,
        incremental=True,
        incremental_min_keyframes=0,
        imu_noise_scale=30.0,
        imu_noise_scale_max=30.0,
    )
    session = uuid.uuid4().hex
    problem = build_full_ba(atlas, 0, default_camera(), cfg, GRAPH, store, _imu_of)
    try:
        reset = solve_full_ba_incremental(problem, cfg, GRAPH, session, 0)
        update = solve_full_ba_incremental(problem, cfg, GRAPH, session, 0)
    finally:
        forget(session)
    assert reset.mode == "isam2-reset" and update.mode == "isam2"
    assert reset.imu_noise_scale < 10.0  # fitted, not the configured 30
    assert update.imu_noise_scale == reset.imu_noise_scale
